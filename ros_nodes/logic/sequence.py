"""The experiment procedure: plan, phases, node parameters and the run-folder summary (pure).

A run: take the reference image of the unloaded sample, start recording, pre-compress to `strain`
at the stage rate, settle, start the camera, fire the pulse after `pre_trigger_s`, capture for
`record_s`, stop the devices, finish the
recording, write the run folder. `ExperimentPlan` holds the numbers; `node_parameters` turns a
plan into the parameters of every node on the simulated rig, `lab_node_parameters` on the
devices of a lab file (system clock); `Phase` names the steps (published on `/rig/phase`).
"""

import json
import math
from dataclasses import asdict, dataclass
from enum import Enum
from pathlib import Path

from hardware_sim.specimen import Imperfections
from metarig.fields import param
from ros_nodes import topics

RECORDING_NAME = "recording.mcap"
SUMMARY_NAME = "run.json"
DESIGN_NAME = "design.json"
IMAGE_TOPIC = topics.IMAGE.name


class Phase(str, Enum):
    STARTING = "starting"
    PRECOMPRESS = "precompress"
    SETTLE = "settle"
    RECORD = "record"
    PULSE = "pulse"
    DEVELOP = "develop"
    STOP = "stop"
    DONE = "done"
    ABORTED = "aborted"
    COMPENSATE = "compensate"  # after starting, with plan.compensate


@dataclass(frozen=True, slots=True)
class ExperimentPlan:
    """The numbers of one experiment (SI)."""

    scene: str = param("precompression-24x18", "design_engine scene of the sample")
    nx: int = param(24, "units along x", 2, 200)
    ny: int = param(16, "units along y", 2, 200)
    design: str = param("", "design file (metarig-design/1) of the sample, e.g. from `metarig "
                        "design`; its lattice sets nx, ny (empty: the scene's periodic design)")
    material: str = param("", "material file (metarig-material/1) of the sample (empty: the default)")
    material_si: str = param("", "the material file's SI values, JSON, as `metarig rig` read "
                             "and checked them (once; the nodes take these, not the file)")
    strain: float = param(0.02, "pre-compression strain", 0.0, 0.09)
    settle_s: float = param(0.02, "hold after pre-compression before recording, s", 0.0, 60.0)
    pre_trigger_s: float = param(0.005, "recording before the pulse starts, s", 0.0, 10.0)
    record_s: float = param(0.1, "camera capture length from the start of recording, s",
                            0.001, 60.0)
    waveform: str = param("pulse", "shaker waveform", choices=("pulse", "burst"))
    amplitude_m: float = param(0.0075, "shaker amplitude A, m", 0.0, 0.05)
    frequency_hz: float = param(30.0, "shaker frequency f, Hz", 0.1, 1000.0)
    cycles: float = param(1.0, "burst length, periods", 0.0, 1000.0)
    compensate: bool = param(False, "before the test, iterate the shaker's drive against its "
                             "measured motion until the measured pulse matches the request "
                             "(/shaker/compensate), then fire the compensated drive")
    fps: float = param(1000.0, "camera frame rate, Hz", 1.0, 100000.0)
    width: int = param(640, "frame width, px", 8, 8192)
    height: int = param(480, "frame height, px", 8, 8192)
    m_per_px: float = param(6.0e-4, "image scale, m/px", 1e-7, 1.0)
    perturb: float = param(0.0, "relative spread of the specimen's true parameters", 0.0, 0.5)
    specimen: Imperfections = param(Imperfections, "how the simulated sample differs from its "
                                    "model (the rig's truth only)")
    seed: int = param(0, "seed of all simulated noise", 0, 2**31 - 1)
    clock_step_s: float = param(0.001, "simulated clock step, s", 1e-5, 0.1)
    real_time_factor: float = param(0.5, "simulated seconds per wall second (0: as fast as "
                                      "possible)", 0.0, 100.0)
    timeout_s: float = param(600.0, "wall-time limit of any one wait, s", 1.0, 86400.0)

    def __post_init__(self):
        for name in ("strain", "settle_s", "pre_trigger_s", "record_s", "amplitude_m",
                     "frequency_hz", "fps", "m_per_px", "clock_step_s"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"{name} must be finite, got {v}")
        if self.record_s < self.pre_trigger_s:
            raise ValueError("record_s must cover pre_trigger_s")
        if self.width < 8 or self.height < 8:
            raise ValueError("frames must be at least 8x8 px")

    @property
    def sample_height_m(self) -> float:
        """Nominal height (ny - 1) x 15 mm pitch that the strain refers to, m."""
        return (self.ny - 1) * 0.015

    def expected_frames(self, t_start_s: float) -> int:
        """Frames at multiples of 1/fps inside the capture window starting at t_start_s."""
        k0 = max(1, math.ceil(t_start_s * self.fps - 1e-9))
        k1 = math.floor((t_start_s + self.record_s) * self.fps + 1e-9)
        return max(0, k1 - k0 + 1)

    def as_dict(self) -> dict:
        return asdict(self)


def node_parameters(plan: ExperimentPlan, out_dir: Path) -> dict[str, dict]:
    """Parameters of every node for a simulated run of `plan` (all on simulated time)."""
    common = {"use_sim_time": True}
    return {
        "shaker": {**common, "seed": plan.seed},
        "stage": {**common, "seed": plan.seed + 1,
                  "device.sample_height_m": plan.sample_height_m,
                  "device.closing_speed_m_s": 0.25 * plan.sample_height_m},
        "camera": {**common, "source": "sim", "fps": plan.fps, "width": plan.width,
                   "height": plan.height, "m_per_px": plan.m_per_px, "scene": plan.scene,
                   "nx": plan.nx, "ny": plan.ny, "design_path": plan.design,
                   "material_path": plan.material, "material_si": plan.material_si,
                   "perturb": plan.perturb, "seed": plan.seed,
                   **{f"specimen.{k}": v for k, v in asdict(plan.specimen).items()},
                   "rate_factor": 0.0},
        "recorder": {**common, "path": str(out_dir / RECORDING_NAME)},
    }


# plan fields that only the simulated rig uses (its camera renderer, specimen and clock); a lab
# run refuses them (`metarig rig --hardware lab`)
SIM_ONLY = ("width", "height", "perturb", "specimen", "seed", "real_time_factor")
# a Zaber reading is two serial round trips: the stage node samples the lab stages this often
LAB_STAGE_RATE_HZ = 50.0
# nothing paces the nodes on the system clock: a shaker node at 1 kHz beside the camera stream
# fell behind by seconds and lost samples here (2 cores, load 3); at 500 Hz it lost none. A
# function generator's joint states are its commanded motion (the waveform itself is on
# /shaker/command at command_rate_hz).
LAB_SHAKER_RATE_HZ = 500.0


def lab_node_parameters(plan: ExperimentPlan, out_dir: Path, lab_file: Path,
                        frame_rate_hz: float = 0.0) -> dict[str, dict]:
    """Parameters of every node for a run of `plan` on the devices of `lab_file`, on the system
    clock. frame_rate_hz: the camera's rate (0: the lab file's)."""
    lab = {"use_sim_time": False, "hardware": "lab", "lab_file": str(lab_file)}
    return {
        "shaker": {**lab, "rate_hz": LAB_SHAKER_RATE_HZ},
        "stage": {**lab, "rate_hz": LAB_STAGE_RATE_HZ},
        "camera": {**lab, "frame_rate_hz": frame_rate_hz, "m_per_px": plan.m_per_px},
        "recorder": {"use_sim_time": False, "path": str(out_dir / RECORDING_NAME)},
    }


def summary(plan: ExperimentPlan, params: dict, report: dict | None, timings: dict,
            events: list[tuple[str, float]], status: str, clock: str = "simulated") -> dict:
    """The machine-readable run summary (`run.json`).

    `frames` compares the frames the camera published (`timings["frames"]`) with those in the
    recording: `lost` counts every frame missing from the file, trailing ones included (frames
    still in transit when the recording stopped leave no gap for the recorder to see); and with
    the plan's capture window from the `record` phase on, `expected` (published differs when a
    node's clock lagged the sequencer's at the camera's start or stop: recorded, not hidden);
    and from a real camera (`timings["camera_lost"]`), `lost_at_camera`: frames the camera's
    frame counter says it took but never delivered (they were never published either), and
    `received_at_camera` (`timings["camera_received"]`): those the driver delivered to the node
    (all of them are published unless the node lost some without counting them).
    `clock` is the rig time of `phases` ("simulated", from 0; "system": the host's clock, s
    since the epoch); on the system clock a free-running camera is started by a call, not at a
    held time, so no `expected` count is given.
    """
    out = {"status": status, "clock": clock, "plan": plan.as_dict(), "node_parameters": params,
           "recording": report, "timings_s": timings,
           "phases": [{"phase": p, "sim_time_s": t} for p, t in events]}
    if "frames" in timings and report is not None:
        published = int(timings["frames"])
        recorded = int(report.get("topics", {}).get(IMAGE_TOPIC, {}).get("count", 0))
        out["frames"] = {"published": published, "recorded": recorded,
                         "lost": max(0, published - recorded)}
        if "camera_lost" in timings:
            out["frames"]["lost_at_camera"] = int(timings["camera_lost"])
        if "camera_received" in timings:
            out["frames"]["received_at_camera"] = int(timings["camera_received"])
        t_rec = next((t for ph, t in events if ph == Phase.RECORD.value), None)
        if t_rec is not None and clock == "simulated":
            out["frames"]["expected"] = plan.expected_frames(t_rec)
    return out


def write_summary(out_dir: Path, data: dict) -> Path:
    path = out_dir / SUMMARY_NAME
    path.write_text(json.dumps(data, indent=2, default=str))
    return path
