"""The camera port's pure logic: settings checked against limits in one line, frame loss from
the camera's counter (jumps, wrap-around, restarts), and the camera-to-host clock map."""

import pytest

from devices.camera.port import (
    Camera,
    CameraLimits,
    CameraSettings,
    ClockMap,
    FrameCounter,
    check_settings,
)

LIMITS = CameraLimits(max_frame_rate_hz=1000, exposure_range_s=(1e-5, 0.1),
                      pixel_formats=("mono8",), sensor_size_px=(640, 480))


@pytest.mark.parametrize("settings, message", [
    (CameraSettings(frame_rate_hz=2000), "above the limit 1000 Hz"),
    (CameraSettings(frame_rate_hz=0), "must be a positive number"),
    (CameraSettings(frame_rate_hz=float("nan")), "must be a positive number"),
    (CameraSettings(frame_rate_hz=100, exposure_s=0.02), "longer than the frame period 0.01 s"),
    (CameraSettings(frame_rate_hz=1, exposure_s=0.5), "outside the allowed 1e-05..0.1 s"),
    (CameraSettings(exposure_s=-1.0), "must be a positive number"),
    (CameraSettings(pixel_format="mono16"), "not allowed here"),
    (CameraSettings(pixel_format="rgb8"), "is not one of mono8, mono16"),
    (CameraSettings(trigger="sometimes"), "is not one of free, software, hardware"),
    (CameraSettings(trigger="hardware", hardware_line=""), "needs an input line"),
    (CameraSettings(roi=(600, 0, 100, 100)), "outside the 640x480 px sensor"),
    (CameraSettings(roi=(0, 0, 0, 100)), "positive width and height"),
    (CameraSettings(roi=(0, 0, 10.5, 100)), "must be 4 integers"),
])
def test_settings_refused_in_one_line(settings, message):
    with pytest.raises(ValueError, match=message) as err:
        check_settings(settings, LIMITS)
    assert "\n" not in str(err.value)


def test_settings_within_limits_pass():
    check_settings(CameraSettings(frame_rate_hz=1000, exposure_s=1e-3, roi=(0, 0, 640, 480)),
                   LIMITS)
    check_settings(CameraSettings(trigger="hardware", hardware_line="Line3"), LIMITS)


def test_frame_counter_jumps_repeats_and_restarts():
    c = FrameCounter()
    assert [c.update(n) for n in (5, 6, 7, 10, 11)] == [0, 0, 0, 2, 0]
    assert c.lost == 2 and c.received == 5
    c.update(11)
    assert c.repeated == 1 and c.lost == 2
    c.update(0)                                   # the camera restarted its counter
    assert c.restarts == 1 and c.lost == 2
    c.update(3)
    assert c.summary() == {"received": 8, "lost": 4, "repeated": 1, "counter_restarts": 1}


def test_frame_counter_wraps_around():
    c = FrameCounter(bits=8)
    for n in (253, 254, 255, 0, 1):
        assert c.update(n) == 0
    assert c.update(4) == 2 and c.lost == 2
    g = FrameCounter(bits=16, wrap_to=1)          # GigE Vision block id: 65535 -> 1
    assert [g.update(n) for n in (65534, 65535, 1, 2)] == [0, 0, 0, 0]
    assert g.update(65535) == 0 and g.restarts == 1
    g2 = FrameCounter(bits=16, wrap_to=1)
    g2.update(65534)
    assert g2.update(2) == 2                      # 65535 and 1 lost across the wrap
    with pytest.raises(ValueError):
        FrameCounter(bits=1)


def test_clock_map_takes_the_least_latency_and_follows_a_window():
    m = ClockMap(window=3)
    with pytest.raises(ValueError, match="no .* pair"):
        m.to_host_ns(1.0)
    offset = 1_700_000_000_000_000_000
    for i, lat_us in enumerate((500, 80, 900, 300)):
        m.add(0.01 * i, offset + round(0.01 * i * 1e9) + lat_us * 1000)
    assert m.offset_ns == offset + 80_000 and m.pairs == 4
    assert m.to_host_ns(1.0) == offset + 1_000_000_000 + 80_000
    m.add(0.04, offset + 40_000_000 + 600_000)    # the 80 us pair leaves the window of 3
    assert m.offset_ns == offset + 300_000
    with pytest.raises(ValueError):
        ClockMap(window=0)


def test_drivers_implement_the_port():
    pylon = pytest.importorskip("devices.camera.pylon", reason="pip install pypylon")
    genicam = pytest.importorskip("devices.camera.genicam", reason="pip install harvesters")
    assert isinstance(pylon.PylonCamera(), Camera)
    assert isinstance(genicam.GenICamCamera("x.cti"), Camera)
