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
    assert due_samples(0.0, 60.0, 1e-3, max_samples=1) == pytest.approx([60.0])
    with pytest.raises(ValueError):
        due_samples(0.0, 1.0, 0.0)


def test_a_call_steps_a_bounded_time_and_the_next_calls_the_rest():
    # a node 10 s behind steps 50 ms a call, oldest samples first, none twice, none skipped
    taken, t_last = [], 0.0
    while due := due_samples(t_last, 10.0, 1e-3, per_call_s=0.05):
        assert len(due) <= 50
        taken += due
        t_last = due[-1]
    assert len(taken) == 10_000 and taken == pytest.approx([k * 1e-3 for k in range(1, 10_001)])
    # the cap on what is due applies first: of the newest 100, the oldest 30 ms
    assert due_samples(0.0, 60.0, 1e-3, max_samples=100, per_call_s=0.03) == \
        pytest.approx([59.901 + k * 1e-3 for k in range(30)])
    # a period longer than a call's time still takes one sample a call
    assert due_samples(0.0, 1.0, 0.2, per_call_s=0.05) == pytest.approx([0.2])
