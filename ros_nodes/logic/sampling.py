"""Fixed-rate sampling of a simulated device driven by a clock that can jump (pure).

A ROS timer on simulated time fires once per clock update, however far the clock moved, and a
busy node falls behind; a device's data acquisition samples every period regardless. The device
nodes therefore catch up: at each timer call they step the device to every sample time that
came due since the last one and publish each reading with its own stamp.
"""

import math

MAX_CATCH_UP = 10_000  # samples taken in one call at most (the newest ones)


def due_samples(t_last_s: float, t_now_s: float, period_s: float,
                max_samples: int = MAX_CATCH_UP) -> list[float]:
    """Sample times k * period_s (k integer) in (t_last_s, t_now_s], oldest first, s.

    At most the newest `max_samples` are returned (a clock that jumped by minutes does not
    flood the network).
    """
    if not period_s > 0:
        raise ValueError(f"the sample period must be positive, got {period_s}")
    k0 = math.floor(t_last_s / period_s + 1e-9) + 1
    k1 = math.floor(t_now_s / period_s + 1e-9)
    k0 = max(k0, k1 - max_samples + 1)
    return [k * period_s for k in range(k0, k1 + 1)]
