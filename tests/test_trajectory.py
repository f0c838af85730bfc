"""The one trajectory type: numpy only, one file format, one conversion to and from ROS poses."""

import subprocess
import sys

import numpy as np
import pytest

from metarig.trajectory import (Trajectory, TrajectoryFileError, backward_rates, from_absolute,
                                from_pose_messages, to_absolute)


def _traj(nt=5, n=4, seed=0, tracked=True):
    rng = np.random.default_rng(seed)
    t = np.arange(nt) * 1e-3
    q = rng.normal(scale=1e-4, size=(nt, n, 3))
    lost = np.zeros((nt, n), bool)
    if not tracked:
        return Trajectory.from_positions(t, q)
    lost[2, 1] = True
    q[lost] = np.nan
    quality = np.where(lost, np.nan, 0.99).astype(np.float32)
    return Trajectory.from_positions(t, q, quality=quality, lost=lost, complete=False)


def test_importing_the_type_loads_no_jax():
    code = "import sys, metarig.trajectory; print('jax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_npz_round_trip_keeps_every_field(tmp_path):
    tr = _traj()
    path = tr.save_npz(tmp_path / "sub" / "tracks.npz", fps=np.array(1000.0))
    back = Trajectory.load_npz(path)
    for name in ("t", "q", "qdot", "quality", "lost"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tr, name))
    assert back.complete is False
    with np.load(path) as f:  # an independent reader sees the documented keys
        assert {"t", "q", "qdot", "quality", "lost", "complete", "fps"} <= set(f.files)
    assert not list(tmp_path.rglob("*.tmp"))  # written atomically, nothing left behind


def test_simulation_trajectories_have_no_tracking_fields(tmp_path):
    back = Trajectory.load_npz(_traj(tracked=False).save_npz(tmp_path / "sim.npz"))
    assert back.quality is None and back.lost is None and back.complete
    assert back.valid.all()


def test_rates_are_backward_differences_and_lost_samples_are_invalid():
    tr = _traj()
    assert np.isnan(tr.qdot[0]).all()
    np.testing.assert_allclose(tr.qdot[3, 0], (tr.q[3, 0] - tr.q[2, 0]) / 1e-3)
    assert np.isnan(tr.qdot[2, 1]).all() and np.isnan(tr.qdot[3, 1]).all()  # next to a lost one
    assert not tr.valid[2, 1] and tr.valid[2, 0]
    t = np.array([0.0, 0.5, 2.0])
    np.testing.assert_allclose(backward_rates(t, np.array([0.0, 1.0, 4.0]))[1:], [2.0, 2.0])


def test_window_slices_every_array_alike():
    w = _traj().window(1, 3)
    assert w.t.shape == (2,) and w.q.shape[0] == w.lost.shape[0] == w.quality.shape[0] == 2
    assert w.lost[1, 1]


def test_shapes_are_checked():
    t, q = np.zeros(3), np.zeros((3, 2, 3))
    with pytest.raises(ValueError, match="q must be"):
        Trajectory(t=t, q=np.zeros((2, 2, 3)), qdot=np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="lost must be"):
        Trajectory(t=t, q=q, qdot=q, lost=np.zeros((3, 3), bool))


def test_a_file_that_is_not_a_trajectory_is_refused_in_one_line(tmp_path):
    np.savez(tmp_path / "x.npz", a=np.zeros(2))
    with pytest.raises(TrajectoryFileError, match="missing q, t"):
        Trajectory.load_npz(tmp_path / "x.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(TrajectoryFileError, match="cannot read"):
        Trajectory.load_npz(tmp_path / "junk.npz")


def test_absolute_poses_round_trip():
    ref = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]])
    q = np.random.default_rng(1).normal(scale=1e-4, size=(6, 3, 3))
    x, y, theta = to_absolute(q, ref)
    np.testing.assert_allclose(x[:, 1], 0.01 + q[:, 1, 0])
    np.testing.assert_allclose(from_absolute(x, y, theta, ref), q, atol=1e-18)


def test_ros_pose_messages_carry_a_trajectory_and_back():
    convert = pytest.importorskip("ros_nodes.convert")
    tr = _traj(nt=6, n=4)
    ref = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01], [0.01, 0.01]])
    t0 = 5_000_000_000
    msgs = [convert.unit_poses(t0 + int(round(tr.t[k] * 1e9)), tr.q[k], ref, tr.quality[k],
                               tr.lost[k]) for k in range(tr.n_t)]
    np.testing.assert_allclose(msgs[3].x, ref[:, 0] + tr.q[3, :, 0])
    back = from_pose_messages(msgs, ref, t0_ns=t0)
    np.testing.assert_allclose(back.t, tr.t, atol=1e-12)
    np.testing.assert_allclose(back.q, tr.q, atol=1e-15)
    np.testing.assert_array_equal(back.lost, tr.lost)
    np.testing.assert_allclose(back.qdot, tr.qdot, rtol=1e-6)
    partial = convert.unit_poses(t0, tr.q[0, :2], ref[:2])  # a message naming units 0, 1 only
    assert from_pose_messages([partial], ref).lost[0].tolist() == [False, False, True, True]
