"""Prescribed motion: input waveforms, stage ramps and the supports that carry them (spec 7).

Every constrained DOF follows `gain * signal[channel](t)`, with three signal channels:
0 = zero (clamp), 1 = input displacement u_in(t), 2 = stage closing delta(t) (total, both rows).
All times ms, displacements mm (internal units).
"""

import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from design_engine._types import Array, Float, Scalar

CH_ZERO, CH_INPUT, CH_STAGE = 0, 1, 2
WAVEFORMS = ("pulse", "harmonic", "measured")
# how the stages reach their strain: "ramp" closes them at `strain_rate` from t = 0 and the
# dynamics follow (the reference's two-stage protocol, spec 7.4); "static" holds them closed from
# t = 0 and the solve starts at rest in the static equilibrium there (`statics`), the pulse
# following after `delay` (the rig closes its stages slowly and settles before it fires)
PRECOMPRESSION = ("ramp", "static")


class Loading(eqx.Module):
    """Input and stage signals (internal units: mm, ms).

    Attributes:
        waveform: "pulse" (one raised-cosine period), "harmonic" (raised cosine, no end) or
            "measured" (linear interpolation of `measured_t`, `measured_u`, held outside).
        amplitude: pulse amplitude A, mm.
        frequency: pulse frequency f, 1/ms.
        delay: input delay t_d, ms (0.1 / f in the paper).
        pulse_start: extra offset before the input starts (the pre-compression time t_c), ms.
        strain: pre-compression strain (0 for none).
        strain_rate: pre-compression rate, 1/ms.
        stage_height: nominal height (N_y - 1) s that the strain refers to, mm.
        measured_t, measured_u: [n] samples of a measured input (ms, mm); used by "measured".
        stage_t, stage_closing: [m] samples of a measured total stage closing (ms, mm); when
            given they replace the ramp.
        precompression: "ramp" or "static" (see `PRECOMPRESSION`); "static" starts every solve
            from the equilibrium under the closed stages, so its `pulse_start` is 0.
    """

    waveform: str = eqx.field(static=True, default="pulse")
    amplitude: float = 7.5
    frequency: float = 0.03
    delay: float = 0.1 / 0.03
    pulse_start: float = 0.0
    strain: float = 0.0
    strain_rate: float = 2.5e-4
    stage_height: float = 0.0
    measured_t: Float[Array, " n"] | None = None
    measured_u: Float[Array, " n"] | None = None
    stage_t: Float[Array, " m"] | None = None
    stage_closing: Float[Array, " m"] | None = None
    precompression: str = eqx.field(static=True, default="ramp")

    def __check_init__(self):
        if self.waveform not in WAVEFORMS:
            raise ValueError(f"waveform must be one of {WAVEFORMS}, got {self.waveform!r}")
        if self.precompression not in PRECOMPRESSION:
            raise ValueError(f"precompression must be one of {PRECOMPRESSION}, got "
                             f"{self.precompression!r}")
        if self.waveform == "measured" and (self.measured_t is None or self.measured_u is None):
            raise ValueError("a measured waveform needs measured_t and measured_u")

    @property
    def precompression_time(self) -> float:
        """Duration t_c of the pre-compression ramp, ms (0 for a static pre-compression)."""
        if self.precompression == "static":
            return 0.0
        return float(self.strain / self.strain_rate) if self.strain > 0 else 0.0

    @property
    def is_static(self) -> bool:
        """True when solves start from the static equilibrium under the closed stages."""
        return self.precompression == "static"


def input_displacement(t: Scalar, ld: Loading) -> Scalar:
    """u_in(t), mm."""
    if ld.waveform == "measured":
        return jnp.interp(t - ld.pulse_start - ld.delay, ld.measured_t, ld.measured_u)
    tau = t - ld.pulse_start - ld.delay
    raised = 0.5 * ld.amplitude * (1.0 - jnp.cos(2.0 * math.pi * ld.frequency * tau))
    if ld.waveform == "pulse":
        on = (tau > 0.0) & (tau < 1.0 / ld.frequency)
    else:
        on = tau > 0.0
    return jnp.where(on, raised, 0.0)


def stage_closing(t: Scalar, ld: Loading) -> Scalar:
    """Total closing delta(t) of the two stage rows, mm (half is applied to each row)."""
    if ld.stage_t is not None:
        return jnp.interp(t, ld.stage_t, ld.stage_closing)
    if ld.precompression == "static":
        return ld.stage_height * ld.strain * jnp.ones_like(t)
    return ld.stage_height * jnp.minimum(ld.strain_rate * t, ld.strain)


def signals(t: Scalar, ld: Loading) -> Float[Array, "3"]:
    """[zero, u_in, delta] at time t."""
    return jnp.stack([jnp.zeros_like(t), input_displacement(t, ld), stage_closing(t, ld)])


@dataclass(frozen=True, eq=False)
class Supports:
    """Which global DOFs (3 b + d) are prescribed, and how.

    Attributes:
        n_blocks: number of blocks.
        constrained: [n_c] sorted global DOF ids that are prescribed.
        channel: [n_c] signal channel of each (CH_ZERO, CH_INPUT, CH_STAGE).
        gain: [n_c] multiplier of the signal (+1 into the specimen from the left, -1/2 top stage...).
    """

    n_blocks: int
    constrained: np.ndarray
    channel: np.ndarray
    gain: np.ndarray

    def __post_init__(self):
        if len(set(self.constrained.tolist())) != len(self.constrained):
            raise ValueError("a DOF is prescribed twice")

    @property
    def free(self) -> np.ndarray:
        """[n_f] free global DOF ids in increasing order."""
        mask = np.ones(3 * self.n_blocks, dtype=bool)
        mask[self.constrained] = False
        return np.nonzero(mask)[0]

    @property
    def assemble_index(self) -> np.ndarray:
        """[3 n_blocks] index into concat(q_free, q_constrained) giving the full DOF vector."""
        idx = np.empty(3 * self.n_blocks, dtype=np.int32)
        free = self.free
        idx[free] = np.arange(free.size)
        idx[self.constrained] = free.size + np.arange(self.constrained.size)
        return idx

    @classmethod
    def from_rules(cls, n_blocks: int, rules: dict[tuple[int, int], tuple[int, float]]) -> "Supports":
        """Build from {(block, dof): (channel, gain)}; later rules for the same DOF win."""
        keys = sorted(3 * b + d for (b, d) in rules)
        lookup = {3 * b + d: v for (b, d), v in rules.items()}
        return cls(
            n_blocks=n_blocks,
            constrained=np.asarray(keys, dtype=np.int32),
            channel=np.asarray([lookup[k][0] for k in keys], dtype=np.int32),
            gain=np.asarray([lookup[k][1] for k in keys], dtype=np.float64),
        )


def make_prescribed(supports: Supports):
    """Factory: `prescribed(t, loading) -> (q_c [n_c], qdot_c [n_c])`, velocities exact by AD."""
    channel = np.asarray(supports.channel)
    gain = np.asarray(supports.gain)

    def values(t, ld):
        return jnp.asarray(gain, t.dtype) * signals(t, ld)[channel]

    def prescribed(t, ld):
        return jax.jvp(lambda tt: values(tt, ld), (t,), (jnp.ones_like(t),))

    return values, prescribed
