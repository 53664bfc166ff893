"""Named reward terms shared by the tasks, and their weighted sum (docs/physics.md §11).

Each term is a pure function returning ``f[..., D]`` (one value per drone). A task returns a dict of its terms;
the env combines them with the weights in its task params (``TaskParams.weights``, traced: they may differ per
world without recompiling) and logs each weighted term in ``metrics["reward/<name>"]``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrones.physics.rotations import quat_to_rotmat

#: Length scales of `closeness`: a broad term (m) that pulls from afar and a sharp one (m) that settles precisely.
BROAD_SCALE_M = 0.3
SHARP_SCALE_M = 0.03


def _safe_norm(x: jax.Array) -> jax.Array:
    sq = jnp.sum(x**2, axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def distance(pos: jax.Array, target: jax.Array) -> jax.Array:
    """‖target − pos‖, m (f[..., D]); its gradient is 0 at the target (not NaN)."""
    return _safe_norm(target - pos)


def distance_sq(pos: jax.Array, target: jax.Array) -> jax.Array:
    """‖target − pos‖², m² (the paper's hover reward is its negative, eq. single)."""
    return jnp.sum((target - pos) ** 2, axis=-1)


def closeness(pos: jax.Array, target: jax.Array) -> jax.Array:
    """exp(−d / 0.3 m) + 2 exp(−(d / 0.03 m)²) with d = ‖target − pos‖: in (0, 3], sharp near the target so that a
    policy settles on it rather than near it."""
    d = distance(pos, target)
    return jnp.exp(-d / BROAD_SCALE_M) + 2.0 * jnp.exp(-((d / SHARP_SCALE_M) ** 2))


def speed_sq(vel: jax.Array) -> jax.Array:
    """‖v‖², (m/s)²."""
    return jnp.sum(vel**2, axis=-1)


def ang_speed_sq(ang_vel: jax.Array) -> jax.Array:
    """‖ω‖², (rad/s)²."""
    return jnp.sum(ang_vel**2, axis=-1)


def tilt(quat: jax.Array) -> jax.Array:
    """1 − cos(tilt) = 1 − R₂₂ (0 level, 2 upside down), from the body z axis in the world frame."""
    return 1.0 - quat_to_rotmat(quat)[..., 2, 2]


def velocity_error_sq(vel: jax.Array, target_vel: jax.Array) -> jax.Array:
    """‖v − v*‖², (m/s)²."""
    return jnp.sum((vel - target_vel) ** 2, axis=-1)


def velocity_tracking(vel: jax.Array, target_vel: jax.Array, scale: float = 0.25) -> jax.Array:
    """exp(−‖v − v*‖ / scale): 1 at the commanded velocity, ``scale`` in m/s."""
    return jnp.exp(-_safe_norm(vel - target_vel) / scale)


def takeoff_paper(z: jax.Array) -> jax.Array:
    """The paper's TakeoffAviary reward: −5 if z < 0.02 m, else −1/(10 z)."""
    low = z < 0.02
    return jnp.where(low, -5.0, -1.0 / (10.0 * jnp.where(low, 1.0, z)))


def combine(
    terms: dict[str, jax.Array], weights: dict[str, jax.Array], nonnegative: bool = False
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Weighted sum of reward terms.

    Args:
        terms: name → f[..., D].
        weights: name → f[] (or broadcastable); every term needs a weight.
        nonnegative: clip the sum at 0 from below (shaped rewards: ending an episode early never pays).

    Returns:
        (reward f[..., D], the weighted terms by name).

    Raises:
        ValueError: a term without a weight.
    """
    missing = sorted(set(terms) - set(weights))
    if missing:
        raise ValueError(f"reward terms {missing} have no weight; weights are given for {sorted(weights)}")
    weighted = {k: weights[k] * v for k, v in terms.items()}
    total = sum(weighted.values())
    return (jnp.maximum(total, 0.0) if nonnegative else total), weighted
