"""Scenes of the paper: lattice + design + supports + loading + targets, built by name.

A `Scene` is static configuration; `build_scene(name, **overrides)` makes one. All overrides take
SI units (or degrees where the name says so); the scene stores internal units (mm, ms, g).
"""

import math
from dataclasses import dataclass, field, replace

import jax.numpy as jnp
import numpy as np

from design_engine.physics.energy import DEFAULT_MODEL, Model
from design_engine.physics.geometry import block_geometry, check_design
from design_engine.physics.lattice import Lattice, kagome, periodic_design, quads
from design_engine.physics.loading import (CH_INPUT, CH_STAGE, CH_ZERO, PRECOMPRESSION, Loading,
                                           Supports)
from design_engine.physics.material import Material, default_si
from design_engine.physics.regions import corner_clamps, driven_units, row_units, window

STRAIN_RATE = 2.5e-4  # pre-compression rate, 1/ms (0.25 1/s)

# name -> recipe. Regions are ((w, h), (sx, sy)) windows; spec sections in comments.
PRESETS: dict[str, dict] = {
    # 8.1 single-target focusing
    "focusing-24x16": dict(kind="quads", shape=(24, 16), supports="corners", side="left", shift=0,
                           targets={"target": ((2, 2), (4, 5))}, periods=2, line_row=13),
    # 8.2 energy splitting
    "splitting-24x16": dict(kind="quads", shape=(24, 16), supports="corners", side="left", shift=0,
                            targets={"target1": ((2, 2), (5, 3)), "target2": ((2, 2), (-3, -3))},
                            periods=2, line_row=13),
    # 8.4 reprogrammable location: two-stage pre-compression; targets are [OPEN] in the sources,
    # our default puts one window in the upper and one in the lower half
    "precompression-24x18": dict(kind="quads", shape=(24, 18), supports="stages", side="left", shift=0,
                                 strain=0.02, targets={"target_upper": ((2, 2), (2, 4)),
                                                       "target_lower": ((2, 2), (2, -4))},
                                 periods=2, line_row=11),
    # 8.5 focusing vs protection (contact angles of the reference code: -10 / -5 deg)
    "protection-24x18": dict(kind="quads", shape=(24, 18), supports="stages", side="left", shift=0,
                             strain=0.01, contact_deg=(-10.0, -5.0),
                             targets={"target": ((2, 2), (2, 2))}, periods=2, line_row=11),
    # 8.6 motion conversion (spin): harmonic input from the bottom
    "spin-24x16": dict(kind="quads", shape=(24, 16), supports="corners", side="bottom", shift=4,
                       waveform="harmonic", targets={"target": ((2, 2), (-3, 3))}, periods=5,
                       n_samples=250, line_row=11, spin=True),
    # 8.7 kagome focusing
    "kagome-20x12": dict(kind="kagome", shape=(20, 12), supports="corners", side="left", shift=0,
                         targets={"target": ((2, 2), (3, 2))}, periods=3, line_row=9, bias_deg=0.0),
}


@dataclass(frozen=True, eq=False)
class Scene:
    """One simulation set-up (internal units inside, SI accessors for the outside).

    Attributes:
        name: preset name.
        lattice: topology.
        supports: prescribed DOFs.
        material: material constants.
        loading: input and stage signals.
        design: [n_design] design vector, mm.
        window_start: start of the dynamic (objective) window, ms.
        window: length T of the dynamic window, ms.
        n_samples: N_t samples on [window_start, window_start + T].
        targets: name -> unit ids of each target region.
        input_units: ids of the units driven by the input.
        clamped_units: ids of units fixed in all DOFs.
        stage_units_bottom, stage_units_top: ids of the stage-driven rows (empty without stages).
        line_row: row used for the "peak kinetic energy along a line" metric.
        spin_point: reference point S of the angular-momentum objective (mm), or None.
        model: the energy model (`energy.Model`: which ligament and contact laws), passed by
            every solve of the scene (simulator, statics, modal analysis, solver policy).
    """

    name: str
    lattice: Lattice
    supports: Supports
    material: Material
    loading: Loading
    design: np.ndarray
    window_start: float
    window: float
    n_samples: int
    targets: dict[str, np.ndarray]
    input_units: np.ndarray
    clamped_units: np.ndarray
    stage_units_bottom: np.ndarray
    stage_units_top: np.ndarray
    line_row: int
    spin_point: np.ndarray | None = None
    recipe: dict = field(default_factory=dict)
    model: Model = DEFAULT_MODEL

    @property
    def n_units(self) -> int:
        return self.lattice.n_blocks

    @property
    def sample_times(self) -> np.ndarray:
        """[n_samples] sample times of the dynamic window, ms (solver time axis)."""
        return self.window_start + np.linspace(0.0, self.window, self.n_samples)

    @property
    def sample_height_m(self) -> float:
        """Nominal height (N_y - 1) s that the pre-compression strain refers to, m."""
        return (self.lattice.shape[1] - 1) * self.lattice.spacing / 1e3

    def reference_polygons_m(self) -> np.ndarray:
        """[n_units, n_vertices, 2] reference outline of every unit in the sample frame, m."""
        g = block_geometry(self.lattice, jnp.asarray(self.design))
        return np.asarray(g.centroids[:, None, :] + g.arms) / 1e3

    def unit_masses_kg(self) -> np.ndarray:
        """[n_units] unit masses, kg."""
        g = block_geometry(self.lattice, jnp.asarray(self.design))
        return np.asarray(self.material.density * g.areas) / 1e3

    def unit_inertias_kgm2(self) -> np.ndarray:
        """[n_units] rotary inertias about the area centroid, kg m^2."""
        g = block_geometry(self.lattice, jnp.asarray(self.design))
        return np.asarray(self.material.density * g.polar_moments) / 1e9

    def with_design(self, design) -> "Scene":
        """The same scene with another design vector (mm), validated."""
        return replace(self, design=check_design(self.lattice, design))


def _supports(lattice: Lattice, kind: str, inputs: np.ndarray, side: str) -> tuple[Supports, dict]:
    rules: dict[tuple[int, int], tuple[int, float]] = {}
    sets = {"clamped": np.zeros(0, np.int64), "bottom": np.zeros(0, np.int64),
            "top": np.zeros(0, np.int64)}
    if kind == "corners":
        sets["clamped"] = corner_clamps(lattice)
        for b in sets["clamped"]:
            for d in range(3):
                rules[(int(b), d)] = (CH_ZERO, 0.0)
    elif kind == "stages":
        ny = lattice.shape[1]
        sets["bottom"], sets["top"] = row_units(lattice, 0), row_units(lattice, ny - 1)
        for ids, gain in ((sets["bottom"], 0.5), (sets["top"], -0.5)):
            for b in ids:
                rules[(int(b), 0)] = (CH_ZERO, 0.0)
                rules[(int(b), 1)] = (CH_STAGE, gain)
                rules[(int(b), 2)] = (CH_ZERO, 0.0)
    elif kind != "free":
        raise ValueError(f"unknown supports {kind!r} (corners, stages, free)")
    axis, sign = {"left": (0, 1.0), "right": (0, -1.0), "bottom": (1, 1.0), "top": (1, -1.0)}[side]
    for b in inputs:
        for d in range(3):
            rules[(int(b), d)] = (CH_INPUT, sign) if d == axis else (CH_ZERO, 0.0)
    return Supports.from_rules(lattice.n_blocks, rules), sets


def build_scene(
    name: str = "focusing-24x16",
    *,
    nx: int | None = None,
    ny: int | None = None,
    bias_angle_deg: float | None = None,
    amplitude_m: float | None = None,
    frequency_hz: float = 30.0,
    strain: float | None = None,
    design: np.ndarray | None = None,
    n_samples: int | None = None,
    target_windows: dict[str, tuple[tuple[int, int], tuple[int, int]]] | None = None,
    side: str | None = None,
    shift: int | None = None,
    contact_deg: tuple[float, float] | None = None,
    periods: float | None = None,
    precompression: str = "static",
) -> Scene:
    """Build a preset scene, optionally resized or re-loaded.

    Args:
        name: a key of `PRESETS`.
        nx, ny: lattice size (units for quads, cells for kagome); default the preset's. A resized
            lattice keeps targets and input offsets at the same relative position (offsets scaled
            by the size ratio and rounded).
        bias_angle_deg: bias angle of the periodic initial design (default 25 deg; kagome 0).
        amplitude_m: input amplitude, m (default half the spacing: 7.5 mm quads, 10 mm kagome).
        frequency_hz: input frequency, Hz (also sets delay 0.1/f and window periods/f).
        strain: pre-compression strain of stage scenes (0..0.2).
        design: design vector in mm (overrides the periodic design); validated.
        n_samples: samples in the dynamic window (default 200; spin 250).
        target_windows: name -> ((w, h), (sx, sy)) target regions replacing the preset's (for
            resized lattices whose preset windows do not fit).
        side, shift: input side (left, right, bottom, top) and offset of the two driven units
            (spec 7.2), replacing the preset's; an explicit shift is used as given (not scaled).
        contact_deg: (theta_min, theta_cutoff) contact angles, degrees (spec 5.3).
        periods: window length T in input periods (default the preset's: 2, spin 5, kagome 3).
        precompression: how a stage scene with strain > 0 is pre-compressed: "static" (default:
            the pulse starts from rest in the static equilibrium under the closed stages, the
            rig's protocol) or "ramp" (the stages close at 0.25 1/s and the dynamics follow,
            the reference's two-stage protocol, spec 7.4; the pulse starts at t_c).
    """
    if name not in PRESETS:
        raise ValueError(f"unknown scene {name!r}; choose one of: {', '.join(PRESETS)}")
    r = dict(PRESETS[name])
    explicit_shift = shift is not None
    r.update({k: v for k, v in (("side", side), ("shift", shift), ("contact_deg", contact_deg),
                                ("periods", periods)) if v is not None})
    if n_samples is not None and n_samples < 2:
        raise ValueError(f"the dynamic window needs at least 2 samples, got {n_samples}")
    if periods is not None and not (math.isfinite(periods) and periods > 0):
        raise ValueError(f"window length must be a positive number of periods, got {periods}")
    shape = (r["shape"][0] if nx is None else nx, r["shape"][1] if ny is None else ny)
    lattice = quads(*shape) if r["kind"] == "quads" else kagome(*shape)
    if frequency_hz <= 0 or not math.isfinite(frequency_hz):
        raise ValueError(f"frequency must be positive, got {frequency_hz} Hz")
    bias = r.get("bias_deg", 25.0) if bias_angle_deg is None else bias_angle_deg
    x = periodic_design(lattice, math.radians(bias)) if design is None else design
    x = check_design(lattice, x)
    d = default_si()  # the default material file (spec 10: -15 / -10 deg)
    cmin, ccut = r.get("contact_deg", (d["contact_min_deg"], d["contact_cutoff_deg"]))
    if not -90.0 < cmin < ccut < 0.0:
        raise ValueError(f"contact angles need -90 < theta_min < theta_cutoff < 0 deg, got "
                         f"{cmin}, {ccut}")
    material = Material.paper(lattice, contact_min_deg=cmin, contact_cutoff_deg=ccut)
    shift = r["shift"]
    if shape != tuple(r["shape"]) and not explicit_shift:
        axis = 1 if r["side"] in ("left", "right") else 0
        shift = round(shift * shape[axis] / r["shape"][axis])
    inputs = driven_units(lattice, r["side"], 2, shift)
    supports, sets = _supports(lattice, r["supports"], inputs, r["side"])
    amp = 0.5 * lattice.spacing if amplitude_m is None else 1e3 * amplitude_m
    if not 0.0 < amp < 2.0 * lattice.spacing:
        raise ValueError(f"amplitude {amp / 1e3} m outside (0, {2 * lattice.spacing / 1e3}) m")
    f = frequency_hz / 1e3
    eps = r.get("strain", 0.0) if strain is None else strain
    if eps and r["supports"] != "stages":
        raise ValueError(f"scene {name!r} has no stages; pre-compression needs a stage scene")
    if not 0.0 <= eps <= 0.2:
        raise ValueError(f"pre-compression strain {eps} outside [0, 0.2]")
    if precompression not in PRECOMPRESSION:
        raise ValueError(f"precompression must be one of {', '.join(PRECOMPRESSION)}, got "
                         f"{precompression!r}")
    mode = precompression if eps > 0 else "ramp"  # without strain both are the same solve
    tc = eps / STRAIN_RATE if eps > 0 and mode == "ramp" else 0.0
    loading = Loading(
        waveform=r.get("waveform", "pulse"),
        amplitude=amp,
        frequency=f,
        delay=0.1 / f,
        pulse_start=tc,
        strain=eps,
        strain_rate=STRAIN_RATE,
        stage_height=(shape[1] - 1) * lattice.spacing,
        precompression=mode,
    )
    if target_windows is not None:
        r["targets"] = dict(target_windows)
    elif shape != tuple(r["shape"]):
        # a resized lattice keeps each target at the same relative position
        fx, fy = shape[0] / r["shape"][0], shape[1] / r["shape"][1]
        r["targets"] = {k: (wh, (round(o[0] * fx), round(o[1] * fy))) for k, (wh, o) in r["targets"].items()}
    targets = {k: window(lattice, *v) for k, v in r["targets"].items()}
    window_start = tc + loading.delay if r["supports"] == "stages" else 0.0
    scene = Scene(
        name=name,
        lattice=lattice,
        supports=supports,
        material=material,
        loading=loading,
        design=x,
        window_start=window_start,
        window=r["periods"] / f,
        n_samples=r.get("n_samples", 200) if n_samples is None else n_samples,
        targets=targets,
        input_units=inputs,
        clamped_units=sets["clamped"],
        stage_units_bottom=sets["bottom"],
        stage_units_top=sets["top"],
        line_row=min(r["line_row"], shape[1] - 1),
        recipe=r,
    )
    if r.get("spin"):
        g = block_geometry(lattice, jnp.asarray(periodic_design(lattice, math.radians(bias))))
        point = np.asarray(g.centroids)[targets["target"]].mean(axis=0)
        scene = replace(scene, spin_point=point)
    return scene
