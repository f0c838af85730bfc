"""Unit conversion between SI (every interface) and the engine's internal mm-ms-g system.

Internally lengths are mm, time ms and mass g. This system is force-consistent
(g*mm/ms^2 = 1 N), so energy is N*mm = mJ and velocity mm/ms = m/s, and every quantity in a
scene is of order 1e-3..1e2, which keeps float64 (and float32 where benchmarked) well scaled.
Nothing outside `design_engine` ever sees internal units.
"""

MM_PER_M = 1.0e3
MS_PER_S = 1.0e3
G_PER_KG = 1.0e3
J_PER_MJ = 1.0e-3  # energy: internal mJ -> J


def length_from_si(x_m):
    """m -> mm."""
    return x_m * MM_PER_M


def time_to_si(t_ms):
    """ms -> s."""
    return t_ms / MS_PER_S


def time_from_si(t_s):
    """s -> ms."""
    return t_s * MS_PER_S


def energy_to_si(e_mj):
    """mJ -> J."""
    return e_mj * J_PER_MJ


def angular_momentum_to_si(l_gmm2_per_ms):
    """g*mm^2/ms -> kg*m^2/s."""
    return l_gmm2_per_ms * MS_PER_S / (G_PER_KG * MM_PER_M**2)
