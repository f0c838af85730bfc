"""A rig recording (MCAP) read back as arrays: design, plan, device motion, poses (no rclpy).

Messages are decoded from the schemas stored in the file (`mcap_ros2`), so no ROS install or
built interface package is needed; frames are read by `tracking.frame_sources`. Times are on
the rig clock (header stamps), s.
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from metarig.trajectory import Trajectory, from_pose_messages
from ros_nodes import topics


class RecordingError(ValueError):
    """A recording that cannot be used (the message names the file and what is missing)."""


@dataclass(frozen=True)
class Recording:
    """What one MCAP recording holds, as arrays (SI, rig clock in s).

    Attributes:
        path: the .mcap file.
        design: the latched design document (`metarig-design/1` + rig context), or None.
        config: the latched rig configuration (plan + node parameters), or None.
        shaker_t_s, shaker_u_m: [n] measured shaker position.
        stage_t_s, stage_closing_m: [m] measured total stage closing (bottom + top travel).
        stage_hold_s: rig time the stages first reported `holding`, or None.
        frame_t_s: [n_f] stamps of the camera frames.
        m_per_px: image scale from the camera info (1 / K[0]), or None.
        pose_messages: topic -> decoded `UnitPose2DArray` records in time order.
    """

    path: Path
    design: dict | None
    config: dict | None
    shaker_t_s: np.ndarray
    shaker_u_m: np.ndarray
    stage_t_s: np.ndarray
    stage_closing_m: np.ndarray
    stage_hold_s: float | None
    frame_t_s: np.ndarray
    m_per_px: float | None
    pose_messages: dict[str, list] = field(default_factory=dict)

    def poses(self, topic: str, reference_m: np.ndarray) -> tuple[Trajectory, float]:
        """The poses of `topic` as a `Trajectory` with t from its first stamp, and that stamp
        on the rig clock (s). `reference_m` [n, 2]: the centroids the absolute poses are
        measured from (the design's)."""
        msgs = self.pose_messages.get(topic) or []
        if not msgs:
            raise RecordingError(f"{self.path}: no poses on {topic}")
        traj = from_pose_messages(msgs, reference_m)
        return traj, stamp_s(msgs[0])

    @property
    def closing_speed_m_s(self) -> float | None:
        """The stages' configured closing speed, m/s, from the recorded node parameters."""
        return configured_closing_speed(self.config)


def configured_closing_speed(config: dict | None) -> float | None:
    """The stages' configured closing speed, m/s, from a rig configuration (`/rig/config`)."""
    params = ((config or {}).get("node_parameters") or {}).get("stage") or {}
    v = params.get("device.closing_speed_m_s")
    return float(v) if v else None


def total_closing_m(positions) -> float:
    """Total stage closing, m: the sum of both stages' travel toward the centre."""
    return float(np.sum(positions))


def is_holding(state: str) -> bool:
    """Whether a `/stage/state` text says the stages hold their target."""
    return str(state).startswith("holding")


def stamp_s(msg) -> float:
    """A message's header stamp, s (rclpy messages and decoded MCAP records alike)."""
    st = msg.header.stamp
    return int(st.sec) + 1e-9 * int(st.nanosec)


def resolve_mcap(source: str | Path) -> Path:
    """A run folder (holding one .mcap) or an .mcap file -> the .mcap path."""
    p = Path(source)
    if p.is_dir():
        files = sorted(p.glob("*.mcap"))
        if len(files) != 1:
            raise RecordingError(f"{p}: expected one .mcap recording in the folder, found "
                                 f"{len(files)}")
        return files[0]
    if not p.exists():
        raise RecordingError(f"{p}: no such file or folder")
    if p.suffix != ".mcap":
        raise RecordingError(f"{p}: not an .mcap recording or a run folder")
    return p


def read_recording(source: str | Path) -> Recording:
    """Read everything but the frame pixels from a recording (run folder or .mcap file).

    Raises:
        RecordingError: unreadable, unfinished or not a rig recording.
    """
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = resolve_mcap(source)
    wanted = {topics.RIG_DESIGN.name, topics.RIG_CONFIG.name, topics.SHAKER_JOINTS.name,
              topics.STAGE_JOINTS.name, topics.STAGE_STATE.name, topics.CAMERA_INFO.name,
              topics.POSES.name, topics.GROUND_TRUTH.name}
    design = config = None
    shaker, stage, frames = [], [], []
    hold = m_per_px = None
    poses: dict[str, list] = {topics.POSES.name: [], topics.GROUND_TRUTH.name: []}
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            if reader.get_summary() is None:
                raise RecordingError(f"{path}: MCAP file has no summary (unfinished recording? "
                                     "run `metarig recover` on it first)")
            for _s, ch, rec, msg in reader.iter_decoded_messages(topics=sorted(wanted),
                                                                 log_time_order=True):
                topic = ch.topic
                if topic == topics.RIG_DESIGN.name:
                    design = json.loads(msg.data)
                elif topic == topics.RIG_CONFIG.name:
                    config = json.loads(msg.data)
                elif topic == topics.SHAKER_JOINTS.name and len(msg.position):
                    shaker.append((stamp_s(msg), float(msg.position[0])))
                elif topic == topics.STAGE_JOINTS.name and len(msg.position):
                    stage.append((stamp_s(msg), total_closing_m(msg.position)))
                elif topic == topics.STAGE_STATE.name:
                    if hold is None and is_holding(msg.data):
                        hold = rec.log_time * 1e-9
                elif topic == topics.CAMERA_INFO.name:
                    frames.append(stamp_s(msg))
                    if m_per_px is None and msg.k[0] > 0:
                        m_per_px = 1.0 / float(msg.k[0])
                else:
                    poses[topic].append(msg)
    except RecordingError:
        raise
    except (OSError, ValueError, json.JSONDecodeError) as exc:
        raise RecordingError(f"{path}: not a readable recording ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - the mcap reader raises assorted types
        raise RecordingError(f"{path}: not a readable MCAP recording ({exc}); cut short? "
                             "`metarig recover` salvages what it can") from None
    sh = np.array(sorted(shaker)).reshape(-1, 2)
    sg = np.array(sorted(stage)).reshape(-1, 2)
    return Recording(path=path, design=design, config=config, shaker_t_s=sh[:, 0],
                     shaker_u_m=sh[:, 1], stage_t_s=sg[:, 0], stage_closing_m=sg[:, 1],
                     stage_hold_s=hold, frame_t_s=np.array(sorted(frames)), m_per_px=m_per_px,
                     pose_messages=poses)
