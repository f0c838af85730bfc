"""Design tasks (spec 8): what to optimise, on which scenes, under which limits; read from TOML.

A task is data. Every preset of the paper is a task file shipped in `design_engine/design/tasks/`
(`metarig design focusing` reads `tasks/focusing.toml`), and a user's own file with the same
keys runs with no new code. The file's layout and the reading of each section are in
`task_schema`; here the task is built from them (`load_task`: lattice, initial design, scenes,
terms) and used (`Task`).

The scalarised objective is sum_i weight_i * quantity_i (spec 9.3). In SI (what `history.json`
and `simulate --task` report) a kinetic-energy term is the target's mean kinetic energy over the
window samples, J_Omega / N_t in J, and an angular-momentum term is J_L in kg m^2/s. The
optimiser sees the reference's numbers: J_Omega summed over samples in mJ, J_L in t mm^2/s.
"""

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from design_engine.design.constraints import ConstraintLimits
from design_engine.design.task_schema import (FORMAT, Budget, OptimizerSettings, TaskError, Term,
                                              fail, read_budget, read_constraints,
                                              read_design_window, read_header, read_initial,
                                              read_lattice, read_optimizer, read_pareto,
                                              read_scenes, read_targets, read_terms)
from design_engine.physics import units
from design_engine.physics.geometry import InvalidDesignError, block_geometry, check_design
from design_engine.physics.lattice import Lattice, kagome, periodic_design, quads
from design_engine.physics.scenes import Scene, build_scene

# internal value of one term -> what the optimiser is fed (the reference's units, spec 8 / 9.1)
OPTIMISER_SCALE = {"kinetic_energy": 1.0, "angular_momentum": 1e-3}  # mJ; g mm^2/ms -> t mm^2/s


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


def load_task(source: str | Path, *, size: tuple[int, int] | None = None,
              max_evals: int | None = None, max_time_s: float | None = None,
              max_solve_steps: int | None = None, bias_angle_deg: float | None = None,
              seed: int | None = None,
              algorithm: str | None = None, weights: tuple[float, ...] | None = None,
              material: str | Path | None = None, initial: str | Path | None = None) -> Task:
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
        initial: design file (metarig-design/1) of the task's lattice to start from instead of
            the periodic design (a redesign continues from the design it improves); recorded
            in the resolved document.

    Raises:
        TaskError: one line naming the file, the key and the problem.
    """
    doc, label = read_task_document(source)
    where = f"task {label}"
    name, goal = read_header(doc, where)
    kind, file_size, shape = read_lattice(doc, where, size)
    lattice = quads(*shape) if kind == "quads" else kagome(*shape)
    bias, amp, seed = read_initial(doc, where, kind, bias_angle_deg, seed)
    if seed is not None:
        amp = amp or 0.15  # the default random amplitude of a seeded start (spec 3.1)
    x0 = (initial_design(lattice, bias, amp, seed, f"{where}.initial") if initial is None
          else given_initial_design(initial, lattice))
    limits = read_constraints(doc, where, lattice)
    budget = read_budget(doc, where, max_evals, max_time_s, max_solve_steps)
    optimizer = read_optimizer(doc, where, algorithm)
    windows = read_targets(doc, where, file_size, shape)
    scenes: dict[str, Scene] = {}
    for sname, (preset, options) in read_scenes(doc, where, kind, file_size, shape).items():
        try:
            scenes[sname] = build_scene(preset, nx=shape[0], ny=shape[1], bias_angle_deg=bias,
                                        design=x0, target_windows=windows, **options)
        except ValueError as exc:
            fail(f"{where}.scenes.{sname}", str(exc))
    material_doc = {}
    if material is not None:
        from design_engine.physics.material_file import (MaterialFileError, read_material_file,
                                                         with_material)

        try:
            given, _ = read_material_file(material)
            scenes = {k: with_material(v, given) for k, v in scenes.items()}
        except MaterialFileError as exc:
            fail("material", str(exc))
        material_doc = {"material": {"file": str(material), "si": given}}
    targets = dict(next(iter(scenes.values())).targets)
    terms = read_terms(doc, where, scenes, targets, weights)
    rule = read_pareto(doc, where, terms)
    window = read_design_window(doc, where, kind, file_size, shape)
    free = (np.arange(lattice.n_design) if window is None
            else design_window_indices(lattice, *window))

    spin_point = None
    if any(t.quantity == "angular_momentum" for t in terms):
        g = block_geometry(lattice, jnp.asarray(x0))
        ids = targets[next(t.target for t in terms if t.quantity == "angular_momentum")]
        spin_point = np.asarray(g.centroids)[ids].mean(axis=0)

    resolved = {
        "format": FORMAT, "name": name, "goal": goal, "source": label,
        "lattice": {"kind": kind, "size": list(shape)},
        "initial": {"bias_angle_deg": bias, "random_amplitude": amp if seed is not None else 0.0,
                    "seed": -1 if seed is None else seed,
                    **({} if initial is None else {"design_file": str(initial)})},
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
        "scenes": {k: dict(v) for k, v in doc["scenes"].items()},
        "objective": [dict(name=t.name, scene=t.scene, target=t.target, weight=t.weight,
                           quantity=t.quantity) for t in terms],
        "design_window": dict(doc.get("design_window", {})),
        "pareto": {"weight_rule": rule},
        "n_free": int(free.size),
        **material_doc,
    }
    return Task(name=name, description=str(doc.get("description", "")), goal=goal, source=label,
                document=resolved, lattice=lattice, scenes=scenes, targets=targets,
                terms=tuple(terms), limits=limits, budget=budget, optimizer=optimizer,
                initial_design=x0, free=free, spin_point=spin_point, weight_rule=rule)


def initial_design(lattice: Lattice, bias_deg: float, amplitude: float, seed: int | None,
                   where: str) -> np.ndarray:
    """The periodic design at `bias_deg`, plus uniform noise of `amplitude` times the spacing
    drawn with `seed` when one is given (spec 3.1); checked."""
    try:
        x0 = periodic_design(lattice, math.radians(bias_deg))
    except ValueError as exc:
        fail(f"{where}.bias_angle_deg", str(exc))
    if seed is not None:
        rng = np.random.default_rng(seed)
        x0 = x0 + rng.uniform(-amplitude * lattice.spacing, amplitude * lattice.spacing,
                              size=x0.shape)
    try:
        return check_design(lattice, x0)
    except InvalidDesignError as exc:
        fail(where, f"the initial design is not valid ({exc}); use a smaller "
             "random_amplitude or another seed")


def given_initial_design(path: str | Path, lattice: Lattice) -> np.ndarray:
    """The design vector (mm) of design file `path`, which must be of `lattice`'s kind and size."""
    from design_engine.design.design_io import load_design

    try:
        given, x = load_design(path)
    except InvalidDesignError as exc:
        fail("initial design", str(exc))
    if given.kind != lattice.kind or tuple(given.shape) != tuple(lattice.shape):
        fail("initial design", f"{path} is a {given.kind} {given.shape[0]}x{given.shape[1]} "
             f"design, the task's lattice is {lattice.kind} {lattice.shape[0]}x{lattice.shape[1]}")
    return x


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
