"""Robustness map (the paper's Fig. 2C): target-to-rest energy ratio over input frequency x amplitude.

For a design and a scene, every grid point (f, A) is the scene with a pulse input of frequency f
and amplitude A. All points share one time axis, tied to the LOWEST frequency f_min of the grid:
input delay t_d = 0.1 / f_min, window t_f = periods / f_min (2 periods for the focusing scene,
sampled at the scene's N_t = 200 points), so that the grid is one batch of `Loading`s on one time
grid and costs one compilation (`jax.vmap` of the simulator, run in chunks of a fixed size; the
last chunk is padded).

The metric is R = J_target / J_rest (`objectives.region_energy_ratio`, both sums of the kinetic
energy over the same samples; the rest includes the clamped units (zero) and the driven units).

Solver policy, per point (the one policy driver's `driver.decide`, as `run.simulate_scene`
applies it to one solve): the batch runs with `run.default_choice(scene)`; a point whose result
the policy rejects (voids reached the contact cutoff, the barrier outgrew the fixed step or the
work-energy balance drifted) is re-run, batched with the other such points, with the
configuration it names, and a point whose solve failed (result code, non-finite or diverged
state) with the fallback. A point that fails with every configuration is NaN in the map and
listed with its reason. `robustness_chunk` evaluates a list of points from plain data (design vector, lattice
description) so that chunks can be sent to other processes (Dask workers).

Units: the public functions take and return SI (Hz, m, J, s); internally mm, ms, mJ.
"""

import logging
import math
import os
import platform
import time
from dataclasses import dataclass, replace

import jax
import jax.numpy as jnp
import numpy as np

from design_engine.physics import units
from design_engine.physics.lattice import lattice_from_description
from design_engine.physics.loading import Loading
from design_engine.physics.scenes import Scene, build_scene
from design_engine.solve.driver import PolicyFailed, decide
from design_engine.solve.objectives import region_energy, region_energy_ratio
from design_engine.solve.policy import choose_config, fallback_config
from design_engine.solve.run import compile_key, config_summary, default_choice
from design_engine.solve.simulate import (SimulationError, SolverConfig, health_failure,
                                          make_simulator, solve_health)

log = logging.getLogger("metarig.robustness")

DEFAULT_CHUNK = 24  # grid points per vmap batch on an accelerator (the 8 x 9 grid is 3 chunks)
# On the CPU a vmap batch costs more per point than single solves (gathers in the batched force;
# focusing-24x16, Verlet float32, 2 loaded cores: 0.11 s/point at 1, 0.14 at 4, 0.18 at 24; the
# spec's 8 x 9 map of the optimised 24x16 design on 2 workers: 282 s at 1, 441 s at 4)
CPU_CHUNK = 1
DELAY_PERIODS = 0.1  # input delay t_d = 0.1 / f_min (as the paper's 0.1 / f)

_BATCHED: dict[tuple, object] = {}


@dataclass(frozen=True)
class RobustnessMap:
    """Result of `robustness_map` (SI).

    Attributes:
        frequencies_hz: [nf] input frequencies, Hz.
        amplitudes_m: [na] input amplitudes, m.
        ratio: [nf, na] R = J_target / J_rest; NaN where every configuration failed.
        target_ke_mean_J: [nf, na] target kinetic energy, mean over the N_t samples, J.
        point_config: [nf, na] index into `configs` of the configuration each point's value
            comes from; -1 where every configuration failed.
        point_notes: [nf, na] why a point was re-solved or failed ("" for none).
        configs: configurations used, each {"solver": config summary, "reasons": [lines]}.
        failures: the failed points, each {"frequency_hz", "amplitude_m", "reason"}.
        target: name of the target region (the scene's first).
        timing: {"tied_to_hz": f_min, "delay_s", "window_s", "n_samples"} shared by all points.
        wall_s: wall time of the whole map (compilation included), s.
    """

    frequencies_hz: np.ndarray
    amplitudes_m: np.ndarray
    ratio: np.ndarray
    target_ke_mean_J: np.ndarray
    point_config: np.ndarray
    point_notes: np.ndarray
    configs: tuple[dict, ...]
    failures: tuple[dict, ...]
    target: str
    timing: dict
    wall_s: float


# ---------------------------------------------------------------------------------------------
# grid and tied timing


def grid_points(frequencies_hz, amplitudes_m) -> np.ndarray:
    """[nf * na, 2] (f Hz, A m) of the grid, frequency-major (point k = (k // na, k % na))."""
    f = np.asarray(frequencies_hz, np.float64).reshape(-1)
    a = np.asarray(amplitudes_m, np.float64).reshape(-1)
    ff, aa = np.meshgrid(f, a, indexing="ij")
    return np.stack([ff.reshape(-1), aa.reshape(-1)], axis=1)


def default_chunk() -> int:
    """Grid points per vmap batch: `DEFAULT_CHUNK` on an accelerator, `CPU_CHUNK` on the CPU."""
    return CPU_CHUNK if jax.default_backend() == "cpu" else DEFAULT_CHUNK


def _periods(scene: Scene) -> float:
    """Window length of the scene in input periods (2 for focusing)."""
    return float(scene.window * scene.loading.frequency)


def check_grid(scene: Scene, frequencies_hz, amplitudes_m) -> tuple[np.ndarray, np.ndarray]:
    """Validated 1-D float arrays (Hz, m); raises ValueError naming the bad value."""
    f = np.asarray(frequencies_hz, np.float64).reshape(-1)
    a = np.asarray(amplitudes_m, np.float64).reshape(-1)
    if f.size == 0 or a.size == 0:
        raise ValueError("the grid needs at least one frequency and one amplitude")
    for v in f:
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"frequencies must be positive, got {v:g} Hz")
    s_m = scene.lattice.spacing / units.MM_PER_M
    for v in a:
        if not (math.isfinite(v) and 0 < v < 2 * s_m):
            raise ValueError(f"amplitudes must lie in (0, 2 s) = (0, {2 * s_m:g}) m, got {v:g} m")
    if len(set(f.tolist())) != f.size or len(set(a.tolist())) != a.size:
        raise ValueError("the grid has a repeated frequency or amplitude")
    return f, a


def tied_timing(scene: Scene, f_min_hz: float) -> dict:
    """Delay, window and samples shared by all grid points (SI), tied to f_min."""
    f = f_min_hz / units.MS_PER_S
    return {"tied_to_hz": float(f_min_hz), "delay_s": units.time_to_si(DELAY_PERIODS / f),
            "window_s": units.time_to_si(_periods(scene) / f), "n_samples": scene.n_samples}


def point_loading(scene: Scene, frequency_hz: float, amplitude_m: float, f_min_hz: float) -> Loading:
    """The scene's loading with frequency f, amplitude A and the delay tied to f_min."""
    return replace(scene.loading, frequency=frequency_hz / units.MS_PER_S,
                   amplitude=units.length_from_si(amplitude_m),
                   delay=DELAY_PERIODS * units.MS_PER_S / f_min_hz)


def point_scene(scene: Scene, frequency_hz: float, amplitude_m: float, f_min_hz: float) -> Scene:
    """The scene of one grid point, tied timing included (for single-point checks).

    Its `sample_times` equal `tied_sample_times(scene, f_min_hz)`.
    """
    loading = point_loading(scene, frequency_hz, amplitude_m, f_min_hz)
    start = loading.pulse_start + loading.delay if scene.recipe.get("supports") == "stages" else 0.0
    return replace(scene, loading=loading, window_start=start,
                   window=_periods(scene) * units.MS_PER_S / f_min_hz)


def tied_sample_times(scene: Scene, f_min_hz: float) -> np.ndarray:
    """[N_t] sample times shared by the grid, ms (solver time axis)."""
    amplitude_m = scene.loading.amplitude / units.MM_PER_M
    return point_scene(scene, f_min_hz, amplitude_m, f_min_hz).sample_times


# ---------------------------------------------------------------------------------------------
# batched solve


def _summary_fn(sim, ids: np.ndarray):
    """Per-point reduction of a solution to scalars (energies summed in float64)."""

    def one(x, material, loading, ts):
        sol = sim(x, material, loading, ts)
        sol64 = jax.tree_util.tree_map(
            lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a, sol)
        return dict(solve_health(sol64), ratio=region_energy_ratio(sol64, ids),
                    target_energy=region_energy(sol64, ids))

    return one


def batched_simulator(scene: Scene, config: SolverConfig, ts_ms):
    """jit(vmap) of the per-point summary over a batch of Loadings (cached per topology).

    Returns `f(x, material, loadings, ts) -> dict of [batch] arrays` (ratio, target_energy mJ,
    result, finite, max_disp mm, max_rot rad, void_margin rad, num_steps); `loadings` is a
    `Loading` whose float fields are [batch] arrays.
    """
    ids = np.asarray(next(iter(scene.targets.values())))
    key = compile_key(scene, config, "robustness", ts_ms) + (ids.tobytes(),)
    if key not in _BATCHED:
        sim = make_simulator(scene.lattice, scene.supports, config, np.asarray(ts_ms),
                             model=scene.model)
        _BATCHED[key] = jax.jit(jax.vmap(_summary_fn(sim, ids), in_axes=(None, None, 0, None)))
    return _BATCHED[key]


def stack_loadings(loadings: list[Loading]) -> Loading:
    """One `Loading` with [batch] float fields from a list of same-waveform Loadings."""
    return jax.tree_util.tree_map(lambda *v: jnp.stack([jnp.asarray(e) for e in v]), *loadings)


def _batch_size(n: int, chunk: int, full: bool) -> int:
    """Size the last batch is padded to: the chunk (one program) or the next power of two."""
    if full or n >= chunk:
        return chunk
    return min(chunk, 1 << max(0, (n - 1).bit_length()))


def _solve(scene: Scene, config: SolverConfig, ts_ms, loadings: list[Loading], chunk: int,
           full: bool):
    """Yield (start, summaries) per batch of `chunk` loadings (last batch padded with its last
    point: to `chunk` when `full`, else to the next power of two)."""
    x = jnp.asarray(scene.design)
    ts = jnp.asarray(ts_ms)
    fn = batched_simulator(scene, config, ts_ms)
    for start in range(0, len(loadings), chunk):
        part = loadings[start:start + chunk]
        size = _batch_size(len(part), chunk, full)
        res = jax.block_until_ready(
            fn(x, scene.material, stack_loadings(part + [part[-1]] * (size - len(part))), ts))
        yield start, {k: np.asarray(v)[:len(part)] for k, v in res.items()}


def _failure(config: SolverConfig, point: dict) -> str | None:
    """Why a point of a batch (its summary scalars) failed (`simulate.health_failure`), or None."""
    msg = health_failure(point, config)
    if msg is None and not np.isfinite(point["ratio"]):
        msg = "non-finite energy ratio"
    return msg


def evaluate_points(scene: Scene, points, *, f_min_hz: float, chunk: int | None = None,
                    choice=None, progress=None) -> dict:
    """Evaluate grid points with the solver policy (see module docstring); plain results.

    Args:
        scene: the scene (design included); its loading gives waveform and pulse start.
        points: [n, 2] (frequency Hz, amplitude m).
        f_min_hz: frequency the timing is tied to (the grid's lowest, also for a sub-list).
        chunk: grid points per vmap batch (default `default_chunk()`).
        choice: `policy.Choice` to start from (default `run.default_choice(scene)`).
        progress: called with the number of points whose result became final.

    Returns:
        dict of lists, one entry per point: "frequency_hz", "amplitude_m", "ratio" (NaN on
        failure), "target_ke_mean_J", "config" (index into "configs", -1 on failure), "note";
        and "configs" ([{"solver": summary, "reasons": [...]}]), "wall_s", "process"
        ("host:pid" that computed them).
    """
    t0 = time.perf_counter()
    chunk = default_chunk() if chunk is None else chunk
    if chunk < 1:
        raise ValueError(f"chunk must be at least 1, got {chunk}")
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    n = pts.shape[0]
    ts = tied_sample_times(scene, f_min_hz)
    loadings = [point_loading(scene, f, a, f_min_hz) for f, a in pts]
    choice = choice or default_choice(scene)
    ratio = np.full(n, np.nan)
    energy = np.full(n, np.nan)
    used = np.full(n, -1, np.int64)
    notes = [""] * n
    configs: list[dict] = []
    tried: list[set[str]] = [set() for _ in range(n)]  # configurations each point has seen
    # (configuration, reasons, points) still to solve; a point that fails goes to the fallback,
    # a point `policy.next_config` sends on goes to the configuration it names (as simulate_scene)
    queue = [(choice.config, list(choice.reasons), list(range(n)))]
    fallback = fallback_config()[0]
    todo: list[int] = []
    first = True
    while queue:
        config, reasons, points = queue.pop(0)
        for i in points:
            tried[i].add(repr(config))
        configs.append({"solver": config_summary(config), "reasons": reasons})
        idx = len(configs) - 1
        groups: dict[str, tuple] = {}
        for start, res in _solve(scene, config, ts, [loadings[i] for i in points], chunk, first):
            final = 0
            for k, i in enumerate(points[start:start + len(res["ratio"])]):
                point = {name: v[k] for name, v in res.items()}
                msg = _failure(config, point)
                try:
                    nxt = (decide(config, scene, health=point) if msg is None else
                           decide(config, scene, error=SimulationError(msg),
                                  fallen_back=config == fallback))
                except PolicyFailed:  # the fallback itself failed
                    notes[i] = f"{configs[idx]['solver']['solver']}: {msg}"
                    todo.append(i)
                    continue
                if nxt is not None:
                    notes[i] = f"{configs[idx]['solver']['solver']}: {msg or nxt.reason}"
                    if repr(nxt.config) in tried[i]:  # nothing new left to try for this point
                        todo.append(i)
                    else:
                        groups.setdefault(repr(nxt.config),
                                          (nxt.config, [nxt.reason], []))[2].append(i)
                    continue
                ratio[i] = float(res["ratio"][k])
                energy[i] = float(res["target_energy"][k])
                used[i] = idx
                final += 1
            if progress is not None and final:
                progress(final)
        first = False
        for cfg, why, members in groups.values():
            log.info("%d of %d points re-solved with %s", len(members), n,
                     config_summary(cfg)["solver"])
            queue.append((cfg, why, members))
    for i in todo:  # failed with every configuration
        notes[i] += " (failed with every configuration)"
    if todo and progress is not None:
        progress(len(todo))
    return {
        "frequency_hz": pts[:, 0].tolist(),
        "amplitude_m": pts[:, 1].tolist(),
        "ratio": ratio.tolist(),
        "target_ke_mean_J": [units.energy_to_si(e / scene.n_samples) for e in energy],
        "config": used.tolist(),
        "note": notes,
        "configs": configs,
        "wall_s": time.perf_counter() - t0,
        "process": f"{platform.node()}:{os.getpid()}",
    }


def robustness_chunk(design_m, lattice_description: dict, points, *, f_min_hz: float,
                     scene_name: str = "focusing-24x16", omega_rad_per_ms: float | None = None,
                     chunk: int | None = None) -> dict:
    """`evaluate_points` for a list of points from plain data (what a Dask task receives).

    Args:
        design_m: [n_design] design vector, m (as in a design file).
        lattice_description: `Lattice.describe()` of the design's lattice.
        points: [n, 2] (frequency Hz, amplitude m).
        f_min_hz: lowest frequency of the WHOLE grid (timing).
        scene_name: preset of the scene (built on the design's lattice size).
        omega_rad_per_ms: highest natural frequency of the design (rad/ms) measured by the
            caller, so every process picks the same step; None measures it here.
        chunk: points per vmap batch (default: all the points in one batch).
    """
    scene = design_scene(design_m, lattice_description, scene_name)
    choice = (default_choice(scene) if omega_rad_per_ms is None
              else choose_config(scene, omega=omega_rad_per_ms))
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    return evaluate_points(scene, pts, f_min_hz=f_min_hz, chunk=chunk or pts.shape[0],
                           choice=choice)


def design_scene(design_m, lattice_description: dict, scene_name: str = "focusing-24x16") -> Scene:
    """The preset scene on the design's lattice with the design (m in, validated).

    Raises ValueError if the preset's lattice differs from the design's (kind, spacing,
    ligament length); `geometry.InvalidDesignError` for an infeasible design.
    """
    lattice = lattice_from_description(lattice_description)
    nx, ny = lattice.shape
    scene = build_scene(scene_name, nx=nx, ny=ny,
                        design=np.asarray(design_m, np.float64) * units.MM_PER_M)
    if scene.lattice.describe() != lattice.describe():
        raise ValueError(f"the design's lattice {lattice.describe()} differs from the "
                         f"{scene_name} scene's {scene.lattice.describe()}")
    return scene


def robustness_map(scene: Scene, frequencies_hz, amplitudes_m, *, chunk: int | None = None,
                   progress=None) -> RobustnessMap:
    """R = J_target / J_rest over the grid frequencies x amplitudes (SI in and out).

    Args:
        scene: the scene with the design (its first target is the target region).
        frequencies_hz: [nf] input frequencies, Hz (> 0); the timing is tied to the lowest.
        amplitudes_m: [na] input amplitudes, m, in (0, 2 s).
        chunk: grid points per vmap batch (one compiled program of this batch size; default
            `default_chunk()`).
        progress: called with the number of points whose result became final.
    """
    t0 = time.perf_counter()
    f, a = check_grid(scene, frequencies_hz, amplitudes_m)
    res = evaluate_points(scene, grid_points(f, a), f_min_hz=float(f.min()), chunk=chunk,
                          progress=progress)
    return assemble_map(scene, f, a, [res], time.perf_counter() - t0)


def merge_configs(parts: list[dict]) -> tuple[list[dict], list[np.ndarray]]:
    """Union of the "configs" of several results; per part, its local -> global index map."""
    configs: list[dict] = []
    maps = []
    for p in parts:
        m = []
        for c in p["configs"]:
            if c not in configs:
                configs.append(c)
            m.append(configs.index(c))
        maps.append(np.asarray(m + [-1], np.int64))  # [-1] maps -1 (failed) to -1
    return configs, maps


def assemble_map(scene: Scene, frequencies_hz, amplitudes_m, parts: list[dict],
                 wall_s: float) -> RobustnessMap:
    """`RobustnessMap` from point results (`evaluate_points` / `robustness_chunk` outputs)."""
    f = np.asarray(frequencies_hz, np.float64)
    a = np.asarray(amplitudes_m, np.float64)
    nf, na = f.size, a.size
    ratio, energy = np.full((nf, na), np.nan), np.full((nf, na), np.nan)
    used = np.full((nf, na), -1, np.int64)
    notes = np.full((nf, na), "", dtype=object)
    seen = np.zeros((nf, na), bool)
    configs, maps = merge_configs(parts)
    failures = []
    for p, m in zip(parts, maps):
        for k, (fk, ak) in enumerate(zip(p["frequency_hz"], p["amplitude_m"])):
            i, j = np.flatnonzero(f == fk), np.flatnonzero(a == ak)
            if i.size == 0 or j.size == 0:
                continue
            i, j = int(i[0]), int(j[0])
            seen[i, j] = True
            ratio[i, j] = p["ratio"][k]
            energy[i, j] = p["target_ke_mean_J"][k]
            used[i, j] = m[p["config"][k]]
            notes[i, j] = p["note"][k]
            if used[i, j] < 0:
                failures.append({"frequency_hz": float(fk), "amplitude_m": float(ak),
                                 "reason": p["note"][k]})
    if not seen.all():
        missing = [(float(f[i]), float(a[j])) for i, j in zip(*np.nonzero(~seen))]
        raise ValueError(f"no result for grid points {missing[:5]}{' ...' if len(missing) > 5 else ''}")
    return RobustnessMap(
        frequencies_hz=f, amplitudes_m=a, ratio=ratio, target_ke_mean_J=energy,
        point_config=used, point_notes=notes, configs=tuple(configs), failures=tuple(failures),
        target=next(iter(scene.targets)), timing=tied_timing(scene, float(f.min())),
        wall_s=float(wall_s))


__all__ = ["CPU_CHUNK", "DEFAULT_CHUNK", "RobustnessMap", "assemble_map", "batched_simulator",
           "check_grid", "default_chunk", "design_scene", "evaluate_points", "grid_points",
           "point_loading", "point_scene", "robustness_chunk", "robustness_map",
           "tied_sample_times", "tied_timing"]
