"""The simulated rig's device records: the same device motion gives the same record, and so
the same specimen input, however many samples after the capture have arrived (load)."""

import numpy as np
import pytest

from design_engine.solve.run import smooth_input
from hardware_sim.rig import MotionRecord, record_complete


def _shaker_samples(t_end_s, period_s=1e-3, phase_s=0.0):
    """A shaker's joint states: a smooth pulse sampled at its own rate, (t s, u m)."""
    t = np.arange(phase_s + period_s, t_end_s + 1e-12, period_s)
    return [(float(ti), float(2e-3 * np.sin(40.0 * ti) ** 2)) for ti in t]


@pytest.mark.parametrize("late", [1, 3, 40])
def test_samples_after_the_capture_change_neither_the_record_nor_the_specimen_input(late):
    t_end = 0.05
    during = _shaker_samples(t_end)
    after = _shaker_samples(t_end + late * 1e-3)
    assert len(after) == len(during) + late
    a = MotionRecord.from_samples(during, t_end)
    b = MotionRecord.from_samples(after[::-1], t_end)  # any arrival order
    assert a.t[-1] == t_end and a.t[0] == 0.0
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.value, b.value)
    # what the specimen is driven with: a spline resampled over the whole record
    for x, y in zip(smooth_input(a.t, a.value), smooth_input(b.t, b.value), strict=True):
        assert x.tobytes() == y.tobytes()


def test_a_record_ending_before_the_capture_is_held_to_its_end():
    rec = MotionRecord.from_samples([(0.01, 1e-3), (0.02, 2e-3)], 0.05)
    np.testing.assert_array_equal(rec.t, [0.0, 0.01, 0.02, 0.05])
    np.testing.assert_array_equal(rec.value, [0.0, 1e-3, 2e-3, 2e-3])
    empty = MotionRecord.from_samples([], 0.05)
    np.testing.assert_array_equal(empty.value, [0.0, 0.0])


def test_a_record_is_complete_once_no_sample_up_to_the_end_can_still_come():
    t_end = 0.01
    ts = [t for t, _ in _shaker_samples(t_end)]  # 1 kHz, one sample due at t_end itself
    assert ts[-1] == pytest.approx(t_end)
    assert record_complete(ts, t_end)
    assert not record_complete(ts[:-1], t_end)  # the sample at t_end is still in flight
    assert not record_complete(ts[:-3], t_end)
    assert record_complete(ts[:-1] + [t_end + 1e-3], t_end)  # a later one came: in order
    # a device whose samples fall between the frames: the next is due after the end
    shifted = [t for t, _ in _shaker_samples(t_end, 2e-3, phase_s=-1.3e-3)]
    assert shifted[-1] < t_end < shifted[-1] + 2e-3
    assert record_complete(shifted, t_end)
    assert not record_complete(shifted[:-1], t_end)
    assert not record_complete([], t_end)
    assert not record_complete([0.002], t_end)
