"""Pareto fronts of two-objective tasks (spec 9.3): dominance, the front, the paper-style plot.

Pure functions of plain records; the sweep that produces the records is `design_engine.sweeps.pareto_sweep`.
"""

from pathlib import Path

import numpy as np


def dominates(p: tuple[float, float], q: tuple[float, float], senses: tuple[str, str]) -> bool:
    """True if point p dominates q: no worse in both objectives and better in one.

    `senses` per objective: "max" or "min" (focusing/splitting: both max; protection: max, min).
    """
    sign = np.array([1.0 if s == "max" else -1.0 for s in senses])
    a, b = sign * np.asarray(p, float), sign * np.asarray(q, float)
    return bool(np.all(a >= b) and np.any(a > b))


def front_indices(values: np.ndarray, senses: tuple[str, str]) -> np.ndarray:
    """Indices of the non-dominated rows of `values` [n, 2], sorted by the first objective.

    Sort-and-sweep: O(n log n). Equal points are all kept.
    """
    v = np.asarray(values, float)
    if v.size == 0:
        return np.zeros(0, dtype=np.int64)
    sign = np.array([1.0 if s == "max" else -1.0 for s in senses])
    w = v * sign  # both maximised now
    order = np.lexsort((-w[:, 1], -w[:, 0]))  # first objective descending, ties: second desc
    keep, best2, last = [], -np.inf, None
    for i in order:
        if w[i, 1] > best2 or (last is not None and np.array_equal(w[i], w[last])):
            keep.append(i)
            if w[i, 1] > best2:
                best2 = w[i, 1]
            last = i
    keep = np.asarray(keep, dtype=np.int64)
    return keep[np.argsort(v[keep, 0], kind="stable")]


def pareto_front(points: list[dict], senses: tuple[str, str]) -> list[dict]:
    """The non-dominated feasible points (each a dict with "J1", "J2", "feasible"), by J1;
    points with identical objectives are listed once (the first)."""
    ok = [p for p in points if p["feasible"] and p["J1"] is not None and p["J2"] is not None
          and np.isfinite(p["J1"]) and np.isfinite(p["J2"])]
    idx = front_indices(np.array([[p["J1"], p["J2"]] for p in ok]).reshape(-1, 2), senses)
    front, seen = [], set()
    for i in idx:  # identical points (e.g. the shared initial design of one start) once
        key = (ok[i]["J1"], ok[i]["J2"])
        if key not in seen:
            seen.add(key)
            front.append(ok[i])
    return front


def plot_pareto(path: str | Path, points: list[dict], front: list[dict], labels: tuple[str, str],
                title: str) -> Path:
    """Every evaluated design as a grey point (J1, J2 in mJ), the front as a polyline."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 5.0))
    pts = np.array([[p["J1"], p["J2"]] for p in points if p["J1"] is not None
                    and p["J2"] is not None], float).reshape(-1, 2) * 1e3
    feas = np.array([p["feasible"] for p in points if p["J1"] is not None
                     and p["J2"] is not None], bool)
    ax.scatter(pts[feas, 0], pts[feas, 1], s=8, color="0.65", label="evaluated designs")
    if (~feas).any():
        ax.scatter(pts[~feas, 0], pts[~feas, 1], s=8, facecolors="none", edgecolors="0.8",
                   label="infeasible")
    if front:
        f = np.array([[p["J1"], p["J2"]] for p in front]) * 1e3
        ax.plot(f[:, 0], f[:, 1], "-o", color="crimson", ms=4, label=f"Pareto front ({len(f)})")
    ax.set_xlabel(f"{labels[0]}: mean target kinetic energy [mJ]")
    ax.set_ylabel(f"{labels[1]}: mean target kinetic energy [mJ]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
