"""The task file's schema: what each section may say, read into typed values.

Layout (`format = "metarig-task/1"`; every key is checked, unknown keys are refused):

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

Each `read_*` function reads one section of a parsed document and returns its values, or raises
`TaskError` with one line naming the key and the problem. `task.load_task` builds the task from
them (lattice, initial design, scenes).
"""

import math
from dataclasses import dataclass, replace

from design_engine.design.constraints import ConstraintLimits
from design_engine.physics.lattice import Lattice
from design_engine.physics.loading import PRECOMPRESSION
from design_engine.physics.scenes import PRESETS
from design_engine.solve.objectives import QUANTITIES

FORMAT = "metarig-task/1"
GOALS = ("max", "min")
ALGORITHMS = ("mma", "nlopt-mma", "nlopt-ccsaq")
WEIGHT_RULES = ("complement", "protect")
# steps one adaptive solve of an evaluation may take: 14x the 1443 Dopri8 steps of a deep-contact
# 24x18 design at 8 % pre-compression (about 10 ms a step with its gradient on 2 cores); a design
# of the focus-vs-protect front that needed more than 10 000 took over 45 min at the solver's
# own 200 000 and its fallback
DEFAULT_MAX_SOLVE_STEPS = 20_000


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


def fail(where: str, msg: str):
    raise TaskError(f"{where}: {msg}")


def table(doc: dict, key: str, where: str, required: bool = True) -> dict:
    if key not in doc:
        if required:
            fail(where, f"missing table [{key}]")
        return {}
    if not isinstance(doc[key], dict):
        fail(where, f"'{key}' must be a table")
    return doc[key]


def known(tab: dict, allowed: set[str], where: str) -> None:
    extra = sorted(set(tab) - allowed)
    if extra:
        fail(where, f"unknown key{'s' if len(extra) > 1 else ''} {', '.join(map(repr, extra))} "
              f"(allowed: {', '.join(sorted(allowed))})")


def number(tab: dict, key: str, where: str, default=None, *, lo=None, hi=None, integer=False,
           positive=False):
    if key not in tab:
        if default is None:
            fail(where, f"missing key '{key}'")
        return default
    v = tab[key]
    ok = isinstance(v, int) if integer else isinstance(v, (int, float))
    if isinstance(v, bool) or not ok or not math.isfinite(v):
        fail(f"{where}.{key}", f"must be {'an integer' if integer else 'a number'}, got {v!r}")
    if positive and v <= 0:
        fail(f"{where}.{key}", f"must be positive, got {v!r}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        fail(f"{where}.{key}", f"must lie in [{lo}, {hi}], got {v!r}")
    return v


def pair(tab: dict, key: str, where: str, default=None, *, integer=True):
    if key not in tab:
        if default is None:
            fail(where, f"missing key '{key}'")
        return tuple(default)
    v = tab[key]
    kind = int if integer else (int, float)
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(a, kind) and not isinstance(a, bool) for a in v)):
        fail(f"{where}.{key}", f"must be a list of two {'integers' if integer else 'numbers'}, "
              f"got {v!r}")
    return tuple(v)


def text(tab: dict, key: str, where: str, default=None, choices=None) -> str:
    if key not in tab:
        if default is None:
            fail(where, f"missing key '{key}'")
        return default
    v = tab[key]
    if not isinstance(v, str) or not v:
        fail(f"{where}.{key}", f"must be a non-empty string, got {v!r}")
    if choices is not None and v not in choices:
        fail(f"{where}.{key}", f"must be one of {', '.join(choices)}, got {v!r}")
    return v


def scaled(offset: tuple[int, int], frm: tuple[int, int], to: tuple[int, int]) -> tuple[int, int]:
    return (round(offset[0] * to[0] / frm[0]), round(offset[1] * to[1] / frm[1]))


def read_header(doc: dict, where: str) -> tuple[str, str]:
    """The top level: known sections only, the format, and (name, goal)."""
    known(doc, {"format", "name", "description", "spec", "goal", "lattice", "initial",
                "design_window", "constraints", "budget", "optimizer", "targets", "scenes",
                "objective", "pareto"}, where)
    if doc.get("format", FORMAT) != FORMAT:
        fail(f"{where}.format", f"must be {FORMAT!r}, got {doc['format']!r}")
    return text(doc, "name", where), text(doc, "goal", where, choices=GOALS)


def read_lattice(doc: dict, where: str, size: tuple[int, int] | None):
    """[lattice] -> (kind, the file's size, the size used: `size` if given)."""
    lat_t = table(doc, "lattice", where)
    known(lat_t, {"kind", "size"}, f"{where}.lattice")
    kind = text(lat_t, "kind", f"{where}.lattice", choices=("quads", "kagome"))
    file_size = pair(lat_t, "size", f"{where}.lattice")
    shape = tuple(size) if size is not None else file_size
    if min(shape) < 2 or min(file_size) < 2:
        fail(f"{where}.lattice.size", f"needs at least 2x2, got {list(shape)}")
    return kind, file_size, shape


def read_initial(doc: dict, where: str, kind: str, bias_angle_deg: float | None,
                 seed: int | None) -> tuple[float, float, int | None]:
    """[initial] -> (bias angle deg, random amplitude, seed or None); arguments override."""
    ini_t = table(doc, "initial", where, required=False)
    known(ini_t, {"bias_angle_deg", "random_amplitude", "seed"}, f"{where}.initial")
    bias = bias_angle_deg if bias_angle_deg is not None else number(
        ini_t, "bias_angle_deg", f"{where}.initial", 25.0 if kind == "quads" else 0.0,
        lo=-44.9, hi=44.9)
    amp = number(ini_t, "random_amplitude", f"{where}.initial", 0.0, lo=0.0, hi=0.45)
    file_seed = number(ini_t, "seed", f"{where}.initial", -1, integer=True)
    seed = seed if seed is not None else (file_seed if file_seed >= 0 else None)
    return bias, amp, seed


def read_constraints(doc: dict, where: str, lattice: Lattice) -> ConstraintLimits:
    """[constraints] -> the manufacturability limits (spec 3.2)."""
    con_t = table(doc, "constraints", where, required=False)
    known(con_t, {"min_void_angle_deg", "min_vertex_angle_deg", "min_edge_length_mm"},
          f"{where}.constraints")
    return ConstraintLimits(
        min_void_angle=math.radians(number(con_t, "min_void_angle_deg", f"{where}.constraints",
                                           0.0, lo=0.0, hi=90.0)),
        min_vertex_angle=math.radians(number(con_t, "min_vertex_angle_deg",
                                             f"{where}.constraints",
                                             math.degrees(lattice.min_vertex_angle), lo=0.0,
                                             hi=89.0)),
        min_edge_length=number(con_t, "min_edge_length_mm", f"{where}.constraints", 3.0, lo=0.0,
                               hi=lattice.spacing),
    )


def read_budget(doc: dict, where: str, max_evals: int | None, max_time_s: float | None,
                max_solve_steps: int | None) -> Budget:
    """[budget] -> `Budget`; arguments override."""
    bud_t = table(doc, "budget", where, required=False)
    known(bud_t, {"max_evals", "max_time_s", "ftol_rel", "max_solve_steps"}, f"{where}.budget")
    budget = Budget(
        max_evals=max_evals if max_evals is not None else number(
            bud_t, "max_evals", f"{where}.budget", 80, integer=True, positive=True),
        max_time_s=max_time_s if max_time_s is not None else number(
            bud_t, "max_time_s", f"{where}.budget", 28800.0, positive=True),
        ftol_rel=number(bud_t, "ftol_rel", f"{where}.budget", 0.0, lo=0.0, hi=1.0),
        max_solve_steps=max_solve_steps if max_solve_steps is not None else number(
            bud_t, "max_solve_steps", f"{where}.budget", DEFAULT_MAX_SOLVE_STEPS, integer=True,
            positive=True),
    )
    if budget.max_evals < 1 or not budget.max_time_s > 0 or budget.max_solve_steps < 1:
        fail(f"{where}.budget", "max_evals, max_time_s and max_solve_steps must be positive")
    return budget


def read_optimizer(doc: dict, where: str, algorithm: str | None) -> OptimizerSettings:
    """[optimizer] -> `OptimizerSettings`; `algorithm` overrides."""
    opt_t = table(doc, "optimizer", where, required=False)
    known(opt_t, {"algorithm", "initial_step_mm", "nlopt_dual_ftol_rel"}, f"{where}.optimizer")
    dual = opt_t.get("nlopt_dual_ftol_rel")
    optimizer = OptimizerSettings(
        algorithm=algorithm or text(opt_t, "algorithm", f"{where}.optimizer", "mma",
                                    choices=ALGORITHMS),
        initial_step_mm=number(opt_t, "initial_step_mm", f"{where}.optimizer", 1.0,
                               positive=True),
        nlopt_dual_ftol_rel=None if dual is None else number(
            opt_t, "nlopt_dual_ftol_rel", f"{where}.optimizer", lo=0.0, hi=1.0),
    )
    if optimizer.algorithm not in ALGORITHMS:
        fail("--algorithm", f"must be one of {', '.join(ALGORITHMS)}")
    return optimizer


def named_tables(doc: dict, key: str, what: str, where: str, not_a_table: str):
    """Yield (name, table, where) of each [key.NAME] table; at least one is required."""
    tab = table(doc, key, where)
    if not tab:
        fail(f"{where}.{key}", f"define at least one {what}")
    for name, t in tab.items():
        w = f"{where}.{key}.{name}"
        if not isinstance(t, dict):
            fail(w, not_a_table)
        yield name, t, w


def read_targets(doc: dict, where: str, file_size, shape) -> dict:
    """[targets.NAME] -> name -> (window size, offset scaled to `shape`)."""
    windows = {}
    for tname, t, w in named_tables(doc, "targets", "target", where,
                                    "must be a table with size and offset"):
        known(t, {"size", "offset"}, w)
        wh, off = pair(t, "size", w), pair(t, "offset", w, (0, 0))
        if min(wh) < 1:
            fail(f"{w}.size", f"must be positive, got {list(wh)}")
        windows[tname] = (wh, scaled(off, file_size, shape))
    return windows


def read_scenes(doc: dict, where: str, kind: str, file_size, shape) -> dict[str, tuple]:
    """[scenes.NAME] -> name -> (preset, keyword arguments of `scenes.build_scene` that the
    section sets; shifts scaled to `shape`)."""
    out = {}
    for sname, s, w in named_tables(doc, "scenes", "scene", where, "must be a table"):
        known(s, {"preset", "side", "shift", "strain", "amplitude_m", "frequency_hz", "periods",
                  "samples", "contact_deg", "precompression"}, w)
        preset = text(s, "preset", w, choices=tuple(PRESETS))
        if PRESETS[preset]["kind"] != kind:
            fail(f"{w}.preset", f"{preset!r} is a {PRESETS[preset]['kind']} scene, the task "
                 f"lattice is {kind}")
        shift = None
        if "shift" in s:
            shift = number(s, "shift", w, integer=True)
            side = s.get("side", PRESETS[preset]["side"])
            axis = 1 if side in ("left", "right") else 0
            shift = round(shift * shape[axis] / file_size[axis])
        out[sname] = (preset, dict(
            amplitude_m=number(s, "amplitude_m", w, -1.0) if "amplitude_m" in s else None,
            frequency_hz=number(s, "frequency_hz", w, 30.0, positive=True),
            strain=number(s, "strain", w, -1.0, lo=0.0, hi=0.2) if "strain" in s else None,
            n_samples=number(s, "samples", w, -1, integer=True, lo=2) if "samples" in s
            else None,
            side=text(s, "side", w, choices=("left", "right", "bottom", "top"))
            if "side" in s else None,
            shift=shift,
            contact_deg=pair(s, "contact_deg", w, integer=False) if "contact_deg" in s
            else None,
            periods=number(s, "periods", w, positive=True) if "periods" in s else None,
            precompression=text(s, "precompression", w, choices=PRECOMPRESSION)
            if "precompression" in s else "static",
        ))
    return out


def read_terms(doc: dict, where: str, scenes, targets,
               weights: tuple[float, ...] | None) -> list[Term]:
    """[[objective]] -> the weighted terms (on the named scenes and targets); `weights`
    replaces the file's weights."""
    obj_t = doc.get("objective")
    if not isinstance(obj_t, list) or not obj_t or not all(isinstance(o, dict) for o in obj_t):
        fail(where, "needs one or more [[objective]] tables")
    terms = []
    target_names = [o.get("target") for o in obj_t]
    for i, o in enumerate(obj_t):
        w = f"{where}.objective[{i}]"
        known(o, {"name", "scene", "target", "weight", "quantity"}, w)
        sc = text(o, "scene", w, choices=tuple(scenes))
        tg = text(o, "target", w, choices=tuple(targets))
        default_name = tg if target_names.count(tg) == 1 else f"{tg}@{sc}"
        terms.append(Term(name=text(o, "name", w, default_name),
                          scene=sc, target=tg, weight=float(number(o, "weight", w, 1.0)),
                          quantity=text(o, "quantity", w, "kinetic_energy", choices=QUANTITIES)))
    if len({t.name for t in terms}) != len(terms):
        fail(where, "objective term names must be unique (set 'name')")
    if weights is not None:
        if len(weights) != len(terms):
            fail("weights", f"{len(terms)} objective terms need {len(terms)} weights, got "
                 f"{len(weights)}")
        terms = [replace(t, weight=float(w)) for t, w in zip(terms, weights)]
    return terms


def read_pareto(doc: dict, where: str, terms: list[Term]) -> str:
    """[pareto] -> the weight rule (default from the weights' signs)."""
    par_t = table(doc, "pareto", where, required=False)
    known(par_t, {"weight_rule"}, f"{where}.pareto")
    return text(par_t, "weight_rule", f"{where}.pareto",
                "protect" if any(t.weight < 0 for t in terms) else "complement",
                choices=WEIGHT_RULES)


def read_design_window(doc: dict, where: str, kind: str, file_size, shape):
    """[design_window] -> (P, offset scaled to `shape`), or None when the section is absent."""
    win_t = table(doc, "design_window", where, required=False)
    if not win_t:
        return None
    w = f"{where}.design_window"
    known(win_t, {"size", "offset"}, w)
    p = number(win_t, "size", w, integer=True, positive=True)
    if kind != "quads":
        fail(w, "a restricted design window is defined for quads lattices only")
    return p, scaled(pair(win_t, "offset", w, (0, 0)), file_size, shape)
