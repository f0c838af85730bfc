"""The loop closed: design, test on the rig, calibrate, redesign from what the rig measured.

`run_loop` runs rounds into `DIR/round-1/`, `DIR/round-2/`, ... Each round's steps, each in
its own folder (or file), in order:

    material.toml  the round's model material (round 1: `--material` or the default; round k:
                   round k-1's model updated with what its calibration determined)
    design/        `metarig design TASK --material material.toml` (or the given `--design`)
    rig/           `metarig rig --design design/design.json ...`: the run folder (recording,
                   tracked poses, comparison with the design document's nominal model)
    objective/     `objective.json`: the task's objective measured (from the tracked poses)
                   and predicted (the round's model on the measured input), `target_ke.npz`
    identify/      `metarig rig` on the same specimen with the identification pulse (a short
                   pulse and a long record: `IDENTIFY_*`), the experiment the calibration
                   fits (`--identify task`: none, the calibration fits rig/)
    calibrate/     `metarig calibrate identify/ --material material.toml`: calibration.json,
                   material.toml

Each step is a `metarig` command in its own process (its progress goes to this terminal), so the
loop runs exactly what a user would type. A step is finished when its folder holds `step.json`
(written last: the command, its wall time); a folder without it is the remains of an
interrupted step and is redone (`metarig design` resumes from its checkpoint), so Ctrl-C loses
no finished step and a second invocation recomputes nothing that is finished.

Round k > 1 starts its design from round k-1's (`metarig design --initial`): a redesign
improves the design that was tested, with the material that its test calibrated; round 1 starts
from the task's initial design (or, with `design_seed`, a seeded random one, `metarig design
--seed`).

Why an identification experiment: the task's input is chosen for the objective, not to show the
material. The focusing task's 30 Hz pulse drives the small lattice nearly quasi-statically (its
shear modes ring at about 150 Hz), and the quasi-static shape depends on ratios of stiffnesses,
not on their size, so a calibration on it may determine nothing (k_shear 3466 +- 5900 N/m on
the task's experiment in README "Closing the loop"). A 10 ms pulse rings those modes, and a
150 ms record follows them until they decay (`benchmarks/bench_loop.py` for what it determines).

The rig is the same in every round: the same flags, so the same simulated specimen statistics,
print-wide errors and seed (the specimen's per-ligament draws follow the seed: the same seed
draws the same scatter per ligament index). A calibrated parameter that its calibration calls
undetermined is not carried into the next model (its value says nothing); stiffnesses that it
determines only in combination (the identification pulse sees k_shear, barely k_bend) are
carried as one common scale of the fitted stiffnesses, so that the model keeps its stiffness
ratios (`common_stiffness_scale`).

Units: SI at every interface; the objective is the task's (the mean over the window's samples of
the target's kinetic energy, J, weighted and summed over the task's terms).
"""

import json
import logging
import math
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ros_nodes.logic.loop_objective import ObjectiveError, objective_of_run
from ros_nodes.logic.loop_record import write_loop_rrd

log = logging.getLogger("metarig.loop")

STEP_DONE = "step.json"
SUMMARY_NAME = "loop.json"
RRD_NAME = "loop.rrd"
MATERIAL_NAME = "material.toml"
DESIGN, RIG, OBJECTIVE, IDENTIFY, CALIBRATE = "design", "rig", "objective", "identify", "calibrate"
# rig flags the loop sets itself (from the task and the round)
LOOP_RIG_FLAGS = ("--design", "--out", "--scene", "--material", "--no-compare", "--nx", "--ny",
                  "--strain", "--amplitude", "--frequency", "--waveform")
FRAME_PX = (480, 360)  # default frame of the simulated camera (the demo's)
FRAME_FILL = 1.2  # the frame spans this much more than the undeformed sample
RECORD_MARGIN_S = 0.01  # capture beyond the task's window
PRE_TRIGGER_S = 0.005  # the rig's default recording before the pulse
# the identification experiment: a 1 mm pulse at 100 Hz (10 ms long), a 150 ms capture
IDENTIFY_AMPLITUDE_M, IDENTIFY_FREQUENCY_HZ, IDENTIFY_RECORD_S = 1e-3, 100.0, 0.15
# what the calibration fits: the identification pulse, or the task's own experiment
IDENTIFY_CHOICES = ("pulse", "task")


class LoopError(RuntimeError):
    """A step of the loop failed or its inputs are unusable (one line, naming the step)."""


@dataclass(frozen=True, slots=True)
class LoopPlan:
    """What `metarig loop` runs.

    Attributes:
        task: task preset name or task file.
        out: the loop's folder.
        rounds: design-test-calibrate rounds.
        design: design file of round 1 (None: optimise one).
        material: the nominal material file of round 1's model (None: the default).
        size: lattice size (nx, ny), or None for the task's.
        max_evals: the design budget of each round (None: the task's).
        rig_args: further `metarig rig` flags (the specimen's: `--perturb`, `--seed`,
            `--specimen-*`; the camera's), the same in every round.
        fit: parameters the calibration fits (None: `metarig calibrate`'s default).
        workers: tracker processes (None: all cores).
        identify: what the calibration fits: "pulse", an identification experiment on the
            same specimen (`IDENTIFY_*`), or "task", the task's own experiment.
        warm_start: round k > 1 designs from round k-1's design (False: from round 1's start).
        design_seed: round 1 designs from the task's periodic design plus the seeded random
            perturbation of `metarig design --seed` (None: the task's initial design).
    """

    task: str
    out: Path
    rounds: int = 2
    design: Path | None = None
    material: Path | None = None
    size: tuple[int, int] | None = None
    max_evals: int | None = None
    rig_args: tuple[str, ...] = field(default=())
    fit: str | None = None
    workers: int | None = None
    identify: str = "pulse"
    warm_start: bool = True
    design_seed: int | None = None


# --- the task on the rig ----------------------------------------------------------------------


def load_plan_task(plan: LoopPlan):
    """The task of the plan, checked for what the rig can test (one scene, kinetic-energy
    objective terms, a pulse or burst input)."""
    from design_engine.design.task import TaskError, load_task

    try:
        task = load_task(plan.task, size=plan.size, max_evals=plan.max_evals,
                         material=plan.material)
    except (TaskError, OSError, ValueError) as exc:
        raise LoopError(f"task {plan.task}: {str(exc).splitlines()[0]}") from None
    if len(task.scenes) != 1:
        raise LoopError(f"task {task.name} has {len(task.scenes)} scenes; the rig tests one")
    if any(t.quantity != "kinetic_energy" for t in task.terms):
        raise LoopError(f"task {task.name}: the loop measures kinetic-energy objectives only")
    scene = next(iter(task.scenes.values()))
    if scene.loading.waveform not in ("pulse", "burst"):
        raise LoopError(f"task {task.name}: the rig's shaker fires a pulse or a burst, not a "
                        f"{scene.loading.waveform} input")
    return task


def _given(args, flag: str) -> bool:
    return any(a == flag or a.startswith(flag + "=") for a in args)


def _value(args, flag: str) -> float:
    for i, a in enumerate(args):
        text = a.split("=", 1)[1] if a.startswith(flag + "=") else (
            args[i + 1] if a == flag and i + 1 < len(args) else None)
        if text is not None:
            try:
                return float(text)
            except ValueError:
                raise LoopError(f"{flag} {text!r}: not a number") from None
    raise LoopError(f"{flag} needs a value")


def rig_arguments(task, rig_args, identify: bool = False) -> list[str]:
    """The `metarig rig` flags of the task's scene: scene preset, strain, amplitude (m),
    frequency (Hz), waveform, a capture covering the objective's window; a frame that holds the
    sample unless `rig_args` sets one; then `rig_args`. With `identify`, those of the
    identification experiment on the same scene and specimen: its pulse (`IDENTIFY_*`) and
    capture instead of the task's (a `--record-s` in `rig_args` still wins).

    Raises:
        LoopError: `rig_args` sets a flag that the loop sets itself.
    """
    clash = [f for f in LOOP_RIG_FLAGS if _given(rig_args, f)]
    if clash:
        raise LoopError(f"the loop sets {', '.join(clash)} of the rig itself (from the task "
                        "and the round); leave them out")
    scene = next(iter(task.scenes.values()))
    ld = scene.loading
    pre = PRE_TRIGGER_S
    if _given(rig_args, "--pre-trigger-s"):
        pre = _value(rig_args, "--pre-trigger-s")
    end_ms = scene.window_start + scene.window  # the window's end on the solver clock, ms
    record_s = math.ceil((pre + end_ms / 1e3 + RECORD_MARGIN_S) * 1e3) / 1e3
    amplitude_m, frequency_hz, waveform = float(ld.amplitude) / 1e3, float(ld.frequency) * 1e3, \
        ld.waveform
    if identify:
        amplitude_m, frequency_hz, waveform = IDENTIFY_AMPLITUDE_M, IDENTIFY_FREQUENCY_HZ, "pulse"
        record_s = round(pre + IDENTIFY_RECORD_S - PRE_TRIGGER_S, 6)
    out = ["--scene", scene.name, "--strain", repr(float(ld.strain)),
           "--amplitude", repr(amplitude_m), "--frequency", repr(frequency_hz),
           "--waveform", waveform]
    if not _given(rig_args, "--record-s"):
        out += ["--record-s", repr(record_s)]
    if not any(_given(rig_args, f) for f in ("--width", "--height", "--m-per-px")):
        nx, ny = task.lattice.shape
        pitch_m = task.lattice.spacing / 1e3
        m_per_px = FRAME_FILL * max(nx * pitch_m / FRAME_PX[0], ny * pitch_m / FRAME_PX[1])
        out += ["--width", str(FRAME_PX[0]), "--height", str(FRAME_PX[1]),
                "--m-per-px", f"{math.ceil(m_per_px * 1e6) / 1e6:.6g}"]
    return out + list(rig_args)


def check_design_fits(path: Path, task) -> None:
    """Refuse a design file that is unreadable or not of the task's lattice."""
    from design_engine.design.design_io import load_design

    try:
        lattice, _ = load_design(path)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise LoopError(f"--design {path}: not a readable design file "
                        f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
                        ) from None
    if lattice.kind != task.lattice.kind or tuple(lattice.shape) != tuple(task.lattice.shape):
        raise LoopError(f"--design {path}: a {lattice.kind} {lattice.shape[0]}x"
                        f"{lattice.shape[1]} design, but task {task.name} is on a "
                        f"{task.lattice.kind} {task.lattice.shape[0]}x{task.lattice.shape[1]} "
                        "lattice (--size sets the task's)")


# --- materials between rounds -----------------------------------------------------------------


def common_stiffness_scale(calibration: dict, start: dict | None = None) -> dict | None:
    """The common factor of the fitted stiffnesses, when the calibration determined them only
    in combination (at least one of them determined, at least one undetermined), else None.

    The identification pulse sees k_shear and barely k_bend (their fitted values are
    correlated at about -0.995: README "Closing the loop"); carrying k_shear alone would move
    the model's k_bend / k_shear ratio by the whole change of k_shear, while the quasi-static
    shape that a design works with depends on that ratio. So the fitted stiffnesses are taken
    to be off their start by one common factor s (a modulus error of the print keeps their
    ratios), and s is the point of that line that the fit makes most likely: with
    x = log(value / start) of the fitted stiffnesses and C their covariance (the stated
    relative errors with the fit's correlations), log s = (1' C^-1 x) / (1' C^-1 1), with
    sd_line(log s) = (1' C^-1 1)^(-1/2) (generalised least squares). That error holds only
    if the stiffnesses really share one factor, which the experiment does not test (on a
    strong correlation it comes out far below any single one's), so the stated error of s is
    the smallest relative stated error of a single fitted stiffness: no more precise than the
    best-determined one alone (and s is determined when any one of them is).

    `start` (SI) stands in for the fit's start values where the calibration gives none.

    Returns:
        {"names": the stiffnesses it scales, "value": s, "stderr": s * sd(log s), "log_stderr":
        sd(log s), "log_stderr_on_line": sd_line(log s), "start": their start values (SI)},
        or None.
    """
    from design_engine.calibration.fit import STIFFNESSES

    params = calibration.get("parameters", {})
    fit = calibration.get("fit") or list(params)
    names = [n for n in fit if n in STIFFNESSES and n in params]
    undetermined = set(calibration.get("undetermined", []))
    if len(names) < 2 or all(n in undetermined for n in names) or not any(
            n in undetermined for n in names):
        return None
    given = {**(start or {}), **calibration.get("start", {})}
    if any(n not in given for n in names):
        return None
    start = {n: float(given[n]) for n in names}
    x = np.array([math.log(float(params[n]["value"]) / start[n]) for n in names])
    sd = np.array([float(params[n]["stderr"]) / float(params[n]["value"]) for n in names])
    corr = np.asarray(calibration.get("correlation") or np.eye(len(fit)), np.float64)
    idx = [fit.index(n) for n in names]
    r = corr[np.ix_(idx, idx)]
    # C^-1 = D^-1 R^-1 D^-1; the pseudo-inverse holds at |correlation| = 1
    w = np.linalg.pinv(r, rcond=1e-12) / np.outer(sd, sd)
    info = float(np.ones(len(names)) @ w @ np.ones(len(names)))
    log_s = float(np.ones(len(names)) @ w @ x) / info
    on_line = 1.0 / math.sqrt(info)
    log_sd = max(on_line, float(sd.min()))
    s = math.exp(log_s)
    return {"names": names, "value": s, "stderr": s * log_sd, "log_stderr": log_sd,
            "log_stderr_on_line": on_line, "start": start}


def carried_material(model: Path | None,
                     calibration: dict) -> tuple[dict, dict, list[str], dict | None]:
    """(values, stderrs, names dropped, the common scale or None) of the next round's model:
    `model`'s values (the
    default file's where it sets none: a complete material) updated with the calibrated
    parameters and the values derived from them, except those the calibration calls
    undetermined (and what derives from them).

    Stiffnesses determined only in combination (`common_stiffness_scale`) are carried as
    their start times the common scale, every fitted one (so the model keeps its stiffness
    ratios), each with the scale's relative error; none of them is then dropped. A damping
    ratio determined beside them is carried as the ratio (its coefficients follow the carried
    stiffnesses, spec 6.3), not as the coefficients the fit derived from its own stiffnesses."""
    from design_engine.physics.material import default_si
    from design_engine.physics.material_file import SI_UNITS, read_material_file

    values, errors = read_material_file(model) if model is not None else ({}, {})
    values, errors = {**default_si(), **values}, dict(errors)
    undetermined = set(calibration.get("undetermined", []))
    derived = calibration.get("derived", {})
    scale = common_stiffness_scale(calibration, values)
    scaled = set(scale["names"]) if scale else set()
    dropped = sorted(undetermined - scaled)
    for name, p in calibration.get("parameters", {}).items():
        if name in undetermined or name in scaled or name not in SI_UNITS:
            continue
        if name == "damping_ratio" and not scaled:  # the calibration derives the coefficients
            continue
        values[name], errors[name] = float(p["value"]), float(p["stderr"])
    for name in scaled:
        values[name] = scale["start"][name] * scale["value"]
        errors[name] = values[name] * scale["log_stderr"]
    ratio_carried = "damping_ratio" in calibration.get("parameters", {}) and \
        "damping_ratio" not in undetermined
    if scaled and ratio_carried:
        for name in ("damping_u", "damping_theta"):  # the carried ratio gives them
            values.pop(name, None)
            errors.pop(name, None)
    elif scaled:
        dropped += sorted(n for n in derived if n in SI_UNITS)
    elif "damping_ratio" not in undetermined and any(n in SI_UNITS for n in derived):
        values.pop("damping_ratio", None)  # the coefficients replace the ratio they came from
        errors.pop("damping_ratio", None)
        for name, p in derived.items():
            if name in SI_UNITS:
                values[name], errors[name] = float(p["value"]), float(p["stderr"])
    else:
        dropped += sorted(n for n in derived if n in SI_UNITS)
    return values, errors, dropped, scale


# --- steps ------------------------------------------------------------------------------------


def _finished(folder: Path) -> dict | None:
    f = folder / STEP_DONE
    if not f.is_file():
        return None
    try:
        return json.loads(f.read_text())
    except (OSError, ValueError):
        return None


def _mark(folder: Path, argv: list[str] | None, wall_s: float, **extra) -> dict:
    doc = {"command": None if argv is None else ["metarig", *argv], "wall_s": round(wall_s, 2),
           **extra}
    tmp = folder / (STEP_DONE + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2))
    tmp.replace(folder / STEP_DONE)
    return doc


def _metarig(name: str, argv: list[str]) -> None:
    """`metarig ARGV` in its own process (the command a user would type; its progress and
    messages go to this terminal)."""
    code = subprocess.run([sys.executable, "-m", "metarig", *argv]).returncode
    if code == 130:
        raise KeyboardInterrupt
    if code != 0:
        raise LoopError(f"{name} failed (exit code {code}); see its messages above")


class _Round:
    """The steps of one round (see the module docstring)."""

    def __init__(self, plan: LoopPlan, task, k: int, rig_argv: list[str],
                 identify_argv: list[str]):
        self.plan, self.task, self.k, self.rig_argv = plan, task, k, rig_argv
        self.identify_argv = identify_argv
        self.dir = plan.out / f"round-{k}"
        self.timings: dict[str, float] = {}  # steps run by this invocation
        self.walls: dict[str, float | None] = {}  # every step, when it ran
        self.skipped: list[str] = []

    def _step(self, name: str, folder: Path, work) -> dict:
        done = _finished(folder)
        label = f"round {self.k}/{self.plan.rounds}: {name}"
        if done is not None:
            log.info("[loop] %s: done already (%s)", label, folder)
            self.skipped.append(name)
            self.walls[name] = done.get("wall_s")
            return done
        log.info("[loop] %s ...", label)
        t0 = time.perf_counter()
        argv, extra = work(folder)
        wall = time.perf_counter() - t0
        self.timings[name] = self.walls[name] = round(wall, 1)
        log.info("[loop] %s: done in %.1f s", label, wall)
        return _mark(folder, argv, wall, **extra)

    def model_material(self) -> Path | None:
        """The round's model material file (written once), or None for the default."""
        path = self.dir / MATERIAL_NAME
        if self.k == 1:
            if self.plan.material is None:
                return None
            if not path.exists():
                self.dir.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(self.plan.material, path)
            return path
        if path.exists():
            return path
        prev = self.plan.out / f"round-{self.k - 1}"
        values, errors, dropped, scale = self.carried()
        from design_engine.physics.material_file import save_material

        self.dir.mkdir(parents=True, exist_ok=True)
        notes = [f"not carried (undetermined by the calibration): {', '.join(dropped)}"] \
            if dropped else []
        if scale is not None:
            notes.append(f"determined only in combination: {', '.join(scale['names'])} carried "
                         f"as their start times one common scale {scale['value']:.4g} +- "
                         f"{scale['stderr']:.2g}")
        note = "; ".join(notes)
        save_material(path, values, errors,
                      f"metarig loop: round {self.k - 1}'s model updated by its calibration "
                      f"({prev / CALIBRATE / 'calibration.json'})", note)
        return path

    def carried(self):
        """`carried_material` of round k-1's model and calibration (k > 1)."""
        prev = self.plan.out / f"round-{self.k - 1}"
        cal = json.loads((prev / CALIBRATE / "calibration.json").read_text())
        before = prev / MATERIAL_NAME
        return carried_material(before if before.exists() else None, cal)

    def start(self) -> list[str]:
        """The `metarig design` flags of the round's initial design: round k-1's design (warm
        start), else round 1's start: the seeded random one or none (the task's)."""
        if self.k > 1 and self.plan.warm_start:
            return ["--initial", str(self.plan.out / f"round-{self.k - 1}" / DESIGN /
                                     "design.json")]
        if self.plan.design_seed is not None:
            return ["--seed", str(self.plan.design_seed)]
        return []

    def design(self, material: Path | None) -> Path:
        folder = self.dir / DESIGN

        def work(folder):
            if self.k == 1 and self.plan.design is not None:
                shutil.rmtree(folder, ignore_errors=True)
                folder.mkdir(parents=True)
                shutil.copyfile(self.plan.design, folder / "design.json")
                return None, {"given": str(self.plan.design)}
            argv = ["design", self.plan.task, "--out", str(folder), "--quiet"]
            if self.plan.size is not None:
                argv += ["--size", f"{self.plan.size[0]}x{self.plan.size[1]}"]
            if self.plan.max_evals is not None:
                argv += ["--max-evals", str(self.plan.max_evals)]
            if material is not None:
                argv += ["--material", str(material)]
            argv += self.start()
            if (folder / "run.json").exists():
                argv.append("--resume")  # an interrupted design continues from its checkpoint
            _metarig("design", argv)
            if not (folder / "design.json").exists():
                raise LoopError(f"round {self.k}: the design found no feasible design")
            return argv, {}

        self._step("design", folder, work)
        return folder / "design.json"

    def rig(self, design: Path, identify: bool = False) -> Path:
        """The task's experiment on the rig (`rig/`), or with `identify` the identification
        experiment on the same specimen (`identify/`)."""
        folder = self.dir / (IDENTIFY if identify else RIG)

        def work(folder):
            shutil.rmtree(folder, ignore_errors=True)  # the remains of an interrupted run
            rig_argv = self.identify_argv if identify else self.rig_argv
            argv = ["rig", "--design", str(design), *rig_argv, "--out", str(folder)]
            if self.plan.workers is not None:
                argv += ["--workers", str(self.plan.workers)]
            _metarig("rig", argv)
            return argv, {}

        self._step("identification experiment (rig, tracking)" if identify else
                   "rig (experiment, tracking, comparison)", folder, work)
        return folder

    def objective(self, run_dir: Path, material: Path | None) -> dict:
        folder = self.dir / OBJECTIVE

        def work(folder):
            folder.mkdir(parents=True, exist_ok=True)
            try:
                doc, arrays = objective_of_run(run_dir, self.task, material)
            except ObjectiveError as exc:
                raise LoopError(str(exc)) from None
            np.savez(folder / "target_ke.npz", **arrays)
            (folder / "objective.json").write_text(json.dumps(doc, indent=2))
            return None, {}

        self._step("objective (measured and predicted)", folder, work)
        return json.loads((folder / "objective.json").read_text())

    def calibrate(self, run_dir: Path, material: Path | None) -> dict:
        folder = self.dir / CALIBRATE

        def work(folder):
            shutil.rmtree(folder, ignore_errors=True)
            argv = ["calibrate", str(run_dir), "--out", str(folder), "--quiet"]
            if material is not None:
                argv += ["--material", str(material)]
            if self.plan.fit is not None:
                argv += ["--fit", self.plan.fit]
            if self.plan.workers is not None:
                argv += ["--workers", str(self.plan.workers)]
            _metarig("calibrate", argv)
            return argv, {}

        self._step("calibrate", folder, work)
        return json.loads((folder / "calibration.json").read_text())

    def run(self) -> dict:
        """Every step of the round (finished ones skipped); returns its summary."""
        material = self.model_material()
        design = self.design(material)
        run_dir = self.rig(design)
        objective = self.objective(run_dir, material)
        if self.plan.identify == "pulse":
            run_dir = self.rig(design, identify=True)
        calibration = self.calibrate(run_dir, material)
        doc = round_summary(self.dir, self.k, design, material, objective, calibration,
                            self.timings, self.skipped)
        doc["calibrated_from"] = str(run_dir)
        if self.k > 1:  # how round k-1's calibration made this round's model
            doc["model_material"]["common_stiffness_scale"] = self.carried()[3]
        doc["design_start"] = self.start()
        doc["steps_wall_s"] = self.walls
        return doc


def round_summary(folder: Path, k: int, design: Path, material: Path | None, objective: dict,
                  calibration: dict, timings: dict, skipped: list[str]) -> dict:
    """One round's entry of `loop.json`."""
    from design_engine.physics.material_file import load_material_file

    doc = json.loads(design.read_text())
    values, errors = load_material_file(material) if material is not None else (None, None)
    return {
        "round": k, "folder": str(folder), "design": str(design),
        "design_objective_J": doc.get("objective"),
        "model_material": {"file": str(material) if material else "default",
                           "values": values, "stderr": errors},
        "predicted_objective_J": objective["predicted_J"],
        "measured_objective_J": objective["measured_J"],
        "measured_over_predicted": objective["measured_over_predicted"],
        "predicted_full_band_objective_J": objective["predicted_full_band_J"],
        "target_units_lost": objective["target_units_lost"],
        "comparison": objective["comparison"],
        "calibrated_material": {
            "file": str(folder / CALIBRATE / MATERIAL_NAME),
            "parameters": calibration.get("parameters", {}),
            "derived": calibration.get("derived", {}),
            "undetermined": calibration.get("undetermined", []),
            "model_error": calibration.get("model_error"),
            "fit": calibration.get("fit"), "correlation": calibration.get("correlation"),
            "residual": calibration.get("residual"), "residual_unit": calibration.get(
                "residual_unit")},
        "timings_s": timings, "steps_done_before": skipped,
    }


PLAN_NAME = "plan.json"
# settings that may change between invocations on one folder (more rounds; fewer tracker cores)
FREE_SETTINGS = ("rounds", "workers", "out")


def plan_settings(plan: LoopPlan) -> dict:
    """The settings that decide what the steps compute (JSON-ready)."""
    return {k: (list(v) if isinstance(v, tuple) else str(v) if isinstance(v, Path) else v)
            for k, v in ((f, getattr(plan, f)) for f in LoopPlan.__slots__)
            if k not in FREE_SETTINGS}


def check_same_settings(plan: LoopPlan) -> None:
    """Record the settings in `DIR/plan.json` on the first invocation; refuse a later one with
    other settings (its finished steps were computed with those).

    Raises:
        LoopError: the folder was run with other settings (named).
    """
    path = plan.out / PLAN_NAME
    now = plan_settings(plan)
    if path.exists():
        try:
            before = json.loads(path.read_text())
        except (OSError, ValueError):
            raise LoopError(f"{path}: unreadable; choose another --out folder") from None
        changed = sorted(k for k in now.keys() | before.keys() if now.get(k) != before.get(k))
        if changed:
            raise LoopError(f"{plan.out} was run with other settings ({', '.join(changed)}: "
                            f"{', '.join(f'{before.get(k)!r}' for k in changed)}); its finished "
                            "steps keep them: resume with those, or choose another --out")
        return
    path.write_text(json.dumps(now, indent=2))


def run_loop(plan: LoopPlan) -> dict:
    """Run (or resume) every round of `plan`, then write `loop.json` and `loop.rrd`; returns
    the `loop.json` document.

    Raises:
        LoopError: a step failed or an input is unusable (one line).
    """
    if plan.rounds < 1:
        raise LoopError("--rounds must be 1 or more")
    for what, path in (("--design", plan.design), ("--material", plan.material)):
        if path is not None and not Path(path).is_file():
            raise LoopError(f"{what} {path}: no such file")
    if plan.material is not None:
        from design_engine.physics.material_file import MaterialFileError, read_material_file

        try:
            read_material_file(plan.material)
        except MaterialFileError as exc:
            raise LoopError(str(exc)) from None
    if plan.identify not in IDENTIFY_CHOICES:
        raise LoopError(f"--identify {plan.identify}: one of {', '.join(IDENTIFY_CHOICES)}")
    task = load_plan_task(plan)
    rig_argv = rig_arguments(task, plan.rig_args)
    identify_argv = rig_arguments(task, plan.rig_args, identify=True)
    if plan.design is not None:
        check_design_fits(plan.design, task)
    plan.out.mkdir(parents=True, exist_ok=True)
    check_same_settings(plan)
    t0 = time.perf_counter()
    rounds = []
    for k in range(1, plan.rounds + 1):
        r = _Round(plan, task, k, rig_argv, identify_argv).run()
        rounds.append(r)
        log.info("[loop] round %d: objective measured %.4g J, predicted %.4g J (x%.3f)", k,
                 r["measured_objective_J"], r["predicted_objective_J"],
                 r["measured_over_predicted"])
    doc = {
        "task": task.name, "goal": task.goal, "out": str(plan.out), "rounds": rounds,
        "rig_arguments": rig_argv, "identify": plan.identify,
        "identify_rig_arguments": identify_argv if plan.identify == "pulse" else None,
        "warm_start": plan.warm_start, "design_seed": plan.design_seed,
        "max_evals": plan.max_evals,
        "lattice": list(task.lattice.shape),
        "objective_unit": "J (mean kinetic energy of the target over the task's window)",
        "wall_s_this_invocation": round(time.perf_counter() - t0, 1),
    }
    (plan.out / SUMMARY_NAME).write_text(json.dumps(doc, indent=2))
    write_loop_rrd(plan.out / RRD_NAME, rounds, {r["round"]: plan.out / f"round-{r['round']}" / OBJECTIVE
                                                for r in rounds})
    return doc
