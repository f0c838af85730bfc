"""The check of every tracked pose against its bonded neighbours (tracking.neighbours)."""

from dataclasses import replace

import numpy as np
from dic_synth import make_scene

from hardware_sim.camera import SpeckleTextures
from tracking.dic import DICConfig, DICTracker, init_state, track_frame
from tracking.neighbours import implausible, ligament_excess
from tracking.units import bonds_from_outlines, load_unit_bonds


def test_ligaments_are_found_in_the_outlines_of_a_design_file(tmp_path):
    # a 3x2 grid of squares bonded corner to facing corner: 2 ligaments per adjacent pair
    scene = make_scene(3, 2)
    bonds = bonds_from_outlines(scene.polygons_m)
    pairs = {(int(a), int(b)) for a, _, b, _ in bonds}
    assert pairs == {(0, 1), (1, 2), (3, 4), (4, 5), (0, 3), (1, 4), (2, 5)}
    assert bonds.shape == (14, 4)
    # a design file names the length; plain outlines carry no lattice
    f = tmp_path / "design.json"
    gap = float(np.min(np.linalg.norm(scene.polygons_m[0, :, None] - scene.polygons_m[1, None],
                                      axis=-1)))
    f.write_text('{"polygons_m": %s, "lattice": {"ligament_length_m": %r}}'
                 % (scene.polygons_m.tolist(), gap))
    np.testing.assert_array_equal(load_unit_bonds(f, scene.polygons_m), bonds)
    f.write_text('{"polygons_m": %s}' % scene.polygons_m.tolist())
    assert load_unit_bonds(f, scene.polygons_m) is None


def test_a_unit_moved_against_its_neighbours_is_implausible_and_they_are_not():
    scene = make_scene(3, 2)
    tr = DICTracker(scene.polygons_m, scene.calib, DICConfig(),
                    bonds_from_outlines(scene.polygons_m))
    n = scene.n
    rng = np.random.default_rng(0)
    # three frames of a common motion with small independent wobbles: all plausible
    alpha = [0.01 * k + rng.normal(0, 1e-3, n) for k in range(3)]
    t = [np.array([0.8, -0.3]) * k + rng.normal(0, 0.05, (n, 2)) for k in range(3)]
    poses = [(alpha[2], t[2]), (alpha[1], t[1]), (alpha[0], t[0])]
    known, history = np.ones(n, bool), np.ones(n, bool)
    assert not implausible(tr, poses, known, history).any()
    # unit 4 (bonded to 1, 3 and 5) jumps 4 px in the last frame: only it is implausible
    jumped = t[2].copy()
    jumped[4] += [4.0, 0.0]
    bad = implausible(tr, [(alpha[2], jumped), *poses[1:]], known, history)
    assert bad.tolist() == [False, False, False, False, True, False]
    # without its history the same unit is judged by its ligaments' rest vectors, whose bound
    # (10 px) a 4 px jump stays within, while a 30 px one does not
    history[4] = False
    assert not implausible(tr, [(alpha[2], jumped), *poses[1:]], known, history).any()
    jumped[4] += [26.0, 0.0]
    exc = ligament_excess(tr, [(alpha[2], jumped), *poses[1:]], history)
    assert np.all(exc[(tr.bonds[:, 0] == 4) | (tr.bonds[:, 2] == 4)] > 0)
    assert implausible(tr, [(alpha[2], jumped), *poses[1:]], known, history)[4]
    # with its history too: 30 px off in all three frames does not accelerate, but departs
    history[4] = True
    off = [(a, tt + np.where(np.arange(n)[:, None] == 4, [30.0, 0.0], 0.0)) for a, tt in poses]
    assert implausible(tr, off, known, history).tolist() == [False] * 4 + [True, False]


def test_a_unit_found_on_its_neighbours_identical_texture_is_never_returned_as_good():
    # units 0 and 1 carry the same speckle; unit 0 is hidden for three frames, then a third of
    # it for two more. The search for it (its window wide enough to reach unit 1, 60 px off)
    # matches unit 1's copy at ZNCC 1.0; its pieces move rigidly with it and the reference
    # image's subset agrees (the same texture): only its ligaments, stretched by 60 px, say
    # that the pose is wrong. Searched again from its neighbours' motion, it is found where it
    # is once it shows whole
    scene = make_scene(3, 2)
    tex = scene.textures
    centres, weights = tex.centres_m.copy(), tex.weights.copy()
    centres[1], weights[1] = centres[0], weights[0]
    scene = replace(scene, textures=SpeckleTextures(centres, weights, tex.sigma_m))
    # unit 0 drifts 0.3 px a frame with the others; a 50 px square over it, then its left part
    truth = np.zeros((10, scene.n, 3))
    truth[..., 0] = 0.3 * np.arange(10)[:, None] * scene.cfg.m_per_px
    col, row = scene.calib.sample_to_px(scene.polygons_m[0].mean(axis=0)) - 25.0
    rr, cc = np.mgrid[:scene.cfg.height_px, :scene.cfg.width_px]
    box = (rr >= row) & (rr < row + 50) & (cc >= col)
    hidden, part = box & (cc < col + 50), box & (cc < col + 19)
    occ = [None] * 3 + [hidden] * 3 + [part] * 2 + [None] * 2
    rng = np.random.default_rng(3)
    frames = [scene.render(p, rng, occlusion=o) for p, o in zip(truth, occ, strict=True)]
    bonds = bonds_from_outlines(scene.polygons_m)

    def run(cfg):
        """(unit-frames wrong by > 0.5 px and not lost, unit 0's lost flags)"""
        tr = DICTracker(scene.polygons_m, scene.calib, cfg, bonds)
        st = init_state(tr, frames[0])
        bad, lost0 = 0, []
        for f, q in zip(frames, truth, strict=True):
            st, fp = track_frame(tr, st, f)
            err = np.hypot(*(fp.q[:, :2] - q[:, :2]).T) / scene.cfg.m_per_px
            bad += int(np.sum(~fp.lost & (err > 0.5)))
            assert not fp.lost[1:].any()  # the check flags no other unit
            lost0.append(bool(fp.lost[0]))
        return bad, lost0

    cfg = DICConfig(lost_search_radius_px=70)
    assert run(replace(cfg, neighbour_px=0.0))[0] > 0  # without the check: wrong, unflagged
    bad, lost0 = run(cfg)
    assert bad == 0
    assert lost0[3] and not any(lost0[:3]) and not any(lost0[8:])


def test_each_worker_checks_the_ligaments_between_its_own_units():
    from tracking.batch import _job_bonds

    scene = make_scene(3, 2)
    bonds = bonds_from_outlines(scene.polygons_m)
    ids = np.array([3, 4, 5])  # the second row, as `track_source` splits 2 workers
    local = _job_bonds(bonds, ids, scene.n)
    assert {(int(a), int(b)) for a, _, b, _ in local} == {(0, 1), (1, 2)}  # 3-4 and 4-5
    keep = np.isin(bonds[:, 0], ids) & np.isin(bonds[:, 2], ids)
    np.testing.assert_array_equal(ids[local[:, [0, 2]]], bonds[keep][:, [0, 2]])
    np.testing.assert_array_equal(local[:, [1, 3]], bonds[keep][:, [1, 3]])
    assert _job_bonds(None, ids, scene.n) is None
