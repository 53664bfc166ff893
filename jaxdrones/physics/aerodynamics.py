"""The paper's aerodynamic effects: drag, per-propeller ground effect and inter-drone downwash; and a per-rotor
downwash model beside the paper's.

Each function is pure, differentiable and broadcasts over leading (world) axes; downwash couples the ``D`` drones
of one world along the drone axis. Equations are those of the paper (eqs. drag, ground, down) as the paper's code
applies them in its PyBullet modes (docs/physics.md §6). The per-rotor downwash (`downwash_thrust`, docs/physics.md
§6.4) samples the jet of Bauersfeld et al. at each rotor of the lower drone and turns it into a thrust change with the
law of Su et al. Each is written once, in component form (``*_c``, see `jaxdrones.physics.rotations`), which the
simulation core runs on; the array-form functions wrap it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrones.physics.kinks import Kinks
from jaxdrones.physics.neighbors import gather
from jaxdrones.physics.params import DroneParams, align_params
from jaxdrones.physics.rotations import GIMBAL_SNAP, Components, dot, join, split

#: The downwash models of `jaxdrones.physics.config.SimConfig.downwash`: the paper's one force at the lower drone's
#: centre of mass (`downwash_force`, docs/physics.md §6.3), the per-rotor thrust changes (`downwash_thrust`, §6.4) and
#: the bounded form fitted to real flights (`downwash_force` with `BOUNDED_DOWNWASH`, §6.5).
DOWNWASH_MODELS = ("paper", "per_rotor", "bounded")
#: Downwash acts only between drones closer than this horizontally, m (docs/physics.md §6.3; the original's).
DOWNWASH_MAX_DIST = 10.0
#: Air density, kg/m³ (ISA sea level), in the hover induced velocity of the per-rotor model's jet.
AIR_DENSITY = 1.225
#: The far-field fit of the jet below a hovering quadrotor (L. Bauersfeld, K. Muller, D. Ziegler, F. Coletti,
#: D. Scaramuzza, "Robotics meets Fluid Dynamics: A Characterization of the Induced Airflow below a Quadrotor as a
#: Turbulent Jet", IEEE RA-L (accepted 2024), arXiv:2403.13321, Eq. (9)): the centreline decay constant B_D, the
#: spreading rate S of the half-width and the virtual origin s̃0, in units of the motor distance l (their Eq. (8)).
JET_DECAY = 10.11
JET_SPREAD = 0.07668
JET_ORIGIN = -5.817
#: Below the source's rotor plane the jet acts from s = 0.1 l on (crazyflow's examples/plugins/downwash.py, which
#: keeps the fit from giving flow above the source); the fit itself was identified beyond 2.5 l (docs/physics.md §6.4).
JET_ONSET = 0.1
#: The per-rotor model's thrust decay coefficient b_v, s/m: each rotor loses the fraction b_v·U of its thrust in a
#: downward inflow U (Y. Su et al., "Downwash-aware Control Allocation for Over-actuated UAV Platforms", IROS 2022,
#: arXiv:2207.09645, Eq. (5)). The value, 0.07 s/m, is the one crazyflow's downwash example uses for the Crazyflie
#: (learnsyslab/crazyflow, examples/plugins/downwash.py), which notes that it must be fitted to the propeller.
THRUST_DECAY = 0.07
#: The bounded downwash's constants (c1, c2, c3 m, δ m; `downwash_force`'s ``bounded``), least squares on the vertical
#: residual force of the 99 two- and three-drone swaps of Neural-Swarm (aerorobotics/neural-swarm at 48b1851: every
#: swap but the three of datacollection20_12_20_2019, held out) while a drone was above within 15 cm horizontally
#: (`python benchmarks/validation/flights.py`, docs/validation.md §3). c3 < 0: the width β = c2 Δz + c3 reaches its
#: floor at Δz = 7.5 cm, below which only a drone directly underneath is pushed (where no flight went).
BOUNDED_DOWNWASH = (4110.178, 0.29964, -0.022552, 1.80706)
#: The thrust the bounded downwash's scaling is relative to, N: a hovering cf2x's, 0.027 kg × 9.8 m/s².
DOWNWASH_THRUST_REF = 0.027 * 9.8
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
    params = align_params(params, vel.ndim - 1)
    return join(drag_force_c(params, split(vel), split(rpm_prev)))


def drag_force_c(
    params: DroneParams, vel: Components, rpm_prev: Components, wind: Components | None = None
) -> Components:
    """`drag_force` in component form: vel (vx, vy, vz) and rpm_prev (4 motors), each f[..., D]. With ``wind``
    (the air's velocity, world frame, m/s, a 3-tuple of f[..., D]) the drag acts on the velocity relative to the
    air, v - wind: the paper's drag model in moving air (docs/physics.md §6.2)."""
    omega_sum = sum(rpm_prev[1:], rpm_prev[0]) * (2 * jnp.pi / 60)
    if wind is not None:
        vel = tuple(v - w for v, w in zip(vel, wind, strict=True))
    return tuple(-omega_sum * params.drag_coeff[..., k] * vel[k] for k in range(3))


def ground_effect_thrust(
    params: DroneParams, pos: jax.Array, rotmat: jax.Array, thrust: jax.Array, kinks: Kinks = Kinks()
) -> jax.Array:
    """Extra per-propeller thrust near the ground, paper eq. (ground): g_i = f_i · C_gnd · (R / (4 h_i))².

    h_i is the world height of propeller i, clipped from below at ``gnd_eff_h_clip`` (so the gain is at most 4/15).
    The effect is on only while |roll| < π/2 and |pitch| < π/2 in PyBullet's Euler angles (docs/physics.md §6.1):
    R[2, 2] > 0, and |sin pitch| = |R[2, 0]| below PyBullet's gimbal-lock snap (0.99999), where it reports
    pitch = ±π/2. The extra force acts along body +z at each propeller, like thrust. ``kinks``
    (`jaxdrones.physics.kinks`) may smooth the height clip and the attitude condition.

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
    params = align_params(params, pos.ndim - 1)
    return join(ground_effect_thrust_c(params, pos[..., 2], rotmat_z, split(thrust), kinks))


def ground_effect_thrust_c(
    params: DroneParams, pos_z: jax.Array, rotmat_z: Components, thrust: Components, kinks: Kinks = Kinks()
) -> Components:
    """`ground_effect_thrust` in component form.

    Args:
        params: DroneParams.
        pos_z: f[..., D] m, world height of the base.
        rotmat_z: (R20, R21, R22), the last row of R, each f[..., D].
        thrust: 4-tuple of f[..., D] N.
        kinks: the kinks' treatment.
    """
    if kinks.mode == "smooth":
        upright = kinks.step(rotmat_z[2], kinks.attitude) * kinks.step(
            GIMBAL_SNAP - jnp.abs(rotmat_z[0]), kinks.attitude
        )
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


def downwash_force(
    params: DroneParams,
    pos: jax.Array,
    kinks: Kinks = Kinks(),
    neighbors: jax.Array | None = None,
    cutoff: float = DOWNWASH_MAX_DIST,
    bounded: jax.Array | tuple[float, ...] | None = None,
    thrust: jax.Array | None = None,
) -> jax.Array:
    """Downwash on each drone from every drone above it, paper eq. (down), along the lower drone's body -z.

    For a lower drone j and a drone i with Δz = z_i - z_j > 0 and horizontal distance d < 10 m:
    α = c1 (R / (4 Δz))², β = c2 Δz + c3, F = -α exp(-½ (d/β)²) (docs/physics.md §6.3). Contributions add up; the upper
    drone's RPM plays no part; drones at equal height do not interact. The coefficients are the lower drone's.
    Where β = 0 (Δz = 0.6875 m for the shipped models) the d → 0 limit is used instead of the original's 0/0.
    ``kinks`` (`jaxdrones.physics.kinks`) may smooth the onset at Δz = 0 (where α is unbounded) and the cut-off.

    Every pair costs the same whether it interacts or not, so the cost grows as D². A shorter ``cutoff`` with a
    neighbour list ``neighbors`` (`jaxdrones.physics.neighbors.cell_candidates`) bounds it to the listed pairs: beyond
    d = 1 m no drone, at any Δz, pushes a cf2x with more than 0.41 % of its weight (0.12 % beyond 2 m).

    Args:
        params: DroneParams.
        pos: f[..., D, 3] m, world frame.
        kinks: the kinks' treatment (default: the original's).
        neighbors: None (every drone) or i32[..., D, K], the drones that may act on each drone (entries equal to
            the drone itself count for nothing).
        cutoff: horizontal distance beyond which drones do not interact, m (the original: 10 m).
        bounded: None (the paper's form with ``params.dw_coeff``) or the bounded form's constants (c1, c2, c3 m,
            δ m), f[4] (`BOUNDED_DOWNWASH` for ``SimConfig(downwash="bounded")``, docs/physics.md §6.5):
            α = c1 (R/4)² (T_j / T_ref) √(T_i / T_ref) / (Δz² + δ²) with T_j, T_i the lower and the upper drone's
            thrust and T_ref = `DOWNWASH_THRUST_REF`: finite as Δz → 0, and growing with either drone's thrust.
        thrust: f[..., D] N, each drone's total rotor thrust (Σ kf rpm²); needed with ``bounded``, else unused.

    Returns:
        f[..., D] N, force along each drone's body z (negative: pushes down).

    Raises:
        ValueError: ``bounded`` without ``thrust``.
    """
    params = align_params(params, pos.ndim - 1)
    return downwash_force_c(params, split(pos), kinks, neighbors, cutoff, bounded, thrust)


def downwash_force_c(
    params: DroneParams,
    pos: Components,
    kinks: Kinks = Kinks(),
    neighbors: jax.Array | None = None,
    cutoff: float = DOWNWASH_MAX_DIST,
    bounded: jax.Array | tuple[float, ...] | None = None,
    thrust: jax.Array | None = None,
) -> jax.Array:
    """`downwash_force` in component form: pos (x, y, z) and ``thrust``, each f[..., D]; returns f[..., D] N."""
    if bounded is not None and thrust is None:
        raise ValueError("downwash_force: the bounded form needs each drone's thrust (thrust=f[..., D] N)")
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
    scale = (params.prop_radius[..., None] / 4) ** 2
    if bounded is None:
        c1, c2, c3 = (params.dw_coeff[..., k, None] for k in range(3))
        alpha = c1 * scale / dz_safe**2
    else:
        c1, c2, c3, soft = bounded[0], bounded[1], bounded[2], bounded[3]
        upper = (thrust[..., None, :] if neighbors is None else gather(thrust, neighbors)) / DOWNWASH_THRUST_REF
        lower = thrust[..., :, None] / DOWNWASH_THRUST_REF
        alpha = c1 * scale * lower * jnp.sqrt(jnp.maximum(upper, 0.0)) / (dz_safe**2 + soft**2)
    beta2 = jnp.maximum((c2 * dz_safe + c3) ** 2, _BETA2_FLOOR)
    force = alpha * jnp.exp(-0.5 * dist2 / beta2)
    if smooth:
        # On from Δz = 0 to 2w by smoothstep², which vanishes as Δz⁴ while α grows as Δz⁻²; off from
        # d = cutoff - w to cutoff + w (d² - cutoff² ≈ 2 cutoff·(d - cutoff)).
        width = kinks.downwash
        onset = kinks.step(dz - width, width) ** 2
        force = force * onset * kinks.step(cutoff**2 - dist2, 2 * cutoff * width)
    return -jnp.sum(jnp.where(active, force, 0.0), axis=-1)


def hover_induced_velocity(params: DroneParams) -> jax.Array:
    """The induced velocity of a hovering drone, U_H = √(m g / (2 ρ π r_P² n)) with n = 4 rotors, m/s
    (momentum theory; Bauersfeld et al., arXiv:2403.13321, Eq. (1)); f[...] like ``params.mass``."""
    disc_area = jnp.pi * params.prop_radius**2 * params.prop_pos.shape[-2]
    return jnp.sqrt(params.mass * params.gravity / (2 * AIR_DENSITY * disc_area))


def jet_speed(s: jax.Array, r2: jax.Array, u_hover: jax.Array, length: jax.Array) -> jax.Array:
    """Mean downward air speed in the jet below a hovering quadrotor, m/s (Bauersfeld et al., arXiv:2403.13321).

    With s̃ = s / l, r̃ = r / l (Eq. (8)), the centreline speed U_c = U_H B_D / (s̃ − s̃0) (Eq. (2)), the half-width
    r̃½ = S (s̃ − s̃0) (Eq. (6)) and ξ = r̃ / r̃½ (Eq. (4)): U = U_c / (1 + (√2 − 1) ξ²)² (Eq. (3)), half the centreline
    speed at ξ = 1; B_D, S, s̃0 are their Eq. (9)'s fit (`JET_DECAY`, `JET_SPREAD`, `JET_ORIGIN`). The caller keeps
    s̃ > s̃0 (the fit diverges at the virtual origin); see `downwash_thrust` for where it is used.

    Args:
        s: f[...] m, distance below the source along its body −z axis.
        r2: f[...] m², squared distance from the source's body z axis (r², so that r = 0 has a finite gradient).
        u_hover: f[...] m/s, the source's `hover_induced_velocity`.
        length: f[...] m, the source's motor distance l (between opposite motors).

    Returns:
        f[...] m/s, along the source's body −z axis.
    """
    axial = s / length - JET_ORIGIN
    xi2 = r2 / (length * JET_SPREAD * axial) ** 2
    return u_hover * JET_DECAY / axial / (1 + (jnp.sqrt(2.0) - 1) * xi2) ** 2


def downwash_thrust(
    params: DroneParams,
    pos: jax.Array,
    rotmat: jax.Array,
    thrust: jax.Array,
    kinks: Kinks = Kinks(),
    neighbors: jax.Array | None = None,
    cutoff: float = DOWNWASH_MAX_DIST,
) -> jax.Array:
    """Per-rotor downwash: the change of each rotor's thrust in the jets of the drones above (docs/physics.md §6.4).

    Each drone i is a hovering source whose jet (`jet_speed`: Bauersfeld et al., "Robotics meets Fluid Dynamics",
    arXiv:2403.13321, Eqs. (1)-(4), (6), (8), (9)) runs along its body −z axis from its centre of mass, with its own
    U_H (`hover_induced_velocity`) and motor distance l = 2·arm. It is sampled at each rotor k of every other drone j,
    at the lever-arm point where the rotor's thrust acts (``(−torque_arm[1, k], torque_arm[0, k], prop_pos[k, 2])``
    in j's body frame), at the distance s below i along i's body z and r from that axis; the speed along j's rotor
    axis is U cos θ (θ between the drones' body z axes), and the sources' contributions add up. Rotor k then changes
    its thrust by ΔT_jk = −b_v U_jk f_jk (Su et al., "Downwash-aware Control Allocation for Over-actuated UAV
    Platforms", arXiv:2207.09645, Eq. (5); b_v = `THRUST_DECAY`), f_jk its motor thrust kf·rpm². This is the model of
    crazyflow's downwash example (learnsyslab/crazyflow, examples/plugins/downwash.py), without its drag of the wake.

    A source acts where s > 0.1 l (`JET_ONSET`; the fit was identified beyond 2.5 l) and the centres are closer than
    ``cutoff`` horizontally. ΔT acts like thrust, along the lower drone's body +z at the rotor, so that unequal losses
    give a roll and pitch torque. ``kinks`` (`jaxdrones.physics.kinks`) may smooth the onset (over
    2·``kinks.downwash`` m below 0.1 l) and the cut-off. ``neighbors`` (`jaxdrones.physics.neighbors.cell_candidates`)
    bounds the pairs, as in `downwash_force`.

    Args:
        params: DroneParams (the source's mass, gravity, prop_radius and arm; the lower drone's lever arms).
        pos: f[..., D, 3] m, world frame.
        rotmat: f[..., D, 3, 3] body→world.
        thrust: f[..., D, 4] N, kf·rpm² of each motor.
        kinks: the kinks' treatment (default: exact).
        neighbors: None (every drone) or i32[..., D, K], the drones that may act on each drone (entries equal to
            the drone itself count for nothing).
        cutoff: horizontal distance between the centres beyond which drones do not interact, m.

    Returns:
        f[..., D, 4] N, the change of each rotor's thrust along its drone's body +z (negative: a loss).
    """
    rows = tuple(split(rotmat[..., r, :]) for r in range(3))
    params = align_params(params, pos.ndim - 1)
    return join(downwash_thrust_c(params, split(pos), rows, split(thrust), kinks, neighbors, cutoff))


def downwash_thrust_c(
    params: DroneParams,
    pos: Components,
    rotmat: tuple[Components, Components, Components],
    thrust: Components,
    kinks: Kinks = Kinks(),
    neighbors: jax.Array | None = None,
    cutoff: float = DOWNWASH_MAX_DIST,
) -> Components:
    """`downwash_thrust` in component form: pos (x, y, z), rotmat's rows and thrust (4 motors), each f[..., D];
    returns the 4-tuple of thrust changes, each f[..., D] N."""
    shape = pos[0].shape
    own = lambda x: jnp.broadcast_to(x, shape)[..., :, None]  # noqa: E731  [..., j (lower), 1]
    index = jnp.broadcast_to(jnp.arange(shape[-1]), shape)
    if neighbors is None:  # every drone: [..., j (lower), i (source)]
        source = lambda x: jnp.broadcast_to(x, shape)[..., None, :]  # noqa: E731
        other = source(index) != own(index)
    else:
        source = lambda x: gather(jnp.broadcast_to(x, shape), neighbors)  # noqa: E731
        other = neighbors != own(index)
    src_pos = tuple(source(p) for p in pos)
    src_axis = tuple(source(row[2]) for row in rotmat)  # the sources' body z axes, world frame
    own_axis = tuple(own(row[2]) for row in rotmat)
    cos_theta = dot(src_axis, own_axis)
    u_hover = source(hover_induced_velocity(params))
    length = source(2 * params.arm)
    dist2 = (src_pos[0] - own(pos[0])) ** 2 + (src_pos[1] - own(pos[1])) ** 2
    smooth = kinks.mode == "smooth"
    reach = cutoff + (kinks.downwash if smooth else 0.0)
    near = other & (dist2 < reach**2)
    arm = params.torque_arm
    onset = JET_ONSET * length
    changes = []
    for k, thrust_k in enumerate(thrust):
        lever = (-arm[..., 1, k], arm[..., 0, k], params.prop_pos[..., k, 2])  # the rotor's thrust point, body frame
        rotor = tuple(p + dot(row, lever) for p, row in zip(pos, rotmat, strict=True))
        d = tuple(own(q) - p for q, p in zip(rotor, src_pos, strict=True))  # source centre → rotor, world frame
        s = -dot(src_axis, d)
        across = tuple(dk + s * a for dk, a in zip(d, src_axis, strict=True))  # d's part normal to the axis
        r2 = dot(across, across)
        active = near & (s > onset)
        s_safe = jnp.where(active, s, length)
        speed = jet_speed(s_safe, r2, u_hover, length) * cos_theta
        if smooth:
            width = kinks.downwash
            speed = speed * kinks.step(s - onset - width, width) * kinks.step(cutoff**2 - dist2, 2 * cutoff * width)
        inflow = jnp.sum(jnp.where(active, speed, 0.0), axis=-1)
        changes.append(-THRUST_DECAY * inflow * thrust_k)
    return tuple(changes)
