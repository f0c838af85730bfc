"""The pylon driver against pylon's camera emulator (PYLON_CAMEMU, set here before pypylon's
transport-layer factory is first used): settings read back, software and free-running
acquisition with the block id as frame counter, a forced failed buffer counted as loss, limits
refused before the device is touched, and the emulator playing our own image files."""

import os
import time

os.environ.setdefault("PYLON_CAMEMU", "2")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

pytest.importorskip("pypylon", reason="pip install pypylon (Basler pylon and its emulator)")

from devices.camera.port import CameraLimits, CameraSettings, FrameCounter  # noqa: E402
from devices.camera.pylon import PylonCamera, list_cameras  # noqa: E402

ROI = (16, 8, 320, 240)


@pytest.fixture(scope="module")
def serials():
    cams = [c for c in list_cameras() if c["device_class"] == "BaslerCamEmu"]
    if not cams:
        pytest.skip("pylon sees no emulated camera (PYLON_CAMEMU was set after pylon started?)")
    return [c["serial"] for c in cams]


@pytest.fixture
def cam(serials):
    with PylonCamera(serial=serials[0]) as c:
        yield c


def test_settings_are_read_back(cam):
    got = cam.configure(CameraSettings(frame_rate_hz=123.4, exposure_s=0.002, roi=ROI))
    assert got.roi == ROI and got.pixel_format == "mono8" and cam.device_pixel_format == "Mono8"
    assert got.frame_rate_hz == pytest.approx(123.4) and got.exposure_s == pytest.approx(0.002)
    assert cam._device.Width.GetValue() == 320 and cam._device.OffsetX.GetValue() == 16
    got = cam.configure(CameraSettings(frame_rate_hz=50, roi=(0, 0, 64, 32), pixel_format="mono16"))
    assert cam.device_pixel_format == "Mono16" and got.exposure_s == pytest.approx(0.002)
    cam.start()
    frame = cam.grab(2.0)
    cam.stop()
    assert frame is not None and frame.image.shape == (32, 64) and frame.image.dtype == np.uint16
    assert "Emulation" in cam.identity and "0815-" in cam.identity


def test_software_trigger_one_frame_per_trigger(cam):
    cam.configure(CameraSettings(frame_rate_hz=200, exposure_s=0.001, roi=ROI,
                                 trigger="software"))
    cam.start()
    assert cam.grab(0.2) is None                 # nothing without a trigger
    counters = []
    for _ in range(5):
        cam.trigger()
        frame = cam.grab(2.0)
        assert frame is not None and frame.image.shape == (240, 320)
        assert cam.grab(0.05) is None            # exactly one frame per trigger
        counters.append(frame.counter)
    cam.stop()
    assert np.diff(counters).tolist() == [1, 1, 1, 1]


def test_hardware_trigger_is_armed_on_the_named_line(cam):
    got = cam.configure(CameraSettings(frame_rate_hz=100, roi=ROI, trigger="hardware",
                                       hardware_line="Line2"))
    assert got.trigger == "hardware" and cam._device.TriggerSource.GetValue() == "Line2"
    assert cam._device.TriggerMode.GetValue() == "On"
    cam.start()
    assert cam.grab(0.2) is None                 # no edge, no frame (the emulator has no lines)
    cam.stop()
    with pytest.raises(ValueError, match="no trigger source 'Line9'"):
        cam.configure(CameraSettings(trigger="hardware", hardware_line="Line9"))


def test_free_run_at_the_set_rate_and_loss_counted(cam):
    rate = 100.0
    cam.configure(CameraSettings(frame_rate_hz=rate, exposure_s=0.001, roi=ROI))
    counter = FrameCounter(*cam.counter_bits)
    cam.start()
    frames = [cam.grab(2.0) for _ in range(40)]
    # two buffers forced to fail: two frames the host never gets
    cam._device.ForceFailedBufferCount.SetValue(2)
    cam._device.ForceFailedBuffer.Execute()
    more = []
    while len(more) < 10:
        frame = cam.grab(2.0)
        if frame is None:
            assert cam.failed_grabs > 0, "timed out without a failed grab"
            continue
        more.append(frame)
    cam.stop()
    assert all(f is not None for f in frames)
    assert np.diff([f.counter for f in frames]).tolist() == [1] * 39
    assert all(f.device_time_s is None for f in frames)    # the emulator sends time stamp 0
    # the camera makes frames at its rate: from frame 10 to 39 the host cannot see them much
    # faster than that (a stall before frame 10 could shorten the span by its length only);
    # the upper bound on the span is generous, for a loaded machine
    span = (frames[-1].host_time_ns - frames[10].host_time_ns) * 1e-9
    assert 29 / rate / 2 < span < 29 / rate * 10 + 2.0
    for f in frames + more:
        counter.update(f.counter)
    assert cam.failed_grabs == 2 and counter.lost == 2 and counter.received == 50


def test_limits_refused_before_the_device_is_touched(serials):
    cam = PylonCamera(serial=serials[0], limits=CameraLimits(max_frame_rate_hz=500))
    with pytest.raises(ValueError, match="above the limit 500 Hz"):
        cam.configure(CameraSettings(frame_rate_hz=1000))
    with pytest.raises(ValueError, match="longer than the frame period"):
        cam.configure(CameraSettings(frame_rate_hz=100, exposure_s=0.02))
    assert cam._device is None                       # never opened
    with pytest.raises(RuntimeError, match="open"):
        cam.configure(CameraSettings(frame_rate_hz=100))


def test_device_range_and_unknown_serial_in_one_line(cam):
    with pytest.raises(ValueError, match="outside the camera's range"):
        cam.configure(CameraSettings(frame_rate_hz=6000))       # emulator max 5000 Hz
    with pytest.raises(ValueError, match="outside the camera's 4096x4096"):
        cam.configure(CameraSettings(roi=(4000, 0, 200, 100)))
    with pytest.raises(ValueError, match=r"no pylon camera with serial 1234; visible: 0815-"):
        PylonCamera(serial="1234").open()


def test_two_cameras_by_serial(serials):
    if len(serials) < 2:
        pytest.skip("needs PYLON_CAMEMU=2")
    with PylonCamera(serial=serials[1]) as b:
        assert serials[1] in b.identity


def test_emulator_plays_our_image_files(serials, tmp_path):
    cv2 = pytest.importorskip("cv2")
    w, h = 64, 48
    for i in range(3):
        img = np.full((h, w), 40 * (i + 1), np.uint8)
        img[0, :3] = (i, 7, 9)
        cv2.imwrite(str(tmp_path / f"frame{i:03d}.png"), img)
    with PylonCamera(serial=serials[0], emulator_images=tmp_path) as cam:
        cam.configure(CameraSettings(frame_rate_hz=100, roi=(0, 0, w, h)))
        cam.start()
        frames = [cam.grab(2.0) for _ in range(4)]
        cam.stop()
    firsts = [int(f.image[0, 0]) for f in frames]
    assert firsts == [0, 1, 2, 0]                 # one file per frame, in name order, looping
    assert int(frames[1].image[10, 10]) == 80 and frames[0].image[0, 1:3].tolist() == [7, 9]


def test_grab_rate_from_the_emulator(cam):
    """Frames/s grabbed from the emulator at full resolution with no rate limit set (the
    number goes into the report, not into a bound)."""
    cam.configure(CameraSettings(frame_rate_hz=5000, exposure_s=1e-4, roi=(0, 0, 1024, 1040)))
    counter = FrameCounter(*cam.counter_bits)
    cam.start()
    t0 = time.perf_counter()
    n = 0
    while n < 100:
        f = cam.grab(2.0)
        assert f is not None
        counter.update(f.counter)
        n += 1
    dt = time.perf_counter() - t0
    cam.stop()
    print(f"pylon emulator: {n} frames 1024x1040 mono8 in {dt:.3f} s = {n / dt:.0f} frames/s")
    assert counter.lost == 0
