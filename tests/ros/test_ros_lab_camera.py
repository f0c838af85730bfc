"""The camera node with `hardware: lab`, in this process on the test's isolated domain: pylon's
emulated camera (PYLON_CAMEMU, set before pypylon's transport-layer factory is first used)
streams through a lab file onto `/camera/image_raw` + `/camera/camera_info`, into the
recorder's MCAP as tracking reads it, and gives snapshots on `/camera/reference_image`;
settings beyond the lab file's limits are refused before the camera is configured; buffers
the emulator is told to fail are counted as lost frames (block id jumps); frame loss across a
16-bit block-id wrap, stamps from the camera clock and a camera that stops delivering, with a
small fake driver (the emulator sends no time stamps and cannot be silenced); a GenICam camera
through the `genicam` wheel's viky.cti."""

import json
import os
import time

os.environ.setdefault("PYLON_CAMEMU", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from rostools import call, spin_until, wait_matched  # noqa: E402

from devices.camera.port import CameraSettings, Frame  # noqa: E402
from ros_nodes import topics as T  # noqa: E402

EMULATOR = ('[camera]\ndriver = "pylon"\nserial = "0815-0000"\nframe_rate_hz = 50.0\n'
            "exposure_s = 0.002\nroi = [0, 0, 1024, 1040]\nmax_frame_rate_hz = 200.0\n"
            "exposure_range_s = [1e-5, 0.01]\n")


def _camera_node(ros_context, executor, lab, **params):
    from rclpy.parameter import Parameter

    from ros_nodes.nodes.camera_node import CameraNode

    overrides = [Parameter("hardware", value="lab"), Parameter("lab_file", value=str(lab))]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    node = CameraNode(context=ros_context, parameter_overrides=overrides)
    executor.add_node(node)
    return node


def _drop(node, executor):
    node.close()
    executor.remove_node(node)
    node.destroy_node()


class _Watch:
    """What the client node hears from the camera: images, camera infos, references, statuses."""

    def __init__(self, node, ex):
        from sensor_msgs.msg import CameraInfo, Image
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        from ros_nodes.nodes._common import LATCHED, STREAM

        self.node, self.ex = node, ex
        self.images, self.infos, self.refs, self.status = [], [], [], []
        self.sub = node.create_subscription(Image, T.IMAGE.name, self.images.append, STREAM)
        node.create_subscription(CameraInfo, T.CAMERA_INFO.name, self.infos.append, STREAM)
        node.create_subscription(Image, T.REFERENCE_IMAGE.name, self.refs.append, LATCHED)
        node.create_subscription(String, T.CAMERA_STATUS.name,
                                 lambda m: self.status.append(json.loads(m.data)), LATCHED)
        self.clients = {name: node.create_client(Trigger, f"/camera/{name}")
                        for name in ("start", "stop", "snapshot")}

    def call(self, name: str):
        from std_srvs.srv import Trigger

        return call(self.clients[name], Trigger.Request(), self.ex, timeout_s=20.0)

    def until(self, predicate, what: str, timeout_s: float = 30.0) -> None:
        spin_until(self.ex, predicate, timeout_s, what)

    def state(self) -> str:
        return self.status[-1]["state"] if self.status else ""


def _ns(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_pylon_emulator_streams_through_the_lab_file(ros_context, ros_node, tmp_path):
    pytest.importorskip("pypylon", reason="pip install pypylon (Basler pylon and its emulator)")
    from devices.camera.pylon import PylonCamera

    lab = tmp_path / "lab.toml"
    lab.write_text(EMULATOR)
    client, ex = ros_node
    w = _Watch(client, ex)
    cam = _camera_node(ros_context, ex, lab)
    try:
        assert isinstance(cam._camera, PylonCamera) and "0815-0000" in cam._camera.identity
        wait_matched(w.sub, ex)
        w.until(lambda: w.state() == "idle", "the ready status")
        # a snapshot before streaming: one frame grabbed from the free-running emulator
        r = w.call("snapshot")
        assert r.success, r.message
        w.until(lambda: w.refs, "the reference image")
        assert (w.refs[0].height, w.refs[0].width, w.refs[0].encoding) == (1040, 1024, "mono8")
        assert w.images == []                          # a snapshot is not a streamed frame
        r = w.call("start")
        assert r.success, r.message
        w.until(lambda: len(w.images) >= 5, "5 frames")
        r = w.call("snapshot")                         # while streaming: the next frame
        assert r.success, r.message
        w.until(lambda: len(w.refs) >= 2 and len(w.images) >= 12, "the second reference")
        assert w.call("stop").success
        w.until(lambda: w.state() == "done", "the done status")
        done = w.status[-1]
        w.until(lambda: len(w.images) >= done["frames"] and len(w.infos) >= done["frames"],
                "every frame")
        stamps = [_ns(m) for m in w.images]
        assert done["frames"] == len(w.images) == cam._published >= 12
        assert all((m.height, m.width, m.encoding, m.step) == (1040, 1024, "mono8", 1024)
                   for m in w.images)
        assert np.all(np.diff(stamps) > 0)             # one stamp per frame, increasing
        assert [_ns(m) for m in w.infos] == stamps     # camera_info beside every image
        assert _ns(w.refs[1]) in stamps                # the reference is a streamed frame
        # host receive times (the emulator sends no stamps) of frames taken at 50 Hz: no lower
        # bound, a grab thread starved by a busy host receives the buffered frames in a burst
        # (seen: 33 frames within 0.12 s beside two busy processes)
        assert (stamps[-1] - stamps[0]) * 1e-9 < 5 * (len(stamps) - 1) / 50 + 2.0
        assert abs(stamps[-1] - time.time_ns()) < 30e9
        assert done["lost"] == 0 and done["received"] == done["frames"]
        assert done["stamps"].startswith("host receive time")
        assert done["settings"]["roi"] == [0, 0, 1024, 1040]
        assert done["message"] == f"published {done['frames']} frames, 0 lost (camera frame counter)"
        # again with the node's software trigger: the node fires at the frame rate
        from rclpy.parameter import Parameter

        cam.set_parameters([Parameter("trigger", value="software"),
                            Parameter("frame_rate_hz", value=100.0)])
        n0 = len(w.images)
        assert w.call("start").success
        w.until(lambda: len(w.images) >= n0 + 5, "5 software-triggered frames")
        assert w.call("stop").success
        w.until(lambda: w.state() == "done", "the done status")
        assert w.status[-1]["settings"]["trigger"] == "software"
        assert w.status[-1]["lost"] == 0
    finally:
        _drop(cam, ex)


def test_the_recorder_records_the_lab_camera_frames_for_tracking(ros_context, ros_node,
                                                                 tmp_path):
    pytest.importorskip("pypylon", reason="pip install pypylon (Basler pylon and its emulator)")
    from rclpy.parameter import Parameter

    from ros_nodes.nodes.recorder_node import RecorderNode
    from tracking.frame_sources import mcap_frames

    lab = tmp_path / "lab.toml"
    lab.write_text(EMULATOR.replace("roi = [0, 0, 1024, 1040]", "roi = [64, 32, 320, 240]"))
    client, ex = ros_node
    w = _Watch(client, ex)
    cam = _camera_node(ros_context, ex, lab)
    path = tmp_path / "recording.mcap"
    rec = RecorderNode(context=ros_context, parameter_overrides=[
        Parameter("path", value=str(path)), Parameter("autostart", value=True)])
    ex.add_node(rec)
    try:
        w.until(lambda: T.IMAGE.name in rec._subs and rec.matched(), "the recorder to subscribe")
        wait_matched(w.sub, ex)
        assert w.call("start").success
        w.until(lambda: len(w.images) >= 10, "10 frames")
        assert w.call("stop").success
        w.until(lambda: w.state() == "done", "the done status")
        n = w.status[-1]["frames"]
        w.until(lambda: rec.message_counts().get(T.IMAGE.name, 0) >= n
                and len(w.images) >= n, "the recorder to write every frame")
        report = rec.stop()
        assert report["topics"][T.IMAGE.name]["count"] == n and report["dropped"] == 0
        frames = list(mcap_frames(path, T.IMAGE.name))      # as `metarig track` reads them
        stamps = [_ns(m) for m in w.images]                   # replayed from the first one
        assert [t for t, _ in frames] == [t - stamps[0] for t in stamps]
        assert all(f.shape == (240, 320) and f.dtype == np.uint8 for _, f in frames)
        assert np.array_equal(frames[3][1], np.asarray(w.images[3].data).reshape(240, 320))
    finally:
        ex.remove_node(rec)
        rec.destroy_node()
        _drop(cam, ex)


def test_buffers_the_emulator_fails_are_counted_as_lost(ros_context, ros_node, tmp_path):
    pytest.importorskip("pypylon", reason="pip install pypylon (Basler pylon and its emulator)")
    lab = tmp_path / "lab.toml"
    lab.write_text(EMULATOR.replace("roi = [0, 0, 1024, 1040]", "roi = [0, 0, 320, 240]"))
    client, ex = ros_node
    w = _Watch(client, ex)
    cam = _camera_node(ros_context, ex, lab)
    try:
        wait_matched(w.sub, ex)
        assert w.call("start").success
        w.until(lambda: len(w.images) >= 5, "5 frames")
        device = cam._camera._device       # the emulator fails the next 2 buffers: 2 frames the
        device.ForceFailedBufferCount.SetValue(2)     # host never gets, a jump of the block id
        device.ForceFailedBuffer.Execute()
        n0 = len(w.images)
        w.until(lambda: len(w.images) >= n0 + 5, "5 frames after the failed buffers")
        assert w.call("stop").success
        w.until(lambda: w.state() == "done", "the done status")
        done = w.status[-1]
        assert done["lost"] == 2 and done["received"] == done["frames"]
        assert done["message"] == f"published {done['frames']} frames, 2 lost (camera frame counter)"
        w.until(lambda: len(w.images) >= done["frames"], "every frame")
        assert len(w.images) == done["frames"]
    finally:
        _drop(cam, ex)


def test_settings_beyond_the_lab_limits_are_refused_before_the_camera_is_configured(
        ros_context, ros_node, tmp_path):
    pytest.importorskip("pypylon", reason="pip install pypylon (Basler pylon and its emulator)")
    from rclpy.parameter import Parameter

    lab = tmp_path / "lab.toml"
    lab.write_text(EMULATOR.replace("max_frame_rate_hz = 200.0", "max_frame_rate_hz = 100.0"))
    client, ex = ros_node
    w = _Watch(client, ex)
    cam = _camera_node(ros_context, ex, lab, frame_rate_hz=500.0)
    configured = []
    configure = cam._camera.configure
    cam._camera.configure = lambda s: (configured.append(s), configure(s))[1]
    try:
        r = w.call("start")
        assert not r.success and r.message == "refused: frame rate 500 Hz is above the limit 100 Hz"
        r = w.call("snapshot")
        assert not r.success and r.message == "refused: frame rate 500 Hz is above the limit 100 Hz"
        cam.set_parameters([Parameter("frame_rate_hz", value=0.0),     # the lab file's 50 Hz
                            Parameter("exposure_s", value=0.05)])
        r = w.call("start")
        assert not r.success and r.message == ("refused: exposure 0.05 s is outside the allowed "
                                               "1e-05..0.01 s")
        assert configured == [] and cam._camera.settings is None    # the device never touched
        assert w.images == [] and cam._stream is None
        cam.set_parameters([Parameter("exposure_s", value=0.0)])
        r = w.call("start")                                           # within the limits: runs
        assert r.success, r.message
        assert configured == [CameraSettings(frame_rate_hz=50.0, exposure_s=0.002,
                                             roi=(0, 0, 1024, 1040))]
        assert w.call("stop").success
    finally:
        _drop(cam, ex)


class _FakeCamera:
    """A camera that sends `counters` (with camera time stamps) and then falls silent."""

    identity = "Fake camera serial 7"
    counter_bits = (16, 1)      # a GigE Vision block id

    def __init__(self, counters, period_s=0.01, offset_ns=0):
        self.counters, self.period_s, self.offset_ns = list(counters), period_s, offset_ns
        self.sent: list[Frame] = []
        self.settings = None
        self.k = 0
        self.stops = 0

    def open(self):
        pass

    def configure(self, settings):
        self.settings = settings
        return settings

    def start(self):
        pass

    def trigger(self):
        pass

    def grab(self, timeout_s):
        if self.k >= len(self.counters):
            time.sleep(timeout_s)
            return None
        c = self.counters[self.k]
        device_s = 100.0 + c * self.period_s
        latency_ns = 1_000_000 + (self.k % 3) * 200_000      # the least: 1 ms, first frame
        host_ns = round(device_s * 1e9) + self.offset_ns + latency_ns
        frame = Frame(np.full((6, 8), c % 256, np.uint8), c, device_s, host_ns)
        self.k += 1
        self.sent.append(frame)
        return frame

    def stop(self):
        self.stops += 1

    def close(self):
        pass


def test_frame_loss_counted_camera_clock_and_a_camera_that_stops_delivering(
        ros_context, ros_node, tmp_path, monkeypatch):
    import devices.connect

    counters = [65533, 65534, 65535, 1, 2, 5, 6, 7, 10, 11]     # wraps to 1; 3, 4, 8, 9 lost
    fake = _FakeCamera(counters, offset_ns=time.time_ns() - 100 * 10**9)
    monkeypatch.setattr(devices.connect, "open_camera", lambda section, **kw: fake)
    lab = tmp_path / "lab.toml"
    lab.write_text('[camera]\ndriver = "pylon"\nframe_rate_hz = 100.0\n')
    client, ex = ros_node
    w = _Watch(client, ex)
    cam = _camera_node(ros_context, ex, lab, grab_timeout_s=0.3)
    try:
        assert cam._camera is fake
        wait_matched(w.sub, ex)
        assert w.call("start").success
        w.until(lambda: w.state() == "error", "the error status")
        err = w.status[-1]
        assert err["message"] == ("Fake camera serial 7 delivered no frame for more than 0.3 s "
                                  "(grab_timeout_s): stream stopped after 10 frames")
        assert (err["frames"], err["received"], err["lost"]) == (10, 10, 4)
        assert err["stamps"].startswith("camera clock")
        assert fake.stops == 1                       # the stream stopped the camera itself
        # frames already published stay published, stamped by the camera clock + the offset
        w.until(lambda: len(w.images) >= 10, "the 10 frames")
        assert [_ns(m) for m in w.images] == [round(f.device_time_s * 1e9) + fake.offset_ns
                                              + 1_000_000 for f in fake.sent]
        r = w.call("stop")
        assert r.success and w.state() == "error"
        r = w.call("snapshot")                       # no frame comes: refused in one line
        assert not r.success and r.message == "refused: Fake camera serial 7 gave no frame within 0.3 s"
        fake.counters += [20, 21, 22]                # the camera is back: a new stream
        assert w.call("start").success
        w.until(lambda: len(w.images) >= 13 and w.state() == "error", "the second stream")
        assert (w.status[-1]["frames"], w.status[-1]["lost"]) == (3, 0)
    finally:
        _drop(cam, ex)


def test_a_lab_camera_that_cannot_be_opened_refuses_with_one_line(ros_context, ros_node,
                                                                 tmp_path):
    pytest.importorskip("pypylon", reason="pip install pypylon (Basler pylon and its emulator)")
    lab = tmp_path / "lab.toml"
    lab.write_text('[camera]\ndriver = "pylon"\nserial = "no-such-camera"\n')
    client, ex = ros_node
    w = _Watch(client, ex)
    cam = _camera_node(ros_context, ex, lab)
    try:
        w.until(lambda: w.state() == "error", "the error status")
        assert w.status[-1]["message"].startswith(
            "cannot open the lab camera: no pylon camera with serial no-such-camera; visible: ")
        r = w.call("start")
        assert not r.success and r.message.startswith("refused: cannot open the lab camera")
        assert "\n" not in r.message
    finally:
        _drop(cam, ex)


def test_genicam_camera_through_viky_cti(ros_context, ros_node, tmp_path):
    pytest.importorskip("harvesters", reason="pip install harvesters genicam (GenTL consumer)")
    from devices.camera.genicam import bundled_producer

    cti = bundled_producer()
    if cti is None:
        pytest.skip("no GenTL producer: pip install genicam (ships viky.cti)")
    lab = tmp_path / "lab.toml"
    lab.write_text(f'[camera]\ndriver = "genicam"\ncti = "{cti}"\nserial = "1"\n'
                   "frame_rate_hz = 50.0\nroi = [0, 0, 320, 240]\n")
    client, ex = ros_node
    w = _Watch(client, ex)
    cam = _camera_node(ros_context, ex, lab)
    try:
        assert "Viky" in cam._camera.identity
        wait_matched(w.sub, ex)
        assert w.call("start").success
        w.until(lambda: len(w.images) >= 5, "5 frames")
        assert w.call("stop").success
        w.until(lambda: w.state() == "done", "the done status")
        done = w.status[-1]
        assert (w.images[0].height, w.images[0].width, w.images[0].encoding) == (240, 320, "mono8")
        assert done["lost"] == 0 and done["received"] == done["frames"] >= 5
        assert np.all(np.diff([_ns(m) for m in w.images]) > 0)
    finally:
        _drop(cam, ex)
