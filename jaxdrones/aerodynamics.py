"""The paper's aerodynamic effects: drag, per-propeller ground effect and inter-drone downwash.

Each function is pure, differentiable and broadcasts over leading (world) axes; downwash couples the ``D`` drones
of one world along the drone axis. Equations are those of the paper (eqs. drag, ground, down) as the paper's code
applies them in its PyBullet modes (facts sheet §6).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrones.params import DroneParams

#: Downwash acts only between drones closer than this horizontally, m (facts §6.3).
DOWNWASH_MAX_DIST = 10.0
#: Floor on the squared downwash width β², m², so that β → 0 (at Δz = -c3/c2) gives the d → 0 limit, not 0/0.
_BETA2_FLOOR = 1e-12


def drag_force(params: DroneParams, vel: jax.Array, rpm_prev: jax.Array) -> jax.Array:
    """Rotor drag, paper eq. (drag): F = -Ω · diag(c_xy, c_xy, c_z) · v, with Ω = Σ_i 2π rpm_i / 60.

    As in the paper's code (facts §6.2), the coefficients act on the world-frame velocity components and Ω uses the
    RPM applied in the *previous* physics substep.

    Args:
        params: DroneParams (``drag_coeff`` f[..., 3]).
        vel: f[..., D, 3] m/s, world frame.
        rpm_prev: f[..., D, 4] RPM of the previous substep.

    Returns:
        f[..., D, 3] N, world frame.
    """
    omega_sum = jnp.sum(rpm_prev, axis=-1, keepdims=True) * (2 * jnp.pi / 60)
    return -omega_sum * params.drag_coeff * vel


def ground_effect_thrust(params: DroneParams, pos: jax.Array, rotmat: jax.Array, thrust: jax.Array) -> jax.Array:
    """Extra per-propeller thrust near the ground, paper eq. (ground): g_i = f_i · C_gnd · (R / (4 h_i))².

    h_i is the world height of propeller i, clipped from below at ``gnd_eff_h_clip`` (so the gain is at most 4/15).
    The effect is on only while the drone is upright, |roll| < π/2 and |pitch| < π/2 (facts §6.1), which is
    R[2, 2] > 0. The extra force acts along body +z at each propeller, like thrust.

    Args:
        params: DroneParams.
        pos: f[..., D, 3] m, world frame.
        rotmat: f[..., D, 3, 3] body→world.
        thrust: f[..., D, 4] N, kf·rpm² of each motor.

    Returns:
        f[..., D, 4] N, extra thrust of each motor.
    """
    prop_height = pos[..., None, 2] + jnp.einsum("...j,...ij->...i", rotmat[..., 2, :], params.prop_pos)
    height = jnp.maximum(prop_height, params.gnd_eff_h_clip[..., None])
    gain = params.gnd_eff_coeff[..., None] * (params.prop_radius[..., None] / (4 * height)) ** 2
    upright = rotmat[..., 2, 2] > 0
    return jnp.where(upright[..., None], thrust * gain, 0.0)


def downwash_force(params: DroneParams, pos: jax.Array) -> jax.Array:
    """Downwash on each drone from every drone above it, paper eq. (down), along the lower drone's body -z.

    For a lower drone j and a drone i with Δz = z_i - z_j > 0 and horizontal distance d < 10 m:
    α = c1 (R / (4 Δz))², β = c2 Δz + c3, F = -α exp(-½ (d/β)²) (facts §6.3). Contributions add up; the upper
    drone's RPM plays no part; drones at equal height do not interact. The coefficients are the lower drone's.
    Where β = 0 (Δz = 0.6875 m for the shipped models) the d → 0 limit is used instead of the original's 0/0.

    Args:
        params: DroneParams.
        pos: f[..., D, 3] m, world frame.

    Returns:
        f[..., D] N, force along each drone's body z (negative: pushes down).
    """
    diff = pos[..., None, :, :] - pos[..., :, None, :]  # [..., j (lower), i (other), 3]
    dz = diff[..., 2]
    dist2 = diff[..., 0] ** 2 + diff[..., 1] ** 2
    active = (dz > 0) & (dist2 < DOWNWASH_MAX_DIST**2)
    dz_safe = jnp.where(active, dz, 1.0)
    c1, c2, c3 = (params.dw_coeff[..., k, None] for k in range(3))
    alpha = c1 * (params.prop_radius[..., None] / (4 * dz_safe)) ** 2
    beta2 = jnp.maximum((c2 * dz_safe + c3) ** 2, _BETA2_FLOOR)
    force = alpha * jnp.exp(-0.5 * dist2 / beta2)
    return -jnp.sum(jnp.where(active, force, 0.0), axis=-1)
