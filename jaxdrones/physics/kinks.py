"""How the JAX core treats the kinks of its physics for gradients: exactly (the default), smoothly, or straight-through.

The original's physics has kinks, where the dynamics is not differentiable and reverse-mode gradients are zero, jump
or blow up:

========================  =====================================================  ================================
kink                      original (``"exact"``)                                 band of the smooth treatment
========================  =====================================================  ================================
RPM clip                  rpm ← clip(rpm, 0, max_rpm)                            ``rpm`` RPM about 0 and max_rpm
ground contact            z ← max(z, rest), v ← (0, 0, max(v_z, 0)), ω ← 0       ``height`` m about the rest height;
                          while z < rest (`jaxdrones.physics.dynamics.ground_contact_c`)  ``speed`` m/s about v_z = 0
ground-effect height      h_i ← max(h_i, gnd_eff_h_clip)                         ``height`` m about the clip
ground-effect attitude    on while R[2,2] > 0 and |R[2,0]| < 0.99999             ``attitude`` about each bound
downwash onset            on while Δz > 0; α = c1 (R / 4Δz)² grows without       on from Δz = 0 to 2·``downwash`` m
                          bound as Δz → 0⁺, then jumps to 0
downwash cut-off          on while the horizontal distance d < 10 m              ``downwash`` m about d = 10 m
========================  =====================================================  ================================

``mode="smooth"`` replaces each kink by a C¹ function that equals the original outside the band, so that
finite differences and gradients agree everywhere, across the kink included: clips and maxima get a quadratic
blend (the Huber-like soft max(x, 0) = (x + w)² / 4w on |x| ≤ w), on/off conditions a cubic smoothstep over the
band, and the downwash onset the squared smoothstep over Δz ∈ [0, 2w], which vanishes faster than α grows. The
forward pass changes inside the bands only.

``mode="straight_through"`` keeps the original forward pass and passes the gradient through the clips and the
ground contact as if they were the identity (Bengio et al., "Estimating or propagating gradients through stochastic
neurons for conditional computation", 2013): a saturated RPM or a drone pushed back onto the ground still
reports how its command or state would move the result. The on/off conditions, which have nothing to pass
through, keep the original's.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxdrones._validate import check_real

#: The treatments of `Kinks.mode`.
MODES = ("exact", "smooth", "straight_through")


@dataclasses.dataclass(frozen=True)
class Kinks:
    """Static treatment of the physics' kinks (`SimConfig.kinks`; hashable, a change recompiles).

    Attributes:
        mode: ``"exact"`` (the original's physics, default), ``"smooth"`` or ``"straight_through"`` (module doc).
        rpm: half-width of the smooth RPM-clip band, RPM (0.5 % of the Crazyflie's 21,702 max RPM by default).
        height: half-width of the smooth ground-contact and ground-effect height bands, m.
        speed: half-width of the smooth band of the ground contact's max(v_z, 0), m/s.
        attitude: half-width of the smooth ground-effect attitude bands (rotation-matrix entries, dimensionless).
        downwash: width of the smooth downwash onset above Δz = 0 and half-width of the 10 m cut-off band, m.

    Raises:
        ValueError: an unknown mode or a non-positive width.
    """

    mode: str = "exact"
    rpm: float = 100.0
    height: float = 1e-3
    speed: float = 1e-2
    attitude: float = 1e-2
    downwash: float = 1e-2

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"Kinks.mode must be one of {MODES}, got {self.mode!r}")
        for name in ("rpm", "height", "speed", "attitude", "downwash"):
            check_real(f"Kinks.{name} (a smoothing band width)", getattr(self, name), 0, low_open=True, finite=False)

    def maximum(self, x: jax.Array, floor: jax.Array | float, width: float) -> jax.Array:
        """max(x, floor), treated by `mode` with band half-width ``width`` (x's units)."""
        exact = jnp.maximum(x, floor)
        if self.mode == "smooth":
            return floor + _soft_relu(x - floor, width)
        return _straight_through(x, exact) if self.mode == "straight_through" else exact

    def clip(self, x: jax.Array, low: jax.Array | float, high: jax.Array | float, width: float) -> jax.Array:
        """Clip x to [low, high], the kinks treated by `mode` with band half-width ``width`` at each bound
        (high - low > 2 width)."""
        exact = jnp.clip(x, low, high)
        if self.mode == "smooth":
            return low + _soft_relu(x - low, width) - _soft_relu(x - high, width)
        return _straight_through(x, exact) if self.mode == "straight_through" else exact

    def choose(self, cond: jax.Array, weight: jax.Array, if_true: jax.Array, if_false: jax.Array) -> jax.Array:
        """``where(cond, if_true, if_false)``: with ``mode="smooth"`` the blend by ``weight`` (the smooth degree of
        ``cond``, in [0, 1]); straight-through passes ``if_false``'s gradient as is."""
        if self.mode == "smooth":
            return weight * if_true + (1 - weight) * if_false
        exact = jnp.where(cond, if_true, if_false)
        return _straight_through(if_false, exact) if self.mode == "straight_through" else exact

    def step(self, x: jax.Array, width: float) -> jax.Array:
        """The condition x > 0 as 0/1 (dtype of x); with ``mode="smooth"`` the smoothstep over x ∈ [-width, width]."""
        if self.mode == "smooth":
            return smoothstep((x + width) / (2 * width))
        return (x > 0).astype(x.dtype)


def smoothstep(t: jax.Array) -> jax.Array:
    """3t² - 2t³ on [0, 1], 0 below and 1 above: C¹, with zero slope at both ends."""
    t = jnp.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _soft_relu(x: jax.Array, width: float) -> jax.Array:
    """max(x, 0) with the C¹ quadratic blend (x + w)² / 4w on |x| ≤ w."""
    # where, not clip: clip's derivative is ½ at a bound, and the blend's slope must be exact on the closed band.
    inner = jnp.where(x < -width, -width, jnp.where(x > width, width, x))
    return jnp.where(x > width, x, (inner + width) ** 2 / (4 * width))


def _straight_through(x: jax.Array, exact: jax.Array) -> jax.Array:
    """``exact``'s value with the gradient of the identity in x."""
    return x + jax.lax.stop_gradient(exact - x)
