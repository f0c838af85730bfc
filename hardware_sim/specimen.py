"""The specimen on the simulated rig: a design_engine scene driven by the measured rig motion.

The sample is simulated by `design_engine.simulate_rig` under the *actual* (measured) shaker and
stage motion, from rest at t = 0. This is a batch computation: the whole record of the
stage closing and of the shaker displacement must be known first, then the trajectory is solved
once and sampled at the requested times (the simulated rig films the sample afterwards, like a
high-speed camera downloading its memory).

The sample is not its model: by default it carries the imperfections of a fabricated sample
(`Imperfections`: cut tolerance of the outlines, scatter of every ligament's stiffness and of
every unit's damping, a ligament thickness error common to the print, friction with the base
plate), seeded, each with a default and a switch (0: off). Only the rig's truth has them: the
design file it publishes (`Specimen.design_json`) holds the nominal design, so the comparison
and the calibration see the sample as it was designed. Optionally the specimen's stiffnesses and
damping are also scaled as a whole (`perturb`, log-normal, seeded).
"""

import json
from dataclasses import asdict, dataclass, replace

import numpy as np

from metarig.fields import param


@dataclass(frozen=True, slots=True)
class Imperfections:
    """How the sample on the rig differs from its design and nominal material (the rig's truth
    only). Each imperfection is off at 0, and `level` multiplies them all (0: the nominal
    specimen, exactly). The random ones are drawn from their own seeded streams
    (`IMPERFECTION_STREAMS`), so switching one off or rescaling leaves the others' draws as
    they were. Defaults and their sources: README, "The specimen is not the model"."""

    level: float = param(1.0, "multiplies every imperfection (0: the nominal specimen; 1: the "
                         "defaults)", 0.0, 10.0)
    tolerance_m: float = param(5.0e-5, "cut tolerance: 1-sigma position error of every vertex "
                               "of the unit outlines (a ligament's two vertices move together), m",
                               0.0, 1.0e-3)
    ligament_scatter: float = param(0.10, "1-sigma log-normal scatter of each ligament's "
                                    "stiffnesses (stretch, shear and bend by one factor)",
                                    0.0, 1.0)
    damping_scatter: float = param(0.20, "1-sigma log-normal scatter of each unit's damping",
                                   0.0, 1.0)
    thickness_error: float = param(-0.03, "ligament thickness error common to the print, "
                                   "relative: k_bend x (1 + e)^3, k_stretch and k_shear x (1 + e)",
                                   -0.5, 0.5)
    friction_hz: float = param(2.0, "viscous friction with the base plate per unit mass, 1/s: "
                               "force -rate m v, torque -rate J omega on every unit", 0.0, 1000.0)


IMPERFECTION_STREAMS = {"tolerance_m": 1, "ligament_scatter": 2, "damping_scatter": 3}
NOMINAL = Imperfections(level=0.0)  # the specimen is its model (tests of the tracker, recordings)


def thickness_factors(error: float) -> dict[str, float]:
    """Stiffness factors of a ligament thickness error e (relative): the shim is a thin plate,
    bending as t^3 (EI, I = w t^3 / 12), stretching and shearing as t (EA, GA); the contact
    between the PLA units does not involve it."""
    t = 1.0 + error
    return {"k_stretch": t, "k_shear": t, "k_bend": t**3}


def imperfect(scene, imp: Imperfections, seed: int) -> tuple[object, dict]:
    """The true scene of a sample with imperfections `imp` (see `Imperfections`), and a
    JSON-ready summary of what they did. The stiffnesses become per-bond [n_bonds] arrays and
    the damping per-unit [n_blocks] arrays where an imperfection varies them
    (`design_engine.physics.material.Material`); a switched-off imperfection changes nothing.

    Friction with the base plate is viscous on the absolute velocity, proportional to each
    unit's weight: force -gamma m_b v and, summed over the unit's footprint, torque
    -gamma J_b omega; the model's damping already has that form, so it adds gamma (m_b, J_b)
    to the unit's damping coefficients."""
    lam = float(imp.level)

    def draws(name: str, n: int) -> np.ndarray:
        return np.random.default_rng([seed, IMPERFECTION_STREAMS[name]]).standard_normal(n)

    summary = {}
    tol_mm = 1e3 * lam * imp.tolerance_m
    if tol_mm > 0:
        dx = tol_mm * draws("tolerance_m", scene.design.size)
        scene = scene.with_design(scene.design + dx)
        summary["vertex_error_rms_m"] = float(np.sqrt(np.mean(dx**2))) / 1e3
    m = scene.material
    stiff = {n: 1.0 for n in ("k_stretch", "k_shear", "k_bend")}
    if lam * imp.thickness_error != 0:
        stiff = thickness_factors(lam * imp.thickness_error)
        summary["thickness_factors"] = stiff
    per_bond = 1.0
    if lam * imp.ligament_scatter > 0:
        per_bond = np.exp(lam * imp.ligament_scatter
                          * draws("ligament_scatter", scene.lattice.n_bonds))
        summary["ligament_factor_range"] = [float(per_bond.min()), float(per_bond.max())]
    fields = {n: getattr(m, n) * f * per_bond for n, f in stiff.items()
              if f != 1.0 or lam * imp.ligament_scatter > 0}
    f = np.ones(scene.lattice.n_blocks)
    if lam * imp.damping_scatter > 0:
        f = np.exp(lam * imp.damping_scatter * draws("damping_scatter", scene.lattice.n_blocks))
        summary["damping_factor_range"] = [float(f.min()), float(f.max())]
    gamma = lam * imp.friction_hz / 1e3  # 1/ms
    if lam * imp.friction_hz > 0:
        summary["friction_rate_hz"] = lam * imp.friction_hz
    if lam * (imp.damping_scatter + imp.friction_hz) > 0:
        fields["damping_u"] = m.damping_u * f + gamma * 1e3 * scene.unit_masses_kg()  # g/ms
        fields["damping_theta"] = (m.damping_theta * f
                                   + gamma * 1e9 * scene.unit_inertias_kgm2())  # g mm^2/ms
    if fields:
        scene = replace(scene, material=m.replaced(**fields))
    return scene, summary


@dataclass(frozen=True, slots=True)
class SpecimenConfig:
    """Which sample is on the rig."""

    scene: str = param("precompression-24x18", "design_engine scene name")
    nx: int = param(24, "units along x", 2, 200)
    ny: int = param(16, "units along y", 2, 200)
    bias_angle_deg: float = param(25.0, "bias angle of the periodic design, deg", -45.0, 45.0)
    design_path: str = param("", "design file (metarig-design/1) of the sample; its lattice "
                             "sets nx, ny (empty: the periodic design)")
    material_path: str = param("", "material file (metarig-material/1) of the sample's nominal "
                               "material (empty: the default)")
    material_si: str = param("", "the sample's nominal material as the SI values of its "
                             "material file, JSON, for a caller that read the file already "
                             "(`metarig rig`); it is then not read again (empty: read "
                             "material_path)")
    perturb: float = param(0.0, "relative (1 sigma) spread of true stiffnesses and damping",
                           0.0, 0.5)
    seed: int = param(0, "seed of the perturbation and of the imperfections", 0, 2**31 - 1)
    imperfections: Imperfections = param(Imperfections, "how the sample differs from its model")


@dataclass(frozen=True)
class Specimen:
    """A built sample: its true scene (imperfect design and parameters) and its true reference
    unit outlines (m), which the camera films.

    `material_si` holds the SI values of the sample's material file (`SpecimenConfig.
    material_path`), recorded in `design_json` so that the comparison uses the same nominal
    material. `nominal_design` (mm) is the design the sample was made from (None: the true
    scene's), the one `design_json` publishes; `imperfections` summarises what the
    imperfections did."""

    config: SpecimenConfig
    scene: object
    polygons_m: np.ndarray
    factors: dict
    material_si: dict | None = None  # SI values the material file gave (None: the default)
    nominal_design: np.ndarray | None = None
    imperfections: dict | None = None

    @property
    def nominal_polygons_m(self) -> np.ndarray:
        """[n_units, n_vertices, 2] the designed outlines (m): where the lab expects the units."""
        if self.nominal_design is None:
            return self.polygons_m
        return np.asarray(self.scene.with_design(self.nominal_design).reference_polygons_m())

    @property
    def n_units(self) -> int:
        return int(self.polygons_m.shape[0])

    def effective_si(self) -> dict[str, float]:
        """The sample's effective material, SI (`Material.to_si` names): each true field's mean
        over the bonds (stiffnesses) or the units (damping, friction included). What a
        calibration of the nominal model against this sample should find, to within what the
        scatter's realisation and the geometry make of it (the model error)."""
        m = self.scene.material
        fields = ("k_stretch", "k_shear", "k_bend", "k_contact", "damping_u", "damping_theta")
        return m.replaced(**{n: float(np.mean(np.asarray(getattr(m, n)))) for n in fields}).to_si()

    def centroids_m(self) -> np.ndarray:
        """[n_units, 2] reference area centroids, m."""
        from metarig.polygon import area_centroids

        return area_centroids(self.polygons_m)

    def design_json(self) -> str:
        """The sample as it was designed, a `metarig-design/1` design file (loadable by `metarig
        simulate --design`), plus the rig context: scene, inputs, stage rows, the true-parameter
        factors and the imperfections' settings (not their draws: what a lab knows)."""
        from design_engine.design.design_io import design_document

        s = self.scene
        design = s.design if self.nominal_design is None else self.nominal_design
        return json.dumps(design_document(
            s.lattice, design,
            scene=self.config.scene, bias_angle_deg=self.config.bias_angle_deg,
            n_units=self.n_units, sample_height_m=float(s.sample_height_m),
            input_units=[int(i) for i in s.input_units],
            stage_units_bottom=[int(i) for i in s.stage_units_bottom],
            stage_units_top=[int(i) for i in s.stage_units_top],
            true_parameter_factors=self.factors,
            specimen_imperfections=asdict(self.config.imperfections),
            **({"material_file": self.config.material_path, "material_si": self.material_si}
               if self.material_si is not None else {}),
        ))


def build(cfg: SpecimenConfig) -> Specimen:
    """Build the scene (strain 0: the stages apply the measured closing), give it the material
    file's nominal material (if any), perturb it and make it imperfect (`imperfect`)."""
    import design_engine as de

    nx, ny, design = cfg.nx, cfg.ny, None
    if cfg.design_path:
        from design_engine.design.design_io import load_design

        lattice, design = load_design(cfg.design_path)
        nx, ny = lattice.shape
    scene = de.build_scene(cfg.scene, nx=nx, ny=ny, bias_angle_deg=cfg.bias_angle_deg,
                           strain=0.0)
    if design is not None:
        if scene.lattice.kind != lattice.kind:
            raise ValueError(f"{cfg.design_path}: a {lattice.kind} design does not fit the "
                             f"{scene.lattice.kind} scene {cfg.scene}")
        scene = scene.with_design(design)
    material_si = None
    if cfg.material_si or cfg.material_path:
        from design_engine.physics.material_file import material_for_scene

        source = json.loads(cfg.material_si) if cfg.material_si else cfg.material_path
        material, material_si = material_for_scene(scene, source)
        scene = replace(scene, material=material)
    factors = {}
    if cfg.perturb > 0:
        rng = np.random.default_rng(cfg.seed)
        names = ("k_stretch", "k_shear", "k_bend", "k_contact", "damping_u", "damping_theta")
        factors = {n: float(np.exp(cfg.perturb * rng.standard_normal())) for n in names}
        scene = replace(scene, material=scene.material.scaled(factors))
    nominal_design = scene.design
    scene, summary = imperfect(scene, cfg.imperfections, cfg.seed)
    return Specimen(cfg, scene, np.asarray(scene.reference_polygons_m()), factors, material_si,
                    nominal_design, summary)


def simulate(specimen: Specimen, times_s, shaker_t_s, shaker_u_m, stage_t_s=None,
             stage_closing_m=None):
    """Unit motion at `times_s` (s, increasing, >= 0) under the measured rig motion.

    Args:
        specimen: the sample.
        times_s: [n_t] output times, s.
        shaker_t_s, shaker_u_m: [n] measured shaker displacement (m) at times (s).
        stage_t_s, stage_closing_m: [m] measured total stage closing (m) at times (s), or None.

    Returns:
        `design_engine.Trajectory` (t [n_t], q and qdot [n_t, n_units, 3], SI).
    """
    import design_engine as de
    from design_engine.solve.policy import contact_config
    from design_engine.solve.run import smooth_input

    has_stages = len(specimen.scene.stage_units_top) > 0
    # the shaker's joint states sample a smooth motion (a 250 Hz second-order drive): the
    # specimen feels their cubic spline, not the polyline with a velocity jump at every sample
    shaker_t_s, shaker_u_m = smooth_input(shaker_t_s, shaker_u_m)
    # the rig's physics: the full model at the reference tolerances (not the fast default,
    # whose error a chaotic large-amplitude scene amplifies into a different motion)
    return de.simulate_rig(specimen.scene, np.asarray(times_s, np.float64),
                           np.asarray(shaker_t_s, np.float64), np.asarray(shaker_u_m, np.float64),
                           stage_t_s if has_stages else None,
                           stage_closing_m if has_stages else None, config=contact_config())
