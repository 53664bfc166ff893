"""Explicit rigid-body dynamics of a quadrotor: motor model, mixer, Newton-Euler equations, integrators.

The update is the paper's explicit model (IROS 2021, eqs. (motors) and (physics); gym-pybullet-drones' DYN mode;
docs/physics.md §3.1, §4): thrust f_i = kf·rpm_i² along body +z, torques from the x/+ lever arms and the yaw
reaction -spin_i·km·rpm_i², Euler's equation J ω̇ = τ - ω × Jω in the body frame, and m a = R (0, 0, Σf) - (0, 0, m g)
in the world frame.
All functions broadcast over leading axes; the drone axis is ``-2`` for f[..., D, k] arrays.

Each equation is written once, in component form (``*_c``: vectors as tuples of f[..., D] arrays, see
`jaxdrones.physics.rotations`), which the simulation core steps on.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxdrones.physics import aerodynamics
from jaxdrones.physics.kinks import Kinks
from jaxdrones.physics.neighbors import cell_candidates
from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.rotations import (
    Components,
    cross,
    dot,
    matvec,
    normalize_c,
    quat_derivative_c,
    quat_integrate_c,
    quat_to_rotmat_c,
    split,
)
from jaxdrones.physics.state import Disturbance


class Effects(NamedTuple):
    """Which aerodynamic effects are on, and how the kinks are treated (static; see `SimConfig`)."""

    drag: bool = False
    ground_effect: bool = False
    downwash: bool | str = False  # False, True (the paper's), "per_rotor" or "bounded", as `SimConfig.downwash`
    kinks: Kinks = Kinks()
    downwash_radius: float | None = None
    cell_capacity: int = 8

    @property
    def downwash_cutoff(self) -> float:
        """Horizontal distance beyond which drones feel no downwash from each other, m."""
        return aerodynamics.DOWNWASH_MAX_DIST if self.downwash_radius is None else self.downwash_radius

    def downwash_neighbors(self, pos: Components) -> jax.Array | None:
        """The drones that may act on each drone through downwash, i32[..., D, 9·cell_capacity]
        (`jaxdrones.physics.neighbors.cell_candidates`) when ``downwash_radius`` is set and the list is shorter than the
        team, else None (every drone)."""
        n = pos[0].shape[-1]
        if not self.downwash or self.downwash_radius is None or 9 * self.cell_capacity >= n - 1:
            return None
        return cell_candidates(pos[0], pos[1], self.downwash_radius, self.cell_capacity)


class Kinematics(NamedTuple):
    """The integrated quantities of ``D`` drones (see `DroneState` for units and frames).

    In component form (the ``*_c`` functions) each field is a k-tuple of f[..., D] arrays.
    """

    pos: jax.Array
    quat: jax.Array
    vel: jax.Array
    ang_vel: jax.Array


class Motors(NamedTuple):
    """What the motors produce for an RPM command, in component form (see `motors_c`).

    It depends on the command only, which a control step holds over all its substeps, so the step computes it once.
    """

    thrust: Components  #: 4-tuple of f[..., D] N, kf·rpm_i² along body +z.
    yaw_torque: jax.Array  #: f[..., D] N·m about body z, -Σ spin_i km rpm_i² (the rotors' reaction torque).


def motors_c(params: DroneParams, rpm: Components) -> Motors:
    """`Motors` of an RPM command given as a 4-tuple of f[..., D] RPM."""
    return Motors(motor_thrust_c(params, rpm), yaw_torque_c(params, rpm))


def motor_decay(tau: jax.Array, dt: float) -> jax.Array:
    """exp(-dt/τ), the fraction of a motor's speed error left after ``dt`` s of first-order lag with time constant
    τ s (f[...]); 0 for τ ≤ 0 (instant motors), with a zero derivative there rather than NaN."""
    positive = tau > 0
    return jnp.where(positive, jnp.exp(-dt / jnp.where(positive, tau, 1.0)), 0.0)


def motor_response_c(params: DroneParams, rpm: Components, command: Components, dt: float) -> Components:
    """The motors' speeds after ``dt`` s of first-order dynamics towards a held command (docs/physics.md §3.3).

    ω(t + dt) = c + (ω(t) - c)·exp(-dt/τ): the exact solution of τ dω/dt = c - ω for a command c held over the
    substep, with τ = ``params.motor_tau_up`` while the motor speeds up (c > ω) and ``motor_tau_down`` otherwise
    (separate rising and falling constants as in L2F / RLtools, Eschmann et al. 2024).

    Args:
        params: DroneParams (``motor_tau_up``, ``motor_tau_down`` f[..., D] s; 0 = instant).
        rpm: 4-tuple of f[..., D] RPM, the motors' speeds now.
        command: 4-tuple of f[..., D] RPM, the (clipped) command.
        dt: the substep, s.

    Returns:
        4-tuple of f[..., D] RPM.
    """
    up, down = motor_decay(params.motor_tau_up, dt), motor_decay(params.motor_tau_down, dt)
    return tuple(c + (r - c) * jnp.where(c > r, up, down) for r, c in zip(rpm, command, strict=True))


def motor_thrust_c(params: DroneParams, rpm: Components) -> Components:
    """Per-motor thrust kf·rpm² (docs/physics.md §3): 4-tuple of f[..., D] RPM -> 4-tuple of f[..., D] N."""
    return tuple(params.kf * r**2 for r in rpm)


def yaw_torque_c(params: DroneParams, rpm: Components) -> jax.Array:
    """Yaw reaction torque of the rotors -Σ spin_i km rpm_i², N·m: 4-tuple of f[..., D] RPM -> f[..., D]."""
    spin = split(params.prop_spin)
    return -dot(tuple(s * params.km for s in spin), tuple(r**2 for r in rpm))


def body_torque_c(params: DroneParams, lift: Components, yaw_torque: jax.Array) -> Components:
    """Body-frame torque from the motors (docs/physics.md §3.1), N·m: (τx, τy) = torque_arm @ lift, τz = ``yaw_torque``.

    Args:
        params: DroneParams (``torque_arm`` f[..., 2, 4] m).
        lift: 4-tuple of f[..., D] N, per-motor force along body z (thrust, plus ground effect when on).
        yaw_torque: f[..., D] N·m, the rotors' reaction torque (`yaw_torque_c`).
    """
    tau_x, tau_y = matvec(params.torque_arm, lift)
    return tau_x, tau_y, yaw_torque


def accelerations_c(
    params: DroneParams,
    effects: Effects,
    kin: Kinematics,
    motors: Motors,
    rpm_prev: Components,
    unit_quat: bool = False,
    neighbors: jax.Array | None = None,
    downwash: jax.Array | None = None,
    disturbance: Disturbance | None = None,
) -> tuple[Components, Components]:
    """Linear (world, m/s²) and angular (body, rad/s²) accelerations, with the motors' output for the applied RPM
    (`motors_c`) and ``rpm_prev`` (4-tuple of f[..., D], the RPM of the previous substep, for drag only).

    ``unit_quat=True`` tells that ``kin.quat`` is of unit norm (as every step leaves it), which skips normalising it
    again for the rotation matrix. ``neighbors`` i32[..., D, K]: the drones whose downwash acts on each drone
    (`Effects.downwash_neighbors`; default: chosen from ``kin.pos``). ``downwash``: `downwash_c`'s output when
    already computed (see `jaxdrones.physics.adjoint`).
    ``disturbance``: a `jaxdrones.physics.state.Disturbance` in component form (each given field a 3-tuple of
    f[..., D]): its force (world) adds to the force, its torque (body) to the torque, its wind to the drag's air
    velocity.

    Returns:
        (ax, ay, az) m/s², world frame, and (ω̇x, ω̇y, ω̇z) rad/s², body frame, each f[..., D].
    """
    rotmat = quat_to_rotmat_c(kin.quat, unit=unit_quat)
    thrust = motors.thrust
    lift = thrust
    if effects.ground_effect:
        extra = aerodynamics.ground_effect_thrust_c(params, kin.pos[2], rotmat[2], thrust, effects.kinks)
        lift = tuple(t + e for t, e in zip(thrust, extra, strict=True))
    if downwash is None:
        downwash = downwash_c(params, effects, kin, motors, neighbors, unit_quat)
    lift, downwash = add_downwash_c(lift, downwash)
    body_z_force = sum(lift[1:], lift[0])
    if downwash is not None:
        body_z_force = body_z_force + downwash
    fx, fy, fz = (row[2] * body_z_force for row in rotmat)
    force = (fx, fy, fz + -params.mass * params.gravity)
    disturbance = Disturbance() if disturbance is None else disturbance
    if effects.drag:
        drag = aerodynamics.drag_force_c(params, kin.vel, rpm_prev, disturbance.wind)
        force = tuple(f + d for f, d in zip(force, drag, strict=True))
    if disturbance.force is not None:
        force = tuple(f + e for f, e in zip(force, disturbance.force, strict=True))
    torque = body_torque_c(params, lift, motors.yaw_torque)
    if disturbance.torque is not None:
        torque = tuple(t + e for t, e in zip(torque, disturbance.torque, strict=True))
    gyro = cross(kin.ang_vel, matvec(params.inertia, kin.ang_vel))
    torque = tuple(t - g for t, g in zip(torque, gyro, strict=True))
    ang_acc = matvec(params.inertia_inv, torque)
    return tuple(f / params.mass for f in force), ang_acc


def downwash_c(
    params: DroneParams,
    effects: Effects,
    kin: Kinematics,
    motors: Motors,
    neighbors: jax.Array | None = None,
    unit_quat: bool = False,
) -> jax.Array | Components | None:
    """The downwash of ``effects.downwash``'s model with the effects' kinks and cut-off, in component form
    (``kin``, ``motors``, ``neighbors`` and ``unit_quat`` as in `accelerations_c`).

    Returns:
        the paper's model (``effects.downwash`` True) or the bounded one (``"bounded"``): the force along each
        drone's body z, f[..., D] N (`aerodynamics.downwash_force_c`);
        ``"per_rotor"``: the change of each rotor's thrust, a 4-tuple of f[..., D] N
        (`aerodynamics.downwash_thrust_c`); None where no downwash acts: the effect is off, or the drone is alone in
        its world. `add_downwash_c` applies either.
    """
    pos = kin.pos
    if not effects.downwash or pos[2].shape[-1] == 1:
        return None
    if neighbors is None:
        neighbors = effects.downwash_neighbors(pos)
    if effects.downwash == "per_rotor":
        rotmat = quat_to_rotmat_c(kin.quat, unit=unit_quat)
        return aerodynamics.downwash_thrust_c(
            params, pos, rotmat, motors.thrust, effects.kinks, neighbors, effects.downwash_cutoff
        )
    if effects.downwash == "bounded":
        thrust = motors.thrust[0] + motors.thrust[1] + motors.thrust[2] + motors.thrust[3]
        return aerodynamics.downwash_force_c(
            params, pos, effects.kinks, neighbors, effects.downwash_cutoff, aerodynamics.BOUNDED_DOWNWASH, thrust
        )
    return aerodynamics.downwash_force_c(params, pos, effects.kinks, neighbors, effects.downwash_cutoff)


def add_downwash_c(lift: Components, downwash: jax.Array | Components | None) -> tuple[Components, jax.Array | None]:
    """The per-motor lift (4-tuple of f[..., D] N) with `downwash_c`'s output added where it acts: per-rotor thrust
    changes (a 4-tuple) add to the lifts, at the rotors; the paper's force (f[..., D] N, or None) is returned as the
    force along body z at the centre of mass, for the caller to add to the lifts' sum."""
    if isinstance(downwash, tuple):
        return tuple(f + d for f, d in zip(lift, downwash, strict=True)), None
    return lift, downwash


def euler_step_c(
    params: DroneParams,
    effects: Effects,
    kin: Kinematics,
    motors: Motors,
    rpm_prev: Components,
    dt: float,
    unit_quat: bool = False,
    neighbors: jax.Array | None = None,
    downwash: jax.Array | None = None,
    disturbance: Disturbance | None = None,
) -> Kinematics:
    """The paper code's semi-implicit Euler update (docs/physics.md §4.5-4.6), one physics step of ``dt`` s.

    v ← v + dt·a; ω ← ω + dt·ω̇; p ← p + dt·v_new; q ← exp-map(q, ω_new, dt), then q is normalised as PyBullet
    does when the state is written back. ``motors``, ``unit_quat``, ``neighbors``, ``downwash`` and ``disturbance``
    as in `accelerations_c`.
    """
    acc, ang_acc = accelerations_c(params, effects, kin, motors, rpm_prev, unit_quat, neighbors, downwash, disturbance)
    vel = tuple(v + dt * a for v, a in zip(kin.vel, acc, strict=True))
    ang_vel = tuple(w + dt * a for w, a in zip(kin.ang_vel, ang_acc, strict=True))
    quat = quat_integrate_c(kin.quat, ang_vel, dt)
    pos = tuple(p + dt * v for p, v in zip(kin.pos, vel, strict=True))
    return Kinematics(pos, normalize_c(quat), vel, ang_vel)


def rk4_step_c(
    params: DroneParams,
    effects: Effects,
    kin: Kinematics,
    motors: Motors,
    rpm_prev: Components,
    dt: float,
    unit_quat: bool = False,
    neighbors: jax.Array | None = None,
    downwash: None = None,
    disturbance: Disturbance | None = None,
) -> Kinematics:
    """Classical 4th-order Runge-Kutta on (p, q, v, ω) with the motor inputs held over the step; q renormalised.

    See docs/physics.md §4.11. ``motors`` and ``unit_quat`` as in `accelerations_c` (``unit_quat`` concerns the first
    stage only: the others are normalised for their rotation matrix); ``neighbors`` and ``disturbance`` too,
    held over the stages (``downwash`` is recomputed at each stage: pass None).
    """
    if neighbors is None:
        neighbors = effects.downwash_neighbors(kin.pos)

    def deriv(k: Kinematics, unit: bool = False) -> Kinematics:
        acc, ang_acc = accelerations_c(params, effects, k, motors, rpm_prev, unit, neighbors, None, disturbance)
        return Kinematics(k.vel, quat_derivative_c(k.quat, k.ang_vel), acc, ang_acc)

    def stage(carry, coeffs):
        # Stages 2-4: k_i = f(x + h_i k_{i-1}), accumulated as k1 + 2 k2 + 2 k3 + k4. A loop rather than three
        # copies keeps the compiled step (and its gradient) small.
        weighted_sum, k_prev = carry
        h, weight = coeffs
        k = deriv(jax.tree.map(lambda x, d: x + h * d, kin, k_prev))
        return (jax.tree.map(lambda total, d: total + weight * d, weighted_sum, k), k), None

    k1 = deriv(kin, unit_quat)
    dtype = kin.pos[0].dtype
    coeffs = (jnp.asarray([dt / 2, dt / 2, dt], dtype), jnp.asarray([2.0, 2.0, 1.0], dtype))
    (weighted_sum, _), _ = jax.lax.scan(stage, (k1, k1), coeffs)
    out = jax.tree.map(lambda x, total: x + dt / 6 * total, kin, weighted_sum)
    return out._replace(quat=normalize_c(out.quat))


#: The integrators, by `SimConfig.integrator` name.
INTEGRATORS = {"euler": euler_step_c, "rk4": rk4_step_c}


def ground_contact_c(params: DroneParams, kin: Kinematics, kinks: Kinks = Kinks()) -> tuple[Kinematics, jax.Array]:
    """Ground plane at z = 0: the collision cylinder cannot go below it.

    Contact rule (docs/physics.md §5.6; not in the paper's explicit model, which fell through the ground): when the base
    is below its resting height ``collision_height / 2`` (0.0125 m for the shipped models, where the original's
    PyBullet drones rest), it is put back at that height and the contact is perfectly inelastic and sticking:
    the velocity becomes (0, 0, max(v_z, 0)) and the angular velocity 0. Orientation is left unchanged. ``kinks``
    (`jaxdrones.physics.kinks`) may smooth the contact over a band of ``kinks.height`` about the rest height, or pass
    gradients straight through it.

    Returns:
        The corrected kinematics and bool[..., D], True where the drone touched the ground (below the rest height).
    """
    rest = 0.5 * params.collision_height
    (x, y, z), (vx, vy, vz) = kin.pos, kin.vel
    touching = z < rest
    weight = kinks.step(rest - z, kinks.height)  # the smooth degree of contact, for kinks.mode == "smooth"
    pos = (x, y, kinks.maximum(z, rest, kinks.height))
    vz = kinks.choose(touching, weight, kinks.maximum(vz, 0.0, kinks.speed), vz)
    vel = (kinks.choose(touching, weight, 0.0, vx), kinks.choose(touching, weight, 0.0, vy), vz)
    ang_vel = tuple(kinks.choose(touching, weight, 0.0, w) for w in kin.ang_vel)
    return Kinematics(pos, kin.quat, vel, ang_vel), touching
