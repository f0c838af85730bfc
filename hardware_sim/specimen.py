"""The specimen on the simulated rig: a design_engine scene driven by the measured rig motion.

The sample is simulated by `design_engine.simulate_rig` under the *actual* (measured) shaker and
stage motion, from rest at t = 0. This is a batch computation: the whole record of the
stage closing and of the shaker displacement must be known first, then the trajectory is solved
once and sampled at the requested times (the simulated rig films the sample afterwards, like a
high-speed camera downloading its memory). Optionally the specimen's "true" stiffnesses and
damping are perturbed from nominal (seeded), so that comparing measurement and nominal model
has something real to find.
"""

import json
from dataclasses import dataclass, replace

import numpy as np

from metarig.fields import param


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
    perturb: float = param(0.0, "relative (1 sigma) spread of true stiffnesses and damping",
                           0.0, 0.5)
    seed: int = param(0, "seed of the perturbation", 0, 2**31 - 1)


@dataclass(frozen=True)
class Specimen:
    """A built sample: its scene (with true parameters) and reference unit outlines (m).

    `material_si` holds the SI values of the sample's material file (`SpecimenConfig.
    material_path`), recorded in `design_json` so that the comparison uses the same nominal
    material."""

    config: SpecimenConfig
    scene: object
    polygons_m: np.ndarray
    factors: dict
    material_si: dict | None = None  # SI values the material file gave (None: the default)

    @property
    def n_units(self) -> int:
        return int(self.polygons_m.shape[0])

    def centroids_m(self) -> np.ndarray:
        """[n_units, 2] reference area centroids, m."""
        from metarig.polygon import area_centroids

        return area_centroids(self.polygons_m)

    def design_json(self) -> str:
        """The sample as a `metarig-design/1` design file (loadable by `metarig simulate --design`)
        plus the rig context: scene, inputs, stage rows and the true-parameter factors."""
        from design_engine.design_io import design_document

        s = self.scene
        return json.dumps(design_document(
            s.lattice, s.design,
            scene=self.config.scene, bias_angle_deg=self.config.bias_angle_deg,
            n_units=self.n_units, sample_height_m=float(s.sample_height_m),
            input_units=[int(i) for i in s.input_units],
            stage_units_bottom=[int(i) for i in s.stage_units_bottom],
            stage_units_top=[int(i) for i in s.stage_units_top],
            true_parameter_factors=self.factors,
            **({"material_file": self.config.material_path, "material_si": self.material_si}
               if self.material_si is not None else {}),
        ))


def build(cfg: SpecimenConfig) -> Specimen:
    """Build the scene (strain 0: the stages apply the measured closing), give it the material
    file's nominal material (if any) and perturb it."""
    import design_engine as de

    nx, ny, design = cfg.nx, cfg.ny, None
    if cfg.design_path:
        from design_engine.design_io import load_design

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
    if cfg.material_path:
        from design_engine.material_file import material_for_scene

        material, material_si = material_for_scene(scene, cfg.material_path)
        scene = replace(scene, material=material)
    factors = {}
    if cfg.perturb > 0:
        rng = np.random.default_rng(cfg.seed)
        names = ("k_stretch", "k_shear", "k_bend", "k_contact", "damping_u", "damping_theta")
        factors = {n: float(np.exp(cfg.perturb * rng.standard_normal())) for n in names}
        scene = replace(scene, material=scene.material.scaled(factors))
    return Specimen(cfg, scene, np.asarray(scene.reference_polygons_m()), factors, material_si)


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
    from design_engine.auto import contact_config
    from design_engine.run import smooth_input

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
