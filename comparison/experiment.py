"""The engine on exactly the measured input: shaker (or driven units) and stage closing.

Times are on the rig clock: s since the rig started at rest (t = 0), as the recording's stamps.
A recording usually starts after the stages have pre-compressed the sample and settled; the
stage closing before its first sample is rebuilt as the rig made it: a constant-speed ramp from
rest that ended when the stages reported `holding` (or at the first sample).
"""

from dataclasses import dataclass

import numpy as np

from metarig.trajectory import Trajectory


@dataclass(frozen=True)
class MeasuredInput:
    """What drove the sample: the input displacement and the stage closing (SI, rig clock).

    Attributes:
        t_s, u_m: [n] input displacement into the specimen, m, at times s.
        source: "tracked" (the driven units' tracked motion) or "shaker" (its joint state).
        stage_t_s, stage_closing_m: [m] total closing of the two stage rows, or None.
        precompression_m: the closing reached before the pulse, m (0 without stages).
    """

    t_s: np.ndarray
    u_m: np.ndarray
    source: str
    stage_t_s: np.ndarray | None
    stage_closing_m: np.ndarray | None
    precompression_m: float


def input_motion(poses: Trajectory, input_units, shaker_t_s=None, shaker_u_m=None,
                 frame_t0_s: float = 0.0) -> tuple[np.ndarray, np.ndarray, str]:
    """The measured input: the driven units' mean tracked u where all of them were tracked in
    every frame, else the shaker's measured position.

    Args:
        poses: tracked motion, t relative to the first frame at rig time `frame_t0_s`.
        input_units: ids of the driven units.
        shaker_t_s, shaker_u_m: [n] shaker position record on the rig clock (or None).

    Raises:
        ValueError: the driven units were not tracked and there is no shaker record.
    """
    ids = np.asarray(input_units, np.int64)
    if ids.size and poses.valid[:, ids].all():
        return poses.t + frame_t0_s, poses.q[:, ids, 0].mean(axis=1), "tracked"
    if shaker_t_s is None or len(shaker_t_s) < 2:
        raise ValueError("the driven units were not tracked in every frame and the recording "
                         "holds no shaker joint states: no measured input")
    return np.asarray(shaker_t_s, np.float64), np.asarray(shaker_u_m, np.float64), "shaker"


def stage_history(stage_t_s, stage_closing_m, closing_speed_m_s: float,
                  hold_t_s: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Stage closing from rest: the measured samples, preceded by the rig's ramp if they start
    pre-compressed (holding), or if they start during the closing (a recording from rest: the
    first sample comes one sample period after the stages set off) by the ramp at the closing
    speed that reaches the first sample. Returns (t [m'] s, closing [m'] m, the closing
    reached: at the first sample when it holds, else when the stages reported `holding`, else
    at the last sample, m)."""
    t = np.asarray(stage_t_s, np.float64)
    c = np.asarray(stage_closing_m, np.float64)
    head = c[: max(1, min(10, c.size))]
    reached = float(np.median(head))
    if float(np.ptp(head)) > max(1e-7, 1e-3 * abs(reached)):  # moving: the record holds the ramp
        reached = float(np.interp(hold_t_s, t, c)) if hold_t_s is not None else float(c[-1])
        if t[0] <= 0 or abs(c[0]) < 1e-9:
            return t, c, reached
        start = max(0.0, t[0] - abs(c[0]) / closing_speed_m_s)
        head_t, head_c = ([0.0, start], [0.0, 0.0]) if start > 0 else ([0.0], [0.0])
        return np.r_[head_t, t], np.r_[head_c, c], reached
    if abs(reached) < 1e-7 or t[0] <= 0:
        return t, c, reached
    end = min(t[0], hold_t_s) if hold_t_s is not None else t[0]
    start = max(0.0, end - abs(reached) / closing_speed_m_s)
    head_t, head_c = [start, end], [0.0, reached]
    if start > 0:
        head_t, head_c = [0.0, *head_t], [0.0, *head_c]
    keep = t > end
    return np.r_[head_t, t[keep]], np.r_[head_c, c[keep]], reached


def measured_input_of(scene, poses: Trajectory, frame_t0_s: float, shaker_t_s=None,
                      shaker_u_m=None, stage_t_s=None, stage_closing_m=None,
                      closing_speed_m_s: float | None = None,
                      stage_hold_s: float | None = None) -> MeasuredInput:
    """What drove the recorded sample (arguments as `compare_experiment`): the input
    (`input_motion`) and, in a scene with stages, the stage closing from rest
    (`stage_history`)."""
    t_in, u_in, source = input_motion(poses, scene.input_units, shaker_t_s, shaker_u_m, frame_t0_s)
    st = sc = None
    reached = 0.0
    if len(scene.stage_units_top) and stage_t_s is not None and len(stage_t_s) >= 2:
        st, sc, reached = stage_history(stage_t_s, stage_closing_m,
                                        closing_speed_m_s or 0.25 * scene.sample_height_m,
                                        stage_hold_s)
    return MeasuredInput(t_in, u_in, source, st, sc, reached)


def engine_input(measured: MeasuredInput) -> tuple[np.ndarray, np.ndarray]:
    """(t s, u m) of the input as the engine takes it: smoothed (`smooth_input`) and at rest
    from t = 0 to the record's start."""
    from design_engine.solve.run import smooth_input

    t_in, u_in = smooth_input(measured.t_s, measured.u_m)
    if t_in[0] > 0:
        t_in, u_in = np.r_[0.0, t_in], np.r_[0.0, u_in]
    return t_in, u_in


def simulate_measured(scene, frame_t_s: np.ndarray, measured: MeasuredInput,
                      config=None) -> Trajectory:
    """The engine's motion of `scene` at the frame times (rig clock, s) under the measured input,
    from rest at t = 0; q from the undeformed reference, as the engine gives it."""
    from design_engine.solve.run import simulate_rig

    t_in, u_in = engine_input(measured)
    has_stages = len(scene.stage_units_top) > 0 and measured.stage_t_s is not None
    return simulate_rig(scene, np.asarray(frame_t_s, np.float64), t_in, u_in,
                        measured.stage_t_s if has_stages else None,
                        measured.stage_closing_m if has_stages else None, config=config)


def scene_of_design(doc: dict):
    """The nominal engine scene of a recorded design document (the rig's `/rig/design`).

    The document names the scene preset and lattice size; a `design_m` vector (metres), when
    present, replaces the preset's periodic design; `material_si` (SI values of the sample's
    material file), when present, replaces the default material. True-parameter factors of a
    perturbed simulated specimen are deliberately ignored: the comparison tests the nominal model.

    Raises:
        ValueError: the document does not describe a scene.
    """
    from design_engine.physics.geometry import InvalidDesignError
    from design_engine.physics.scenes import build_scene

    try:
        nx, ny = (doc["nx"], doc["ny"]) if "nx" in doc else doc["lattice"]["shape"]
        scene = build_scene(doc["scene"], nx=int(nx), ny=int(ny),
                            bias_angle_deg=doc.get("bias_angle_deg"), strain=0.0)
        if doc.get("design_m") is not None:
            scene = scene.with_design(np.asarray(doc["design_m"], np.float64) * 1e3)
        if doc.get("material_si") is not None:
            from design_engine.physics.material_file import with_material

            scene = with_material(scene, dict(doc["material_si"]))
    except (KeyError, TypeError) as exc:
        raise ValueError(f"the design document lacks the scene or lattice size ({exc})") from None
    except InvalidDesignError as exc:
        raise ValueError(f"the recorded design is invalid: {exc}") from None
    return scene


@dataclass(frozen=True)
class ExperimentComparison:
    """One experiment against its simulation: inputs used, both trajectories and the result.

    Attributes:
        measured: tracked motion, t from the first frame, q from the first frame.
        simulated: the engine's motion at the same times, q from the same first frame.
        simulated_abs: the engine's motion with q from the undeformed design (for drawing).
        input: what drove the simulation.
        comparison: fields and errors (`comparison.metrics.Comparison`).
        frame_t0_s: rig time of the first frame, s.
    """

    measured: Trajectory
    simulated: Trajectory
    simulated_abs: Trajectory
    input: MeasuredInput
    comparison: object
    frame_t0_s: float


def compare_experiment(scene, poses: Trajectory, frame_t0_s: float, shaker_t_s=None,
                       shaker_u_m=None, stage_t_s=None, stage_closing_m=None,
                       closing_speed_m_s: float | None = None, stage_hold_s: float | None = None,
                       config=None) -> ExperimentComparison:
    """Simulate the measured experiment and compare (spec 12.4).

    Args:
        scene: the nominal scene of the design on the rig (`scene_of_design`).
        poses: tracked motion, t [n_t] s from the first frame, q from the reference frame.
        frame_t0_s: rig time of the first frame, s.
        shaker_t_s, shaker_u_m: measured shaker position record (rig clock), or None.
        stage_t_s, stage_closing_m: measured total stage closing (rig clock), or None.
        closing_speed_m_s: the stages' closing speed (rebuilds the ramp before the record).
        stage_hold_s: rig time the stages reported `holding`, or None.

    Raises:
        ValueError: inconsistent inputs (the message says which).
    """
    from comparison.metrics import compare, pulse_onset
    from design_engine.physics.regions import row_units

    if poses.n_units != scene.n_units:
        raise ValueError(f"the recording tracks {poses.n_units} units but the design has "
                         f"{scene.n_units}: the design does not match the recording")
    if poses.n_t < 3:
        raise ValueError(f"the recording holds {poses.n_t} frames; the comparison needs 3 or more")
    measured_input = measured_input_of(scene, poses, frame_t0_s, shaker_t_s, shaker_u_m,
                                       stage_t_s, stage_closing_m, closing_speed_m_s,
                                       stage_hold_s)
    t_in, u_in = measured_input.t_s, measured_input.u_m
    sim_abs = simulate_measured(scene, poses.t + frame_t0_s, measured_input, config=config)
    if not np.all(np.isfinite(sim_abs.q)):
        raise ValueError("the simulation of the measured experiment did not finish (non-finite)")
    sim_abs = Trajectory(t=poses.t, q=sim_abs.q, qdot=sim_abs.qdot)
    simulated = Trajectory.from_positions(poses.t, sim_abs.q - sim_abs.q[0])
    onset = pulse_onset(t_in - frame_t0_s, u_in)
    target = np.unique(np.concatenate([np.asarray(v) for v in scene.targets.values()]))
    row = row_units(scene.lattice, scene.line_row)
    measured = Trajectory.from_positions(poses.t, poses.q - np.nan_to_num(poses.q[0]),
                                         quality=poses.quality, lost=poses.lost,
                                         sigma=poses.sigma)
    result = compare(measured, simulated, scene.unit_masses_kg(), scene.unit_inertias_kgm2(),
                     target, row, onset)
    return ExperimentComparison(measured, simulated, sim_abs, measured_input, result, frame_t0_s)
