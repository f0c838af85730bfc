"""Design tasks (spec 8): what to optimise, on which scenes, under which limits; read from TOML.

A task is data. Every preset of the paper is a task file shipped in `design_engine/design/tasks/`
(`metarig design focusing` reads `tasks/focusing.toml`), and a user's own file with the same
keys runs with no new code. Layout (`format = "metarig-task/1"`; every key is checked, unknown
keys are refused):

    name, description, spec, goal ("max" | "min")
    [lattice]      kind ("quads" | "kagome"), size = [nx, ny]
    [initial]      bias_angle_deg, random_amplitude (fraction of the spacing), seed
    [design_window] size = P, offset = [sx, sy]          (optional: only a P x P patch is free)
    [constraints]  min_void_angle_deg, min_vertex_angle_deg, min_edge_length_mm
    [budget]       max_evals, max_time_s, ftol_rel, max_solve_steps (steps one adaptive solve
                   of an evaluation may take before the design counts as failed)
    [optimizer]    algorithm ("mma" | "nlopt-mma" | "nlopt-ccsaq"), initial_step_mm,
                   nlopt_dual_ftol_rel
    [targets.NAME] size = [w, h], offset = [sx, sy]      (spec 8 windows)
    [scenes.NAME]  preset, and optional side, shift, strain, amplitude_m, frequency_hz,
                   periods, samples, contact_deg = [theta_min, theta_cutoff],
                   precompression = "static" (default: the pulse starts from the equilibrium
                   under the closed stages) or "ramp" (the reference's dynamic two-stage ramp)
    [[objective]]  scene, target, weight, quantity ("kinetic_energy" | "angular_momentum"), name
    [pareto]       weight_rule ("complement": w2 = 1 - w1, both maximised; "protect":
                   w2 = w1 - 1, the second term minimised; default from the weights' signs)

The scalarised objective is sum_i weight_i * quantity_i (spec 9.3). In SI (what `history.json`
and `simulate --task` report) a kinetic-energy term is the target's mean kinetic energy over the
window samples, J_Omega / N_t in J, and an angular-momentum term is J_L in kg m^2/s. The
optimiser sees the reference's numbers: J_Omega summed over samples in mJ, J_L in t mm^2/s.
"""

import math
import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from design_engine.physics import units
from design_engine.design.constraints import ConstraintLimits
from design_engine.physics.geometry import InvalidDesignError, block_geometry, check_design
from design_engine.physics.lattice import Lattice, kagome, periodic_design, quads
from design_engine.physics.loading import PRECOMPRESSION
from design_engine.design.objectives import QUANTITIES
from design_engine.physics.scenes import PRESETS, Scene, build_scene

FORMAT = "metarig-task/1"
GOALS = ("max", "min")
ALGORITHMS = ("mma", "nlopt-mma", "nlopt-ccsaq")
WEIGHT_RULES = ("complement", "protect")
# steps one adaptive solve of an evaluation may take: 14x the 1443 Dopri8 steps of a deep-contact
# 24x18 design at 8 % pre-compression (about 10 ms a step with its gradient on 2 cores); a design
# of the focus-vs-protect front that needed more than 10 000 took over 45 min at the solver's
# own 200 000 and its fallback
DEFAULT_MAX_SOLVE_STEPS = 20_000
# internal value of one term -> what the optimiser is fed (the reference's units, spec 8 / 9.1)
OPTIMISER_SCALE = {"kinetic_energy": 1.0, "angular_momentum": 1e-3}  # mJ; g mm^2/ms -> t mm^2/s


class TaskError(ValueError):
    """A task file or preset that cannot be used; the message names the key and the problem."""


@dataclass(frozen=True)
class Term:
    """One weighted term of the scalarised objective.

    Attributes:
        name: label in histories and design files.
        scene: name of the scene it is measured on.
        target: name of the target region.
        weight: weight w_i (may be negative, e.g. protection).
        quantity: "kinetic_energy" (J_Omega) or "angular_momentum" (J_L, spec 8.6).
    """

    name: str
    scene: str
    target: str
    weight: float
    quantity: str


@dataclass(frozen=True)
class Budget:
    """Stopping criteria: evaluations (MMA inner iterations included), wall time (s), ftol; and
    the steps one adaptive solve of an evaluation may take (`max_solve_steps`): a design that
    needs more (voids driven against the contact asymptote, where the barrier's frequency
    grows without bound) is recorded as a failed evaluation, which MMA steps back from."""

    max_evals: int
    max_time_s: float
    ftol_rel: float = 0.0
    max_solve_steps: int = DEFAULT_MAX_SOLVE_STEPS


@dataclass(frozen=True)
class OptimizerSettings:
    """Algorithm and its settings: initial move limit (mm), NLopt dual tolerance (None: NLopt's)."""

    algorithm: str = "mma"
    initial_step_mm: float = 1.0
    nlopt_dual_ftol_rel: float | None = None


@dataclass(frozen=True, eq=False)
class Task:
    """A resolved task: scenes built, targets resolved to unit ids, initial design made.

    Attributes:
        name, description, goal: as in the file.
        source: preset name or file path it came from.
        document: the resolved task as a TOML-like dict (provenance; resume checks it).
        lattice: the lattice every scene shares.
        scenes: scene name -> `Scene` (all with the initial design).
        targets: target name -> [k] unit ids.
        terms: the weighted objective terms.
        limits: manufacturability limits (spec 3.2).
        budget, optimizer: stopping and algorithm settings.
        initial_design: [n_design] mm.
        free: [n_free] indices of the design vector the optimiser may move (all, or a window).
        spin_point: [2] mm, point S of the angular-momentum objective (initial target centre).
    """

    name: str
    description: str
    goal: str
    source: str
    document: dict
    lattice: Lattice
    scenes: dict[str, Scene]
    targets: dict[str, np.ndarray]
    terms: tuple[Term, ...]
    limits: ConstraintLimits
    budget: Budget
    optimizer: OptimizerSettings
    initial_design: np.ndarray
    free: np.ndarray
    spin_point: np.ndarray | None = field(default=None)
    weight_rule: str = "complement"

    def pareto_weights(self, w1: float) -> tuple[float, float]:
        """(w1, w2) of a two-term task for a sweep: w2 = 1 - w1 ("complement", both
        maximised) or w2 = w1 - 1 ("protect", the second term minimised), spec 9.3."""
        if len(self.terms) != 2:
            raise TaskError(f"task {self.name} has {len(self.terms)} objective terms; a Pareto "
                            "sweep needs two")
        if not 0.0 <= w1 <= 1.0:
            raise TaskError(f"weight w1 must lie in [0, 1], got {w1}")
        return (w1, 1.0 - w1) if self.weight_rule == "complement" else (w1, w1 - 1.0)

    @property
    def senses(self) -> tuple[str, ...]:
        """Per term "max" or "min" for Pareto dominance (spec 9.3)."""
        if self.weight_rule == "protect":
            return ("max", "min")
        return tuple("max" for _ in self.terms)

    def embed(self, x_free) -> np.ndarray:
        """Full design vector [n_design] (mm) from the free variables [n_free]."""
        x = self.initial_design.copy()
        x[self.free] = x_free
        return x

    @property
    def sign(self) -> float:
        """+1 to maximise, -1 to minimise (the optimiser minimises -sign * objective)."""
        return 1.0 if self.goal == "max" else -1.0

    def term_si(self, term: Term, internal_value: float) -> float:
        """A term's internal value (J_Omega mJ summed over samples, or J_L g mm^2/ms) in SI."""
        if term.quantity == "angular_momentum":
            return units.angular_momentum_to_si(internal_value)
        return units.energy_to_si(internal_value / self.scenes[term.scene].n_samples)

    def objectives_si(self, internal: dict[str, float]) -> dict[str, float]:
        """Term name -> SI value (see module docstring)."""
        return {t.name: self.term_si(t, internal[t.name]) for t in self.terms}

    def scalarised_si(self, internal: dict[str, float]) -> float:
        """sum_i w_i * (SI value of term i): the `objective` of history.json."""
        si = self.objectives_si(internal)
        return float(sum(t.weight * si[t.name] for t in self.terms))

    def metrics(self, internal: dict[str, float]) -> dict[str, float]:
        """Task metrics beyond the objective: the ratio J1/J2 of a two-term energy task."""
        if len(self.terms) == 2 and all(t.quantity == "kinetic_energy" for t in self.terms):
            a, b = (internal[t.name] for t in self.terms)
            return {"ratio": float(a / b) if b != 0 else float("inf")}
        return {}


def preset_names() -> list[str]:
    """Names of the task presets shipped with the package."""
    return sorted(p.name[:-5] for p in resources.files("design_engine").joinpath("design", "tasks").iterdir()
                  if p.name.endswith(".toml"))


def preset_path(name: str) -> Path:
    return Path(str(resources.files("design_engine").joinpath("design", "tasks", f"{name}.toml")))


def read_task_document(source: str | Path) -> tuple[dict, str]:
    """Parse a task preset name or TOML file -> (document, source label)."""
    path = Path(source)
    if not path.suffix and str(source) in preset_names():
        path = preset_path(str(source))
    elif not path.exists():
        raise TaskError(f"no task preset or file {str(source)!r} (presets: "
                        f"{', '.join(preset_names())})")
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise TaskError(f"task file {path}: cannot be read ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise TaskError(f"task file {path}: not valid TOML ({exc})") from None
    return doc, str(source)


# --- schema ------------------------------------------------------------------------------------

def _fail(where: str, msg: str):
    raise TaskError(f"{where}: {msg}")


def _table(doc: dict, key: str, where: str, required: bool = True) -> dict:
    if key not in doc:
        if required:
            _fail(where, f"missing table [{key}]")
        return {}
    if not isinstance(doc[key], dict):
        _fail(where, f"'{key}' must be a table")
    return doc[key]


def _known(tab: dict, allowed: set[str], where: str) -> None:
    extra = sorted(set(tab) - allowed)
    if extra:
        _fail(where, f"unknown key{'s' if len(extra) > 1 else ''} {', '.join(map(repr, extra))} "
              f"(allowed: {', '.join(sorted(allowed))})")


def _num(tab: dict, key: str, where: str, default=None, *, lo=None, hi=None, integer=False,
         positive=False):
    if key not in tab:
        if default is None:
            _fail(where, f"missing key '{key}'")
        return default
    v = tab[key]
    ok = isinstance(v, int) if integer else isinstance(v, (int, float))
    if isinstance(v, bool) or not ok or not math.isfinite(v):
        _fail(f"{where}.{key}", f"must be {'an integer' if integer else 'a number'}, got {v!r}")
    if positive and v <= 0:
        _fail(f"{where}.{key}", f"must be positive, got {v!r}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        _fail(f"{where}.{key}", f"must lie in [{lo}, {hi}], got {v!r}")
    return v


def _pair(tab: dict, key: str, where: str, default=None, *, integer=True):
    if key not in tab:
        if default is None:
            _fail(where, f"missing key '{key}'")
        return tuple(default)
    v = tab[key]
    kind = int if integer else (int, float)
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(a, kind) and not isinstance(a, bool) for a in v)):
        _fail(f"{where}.{key}", f"must be a list of two {'integers' if integer else 'numbers'}, "
              f"got {v!r}")
    return tuple(v)


def _str(tab: dict, key: str, where: str, default=None, choices=None) -> str:
    if key not in tab:
        if default is None:
            _fail(where, f"missing key '{key}'")
        return default
    v = tab[key]
    if not isinstance(v, str) or not v:
        _fail(f"{where}.{key}", f"must be a non-empty string, got {v!r}")
    if choices is not None and v not in choices:
        _fail(f"{where}.{key}", f"must be one of {', '.join(choices)}, got {v!r}")
    return v


def _scaled(offset: tuple[int, int], frm: tuple[int, int], to: tuple[int, int]) -> tuple[int, int]:
    return (round(offset[0] * to[0] / frm[0]), round(offset[1] * to[1] / frm[1]))


def load_task(source: str | Path, *, size: tuple[int, int] | None = None,
              max_evals: int | None = None, max_time_s: float | None = None,
              max_solve_steps: int | None = None, bias_angle_deg: float | None = None,
              seed: int | None = None,
              algorithm: str | None = None, weights: tuple[float, ...] | None = None,
              material: str | Path | None = None) -> Task:
    """Read and resolve a task preset (by name) or task file, with command-line overrides.

    Args:
        source: preset name (`preset_names()`) or path of a TOML task file.
        size: (nx, ny) lattice size replacing the file's; target offsets, input shifts and the
            design window's offset are scaled by the size ratio (rounded).
        max_evals, max_time_s, max_solve_steps: budget overrides.
        bias_angle_deg: bias angle of the periodic initial design.
        seed: random initial guess (periodic design plus uniform noise of `random_amplitude`
            times the spacing, default 0.15, spec 3.1) drawn with this seed.
        algorithm: optimiser override.
        weights: one weight per objective term, replacing the file's (Pareto sweeps).
        material: material file (metarig-material/1) given to every scene (contact angles the
            file does not set stay the scene's); recorded in the resolved document.

    Raises:
        TaskError: one line naming the file, the key and the problem.
    """
    doc, label = read_task_document(source)
    where = f"task {label}"
    _known(doc, {"format", "name", "description", "spec", "goal", "lattice", "initial",
                 "design_window", "constraints", "budget", "optimizer", "targets", "scenes",
                 "objective", "pareto"}, where)
    if doc.get("format", FORMAT) != FORMAT:
        _fail(f"{where}.format", f"must be {FORMAT!r}, got {doc['format']!r}")
    name = _str(doc, "name", where)
    goal = _str(doc, "goal", where, choices=GOALS)

    lat_t = _table(doc, "lattice", where)
    _known(lat_t, {"kind", "size"}, f"{where}.lattice")
    kind = _str(lat_t, "kind", f"{where}.lattice", choices=("quads", "kagome"))
    file_size = _pair(lat_t, "size", f"{where}.lattice")
    shape = tuple(size) if size is not None else file_size
    if min(shape) < 2 or min(file_size) < 2:
        _fail(f"{where}.lattice.size", f"needs at least 2x2, got {list(shape)}")
    lattice = quads(*shape) if kind == "quads" else kagome(*shape)

    ini_t = _table(doc, "initial", where, required=False)
    _known(ini_t, {"bias_angle_deg", "random_amplitude", "seed"}, f"{where}.initial")
    bias = bias_angle_deg if bias_angle_deg is not None else _num(
        ini_t, "bias_angle_deg", f"{where}.initial", 25.0 if kind == "quads" else 0.0,
        lo=-44.9, hi=44.9)
    amp = _num(ini_t, "random_amplitude", f"{where}.initial", 0.0, lo=0.0, hi=0.45)
    file_seed = _num(ini_t, "seed", f"{where}.initial", -1, integer=True)
    seed = seed if seed is not None else (file_seed if file_seed >= 0 else None)
    try:
        x0 = periodic_design(lattice, math.radians(bias))
    except ValueError as exc:
        _fail(f"{where}.initial.bias_angle_deg", str(exc))
    if seed is not None:
        amp = amp or 0.15
        rng = np.random.default_rng(seed)
        x0 = x0 + rng.uniform(-amp * lattice.spacing, amp * lattice.spacing, size=x0.shape)
    try:
        x0 = check_design(lattice, x0)
    except InvalidDesignError as exc:
        _fail(f"{where}.initial", f"the initial design is not valid ({exc}); use a smaller "
              "random_amplitude or another seed")

    con_t = _table(doc, "constraints", where, required=False)
    _known(con_t, {"min_void_angle_deg", "min_vertex_angle_deg", "min_edge_length_mm"},
           f"{where}.constraints")
    limits = ConstraintLimits(
        min_void_angle=math.radians(_num(con_t, "min_void_angle_deg", f"{where}.constraints", 0.0,
                                         lo=0.0, hi=90.0)),
        min_vertex_angle=math.radians(_num(con_t, "min_vertex_angle_deg", f"{where}.constraints",
                                           math.degrees(lattice.min_vertex_angle), lo=0.0,
                                           hi=89.0)),
        min_edge_length=_num(con_t, "min_edge_length_mm", f"{where}.constraints", 3.0, lo=0.0,
                             hi=lattice.spacing),
    )

    bud_t = _table(doc, "budget", where, required=False)
    _known(bud_t, {"max_evals", "max_time_s", "ftol_rel", "max_solve_steps"}, f"{where}.budget")
    budget = Budget(
        max_evals=max_evals if max_evals is not None else _num(
            bud_t, "max_evals", f"{where}.budget", 80, integer=True, positive=True),
        max_time_s=max_time_s if max_time_s is not None else _num(
            bud_t, "max_time_s", f"{where}.budget", 28800.0, positive=True),
        ftol_rel=_num(bud_t, "ftol_rel", f"{where}.budget", 0.0, lo=0.0, hi=1.0),
        max_solve_steps=max_solve_steps if max_solve_steps is not None else _num(
            bud_t, "max_solve_steps", f"{where}.budget", DEFAULT_MAX_SOLVE_STEPS, integer=True,
            positive=True),
    )
    if budget.max_evals < 1 or not budget.max_time_s > 0 or budget.max_solve_steps < 1:
        _fail(f"{where}.budget", "max_evals, max_time_s and max_solve_steps must be positive")

    opt_t = _table(doc, "optimizer", where, required=False)
    _known(opt_t, {"algorithm", "initial_step_mm", "nlopt_dual_ftol_rel"}, f"{where}.optimizer")
    dual = opt_t.get("nlopt_dual_ftol_rel")
    optimizer = OptimizerSettings(
        algorithm=algorithm or _str(opt_t, "algorithm", f"{where}.optimizer", "mma",
                                    choices=ALGORITHMS),
        initial_step_mm=_num(opt_t, "initial_step_mm", f"{where}.optimizer", 1.0, positive=True),
        nlopt_dual_ftol_rel=None if dual is None else _num(
            opt_t, "nlopt_dual_ftol_rel", f"{where}.optimizer", lo=0.0, hi=1.0),
    )
    if optimizer.algorithm not in ALGORITHMS:
        _fail("--algorithm", f"must be one of {', '.join(ALGORITHMS)}")

    tgt_t = _table(doc, "targets", where)
    if not tgt_t:
        _fail(f"{where}.targets", "define at least one target")
    windows = {}
    for tname, t in tgt_t.items():
        w = f"{where}.targets.{tname}"
        if not isinstance(t, dict):
            _fail(w, "must be a table with size and offset")
        _known(t, {"size", "offset"}, w)
        wh, off = _pair(t, "size", w), _pair(t, "offset", w, (0, 0))
        if min(wh) < 1:
            _fail(f"{w}.size", f"must be positive, got {list(wh)}")
        windows[tname] = (wh, _scaled(off, file_size, shape))

    scn_t = _table(doc, "scenes", where)
    if not scn_t:
        _fail(f"{where}.scenes", "define at least one scene")
    scenes: dict[str, Scene] = {}
    for sname, s in scn_t.items():
        w = f"{where}.scenes.{sname}"
        if not isinstance(s, dict):
            _fail(w, "must be a table")
        _known(s, {"preset", "side", "shift", "strain", "amplitude_m", "frequency_hz", "periods",
                   "samples", "contact_deg", "precompression"}, w)
        preset = _str(s, "preset", w, choices=tuple(PRESETS))
        if PRESETS[preset]["kind"] != kind:
            _fail(f"{w}.preset", f"{preset!r} is a {PRESETS[preset]['kind']} scene, the task "
                  f"lattice is {kind}")
        shift = None
        if "shift" in s:
            shift = _num(s, "shift", w, integer=True)
            side = s.get("side", PRESETS[preset]["side"])
            axis = 1 if side in ("left", "right") else 0
            shift = round(shift * shape[axis] / file_size[axis])
        try:
            scenes[sname] = build_scene(
                preset, nx=shape[0], ny=shape[1], bias_angle_deg=bias, design=x0,
                amplitude_m=_num(s, "amplitude_m", w, -1.0) if "amplitude_m" in s else None,
                frequency_hz=_num(s, "frequency_hz", w, 30.0, positive=True),
                strain=_num(s, "strain", w, -1.0, lo=0.0, hi=0.2) if "strain" in s else None,
                n_samples=_num(s, "samples", w, -1, integer=True, lo=2) if "samples" in s
                else None,
                target_windows=windows,
                side=_str(s, "side", w, choices=("left", "right", "bottom", "top"))
                if "side" in s else None,
                shift=shift,
                contact_deg=_pair(s, "contact_deg", w, integer=False) if "contact_deg" in s
                else None,
                periods=_num(s, "periods", w, positive=True) if "periods" in s else None,
                precompression=_str(s, "precompression", w, choices=PRECOMPRESSION)
                if "precompression" in s else "static",
            )
        except ValueError as exc:
            _fail(w, str(exc))
    material_doc = {}
    if material is not None:
        from design_engine.physics.material_file import MaterialFileError, read_material_file, with_material

        try:
            given, _ = read_material_file(material)
            scenes = {k: with_material(v, given) for k, v in scenes.items()}
        except MaterialFileError as exc:
            _fail("material", str(exc))
        material_doc = {"material": {"file": str(material), "si": given}}
    first = next(iter(scenes.values()))
    targets = dict(first.targets)

    obj_t = doc.get("objective")
    if not isinstance(obj_t, list) or not obj_t or not all(isinstance(o, dict) for o in obj_t):
        _fail(where, "needs one or more [[objective]] tables")
    terms = []
    target_names = [o.get("target") for o in obj_t]
    for i, o in enumerate(obj_t):
        w = f"{where}.objective[{i}]"
        _known(o, {"name", "scene", "target", "weight", "quantity"}, w)
        sc = _str(o, "scene", w, choices=tuple(scenes))
        tg = _str(o, "target", w, choices=tuple(targets))
        default_name = tg if target_names.count(tg) == 1 else f"{tg}@{sc}"
        terms.append(Term(name=_str(o, "name", w, default_name),
                          scene=sc, target=tg, weight=float(_num(o, "weight", w, 1.0)),
                          quantity=_str(o, "quantity", w, "kinetic_energy", choices=QUANTITIES)))
    if len({t.name for t in terms}) != len(terms):
        _fail(where, "objective term names must be unique (set 'name')")
    if weights is not None:
        if len(weights) != len(terms):
            _fail("weights", f"{len(terms)} objective terms need {len(terms)} weights, got "
                  f"{len(weights)}")
        terms = [replace(t, weight=float(w)) for t, w in zip(terms, weights)]
    par_t = _table(doc, "pareto", where, required=False)
    _known(par_t, {"weight_rule"}, f"{where}.pareto")
    rule = _str(par_t, "weight_rule", f"{where}.pareto",
                "protect" if any(t.weight < 0 for t in terms) else "complement",
                choices=WEIGHT_RULES)

    free = np.arange(lattice.n_design)
    win_t = _table(doc, "design_window", where, required=False)
    if win_t:
        w = f"{where}.design_window"
        _known(win_t, {"size", "offset"}, w)
        p = _num(win_t, "size", w, integer=True, positive=True)
        if kind != "quads":
            _fail(w, "a restricted design window is defined for quads lattices only")
        free = design_window_indices(lattice, p, _scaled(_pair(win_t, "offset", w, (0, 0)),
                                                         file_size, shape))

    spin_point = None
    if any(t.quantity == "angular_momentum" for t in terms):
        g = block_geometry(lattice, jnp.asarray(x0))
        ids = targets[next(t.target for t in terms if t.quantity == "angular_momentum")]
        spin_point = np.asarray(g.centroids)[ids].mean(axis=0)

    resolved = {
        "format": FORMAT, "name": name, "goal": goal, "source": label,
        "lattice": {"kind": kind, "size": list(shape)},
        "initial": {"bias_angle_deg": bias, "random_amplitude": amp if seed is not None else 0.0,
                    "seed": -1 if seed is None else seed},
        "constraints": {"min_void_angle_deg": math.degrees(limits.min_void_angle),
                        "min_vertex_angle_deg": math.degrees(limits.min_vertex_angle),
                        "min_edge_length_mm": limits.min_edge_length},
        "budget": {"max_evals": budget.max_evals, "max_time_s": budget.max_time_s,
                   "ftol_rel": budget.ftol_rel, "max_solve_steps": budget.max_solve_steps},
        "optimizer": {"algorithm": optimizer.algorithm,
                      "initial_step_mm": optimizer.initial_step_mm,
                      **({} if optimizer.nlopt_dual_ftol_rel is None else
                         {"nlopt_dual_ftol_rel": optimizer.nlopt_dual_ftol_rel})},
        "targets": {k: {"size": list(v[0]), "offset": list(v[1])} for k, v in windows.items()},
        "scenes": {k: dict(v) for k, v in scn_t.items()},
        "objective": [dict(name=t.name, scene=t.scene, target=t.target, weight=t.weight,
                           quantity=t.quantity) for t in terms],
        "design_window": dict(win_t),
        "pareto": {"weight_rule": rule},
        "n_free": int(free.size),
        **material_doc,
    }
    return Task(name=name, description=str(doc.get("description", "")), goal=goal, source=label,
                document=resolved, lattice=lattice, scenes=scenes, targets=targets,
                terms=tuple(terms), limits=limits, budget=budget, optimizer=optimizer,
                initial_design=x0, free=free, spin_point=spin_point, weight_rule=rule)


def design_window_indices(lattice: Lattice, p: int, offset: tuple[int, int]) -> np.ndarray:
    """Design-vector indices of the vertices of the units in a P x P patch (spec 3.1)."""
    nx, ny = lattice.shape
    i0 = max((nx - p) // 2 + offset[0], 0)
    i1 = min((nx + p) // 2 + offset[0], nx)
    j0 = max((ny - p) // 2 + offset[1], 0)
    j1 = min((ny + p) // 2 + offset[1], ny)
    if i0 >= i1 or j0 >= j1:
        raise TaskError(f"design window {p}x{p} at offset {list(offset)} lies outside the lattice")
    rows = {int(r) for b in range(lattice.n_blocks)
            if i0 <= lattice.cell_of_block[b, 0] < i1 and j0 <= lattice.cell_of_block[b, 1] < j1
            for r in lattice.shift_index[b]}
    return np.asarray(sorted(c for r in rows for c in (2 * r, 2 * r + 1)), dtype=np.int64)
