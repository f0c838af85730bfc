"""Plots of an optimisation run: files written, and the figures hold the right data."""

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import LogNorm

from design_engine.design import plots as dp

PNG = b"\x89PNG\r\n\x1a\n"


def _is_png(path) -> bool:
    data = path.read_bytes()
    return data[:8] == PNG and len(data) > 1000


def _squares(n: int, offset: float = 0.0) -> np.ndarray:
    """n unit squares of side 10 mm in a row, [n, 4, 2] m (CCW)."""
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float) * 0.010
    return np.stack([sq + [0.012 * i + offset, 0.0] for i in range(n)])


EVALS = [
    {"eval": 1, "objective": 2e-5, "feasible": False, "event": None},
    {"eval": 2, "objective": 1e-5, "feasible": True, "event": None},
    {"eval": 3, "objective": None, "feasible": False, "event": "solver failed"},
    {"eval": 4, "objective": 5e-5, "feasible": True, "event": None},
    {"eval": 5, "objective": float("nan"), "feasible": True, "event": "nan in gradient"},
    {"eval": 6, "objective": 3e-5, "feasible": True, "event": None},
    {"eval": 7, "objective": 9e-4, "feasible": False, "event": None},
    {"eval": 8, "objective": 8e-5, "feasible": True, "event": None},
]


def _line(ax, label_start: str):
    return next(ln for ln in ax.get_lines() if ln.get_label().startswith(label_start))


def test_running_best_max_and_min():
    f = np.array([2.0, 1.0, np.nan, 5.0, 3.0, 9.0, 8.0])
    feas = np.array([False, True, True, True, True, False, True])
    np.testing.assert_array_equal(dp.running_best(f, feas, "max"), [np.nan, 1, 1, 5, 5, 5, 8])
    np.testing.assert_array_equal(dp.running_best(f, feas, "min"), [np.nan, 1, 1, 1, 1, 1, 1])
    with pytest.raises(ValueError, match="goal"):
        dp.running_best(f, feas, "best")


def test_history_figure_markers_running_best_and_log_scale(tmp_path):
    fig = dp.history_figure(list(reversed(EVALS)), "max", "history")  # order of records ignored
    ax = fig.axes[0]
    best = _line(ax, dp.RUNNING_BEST_LABEL)
    np.testing.assert_array_equal(best.get_xdata(), np.arange(1, 9))
    np.testing.assert_allclose(best.get_ydata(),
                               [np.nan, 1e-5, 1e-5, 5e-5, 5e-5, 5e-5, 5e-5, 8e-5])
    assert best.get_drawstyle().startswith("steps")
    feas = _line(ax, "feasible (")
    np.testing.assert_array_equal(feas.get_xdata(), [2, 4, 6, 8])
    infeas = _line(ax, "infeasible (")
    np.testing.assert_array_equal(infeas.get_xdata(), [1, 7])
    assert infeas.get_markerfacecolor() == "none"  # hollow, feasible ones are filled
    assert feas.get_markerfacecolor() != "none"
    failed = _line(ax, "failed (2)")
    np.testing.assert_array_equal(failed.get_xdata(), [3, 5])
    assert failed.get_marker() == "x" and failed.get_color() == "red"
    np.testing.assert_array_equal(failed.get_ydata(), [0, 0])  # on the x axis (axes coords)
    assert failed.get_transform() == ax.get_xaxis_transform()
    assert "solver failed" in failed.get_label() and "nan in gradient" in failed.get_label()
    assert ax.get_yscale() == "log"  # positive, 1e-5 .. 9e-4
    fig = dp.history_figure(EVALS, "min", "history")
    best = _line(fig.axes[0], dp.RUNNING_BEST_LABEL)
    np.testing.assert_allclose(best.get_ydata(), [np.nan] + [1e-5] * 7)
    path = dp.plot_history(tmp_path / "history.png", EVALS, "max", "history")
    assert path == tmp_path / "history.png" and _is_png(path)


def test_history_linear_scale_for_signed_or_narrow_values():
    narrow = [{"eval": i, "objective": 1.0 + 0.1 * i, "feasible": True, "event": None}
              for i in range(5)]
    signed = narrow + [{"eval": 5, "objective": -1.0, "feasible": True, "event": None}]
    for recs in (narrow, signed):
        assert dp.history_figure(recs, "max", "t").axes[0].get_yscale() == "linear"
    with pytest.raises(ValueError, match="goal"):
        dp.history_figure(narrow, "maximise", "t")


def test_design_comparison_shares_one_log_scale(tmp_path):
    init, final = _squares(5), _squares(5, offset=0.001)
    ke0 = np.array([2e-3, 2e-6, 0.0, 4e-6, 1e-5])
    ke1 = np.array([1e-7, 3e-6, 5e-5, 2e-4, 1e-3])
    targets = {"focus": np.array([3, 4])}
    fig = dp.design_comparison_figure(init, ke0, final, ke1, targets, "comparison")
    pcs = [next(c for c in ax.collections if isinstance(c, PolyCollection))
           for ax in fig.axes[:2]]
    assert pcs[0].norm is pcs[1].norm and isinstance(pcs[0].norm, LogNorm)
    norm = pcs[0].norm
    assert norm.vmax == pytest.approx(2.0)  # 2e-3 J = 2 mJ, the initial panel's largest
    assert norm.vmin == pytest.approx(2e-4)  # 4 decades below (1e-7 J in ke1 is lower)
    np.testing.assert_allclose(pcs[0].get_array(), np.maximum(ke0 * 1e3, norm.vmin))
    np.testing.assert_allclose(pcs[1].get_array(), np.maximum(ke1 * 1e3, norm.vmin))
    np.testing.assert_allclose(pcs[1].get_paths()[2].vertices[:4], final[2] * 1e3)  # in mm
    for ax in fig.axes[:2]:
        outlined = [p for p in ax.patches if p.get_edgecolor()[:3] == (0.0, 1.0, 1.0)]
        assert len(outlined) == 2
    assert "target KE 1.4e-05 J" in fig.axes[0].get_title()
    assert len(fig.axes) == 3  # two panels and one colour bar for both
    path = dp.plot_design_comparison(tmp_path / "cmp.png", init, ke0, final, ke1, targets, "c")
    assert _is_png(path)
    with pytest.raises(ValueError, match="kinetic energies"):
        dp.design_comparison_figure(init, ke0[:4], final, ke1, targets, "bad")


def test_active_constraints_segments_points_and_counts(tmp_path):
    polys = _squares(3)
    edges = np.zeros((3, 4), dtype=bool)
    edges[0, 0] = edges[2, 3] = True
    verts = np.zeros((3, 4), dtype=bool)
    verts[1, 2] = True
    voids = np.array([True, False])
    bond_pts = np.array([[0.011, 0.005], [0.023, 0.005]])
    fig = dp.active_constraints_figure(polys, edges, verts, voids, bond_pts, "active")
    ax = fig.axes[0]
    lc = next(c for c in ax.collections if isinstance(c, LineCollection))
    segs = [np.asarray(s) for s in lc.get_segments()]
    # edge 0 joins vertex 3 and vertex 0; edge 3 joins vertex 2 and vertex 3
    np.testing.assert_allclose(segs[0], polys[0, [3, 0]] * 1e3)
    np.testing.assert_allclose(segs[1], polys[2, [2, 3]] * 1e3)
    vl = next(ln for ln in ax.get_lines() if ln.get_gid() == "active-vertices")
    np.testing.assert_allclose(np.c_[vl.get_xdata(), vl.get_ydata()], polys[1, [2]] * 1e3)
    vo = next(ln for ln in ax.get_lines() if ln.get_gid() == "active-voids")
    np.testing.assert_allclose(np.c_[vo.get_xdata(), vo.get_ydata()], [[11.0, 5.0]])
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert texts == ["edge length: 2 active", "vertex angle: 1 active", "void angle: 1 active"]
    path = dp.plot_active_constraints(tmp_path / "active.png", polys, edges, verts, voids,
                                      bond_pts, "active")
    assert _is_png(path)
    with pytest.raises(ValueError, match="active_voids"):
        dp.active_constraints_figure(polys, edges, verts, voids[:1], bond_pts, "bad")


def test_plots_leave_no_pyplot_figures_open(tmp_path):
    before = len(plt.get_fignums())
    dp.plot_history(tmp_path / "h.png", EVALS, "min", "h")
    dp.plot_active_constraints(tmp_path / "a.png", _squares(2), np.zeros((2, 4), bool),
                               np.zeros((2, 4), bool), np.zeros(0, bool), np.zeros((0, 2)), "a")
    dp.plot_design_comparison(tmp_path / "c.png", _squares(2), np.ones(2), _squares(2), np.ones(2),
                              {}, "c")
    assert len(plt.get_fignums()) == before
    assert all(_is_png(tmp_path / f) for f in ("h.png", "a.png", "c.png"))
