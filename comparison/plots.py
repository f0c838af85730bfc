"""PNG figures of an experiment-vs-simulation comparison for the run folder (numpy, matplotlib).

Every function takes SI arrays and a path and writes one figure; `write_plots` writes them all.
Figures show mm, mm/s, mJ and ms (since the pulse onset) for readability. The sample frame is
x right, y up; outlines are the units' reference polygons posed rigidly by their q.
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize
from matplotlib.ticker import MaxNLocator

from comparison.metrics import Comparison
from metarig.polygon import area_centroids

SPEED_CMAP = "viridis"  # the one speed colour map, shared with comparison.rerun_log
EXCLUDED_GREY = (0.72, 0.72, 0.72)
EXP_COLOUR, SIM_COLOUR = "tab:red", "tab:blue"
DPI = 110


def posed_outlines(polygons_m: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Reference outlines [n, nv, 2] (m) moved by poses q [..., n, 3] (u, v in m; theta in rad,
    counter-clockwise about each area centroid). Returns [..., n, nv, 2] m."""
    polygons_m = np.asarray(polygons_m, np.float64)
    q = np.asarray(q, np.float64)
    cent = area_centroids(polygons_m)  # [n, 2]
    rel = polygons_m - cent[:, None, :]
    c, s = np.cos(q[..., 2])[..., None], np.sin(q[..., 2])[..., None]
    x = c * rel[..., 0] - s * rel[..., 1]
    y = s * rel[..., 0] + c * rel[..., 1]
    return np.stack([x, y], axis=-1) + (cent + q[..., :2])[..., None, :]


def window_samples(comparison: Comparison, t_s: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The samples of values [n_f, ...] at times t_s [n_f] (s, the trajectories' axis) that fall in
    the comparison's window (from the onset on), as `compare` selects them: [n_t, ...]."""
    keep = np.asarray(t_s, np.float64) >= comparison.metrics["onset_s"] - 1e-9
    out = np.asarray(values)[keep]
    if out.shape[0] != comparison.t.shape[0]:
        raise ValueError(
            f"{out.shape[0]} samples after the onset, the comparison has "
            f"{comparison.t.shape[0]}: not the trajectories it was computed from"
        )
    return out


def speed_range(*speeds: np.ndarray) -> tuple[float, float]:
    """One colour scale (0, max) in m/s over every finite speed given (a unit span if none)."""
    finite = [s[np.isfinite(s)] for s in map(np.asarray, speeds)]
    top = max((float(f.max()) for f in finite if f.size), default=0.0)
    return 0.0, top if top > 0 else 1.0


def snapshot_indices(comparison: Comparison, n: int = 4) -> np.ndarray:
    """n sample indices spread around the peak of the target kinetic energy: at 0.4, 0.7, 1.0 and
    1.3 times its time since the onset (n = 4; evenly from 0.4 to 1.3 otherwise); duplicates
    (a peak at the window's end) are dropped."""
    ke = comparison.target_ke_sim
    if not np.any(np.isfinite(ke) & (ke > 0)):
        ke = comparison.target_ke_exp
    t = comparison.t
    k_peak = int(np.nanargmax(ke)) if np.any(np.isfinite(ke)) else len(t) - 1
    t_peak = max(float(t[k_peak]), float(t[min(len(t) - 1, 3)]))
    wanted = np.linspace(0.4, 1.3, n) * t_peak
    return np.unique(np.abs(t[None, :] - wanted[:, None]).argmin(axis=1))


def _draw_units(ax, outlines_mm, speed_mm_s, target_ids, norm):
    """Speed-filled outlines, excluded (NaN speed) ones grey and hatched, targets outlined."""
    ok = np.isfinite(speed_mm_s)
    pc = PolyCollection(
        outlines_mm[ok],
        array=speed_mm_s[ok],
        cmap=SPEED_CMAP,
        norm=norm,
        edgecolors="0.3",
        linewidths=0.2,
    )
    ax.add_collection(pc)
    if (~ok).any():
        ax.add_collection(
            PolyCollection(
                outlines_mm[~ok],
                facecolors=EXCLUDED_GREY,
                edgecolors="0.45",
                linewidths=0.3,
                hatch="////",
            )
        )
    ax.add_collection(
        PolyCollection(
            outlines_mm[np.asarray(target_ids, np.int64)],
            facecolors="none",
            edgecolors="magenta",
            linewidths=1.4,
        )
    )
    return pc


def plot_velocity_maps(
    path: str | Path,
    comparison: Comparison,
    polygons_m: np.ndarray,
    q_exp: np.ndarray,
    q_sim: np.ndarray,
    target_ids: np.ndarray,
    n_times: int = 4,
) -> Path:
    """Tracked (top row) and simulated (bottom row) outlines at `n_times` times around the target
    energy peak, filled by speed on one colour scale over all panels.

    Args:
        comparison: from `compare`; its speeds [n_t, n] (m/s, NaN for excluded units).
        polygons_m: [n, nv, 2] reference outlines, m (sample frame, y up).
        q_exp, q_sim: [n_t, n, 3] poses on the comparison's window (see `window_samples`); a
            non-finite pose (a lost unit) is drawn at the reference.
        target_ids: ids of the target units (outlined in magenta).
    """
    idx = snapshot_indices(comparison, n_times)
    rows = (("tracked", q_exp, comparison.speed_exp), ("simulated", q_sim, comparison.speed_sim))
    vmin, vmax = speed_range(*(s[idx] for _, _, s in rows))
    norm = Normalize(vmin * 1e3, vmax * 1e3)
    span = np.ptp(np.asarray(polygons_m).reshape(-1, 2), axis=0)
    panel_h = 3.2 * min(max(span[1] / span[0], 0.3), 2.0) + 0.5  # panels keep the lattice aspect
    fig, axes = plt.subplots(
        2,
        len(idx),
        figsize=(3.2 * len(idx) + 1.2, 2 * panel_h),
        squeeze=False,
        sharex=True,
        sharey=True,
        layout="constrained",
    )
    for r, (label, q, speed) in enumerate(rows):
        for c, k in enumerate(idx):
            qk = np.where(np.isfinite(q[k]), q[k], 0.0)
            ax = axes[r, c]
            pc = _draw_units(
                ax, posed_outlines(polygons_m, qk) * 1e3, speed[k] * 1e3, target_ids, norm
            )
            ax.set_title(f"{label}, t = {comparison.t[k] * 1e3:.1f} ms", fontsize=9)
            ax.set_aspect("equal")
            ax.autoscale_view()
            ax.tick_params(labelsize=7)
        axes[r, 0].set_ylabel("y [mm]")
    for ax in axes[-1]:
        ax.set_xlabel("x [mm]")
    fig.colorbar(pc, ax=axes, label="speed [mm/s]  (grey hatched: excluded)", shrink=0.85)
    return _save(fig, path)


def plot_target_ke(path: str | Path, comparison: Comparison) -> Path:
    """Kinetic energy of the target units over time since the onset, measured and simulated."""
    fig, ax = plt.subplots(figsize=(6.4, 3.6), layout="constrained")
    t_ms = comparison.t * 1e3
    ax.plot(t_ms, comparison.target_ke_exp * 1e3, color=EXP_COLOUR, label="experiment")
    ax.plot(t_ms, comparison.target_ke_sim * 1e3, color=SIM_COLOUR, ls="--", label="simulation")
    m = comparison.metrics
    ax.set_title(
        f"target kinetic energy (peak error {m['target_peak_ke_rel_err']:+.1%})", fontsize=10
    )
    ax.set_xlabel("time since pulse onset [ms]")
    ax.set_ylabel("kinetic energy [mJ]")
    ax.legend()
    ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_row_peak_ke(path: str | Path, comparison: Comparison, row_x_m: np.ndarray) -> Path:
    """Peak kinetic energy of each unit along the row, measured and simulated (log scale).

    Args:
        row_x_m: [n_row] position along the row (reference x of those units), m.
    """
    fig, ax = plt.subplots(figsize=(6.4, 3.6), layout="constrained")
    x_mm = np.asarray(row_x_m) * 1e3
    ax.semilogy(
        x_mm, comparison.row_peak_ke_exp * 1e3, "o-", color=EXP_COLOUR, ms=3, label="experiment"
    )
    ax.semilogy(
        x_mm, comparison.row_peak_ke_sim * 1e3, "s--", color=SIM_COLOUR, ms=3, label="simulation"
    )
    ax.set_xlabel("position along the row [mm]")
    ax.set_ylabel("peak kinetic energy [mJ]")
    ax.set_title("peak kinetic energy along the row (gaps: excluded units)", fontsize=10)
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    return _save(fig, path)


def plot_tracking_quality(
    path: str | Path, t_s: np.ndarray, quality: np.ndarray, lost: np.ndarray
) -> Path:
    """Median and minimum tracking score (ZNCC) over the tracked units per frame, and the number
    of lost units per frame.

    Args:
        t_s: [n_f] frame times since the pulse onset, s (negative before it).
        quality: [n_f, n] score in [-1, 1]; lost: [n_f, n] bool.
    """
    q = np.where(np.asarray(lost, bool), np.nan, np.asarray(quality, np.float64))
    has = np.isfinite(q).any(axis=1)
    med = np.full(len(t_s), np.nan)
    low = np.full(len(t_s), np.nan)
    med[has] = np.nanmedian(q[has], axis=1)
    low[has] = np.nanmin(q[has], axis=1)
    t_ms = np.asarray(t_s) * 1e3
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(6.4, 4.8), sharex=True, layout="constrained")
    a0.plot(t_ms, med, color="k", label="median")
    a0.plot(t_ms, low, color="tab:orange", label="minimum")
    a0.set_ylabel("ZNCC over units")
    a0.legend(fontsize=8)
    a0.grid(alpha=0.3)
    a1.step(t_ms, np.asarray(lost, bool).sum(axis=1), where="mid", color="tab:red")
    a1.set_ylabel("lost units")
    a1.yaxis.set_major_locator(MaxNLocator(integer=True))
    a1.set_xlabel("time since pulse onset [ms]")
    a1.grid(alpha=0.3)
    for a in (a0, a1):
        a.axvline(0.0, color="0.5", lw=0.8, ls=":")
    a0.set_title("tracking quality", fontsize=10)
    return _save(fig, path)


def write_plots(
    out_dir: str | Path,
    comparison: Comparison,
    polygons_m: np.ndarray,
    q_exp: np.ndarray,
    q_sim: np.ndarray,
    target_ids: np.ndarray,
    row_ids: np.ndarray,
    quality: np.ndarray | None = None,
    lost: np.ndarray | None = None,
    t_frames_s: np.ndarray | None = None,
    n_times: int = 4,
) -> list[Path]:
    """Write velocity_maps.png, target_ke.png, row_peak_ke.png and (given the tracking scores)
    tracking_quality.png into out_dir.

    Args:
        comparison: from `compare`.
        polygons_m: [n, nv, 2] reference outlines, m.
        q_exp, q_sim: [n_t, n, 3] poses on the comparison's window (`window_samples`).
        target_ids: ids of the target units; row_ids: [n_row] ids along the row, in order.
        quality, lost: [n_f, n] tracking score and lost flags of every frame, or None.
        t_frames_s: [n_f] those frames' times since the pulse onset, s.

    Returns:
        The paths written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    row_x = area_centroids(np.asarray(polygons_m))[np.asarray(row_ids, np.int64), 0]
    paths = [
        plot_velocity_maps(
            out / "velocity_maps.png", comparison, polygons_m, q_exp, q_sim, target_ids, n_times
        ),
        plot_target_ke(out / "target_ke.png", comparison),
        plot_row_peak_ke(out / "row_peak_ke.png", comparison, row_x),
    ]
    if quality is not None and lost is not None and t_frames_s is not None:
        paths.append(plot_tracking_quality(out / "tracking_quality.png", t_frames_s, quality, lost))
    return paths


def _save(fig, path) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path
