"""Fixed-rate sampling of a simulated device driven by a clock that can jump (pure).

A ROS timer on simulated time fires once per clock update, however far the clock moved, and a
busy node falls behind; a device's data acquisition samples every period regardless. The device
nodes therefore catch up: at each timer call they step the device to the sample times that
came due since the last one and publish each reading with its own stamp. A call steps a bounded
device time (the rest in the next calls): a node that fell behind (a loaded machine) answers
its requests between calls, within one call's time, instead of after the whole catch-up.
"""

import math

MAX_CATCH_UP = 10_000  # samples due at most (the newest ones; older ones are dropped)
PER_CALL_S = 0.02  # device time one call steps at most, s (the oldest due samples)


def due_samples(t_last_s: float, t_now_s: float, period_s: float,
                max_samples: int = MAX_CATCH_UP, per_call_s: float = PER_CALL_S) -> list[float]:
    """Sample times k * period_s (k integer) in (t_last_s, t_now_s], oldest first, s.

    Of those, only the newest `max_samples` are due (a clock that jumped by minutes does not
    flood the network), and of these the ones within `per_call_s` of the oldest are returned
    (at least one): the next call, from the last one taken, returns the following ones.
    """
    if not period_s > 0:
        raise ValueError(f"the sample period must be positive, got {period_s}")
    k0 = math.floor(t_last_s / period_s + 1e-9) + 1
    k1 = math.floor(t_now_s / period_s + 1e-9)
    k0 = max(k0, k1 - max_samples + 1)
    per_call = max(1, math.floor(per_call_s / period_s + 1e-9))
    return [k * period_s for k in range(k0, min(k1, k0 + per_call - 1) + 1)]
