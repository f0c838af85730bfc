"""PNG plots of a simulated (or tracked) scene. Matplotlib with the Agg backend, SI units."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402


def deformed_polygons(polygons_m: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Move reference outlines [n, nv, 2] (m) by poses q [n, 3] (u, v m; theta rad about the
    area centroid). Returns [n, nv, 2] m."""
    from metarig.polygon import area_centroids

    cent = area_centroids(polygons_m)
    c, s = np.cos(q[:, 2])[:, None], np.sin(q[:, 2])[:, None]
    d = polygons_m - cent[:, None, :]
    rot = np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], axis=-1)
    return cent[:, None, :] + q[:, None, :2] + rot


def plot_ke_map(path: str | Path, polygons_m: np.ndarray, q: np.ndarray, mean_ke_j: np.ndarray,
                targets: dict[str, np.ndarray], title: str) -> Path:
    """Time-averaged kinetic energy per unit (J, log colour) drawn on the deformed lattice."""
    polys = deformed_polygons(polygons_m, q) * 1e3
    fig, ax = plt.subplots(figsize=(9, 6.5))
    vals = np.maximum(mean_ke_j * 1e3, 1e-12)
    pc = PolyCollection(polys, array=vals, cmap="inferno", norm=LogNorm(vmin=max(vals.max() * 1e-4, 1e-12),
                                                                       vmax=vals.max()),
                        edgecolors="0.4", linewidths=0.2)
    ax.add_collection(pc)
    for ids in targets.values():
        for b in ids:
            ax.add_patch(plt.Polygon(polys[b], fill=False, edgecolor="cyan", linewidth=1.2))
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_title(title)
    fig.colorbar(pc, ax=ax, label="time-averaged kinetic energy [mJ]", shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_energy_components(path: str | Path, t_s: np.ndarray, components_j: dict[str, np.ndarray],
                           target_ke_j: np.ndarray | None, title: str) -> Path:
    """Kinetic and strain-energy components summed over the lattice against time."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, series in components_j.items():
        ax.plot(t_s * 1e3, series * 1e3, label=name)
    if target_ke_j is not None:
        ax.plot(t_s * 1e3, target_ke_j * 1e3, "k--", label="kinetic (target)")
    ax.set_xlabel("t [ms]")
    ax.set_ylabel("energy [mJ]")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.set_title(title)
    ax.legend(fontsize=8, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_line_peaks(path: str | Path, columns: np.ndarray, peak_ke_j: np.ndarray, row: int,
                    title: str) -> Path:
    """Peak kinetic energy of each unit along one row against its column."""
    fig, ax = plt.subplots(figsize=(7, 3.8))
    ax.semilogy(columns, peak_ke_j * 1e3, "o-")
    ax.set_xlabel("column")
    ax.set_ylabel(f"peak kinetic energy, row {row} [mJ]")
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
