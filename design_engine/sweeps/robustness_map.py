"""Robustness maps as a resumable job: a grid of (frequency, amplitude) points of a design,
computed chunk by chunk (in process or on Dask), stored in `robustness.json` after every chunk,
reported and drawn as a heat map (paper Fig. 2C). The points themselves are
`sweeps.robustness.evaluate_points`; `metarig robustness` is the command.
"""

import hashlib
import json
import logging
import math
import os
import platform
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

log = logging.getLogger("metarig.robustness")

FORMAT = "metarig-robustness/1"
NOMINAL_HZ, NOMINAL_S = 30.0, 0.5  # the design point marked on the map (30 Hz, 7.5 mm)
AMPLITUDE_UNITS = {"s": None, "mm": 1e-3, "m": 1.0}


class MapError(Exception):
    """A mistake in the request (an unknown scene, an amplitude too large, a folder that cannot
    be resumed): one line for the user."""


@dataclass
class MapRequest:
    """What to map: the design file, the output folder and the grid (amplitudes in
    `amplitude_unit`: s = the lattice spacing, mm or m), where to compute (`chunk` points per
    batch, `workers` local Dask workers or a `scheduler` address) and the outputs."""

    design: Path
    out: Path
    frequencies: list[float]
    amplitudes: list[float]
    amplitude_unit: str = "s"
    scene: str = "focusing-24x16"
    chunk: int | None = None
    workers: int | None = None
    scheduler: str | None = None
    no_plot: bool = False
    quiet: bool = False


# ---------------------------------------------------------------------------------------------
# the run


def run_map(request: MapRequest) -> dict:
    """Compute the points of the map that `request.out` does not hold yet, chunk by chunk,
    writing robustness.json after each (status "partial", then "complete"), then report and
    draw it; returns the document. Raises `MapError` for a mistake in the request."""
    from design_engine.design.design_io import load_design
    from design_engine.physics.scenes import PRESETS
    from design_engine.sweeps.robustness import check_grid, default_chunk, design_scene, tied_timing

    t_start = time.perf_counter()
    if request.chunk is None:  # the caller's request is left as it came
        request = replace(request, chunk=default_chunk())
    if request.scene not in PRESETS:
        raise MapError(f"unknown scene {request.scene!r}; choose one of: {', '.join(PRESETS)}")
    lattice, x_mm = load_design(request.design)
    x_m = np.asarray(x_mm, np.float64) / 1e3
    scene = design_scene(x_m, lattice.describe(), request.scene)
    s_m = lattice.spacing / 1e3
    scale = AMPLITUDE_UNITS[request.amplitude_unit] or s_m
    for v in request.amplitudes:
        if not v * scale < 2 * s_m:
            raise MapError(f"amplitude {v:g} {request.amplitude_unit} = {v * scale * 1e3:g} mm is "
                            f"not below 2 s = {2 * s_m * 1e3:g} mm")
    freqs = np.round(np.asarray(request.frequencies, np.float64), 9)
    amps = np.round(np.asarray(request.amplitudes, np.float64) * scale, 12)  # m
    freqs, amps = check_grid(scene, freqs, amps)
    timing = tied_timing(scene, float(freqs.min()))
    fingerprint = {"scene": request.scene, "lattice": lattice.describe(),
                   "design_sha256": hashlib.sha256(x_m.tobytes()).hexdigest(), "timing": timing}
    out: Path = request.out
    path = out / "robustness.json"
    store = _load_store(path, fingerprint)
    grid = [(float(f), float(a)) for f in freqs for a in amps]
    todo = [p for p in grid if _key(*p) not in store["points"]]
    log.info("robustness map of %s on the %s scene (%s %dx%d): %d frequencies x %d amplitudes; "
             "delay %.4g s, window %.4g s, %d samples (tied to %g Hz)", request.design, request.scene,
             lattice.kind, *lattice.shape, freqs.size, amps.size, timing["delay_s"],
             timing["window_s"], timing["n_samples"], timing["tied_to_hz"])
    log.info("%d of %d grid points already in %s; computing %d", len(grid) - len(todo), len(grid),
             path, len(todo))
    out.mkdir(parents=True, exist_ok=True)
    run = {"computed_points": 0, "reused_points": len(grid) - len(todo), "compute_s": 0.0,
           "chunks": 0,
           "workers": request.scheduler if request.scheduler is not None else (request.workers or 1),
           "processes": []}

    def write(status: str) -> None:
        doc = _document(scene, request, fingerprint, store, freqs, amps, status, run,
                        time.perf_counter() - t_start)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        os.replace(tmp, path)

    if todo:
        bar = _progress(len(grid), len(grid) - len(todo), request.quiet)
        try:
            for res in _compute(scene, request, x_m, lattice.describe(), todo, float(freqs.min()),
                                bar):
                _merge(store, res)
                run["computed_points"] += len(res["ratio"])
                run["compute_s"] += res["wall_s"]
                run["chunks"] += 1
                if res["process"] not in run["processes"]:
                    run["processes"].append(res["process"])
                write("partial")
        finally:
            if bar is not None:
                bar.close()
    write("complete")
    doc = json.loads(path.read_text())
    _report(doc)
    if not request.no_plot:
        try:
            plot_robustness(out / "robustness.png", doc)
        except Exception as exc:  # noqa: BLE001  (a plot must never cost the results)
            log.warning("robustness.png failed: %s", exc)
    log.info("wrote %s", ", ".join(sorted(f.name for f in out.iterdir() if not
                                          f.name.endswith(".tmp"))))
    return doc


def _progress(total: int, done: int, quiet: bool):
    if quiet:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="robustness", unit="point", dynamic_ncols=True)


def _chunks(points: list, size: int) -> list[list]:
    return [points[k:k + size] for k in range(0, len(points), size)]


def _compute(scene, request, x_m, lattice_desc, todo, f_min_hz, bar):
    """Yield `evaluate_points` results chunk by chunk (in process, or as Dask tasks finish)."""
    from design_engine.solve.run import default_choice
    from design_engine.sweeps.robustness import evaluate_points, robustness_chunk

    choice = default_choice(scene)  # measured once; passed on so every worker takes the same step
    for line in choice.reasons:
        log.info("solver: %s", line)
    progress = bar.update if bar is not None else None
    if request.scheduler is None and (request.workers or 1) == 1:
        for part in _chunks(todo, request.chunk):
            yield evaluate_points(scene, np.asarray(part), f_min_hz=f_min_hz, chunk=request.chunk,
                                  choice=choice, progress=progress)
        return

    from design_engine.sweeps.distributed import dask_client

    with dask_client(workers=request.workers if request.scheduler is None else None,
                     scheduler=request.scheduler) as client:
        from distributed import as_completed

        n_workers = max(1, len(client.scheduler_info().get("workers", {})) or (request.workers or 1))
        n_chunks = math.ceil(len(todo) / request.chunk)
        n_chunks = math.ceil(n_chunks / n_workers) * n_workers  # every worker busy
        size = math.ceil(len(todo) / n_chunks)
        parts = _chunks(todo, size)
        log.info("%d chunks of up to %d points on %d Dask workers", len(parts), size, n_workers)
        futures = {client.submit(robustness_chunk, x_m, lattice_desc, np.asarray(part),
                                 f_min_hz=f_min_hz, scene_name=request.scene,
                                 omega_rad_per_ms=choice.omega_max, chunk=size, pure=False): part
                   for part in parts}
        for fut in as_completed(futures):
            res = fut.result()
            if bar is not None:
                bar.update(len(futures[fut]))
            yield res


# ---------------------------------------------------------------------------------------------
# the store (robustness.json)


def _key(f_hz: float, a_m: float) -> str:
    return f"{f_hz!r}|{a_m!r}"


def _load_store(path: Path, fingerprint: dict) -> dict:
    """Points and configurations of an earlier run of the same map in `path` (else empty)."""
    if not path.exists():
        return {"points": {}, "configs": []}
    try:
        doc = json.loads(path.read_text())
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise ValueError("not a metarig-robustness/1 file")
        old = doc["fingerprint"]
        if not isinstance(old, dict):
            raise TypeError("its fingerprint is not a table")
        points = {_key(p["frequency_hz"], p["amplitude_m"]): p for p in doc["points"]}
        configs = list(doc["configs"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MapError(f"{path} exists but cannot be resumed (damaged? {exc}); restore it "
                        "from a copy, or choose another --out (it is left as it is)") from None
    labels = {"design_sha256": "design", "timing": "timing (lowest frequency, window, samples)"}
    for k, value in fingerprint.items():
        if old.get(k) != json.loads(json.dumps(value)):
            raise MapError(f"{path} holds the map of another {labels.get(k, k)}; remove it or "
                            "choose another --out")
    return {"points": points, "configs": configs}


def _finite_or_none(v: float):
    return float(v) if v is not None and math.isfinite(v) else None


def _merge(store: dict, res: dict) -> None:
    """Add an `evaluate_points` result to the store (configurations de-duplicated)."""
    index = []
    for c in res["configs"]:
        c = json.loads(json.dumps(c))
        if c not in store["configs"]:
            store["configs"].append(c)
        index.append(store["configs"].index(c))
    for k, (f, a) in enumerate(zip(res["frequency_hz"], res["amplitude_m"])):
        used = res["config"][k]
        store["points"][_key(f, a)] = {
            "frequency_hz": float(f), "amplitude_m": float(a),
            "ratio": _finite_or_none(res["ratio"][k]),
            "target_ke_mean_J": _finite_or_none(res["target_ke_mean_J"][k]),
            "config": index[used] if used >= 0 else -1,
            "status": "ok" if used >= 0 else "failed", "note": res["note"][k]}


def _machine() -> dict:
    import jax

    try:
        load = [round(v, 2) for v in os.getloadavg()]
    except OSError:
        load = None
    return {"hostname": platform.node(), "platform": platform.platform(),
            "python": platform.python_version(), "cpu_count": os.cpu_count(),
            "load_average_1_5_15min": load, "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()]}


def _document(scene, request, fingerprint, store, freqs, amps, status, run, wall_s) -> dict:
    from design_engine.design.run_outputs import provenance

    nf, na = freqs.size, amps.size
    ratio = [[None] * na for _ in range(nf)]
    energy = [[None] * na for _ in range(nf)]
    config = [[None] * na for _ in range(nf)]
    done = 0
    for i, f in enumerate(freqs):
        for j, a in enumerate(amps):
            p = store["points"].get(_key(float(f), float(a)))
            if p is not None:
                ratio[i][j], energy[i][j], config[i][j] = (p["ratio"], p["target_ke_mean_J"],
                                                          p["config"])
                done += 1
    grid_keys = {_key(float(f), float(a)) for f in freqs for a in amps}
    points = sorted(store["points"].values(), key=lambda p: (p["frequency_hz"], p["amplitude_m"]))
    s_m = scene.lattice.spacing / 1e3
    return {
        "format": FORMAT,
        "status": status,
        "design": str(request.design),
        "scene": request.scene,
        "lattice": scene.lattice.describe(),
        "target": next(iter(scene.targets)),
        "target_units": [int(b) for b in next(iter(scene.targets.values()))],
        "metric": "R = J_target / J_rest, kinetic energy summed over the same samples; the rest "
                  "includes the clamped and the driven units",
        "timing": fingerprint["timing"],
        "fingerprint": fingerprint,
        "frequencies_hz": freqs.tolist(),
        "amplitudes_m": amps.tolist(),
        "amplitudes_over_spacing": (amps / s_m).tolist(),
        "ratio": ratio,
        "target_ke_mean_J": energy,
        "config": config,
        "configs": store["configs"],
        "grid_points_done": done,
        "grid_points": nf * na,
        "failures": [{"frequency_hz": p["frequency_hz"], "amplitude_m": p["amplitude_m"],
                      "reason": p["note"]} for p in points
                     if p["status"] == "failed" and _key(p["frequency_hz"], p["amplitude_m"])
                     in grid_keys],
        "points": points,
        "run": dict(run, wall_s=wall_s),
        "machine": _machine(),
        "provenance": provenance(),
    }


def _report(doc: dict) -> None:
    r = np.array([[np.nan if v is None else v for v in row] for row in doc["ratio"]], float)
    f, a = np.asarray(doc["frequencies_hz"]), np.asarray(doc["amplitudes_m"])
    for c, cfg in enumerate(doc["configs"]):
        n = sum(row.count(c) for row in doc["config"])
        if n:
            log.info("configuration %d (%s, %s, contact %s): %d points", c, cfg["solver"]["solver"],
                     cfg["solver"]["dtype"], cfg["solver"]["use_contact"], n)
    if np.isfinite(r).any():
        i, j = np.unravel_index(np.nanargmax(r), r.shape)
        log.info("R from %.4g to %.4g; highest at %g Hz, %.4g mm", np.nanmin(r), np.nanmax(r),
                 f[i], a[j] * 1e3)
    for fail in doc["failures"]:
        log.warning("failed at %g Hz, %.4g mm: %s", fail["frequency_hz"],
                    fail["amplitude_m"] * 1e3, fail["reason"])
    run = doc["run"]
    log.info("computed %d points (%d reused) in %d chunks; wall time %.1f s", run["computed_points"],
             run["reused_points"], run["chunks"], run["wall_s"])


# ---------------------------------------------------------------------------------------------
# heat map


def _edges(v: np.ndarray) -> np.ndarray:
    if v.size == 1:
        d = 0.1 * abs(v[0]) or 1.0
        return np.array([v[0] - d, v[0] + d])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])


def robustness_figure(doc: dict):
    """Heat map of a robustness.json document: frequency (Hz) on x, amplitude (mm) on y, R as
    colour (log scale when it spans more than a decade); the design point (30 Hz, 0.5 s) boxed
    in red if on the grid. Returns a `matplotlib.figure.Figure`."""
    import matplotlib
    from matplotlib.colors import LogNorm, Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    f = np.asarray(doc["frequencies_hz"], float)
    a_mm = np.asarray(doc["amplitudes_m"], float) * 1e3
    r = np.array([[np.nan if v is None else v for v in row] for row in doc["ratio"]], float)
    good = r[np.isfinite(r) & (r > 0)]
    lo, hi = (good.min(), good.max()) if good.size else (1e-3, 1.0)
    norm = LogNorm(lo, hi) if hi > 10 * lo else Normalize(lo, hi if hi > lo else lo + 1e-12)
    fig = Figure(figsize=(7.5, 5.5))
    ax = fig.add_subplot()
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.75")
    mesh = ax.pcolormesh(_edges(f), _edges(a_mm), np.ma.masked_invalid(r.T), cmap=cmap, norm=norm)
    fig.colorbar(mesh, ax=ax, label=r"$R = J_\mathrm{target} / J_\mathrm{rest}$"
                 + (" (log scale)" if isinstance(norm, LogNorm) else ""))
    if r.size <= 200:
        for i in range(f.size):
            for j in range(a_mm.size):
                ok = np.isfinite(r[i, j]) and r[i, j] > 0
                light = ok and float(norm(r[i, j])) > 0.6  # dark text on the bright colours
                ax.text(f[i], a_mm[j], f"{r[i, j]:.3g}" if ok else "failed", ha="center",
                        va="center", fontsize=6, color="k" if light else "w")
    s_mm = doc["lattice"]["spacing_m"] * 1e3
    i = np.flatnonzero(np.isclose(f, NOMINAL_HZ))
    j = np.flatnonzero(np.isclose(a_mm, NOMINAL_S * s_mm))
    marked = ""
    if i.size and j.size:
        fe, ae = _edges(f), _edges(a_mm)
        ax.add_patch(Rectangle((fe[i[0]], ae[j[0]]), fe[i[0] + 1] - fe[i[0]],
                               ae[j[0] + 1] - ae[j[0]], fill=False, edgecolor="red", linewidth=2))
        marked = (f"\n(red box) design point {NOMINAL_HZ:g} Hz, {NOMINAL_S * s_mm:g} mm: "
                  f"R = {r[i[0], j[0]]:.3g}")
    ax.set_xlabel("input frequency f [Hz]")
    ax.set_ylabel("input amplitude A [mm]")
    ax.set_xticks(f)
    ax.set_yticks(a_mm)
    n_failed = len(doc.get("failures", []))
    ax.set_title(f"Robustness map: {doc['scene']}, {doc['design']}"
                 + (f" ({n_failed} failed point(s), grey)" if n_failed else "") + marked, fontsize=9)
    fig.tight_layout()
    return fig


def plot_robustness(path: str | Path, doc: dict) -> Path:
    """Write `robustness_figure(doc)` as PNG; returns the path."""
    robustness_figure(doc).savefig(path, dpi=120)
    return Path(path)


__all__ = ["MapError", "MapRequest", "plot_robustness", "robustness_figure", "run_map"]
