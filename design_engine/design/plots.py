"""PNG plots of an optimisation run: objective history, initial vs optimised design, active
constraints. Inputs in SI, drawings in mm.

Figures are plain `matplotlib.figure.Figure` objects rendered by Agg (as `savefig` does for PNG),
never pyplot windows: nothing global to close, safe in a headless or threaded run. Each `plot_*`
function writes one file and returns its path; the matching `*_figure` function builds the same
figure and returns it (for inspection).
"""

import math
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Polygon

# the look of `design_engine.solve.plots.plot_ke_map`, so run plots and simulation plots read alike
KE_CMAP = "inferno"
KE_DECADES = 4.0  # colour range below the largest value
UNIT_EDGE = {"edgecolors": "0.4", "linewidths": 0.2}
TARGET_COLOURS = ("cyan", "lime", "magenta", "yellow")

RUNNING_BEST_LABEL = "running best (feasible)"


def _save(fig: Figure, path: str | Path) -> Path:
    fig.savefig(path, dpi=110)
    return Path(path)


# ------------------------------------------------------------------------------ objective history


def running_best(objectives: np.ndarray, feasible: np.ndarray, goal: str) -> np.ndarray:
    """Best feasible finite objective up to and including each evaluation; NaN before the first.

    Args:
        objectives: [n] objective values (non-finite for failed evaluations).
        feasible: [n] bool, whether each evaluation satisfied the constraints.
        goal: "max" or "min".

    Returns:
        [n] running best, NaN where no feasible finite evaluation came yet.
    """
    if goal not in ("max", "min"):
        raise ValueError(f"goal must be 'max' or 'min', got {goal!r}")
    f = np.asarray(objectives, dtype=np.float64)
    ok = np.asarray(feasible, dtype=bool) & np.isfinite(f)
    fill = -np.inf if goal == "max" else np.inf
    acc = np.maximum.accumulate if goal == "max" else np.minimum.accumulate
    best = acc(np.where(ok, f, fill)) if f.size else f
    return np.where(np.isfinite(best), best, np.nan)


def _as_float(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def history_figure(evaluations: list[dict], goal: str, title: str) -> Figure:
    """Objective against evaluation index (see `plot_history`); returns the figure."""
    if goal not in ("max", "min"):
        raise ValueError(f"goal must be 'max' or 'min', got {goal!r}")
    recs = sorted(evaluations, key=lambda r: r["eval"])
    n = np.array([r["eval"] for r in recs], dtype=np.float64)
    f = np.array([_as_float(r.get("objective")) for r in recs], dtype=np.float64)
    feas = np.array([bool(r.get("feasible")) for r in recs], dtype=bool)
    finite = np.isfinite(f)
    failed = ~finite  # failed evaluations (an event, or no objective at all): nothing to plot

    fig = Figure(figsize=(8, 4.5), layout="tight")
    ax = fig.add_subplot()
    sel = finite & feas
    ax.plot(n[sel], f[sel], "o", color="C0", markersize=4, label=f"feasible ({sel.sum()})")
    sel = finite & ~feas
    ax.plot(n[sel], f[sel], "o", markerfacecolor="none", markeredgecolor="C1", markersize=5,
            label=f"infeasible ({sel.sum()})")
    if failed.any():
        reasons = sorted({str(r.get("event")) for r, bad in zip(recs, failed) if bad
                          and r.get("event") is not None})
        text = f"failed ({failed.sum()})" + (f": {', '.join(reasons)}" if reasons else "")
        # on the x axis itself: x in data, y in axes coordinates
        ax.plot(n[failed], np.zeros(failed.sum()), "x", color="red", markersize=7,
                markeredgewidth=1.5, transform=ax.get_xaxis_transform(), clip_on=False,
                label=text)
    best = running_best(f, feas, goal)
    ax.step(n, best, where="post", color="k", linewidth=1.2, label=RUNNING_BEST_LABEL)
    vals = f[finite]
    if vals.size and np.all(vals > 0) and vals.max() > 10.0 * vals.min():
        ax.set_yscale("log")
    if not n.size:
        ax.text(0.5, 0.5, "no evaluations", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("evaluation")
    ax.set_ylabel(f"objective ({goal}imised)")
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig


def plot_history(path: str | Path, evaluations: list[dict], goal: str, title: str) -> Path:
    """Objective against evaluation index.

    Args:
        path: PNG file to write.
        evaluations: records with "eval" (int, used as is), "objective" (float SI, or None /
            non-finite for a failed evaluation), "feasible" (bool), "event" (None or a reason).
        goal: "max" or "min", the direction of the running best.
        title: figure title.

    Feasible evaluations are filled blue dots, infeasible ones hollow orange circles, failed ones
    (no finite objective) red crosses on the x axis; the running best feasible objective is a step
    line. The y axis is logarithmic when every finite value is positive and they span more than a
    decade.
    """
    return _save(history_figure(evaluations, goal, title), path)


# -------------------------------------------------------------------------- design comparison


def _ke_norm(*ke_j: np.ndarray) -> LogNorm:
    """One log colour scale (mJ) for several kinetic-energy maps: KE_DECADES below the largest
    value, or down to the smallest positive one if that is higher."""
    vals = np.concatenate([np.asarray(k, dtype=np.float64).ravel() for k in ke_j]) * 1e3
    pos = vals[np.isfinite(vals) & (vals > 0)]
    if not pos.size:
        return LogNorm(vmin=1e-12, vmax=1e-9)
    vmax = float(pos.max())
    vmin = max(float(pos.min()), vmax * 10.0 ** -KE_DECADES)
    if vmin >= vmax:
        vmin = vmax / 10.0
    return LogNorm(vmin=vmin, vmax=vmax)


def _ke_panel(ax, polygons_mm: np.ndarray, ke_j: np.ndarray, norm: LogNorm,
              targets: dict[str, np.ndarray]) -> PolyCollection:
    vals = np.asarray(ke_j, dtype=np.float64) * 1e3
    # units below the scale take its lowest colour; non-finite ones are drawn grey ("bad")
    vals = np.where(np.isfinite(vals), np.maximum(vals, norm.vmin), np.nan)
    cmap = matplotlib.colormaps[KE_CMAP].with_extremes(bad="0.75")
    pc = PolyCollection(polygons_mm, array=np.ma.masked_invalid(vals), cmap=cmap, norm=norm,
                        **UNIT_EDGE)
    ax.add_collection(pc)
    for (name, ids), colour in zip(targets.items(), TARGET_COLOURS * len(targets)):
        for i, b in enumerate(np.asarray(ids, dtype=int).ravel()):
            ax.add_patch(Polygon(polygons_mm[b], closed=True, fill=False, edgecolor=colour,
                                 linewidth=1.2, label=f"target: {name}" if i == 0 else None))
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    return pc


def design_comparison_figure(polygons_initial_m: np.ndarray, ke_initial_j: np.ndarray,
                             polygons_final_m: np.ndarray, ke_final_j: np.ndarray,
                             targets: dict[str, np.ndarray], title: str) -> Figure:
    """Initial and optimised design side by side (see `plot_design_comparison`); returns the
    figure. Its two PolyCollections share one LogNorm."""
    panels = []
    for polys, ke, which in ((polygons_initial_m, ke_initial_j, "initial"),
                             (polygons_final_m, ke_final_j, "final")):
        polys, ke = np.asarray(polys, dtype=np.float64), np.asarray(ke, dtype=np.float64)
        if polys.ndim != 3 or polys.shape[2] != 2 or ke.shape != polys.shape[:1]:
            raise ValueError(f"{which} design: polygons {polys.shape} must be [n_units, "
                             f"n_vertices, 2] and kinetic energies {ke.shape} [n_units]")
        panels.append((polys * 1e3, ke))
    norm = _ke_norm(ke_initial_j, ke_final_j)
    fig = Figure(figsize=(13, 5), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    pc = None
    for ax, (polys_mm, ke), name in zip(axes, panels, ("initial", "optimised")):
        pc = _ke_panel(ax, polys_mm, ke, norm, targets)
        ids = np.concatenate([np.asarray(v, dtype=int).ravel() for v in targets.values()]) \
            if targets else np.zeros(0, dtype=int)
        sub = f", target KE {ke[ids].sum():.4g} J" if ids.size else ""
        ax.set_title(f"{name}{sub}")
    if targets:
        axes[1].legend(fontsize=8, loc="upper right")
    fig.suptitle(title)
    fig.colorbar(pc, ax=list(axes), label="time-averaged kinetic energy [mJ]", shrink=0.8)
    return fig


def plot_design_comparison(path: str | Path, polygons_initial_m: np.ndarray,
                           ke_initial_j: np.ndarray, polygons_final_m: np.ndarray,
                           ke_final_j: np.ndarray, targets: dict[str, np.ndarray],
                           title: str) -> Path:
    """Initial and optimised design side by side, every unit filled by its time-averaged kinetic
    energy on ONE log colour scale shared by both panels, target units outlined.

    Args:
        polygons_initial_m, polygons_final_m: [n_units, n_vertices, 2] unit outlines, m (drawn
            in mm).
        ke_initial_j, ke_final_j: [n_units] time-averaged kinetic energy of each unit, J (shown
            in mJ, like `design_engine.solve.plots.plot_ke_map`).
        targets: name -> unit ids of each target region.
    """
    return _save(design_comparison_figure(polygons_initial_m, ke_initial_j, polygons_final_m,
                                          ke_final_j, targets, title), path)


# --------------------------------------------------------------------------- active constraints


def active_constraints_figure(polygons_m: np.ndarray, active_edges: np.ndarray,
                              active_vertices: np.ndarray, active_voids: np.ndarray,
                              bond_points_m: np.ndarray, title: str) -> Figure:
    """The design with its active constraints (see `plot_active_constraints`); returns the
    figure."""
    polys = np.asarray(polygons_m, dtype=np.float64) * 1e3
    edges = np.asarray(active_edges, dtype=bool)
    verts = np.asarray(active_vertices, dtype=bool)
    voids = np.asarray(active_voids, dtype=bool)
    bonds = np.asarray(bond_points_m, dtype=np.float64).reshape(-1, 2) * 1e3
    if polys.ndim != 3 or edges.shape != polys.shape[:2] or verts.shape != polys.shape[:2]:
        raise ValueError(f"active_edges {edges.shape} and active_vertices {verts.shape} must match "
                         f"the polygons' [n_units, n_vertices] {polys.shape[:2]}")
    if voids.shape != bonds.shape[:1]:
        raise ValueError(f"active_voids {voids.shape} must be [n_bonds] like bond_points_m "
                         f"{bonds.shape}")
    fig = Figure(figsize=(9, 6.5), layout="tight")
    ax = fig.add_subplot()
    ax.add_collection(PolyCollection(polys, facecolors="0.92", edgecolors="0.55", linewidths=0.4))
    # edge k joins vertex k-1 and vertex k
    b, k = np.nonzero(edges)
    nv = polys.shape[1]
    segs = np.stack([polys[b, (k - 1) % nv], polys[b, k]], axis=1)
    ax.add_collection(LineCollection(segs, colors="C3", linewidths=2.2, gid="active-edges"))
    b, k = np.nonzero(verts)
    ax.plot(polys[b, k, 0], polys[b, k, 1], "^", color="C0", markersize=6, gid="active-vertices")
    ax.plot(bonds[voids, 0], bonds[voids, 1], "o", color="C2", markersize=6,
            markerfacecolor="none", markeredgewidth=1.5, gid="active-voids")
    handles = [
        Line2D([], [], color="C3", linewidth=2.2, label=f"edge length: {int(edges.sum())} active"),
        Line2D([], [], color="C0", marker="^", linestyle="none",
               label=f"vertex angle: {int(verts.sum())} active"),
        Line2D([], [], color="C2", marker="o", markerfacecolor="none", linestyle="none",
               label=f"void angle: {int(voids.sum())} active"),
    ]
    ax.legend(handles=handles, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12),
              ncol=3, frameon=False)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_title(title)
    return fig


def plot_active_constraints(path: str | Path, polygons_m: np.ndarray, active_edges: np.ndarray,
                            active_vertices: np.ndarray, active_voids: np.ndarray,
                            bond_points_m: np.ndarray, title: str) -> Path:
    """The final design with its active constraints highlighted, counts in the legend.

    Args:
        polygons_m: [n_units, n_vertices, 2] unit outlines, m (drawn in mm).
        active_edges: [n_units, n_vertices] bool, edge-length constraint active on edge k (which
            joins vertex k-1 and vertex k): thick red segment.
        active_vertices: [n_units, n_vertices] bool, vertex-angle constraint active at vertex k:
            blue triangle.
        active_voids: [n_bonds] bool, void-angle constraint active at the ligament: green circle.
        bond_points_m: [n_bonds, 2] ligament midpoints, m.
    """
    return _save(active_constraints_figure(polygons_m, active_edges, active_vertices, active_voids,
                                           bond_points_m, title), path)
