"""The GenICam driver (harvesters) against the emulating GenTL producer of the `genicam` wheel
(viky.cti: 3 cameras, 400x400, RGBa8 or Mono8, no exposure, no trigger, no time stamps)."""

import time

import numpy as np
import pytest

pytest.importorskip("harvesters", reason="pip install harvesters genicam (GenTL consumer)")

from devices.camera.genicam import GenICamCamera, bundled_producer, colour_to_mono8  # noqa: E402
from devices.camera.port import CameraLimits, CameraSettings, FrameCounter  # noqa: E402

CTI = bundled_producer()
pytestmark = pytest.mark.skipif(
    CTI is None, reason="no GenTL producer: pip install genicam (ships viky.cti)")


@pytest.fixture
def cam():
    with GenICamCamera(CTI, serial="1") as c:
        yield c


def test_settings_read_back_and_frames_at_the_set_rate(cam):
    assert "Viky" in cam.identity and "serial 1" in cam.identity
    got = cam.configure(CameraSettings(frame_rate_hz=50, roi=(0, 0, 320, 240)))
    assert got.frame_rate_hz == 50.0 and got.roi == (0, 0, 320, 240) and got.exposure_s is None
    assert cam.device_pixel_format == "Mono8"
    counter = FrameCounter(*cam.counter_bits)
    cam.start()
    frames = [cam.grab(3.0) for _ in range(20)]
    cam.stop()
    assert all(f is not None for f in frames)
    assert frames[0].image.shape == (240, 320) and frames[0].image.dtype == np.uint8
    for f in frames:
        counter.update(f.counter)
    assert np.diff([f.counter for f in frames]).tolist() == [1] * 19 and counter.lost == 0
    assert all(f.device_time_s is None for f in frames)   # the producer has no time stamps
    span = (frames[-1].host_time_ns - frames[5].host_time_ns) * 1e-9
    assert 14 / 50 / 2 < span < 14 / 50 * 10 + 2.0
    # a skipped counter value is a lost frame
    skipping = FrameCounter(*cam.counter_bits)
    for f in frames[:7] + frames[8:]:
        skipping.update(f.counter)
    assert skipping.lost == 1 and skipping.received == 19


def test_frame_rate_rounded_by_the_device(cam):
    got = cam.configure(CameraSettings(frame_rate_hz=33.4, roi=(0, 0, 100, 100)))
    assert got.frame_rate_hz in (33.0, 34.0)


def test_colour_camera_turned_into_mono_honestly():
    with GenICamCamera(CTI, serial="0", device_format="RGBa8") as cam:
        cam.configure(CameraSettings(frame_rate_hz=100, roi=(0, 0, 200, 100)))
        assert cam.device_pixel_format == "RGBa8"
        cam.start()
        frame = cam.grab(3.0)
        cam.stop()
    assert frame.image.shape == (100, 200) and frame.image.dtype == np.uint8
    rgba = np.array([[[255, 0, 0, 9], [0, 255, 0, 9], [0, 0, 255, 9], [10, 20, 30, 0]]], np.uint8)
    mono = colour_to_mono8(rgba.ravel(), "RGBa8", 4, 1)
    assert mono.tolist() == [[76, 150, 29, round(0.299 * 10 + 0.587 * 20 + 0.114 * 30)]]


def test_settings_the_device_lacks_are_refused(cam):
    with pytest.raises(ValueError, match=r"has no exposure time \(ExposureTime\)"):
        cam.configure(CameraSettings(frame_rate_hz=20, exposure_s=0.01))
    with pytest.raises(ValueError, match="has no trigger"):
        cam.configure(CameraSettings(frame_rate_hz=20, trigger="software"))
    with pytest.raises(ValueError, match="has no region offset"):
        cam.configure(CameraSettings(frame_rate_hz=20, roi=(10, 0, 100, 100)))
    with pytest.raises(ValueError, match="offers no Mono16/Mono12/Mono10"):
        cam.configure(CameraSettings(frame_rate_hz=20, pixel_format="mono16"))
    with pytest.raises(ValueError, match="outside the camera's range 1..200 Hz"):
        cam.configure(CameraSettings(frame_rate_hz=500))


def test_limits_before_the_device_and_unknown_serial():
    cam = GenICamCamera(CTI, serial="0", limits=CameraLimits(max_frame_rate_hz=60))
    with pytest.raises(ValueError, match="above the limit 60 Hz"):
        cam.configure(CameraSettings(frame_rate_hz=100))
    assert cam._device is None                        # never opened
    with pytest.raises(ValueError, match=r"no GenTL camera with serial 7 .*visible: 0 \(Viky\)"):
        GenICamCamera(CTI, serial="7").open()
    with pytest.raises(ValueError, match="does not exist"):
        GenICamCamera("/nonexistent/producer.cti").open()


def test_grab_rate_from_the_producer(cam):
    cam.configure(CameraSettings(frame_rate_hz=200, roi=(0, 0, 400, 400)))
    cam.start()
    t0 = time.perf_counter()
    frames = [cam.grab(3.0) for _ in range(40)]
    dt = time.perf_counter() - t0
    cam.stop()
    assert all(f is not None for f in frames)
    print(f"viky.cti: 40 frames 400x400 mono8 in {dt:.3f} s = {40 / dt:.0f} frames/s (set 200)")
