"""Device nodes sample at a fixed rate even when the simulated clock jumps (pure logic)."""

import pytest

from ros_nodes.logic.sampling import due_samples


def test_every_period_boundary_since_the_last_sample_is_due_once():
    # the clock jumped from 0.1000 s to 0.1043 s: four 1 ms samples came due
    due = due_samples(0.1000, 0.1043, 1e-3)
    assert due == pytest.approx([0.101, 0.102, 0.103, 0.104])
    # the next call continues from the last one taken, none twice, none skipped
    assert due_samples(due[-1], 0.1061, 1e-3) == pytest.approx([0.105, 0.106])
    assert due_samples(0.106, 0.1065, 1e-3) == []


def test_off_grid_start_and_the_catch_up_cap():
    assert due_samples(0.01234, 0.0142, 1e-3) == pytest.approx([0.013, 0.014])
    due = due_samples(0.0, 60.0, 1e-3, max_samples=5)
    assert due == pytest.approx([59.996, 59.997, 59.998, 59.999, 60.0])
    with pytest.raises(ValueError):
        due_samples(0.0, 1.0, 0.0)
