"""The paper's aerodynamic effects: drag, per-propeller ground effect and inter-drone downwash.

Each function is pure, differentiable and broadcasts over leading (world) axes; downwash couples the ``D`` drones
of one world along the drone axis. Equations are those of the paper (eqs. drag, ground, down) as the paper's code
applies them in its PyBullet modes (docs/physics.md §6). Each is written once, in component form (``*_c``, see
`jaxdrones.rotations`), which the simulation core runs on; the array-form functions wrap it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrones.kinks import Kinks
from jaxdrones.neighbors import gather
from jaxdrones.params import DroneParams
from jaxdrones.rotations import GIMBAL_SNAP, Components, dot, join, split

#: Downwash acts only between drones closer than this horizontally, m (docs/physics.md §6.3; the original's).
DOWNWASH_MAX_DIST = 10.0
#: Floor on the squared downwash width β², m², so that β → 0 (at Δz = -c3/c2) gives the d → 0 limit, not 0/0.
_BETA2_FLOOR = 1e-12


def drag_force(params: DroneParams, vel: jax.Array, rpm_prev: jax.Array) -> jax.Array:
    """Rotor drag, paper eq. (drag): F = -Ω · diag(c_xy, c_xy, c_z) · v, with Ω = Σ_i 2π rpm_i / 60.

    As in the paper's code (docs/physics.md §6.2), the coefficients act on the world-frame velocity components and
    Ω uses the RPM applied in the *previous* physics substep.

    Args:
        params: DroneParams (``drag_coeff`` f[..., 3]).
        vel: f[..., D, 3] m/s, world frame.
        rpm_prev: f[..., D, 4] RPM of the previous substep.

    Returns:
        f[..., D, 3] N, world frame.
    """
    return join(drag_force_c(params, split(vel), split(rpm_prev)))


def drag_force_c(params: DroneParams, vel: Components, rpm_prev: Components,
                 wind: Components | None = None) -> Components:
    """`drag_force` in component form: vel (vx, vy, vz) and rpm_prev (4 motors), each f[..., D]. With ``wind``
    (the air's velocity, world frame, m/s, a 3-tuple of f[..., D]) the drag acts on the velocity relative to the
    air, v - wind: the paper's drag model in moving air (docs/physics.md §6.2)."""
    omega_sum = sum(rpm_prev[1:], rpm_prev[0]) * (2 * jnp.pi / 60)
    if wind is not None:
        vel = tuple(v - w for v, w in zip(vel, wind, strict=True))
    return tuple(-omega_sum * params.drag_coeff[..., k] * vel[k] for k in range(3))


def ground_effect_thrust(params: DroneParams, pos: jax.Array, rotmat: jax.Array, thrust: jax.Array,
                         kinks: Kinks = Kinks()) -> jax.Array:
    """Extra per-propeller thrust near the ground, paper eq. (ground): g_i = f_i · C_gnd · (R / (4 h_i))².

    h_i is the world height of propeller i, clipped from below at ``gnd_eff_h_clip`` (so the gain is at most 4/15).
    The effect is on only while |roll| < π/2 and |pitch| < π/2 in PyBullet's Euler angles (docs/physics.md §6.1):
    R[2, 2] > 0, and |sin pitch| = |R[2, 0]| below PyBullet's gimbal-lock snap (0.99999), where it reports
    pitch = ±π/2. The extra force acts along body +z at each propeller, like thrust. ``kinks`` (`jaxdrones.kinks`)
    may smooth the height clip and the attitude condition.

    Args:
        params: DroneParams.
        pos: f[..., D, 3] m, world frame.
        rotmat: f[..., D, 3, 3] body→world.
        thrust: f[..., D, 4] N, kf·rpm² of each motor.
        kinks: the kinks' treatment (default: the original's).

    Returns:
        f[..., D, 4] N, extra thrust of each motor.
    """
    rotmat_z = split(rotmat[..., 2, :])
    return join(ground_effect_thrust_c(params, pos[..., 2], rotmat_z, split(thrust), kinks))


def ground_effect_thrust_c(params: DroneParams, pos_z: jax.Array, rotmat_z: Components,
                           thrust: Components, kinks: Kinks = Kinks()) -> Components:
    """`ground_effect_thrust` in component form.

    Args:
        params: DroneParams.
        pos_z: f[..., D] m, world height of the base.
        rotmat_z: (R20, R21, R22), the last row of R, each f[..., D].
        thrust: 4-tuple of f[..., D] N.
        kinks: the kinks' treatment.
    """
    if kinks.mode == "smooth":
        upright = kinks.step(rotmat_z[2], kinks.attitude) * kinks.step(GIMBAL_SNAP - jnp.abs(rotmat_z[0]),
                                                                        kinks.attitude)
        on = lambda value: upright * value  # noqa: E731
    else:
        upright = (rotmat_z[2] > 0) & (jnp.abs(rotmat_z[0]) < GIMBAL_SNAP)
        on = lambda value: jnp.where(upright, value, 0.0)  # noqa: E731
    extra = []
    for i, thrust_i in enumerate(thrust):
        height = pos_z + dot(rotmat_z, split(params.prop_pos[..., i, :]))
        height = kinks.maximum(height, params.gnd_eff_h_clip, kinks.height)
        gain = params.gnd_eff_coeff * (params.prop_radius / (4 * height)) ** 2
        extra.append(on(thrust_i * gain))
    return tuple(extra)


def downwash_force(params: DroneParams, pos: jax.Array, kinks: Kinks = Kinks(),
                   neighbors: jax.Array | None = None, cutoff: float = DOWNWASH_MAX_DIST) -> jax.Array:
    """Downwash on each drone from every drone above it, paper eq. (down), along the lower drone's body -z.

    For a lower drone j and a drone i with Δz = z_i - z_j > 0 and horizontal distance d < 10 m:
    α = c1 (R / (4 Δz))², β = c2 Δz + c3, F = -α exp(-½ (d/β)²) (docs/physics.md §6.3). Contributions add up; the upper
    drone's RPM plays no part; drones at equal height do not interact. The coefficients are the lower drone's.
    Where β = 0 (Δz = 0.6875 m for the shipped models) the d → 0 limit is used instead of the original's 0/0.
    ``kinks`` (`jaxdrones.kinks`) may smooth the onset at Δz = 0 (where α is unbounded) and the cut-off.

    Every pair costs the same whether it interacts or not, so the cost grows as D². A shorter ``cutoff`` with a
    neighbour list ``neighbors`` (`jaxdrones.neighbors.cell_candidates`) bounds it to the listed pairs: beyond
    d = 1 m no drone, at any Δz, pushes a cf2x with more than 0.41 % of its weight (0.12 % beyond 2 m).

    Args:
        params: DroneParams.
        pos: f[..., D, 3] m, world frame.
        kinks: the kinks' treatment (default: the original's).
        neighbors: None (every drone) or i32[..., D, K], the drones that may act on each drone (entries equal to
            the drone itself count for nothing).
        cutoff: horizontal distance beyond which drones do not interact, m (the original: 10 m).

    Returns:
        f[..., D] N, force along each drone's body z (negative: pushes down).
    """
    return downwash_force_c(params, split(pos), kinks, neighbors, cutoff)


def downwash_force_c(params: DroneParams, pos: Components, kinks: Kinks = Kinks(),
                     neighbors: jax.Array | None = None, cutoff: float = DOWNWASH_MAX_DIST) -> jax.Array:
    """`downwash_force` in component form: pos (x, y, z), each f[..., D]; returns f[..., D] N."""
    if neighbors is None:  # every drone, itself included (Δz = 0: no force)
        others = tuple(p[..., None, :] for p in pos)
    else:
        others = tuple(gather(p, neighbors) for p in pos)
    dx, dy, dz = (o - p[..., :, None] for o, p in zip(others, pos, strict=True))  # [..., j (lower), i (other)]
    dist2 = dx**2 + dy**2
    smooth = kinks.mode == "smooth"
    reach = cutoff + (kinks.downwash if smooth else 0.0)
    active = (dz > 0) & (dist2 < reach**2)
    dz_safe = jnp.where(active, dz, 1.0)
    c1, c2, c3 = (params.dw_coeff[..., k, None] for k in range(3))
    alpha = c1 * (params.prop_radius[..., None] / (4 * dz_safe)) ** 2
    beta2 = jnp.maximum((c2 * dz_safe + c3) ** 2, _BETA2_FLOOR)
    force = alpha * jnp.exp(-0.5 * dist2 / beta2)
    if smooth:
        # On from Δz = 0 to 2w by smoothstep², which vanishes as Δz⁴ while α grows as Δz⁻²; off from
        # d = cutoff - w to cutoff + w (d² - cutoff² ≈ 2 cutoff·(d - cutoff)).
        width = kinks.downwash
        onset = kinks.step(dz - width, width) ** 2
        force = force * onset * kinks.step(cutoff**2 - dist2, 2 * cutoff * width)
    return -jnp.sum(jnp.where(active, force, 0.0), axis=-1)
