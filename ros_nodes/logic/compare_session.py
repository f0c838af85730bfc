"""What the comparison node has heard, and the comparison made from it (pure: no rclpy).

`CompareSession` buffers what arrives on the rig topics (pose messages, shaker and stage
samples, the stage state, the latched design and configuration, the phase) as plain values and
compares on request: the same steps as `metarig compare` on a recording
(`ros_nodes.logic.comparison_run`). Thread-safe: callbacks add while a worker compares.
Times on the rig clock, s; lengths m.
"""

import json
import threading
from dataclasses import dataclass

import numpy as np

from metarig.polygon import area_centroids
from metarig.trajectory import Trajectory, from_pose_messages
from ros_nodes import topics
from ros_nodes.logic import comparison_run as run
from ros_nodes.logic.comparison_run import CompareError
from ros_nodes.logic.recording import configured_closing_speed, is_holding, stamp_s
from ros_nodes.logic.sequence import Phase

AUTO_PHASES = (Phase.STOP.value, Phase.DONE.value)  # `/rig/phase` values that trigger `auto`
NEW_RUN_PHASE = Phase.STARTING.value  # a new experiment: the measurement so far is dropped
LIVE = "live"  # the summary's `recording` of a comparison made from topics


@dataclass(frozen=True)
class SessionResult:
    """One finished comparison.

    Attributes:
        ec: `comparison.experiment.ExperimentComparison`.
        summary: the summary dict (keys as `metarig compare`'s summary.json).
        scene: the design's nominal scene; polygons: its outlines [n, k, 2] m.
        poses: the measured `Trajectory` (t from the first frame, s).
        reference_m: [n, 2] the design's centroids (absolute poses are measured from them).
    """

    ec: object
    summary: dict
    scene: object
    polygons: np.ndarray
    poses: Trajectory
    reference_m: np.ndarray


def _json(doc) -> dict:
    if isinstance(doc, dict):
        return doc
    try:
        out = json.loads(doc)
    except (TypeError, ValueError) as exc:
        raise CompareError(f"not a JSON document ({exc})") from None
    if not isinstance(out, dict):
        raise CompareError("not a JSON object")
    return out


class CompareSession:
    """Buffers of one experiment as heard on the topics; `compare()` runs the comparison.

    Args:
        min_frames: fewer pose frames than this are refused (at least 3).
        poses_topic: where the poses come from (named in the summary and the refusals).
    """

    def __init__(self, min_frames: int = run.MIN_FRAMES, poses_topic: str = topics.POSES.name):
        self.min_frames = int(min_frames)
        self.poses_topic = poses_topic
        self._lock = threading.Lock()
        self._design: dict | None = None
        self._config: dict | None = None
        self._auto_at = 0  # frames held at the last automatic comparison
        self.clear()

    # what arrives -----------------------------------------------------------------------------
    def clear(self) -> None:
        """Drop the measurement (poses, shaker, stage); the design and config stay."""
        with self._lock:
            self._poses: list = []
            self._shaker: list[tuple[float, float]] = []
            self._stage: list[tuple[float, float]] = []
            self._hold_s: float | None = None
            self._auto_at = 0

    def set_design(self, doc: dict | str) -> None:
        """The design document (`/rig/design`, JSON text or dict). Raises `CompareError` for
        text that is not a JSON object."""
        doc = _json(doc)
        with self._lock:
            self._design = doc

    def set_config(self, doc: dict | str) -> None:
        """The rig configuration (`/rig/config`): the stages' closing speed comes from it."""
        doc = _json(doc)
        with self._lock:
            self._config = doc

    def add_poses(self, msg) -> None:
        """One `UnitPose2DArray` frame (rclpy message or decoded record: fields are read)."""
        with self._lock:
            self._poses.append(msg)

    def add_shaker(self, t_s: float, u_m: float) -> None:
        """One shaker position sample: stamp s, position m."""
        with self._lock:
            self._shaker.append((float(t_s), float(u_m)))

    def add_stage(self, t_s: float, closing_m: float) -> None:
        """One stage sample: stamp s, total closing (both stages' travel) m."""
        with self._lock:
            self._stage.append((float(t_s), float(closing_m)))

    def stage_state(self, state: str, t_s: float) -> None:
        """A `/stage/state` text received at rig time t_s (s): the first `holding` is kept."""
        with self._lock:
            if self._hold_s is None and is_holding(state):
                self._hold_s = float(t_s)

    def phase(self, name: str) -> bool:
        """A `/rig/phase` value; True when it asks for the automatic comparison (stop or done,
        with poses not compared automatically yet). `starting` clears the measurement."""
        if name == NEW_RUN_PHASE:
            self.clear()
            return False
        with self._lock:
            n = len(self._poses)
            if name in AUTO_PHASES and n > 0 and n != self._auto_at:
                self._auto_at = n
                return True
        return False

    @property
    def n_frames(self) -> int:
        with self._lock:
            return len(self._poses)

    @property
    def has_design(self) -> bool:
        with self._lock:
            return self._design is not None

    # the comparison ---------------------------------------------------------------------------
    def refusal(self) -> str | None:
        """The one-line reason a comparison is impossible that is known without simulating (no
        design, too few frames), or None."""
        with self._lock:
            n, has_design = len(self._poses), self._design is not None
        need = max(self.min_frames, run.MIN_FRAMES)
        if not has_design:
            return f"no design received on {topics.RIG_DESIGN.name}"
        if n == 0:
            return f"no poses received on {self.poses_topic}"
        if n < need:
            return f"only {n} frames on {self.poses_topic}; the comparison needs {need} or more"
        return None

    def compare(self) -> SessionResult:
        """Compare what has been heard with its simulation (seconds of work).

        Raises:
            CompareError: with a one-line reason (no design, too few frames, every unit lost,
                a design that does not match the poses, an input the engine refuses).
        """
        reason = self.refusal()
        if reason is not None:
            raise CompareError(reason)
        with self._lock:
            doc, config, hold = self._design, self._config, self._hold_s
            msgs = sorted(self._poses, key=stamp_s)
            shaker = np.array(sorted(self._shaker), np.float64).reshape(-1, 2)
            stage = np.array(sorted(self._stage), np.float64).reshape(-1, 2)
        scene, polygons = run.design_scene(doc)
        reference = area_centroids(polygons)
        try:
            poses = from_pose_messages(msgs, reference)
        except ValueError as exc:
            raise CompareError(f"the poses on {self.poses_topic} do not match the design "
                               f"({exc})") from None
        run.check_poses(scene, poses, min_frames=self.min_frames)
        t0 = stamp_s(msgs[0])
        ec = run.simulate_and_compare(scene, poses, t0, shaker[:, 0], shaker[:, 1], stage[:, 0],
                                      stage[:, 1], configured_closing_speed(config), hold)
        summary = run.summary_of(ec, scene, self.poses_topic, LIVE)
        return SessionResult(ec, summary, scene, polygons, poses, reference)
