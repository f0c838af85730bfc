"""Messages <-> domain types. The one module outside `ros_nodes/nodes/` that imports `*_msgs`.

Times are integer nanoseconds on the domain side; lengths m, angles rad (REP-103).
"""

import importlib
import json

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from metarig_msgs.msg import ComparisonResult, UnitPose2DArray
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import Float64, String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from metarig.trajectory import to_absolute
from ros_nodes import topics as T
from ros_nodes.logic import comparison_run as run

SHAKER_JOINT = "shaker"
STAGE_JOINTS = ("stage_bottom", "stage_top")
ENCODINGS = {"mono8": np.uint8, "mono16": np.uint16}


def stamp(ns: int) -> Time:
    """Integer nanoseconds -> builtin_interfaces/Time."""
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def to_ns(t: Time) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def message_class(type_name: str):
    """`pkg/msg/Type` -> the Python message class."""
    parts = type_name.strip("/").split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3:
        raise ValueError(f"not a message type name: {type_name!r}")
    return getattr(importlib.import_module(f"{parts[0]}.{parts[1]}"), parts[2])


def clock(ns: int) -> Clock:
    return Clock(clock=stamp(ns))


def shaker_state(ns: int, x_m: float, v_m_s: float) -> JointState:
    m = JointState(name=[SHAKER_JOINT], position=[float(x_m)], velocity=[float(v_m_s)])
    m.header.stamp = stamp(ns)
    return m


def stage_state(ns: int, bottom_m: float, top_m: float) -> JointState:
    """Stage positions: each stage's travel toward the sample centre, m."""
    m = JointState(name=list(STAGE_JOINTS), position=[float(bottom_m), float(top_m)])
    m.header.stamp = stamp(ns)
    return m


def joint_state_arrays(msg: JointState) -> tuple[int, list[str], np.ndarray, np.ndarray]:
    return (to_ns(msg.header.stamp), list(msg.name), np.asarray(msg.position, np.float64),
            np.asarray(msg.velocity, np.float64))


def command_trajectory(start_ns: int, t_rel_s: np.ndarray, u_m: np.ndarray,
                       v_m_s: np.ndarray) -> JointTrajectory:
    """The commanded shaker waveform: one point per sample, times from `start_ns`."""
    m = JointTrajectory(joint_names=[SHAKER_JOINT])
    m.header.stamp = stamp(start_ns)
    pts = []
    for t, u, v in zip(np.asarray(t_rel_s, np.float64), u_m, v_m_s):
        ns = int(round(t * 1e9))
        p = JointTrajectoryPoint(positions=[float(u)], velocities=[float(v)])
        p.time_from_start.sec, p.time_from_start.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
        pts.append(p)
    m.points = pts
    return m


def trajectory_arrays(msg: JointTrajectory) -> tuple[int, np.ndarray, np.ndarray]:
    """(start ns, [n] times from start s, [n] positions m) of a single-joint trajectory."""
    t = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
    u = np.array([p.positions[0] for p in msg.points])
    return to_ns(msg.header.stamp), t, u


def image(ns: int, frame: np.ndarray, frame_id: str = "camera") -> Image:
    """uint8 / uint16 [H, W] array -> mono8 / mono16 Image (little-endian)."""
    enc = {np.dtype(np.uint8): "mono8", np.dtype(np.uint16): "mono16"}.get(frame.dtype)
    if enc is None or frame.ndim != 2:
        raise ValueError(f"frames must be 2-D uint8 or uint16, got {frame.dtype} {frame.shape}")
    f = np.ascontiguousarray(frame)
    m = Image(height=f.shape[0], width=f.shape[1], encoding=enc, is_bigendian=0,
              step=f.shape[1] * f.itemsize)
    m.header.stamp = stamp(ns)
    m.header.frame_id = frame_id
    m.data = f.tobytes()
    return m


def image_array(msg: Image) -> np.ndarray:
    """mono8 / mono16 Image -> [H, W] array (a view on the message buffer); colour encodings ->
    [H, W, C] BGR. The one decoder: `tracking.frame_sources.image_from_msg`."""
    from tracking.frame_sources import image_from_msg

    return image_from_msg(msg)


def camera_info(ns: int, width: int, height: int, m_per_px: float,
                frame_id: str = "camera") -> CameraInfo:
    """Calibration of the square-on camera: K holds f = 1 / m_per_px (pixels per metre of sample
    at unit working distance), so the image scale is recovered as 1 / K[0]; no distortion."""
    f = 1.0 / m_per_px
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    m = CameraInfo(width=width, height=height, distortion_model="plumb_bob",
                   d=[0.0] * 5, k=[f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
                   r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                   p=[f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    m.header.stamp = stamp(ns)
    m.header.frame_id = frame_id
    return m


def unit_poses(ns: int, q: np.ndarray, reference_m: np.ndarray, quality=None, lost=None,
               frame_id: str = "sample", sigma=None) -> UnitPose2DArray:
    """One frame of a `Trajectory` -> message: displacements q [n, 3] (m, rad) from the
    reference centroids [n, 2] (sample frame, m) become absolute poses; quality, lost [n];
    sigma [n, 3] standard errors of q (None: the sigma fields stay empty).
    The way back, for any number of frames: `metarig.trajectory.from_pose_messages`."""
    q = np.asarray(q, np.float64)
    n = q.shape[0]
    x, y, theta = to_absolute(q, reference_m)
    m = UnitPose2DArray()
    m.header.stamp = stamp(ns)
    m.header.frame_id = frame_id
    m.ids = np.arange(n, dtype=np.uint32)
    m.x, m.y, m.theta = x, y, np.asarray(theta, np.float64)
    m.quality = np.ones(n, np.float32) if quality is None else np.asarray(quality, np.float32)
    m.lost = [False] * n if lost is None else [bool(v) for v in lost]
    if sigma is not None:
        sig = np.asarray(sigma, np.float32).reshape(n, 3)
        m.sigma_x, m.sigma_y, m.sigma_theta = sig[:, 0].copy(), sig[:, 1].copy(), sig[:, 2].copy()
    return m


def comparison_result(onset_ns: int, comparison, summary: dict) -> ComparisonResult:
    """A `comparison.metrics.Comparison` and its run summary -> the typed result message."""
    m = comparison.metrics
    r = ComparisonResult(
        velocity_nrmse=float(m["velocity_nrmse"]),
        energy_map_correlation=float(m["energy_map_correlation"]),
        target_peak_ke_rel_err=float(m["target_peak_ke_rel_err"]),
        max_displacement_error_m=float(m["max_displacement_error_m"]),
        target_peak_ke_exp=float(m["target_peak_ke_exp_J"]),
        target_peak_ke_sim=float(m["target_peak_ke_sim_J"]),
        lost_units=int(m["lost_units"]), units_compared=int(m["units_compared"]),
        input_source=str(summary.get("input_source", "")),
        precompression_m=float(summary.get("precompression_m", 0.0)))
    r.header.stamp = stamp(onset_ns)
    r.t = np.asarray(comparison.t, np.float64)
    r.target_ke_exp = np.asarray(comparison.target_ke_exp, np.float64)
    r.target_ke_sim = np.asarray(comparison.target_ke_sim, np.float64)
    r.velocity_error = np.asarray(comparison.velocity_error_t, np.float64)
    return r


def serialize(msg) -> bytes:
    """CDR bytes of a message (what the recorder writes), without a running context."""
    from rclpy.serialization import serialize_message

    return serialize_message(msg)


def text(s: str) -> String:
    return String(data=s)


def json_text(obj) -> String:
    return String(data=json.dumps(obj))


def scalar(v: float) -> Float64:
    return Float64(data=float(v))


_LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN,
           "error": DiagnosticStatus.ERROR, "stale": DiagnosticStatus.STALE}


def diagnostics(ns: int, name: str, level: str, message: str,
                values: dict[str, object] | None = None) -> DiagnosticArray:
    """One-status DiagnosticArray; `level` is ok / warn / error / stale."""
    st = DiagnosticStatus(level=_LEVELS[level], name=name, message=message, hardware_id=name,
                          values=[KeyValue(key=k, value=str(v)) for k, v in (values or {}).items()])
    m = DiagnosticArray(status=[st])
    m.header.stamp = stamp(ns)
    return m


def comparison_messages(ec, summary: dict, reference_m: np.ndarray) -> list[tuple[str, int, object]]:
    """The comparison as (topic, stamp ns, rclpy message): the simulated poses of every frame
    (`/compare/simulated_poses`), then at the last frame the result (`/compare/result`,
    stamped at the pulse onset), the summary (`/compare/summary`) and the `/diagnostics` status.
    `reference_m` [n, 2]: the design's centroids (absolute poses are measured from them)."""
    t_ns = run.frame_stamps_ns(ec)
    out = [(T.COMPARE_SIMULATED.name, int(ns),
            unit_poses(int(ns), ec.simulated_abs.q[k], reference_m))
           for k, ns in enumerate(t_ns)]
    end_ns = int(t_ns[-1])
    onset_ns = round((ec.frame_t0_s + summary["onset_s"]) * 1e9)
    out.append((T.COMPARE_RESULT.name, end_ns,
                comparison_result(onset_ns, ec.comparison, summary)))
    out.append((T.COMPARE_SUMMARY.name, end_ns, json_text(summary)))
    out.append((T.DIAGNOSTICS.name, end_ns, ok_diagnostics(end_ns, summary)))
    return out


def ok_diagnostics(ns: int, summary: dict):
    """The `/diagnostics` status of a finished comparison: ok, with the summary metrics."""
    return diagnostics(ns, run.DIAGNOSTIC_NAME, "ok", "experiment against simulation",
                       {k: summary[k] for k in run.SUMMARY_KEYS})


def error_diagnostics(ns: int, reason: str):
    """The `/diagnostics` status of a refused comparison: error, with its one-line reason."""
    return diagnostics(ns, run.DIAGNOSTIC_NAME, "error", reason.splitlines()[0] if reason
                       else "comparison failed")
