"""Explicit rigid-body dynamics of a quadrotor: motor model, mixer, Newton-Euler equations, integrators.

The update is the paper's explicit model (IROS 2021, eqs. 1-2; gym-pybullet-drones' DYN mode, facts §3.1, §4):
thrust f_i = kf·rpm_i² along body +z, torques from the x/+ lever arms and the yaw reaction -spin_i·km·rpm_i²,
Euler's equation J ω̇ = τ - ω × Jω in the body frame, and m a = R (0, 0, Σf) - (0, 0, m g) in the world frame.
All functions broadcast over leading axes; the drone axis is ``-2`` for f[..., D, k] arrays.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxdrones import aerodynamics
from jaxdrones.params import DroneParams
from jaxdrones.rotations import quat_derivative, quat_integrate, quat_to_rotmat


class Effects(NamedTuple):
    """Which aerodynamic effects are on (static)."""

    drag: bool = False
    ground_effect: bool = False
    downwash: bool = False


class Kinematics(NamedTuple):
    """The integrated quantities of ``D`` drones (see `DroneState` for units and frames)."""

    pos: jax.Array
    quat: jax.Array
    vel: jax.Array
    ang_vel: jax.Array


def motor_thrust(params: DroneParams, rpm: jax.Array) -> jax.Array:
    """Per-motor thrust kf·rpm², f[..., D, 4] RPM -> f[..., D, 4] N."""
    return params.kf[..., None] * rpm**2


def body_torque(params: DroneParams, lift: jax.Array, rpm: jax.Array) -> jax.Array:
    """Body-frame torque from the motors (facts §3.1), N·m, f[..., D, 3].

    Args:
        params: DroneParams (``torque_arm`` f[..., 2, 4] m, ``prop_spin`` f[..., 4], ``km``).
        lift: f[..., D, 4] N, per-motor force along body z (thrust, plus ground effect when on).
        rpm: f[..., D, 4] RPM, for the yaw reaction torque -Σ spin_i km rpm_i².
    """
    tau_xy = jnp.einsum("...ij,...j->...i", params.torque_arm, lift)
    tau_z = -jnp.sum(params.prop_spin * params.km[..., None] * rpm**2, axis=-1, keepdims=True)
    return jnp.concatenate([tau_xy, tau_z], axis=-1)


def accelerations(params: DroneParams, effects: Effects, kin: Kinematics, rpm: jax.Array, rpm_prev: jax.Array):
    """Linear (world, m/s²) and angular (body, rad/s²) accelerations, each f[..., D, 3].

    Args:
        params: DroneParams.
        effects: which aerodynamic effects to add.
        kin: the drones' kinematics.
        rpm: f[..., D, 4] RPM applied now (already clipped).
        rpm_prev: f[..., D, 4] RPM of the previous substep (drag only).
    """
    rotmat = quat_to_rotmat(kin.quat)
    thrust = motor_thrust(params, rpm)
    lift = thrust
    if effects.ground_effect:
        lift = lift + aerodynamics.ground_effect_thrust(params, kin.pos, rotmat, thrust)
    body_z_force = jnp.sum(lift, axis=-1)
    if effects.downwash:
        body_z_force = body_z_force + aerodynamics.downwash_force(params, kin.pos)
    force = rotmat[..., :, 2] * body_z_force[..., None]
    force = force.at[..., 2].add(-params.mass * params.gravity)
    if effects.drag:
        force = force + aerodynamics.drag_force(params, kin.vel, rpm_prev)
    torque = body_torque(params, lift, rpm)
    ang_mom = jnp.einsum("...ij,...j->...i", params.inertia, kin.ang_vel)
    torque = torque - jnp.cross(kin.ang_vel, ang_mom)
    ang_acc = jnp.einsum("...ij,...j->...i", params.inertia_inv, torque)
    return force / params.mass[..., None], ang_acc


def euler_step(params, effects, kin: Kinematics, rpm, rpm_prev, dt: float) -> Kinematics:
    """The paper code's semi-implicit Euler update (facts §4.5-4.6), one physics step of ``dt`` s.

    v ← v + dt·a; ω ← ω + dt·ω̇; p ← p + dt·v_new; q ← exp-map(q, ω_new, dt), then q is normalised as PyBullet
    does when the state is written back.
    """
    acc, ang_acc = accelerations(params, effects, kin, rpm, rpm_prev)
    vel = kin.vel + dt * acc
    ang_vel = kin.ang_vel + dt * ang_acc
    quat = quat_integrate(kin.quat, ang_vel, dt)
    return Kinematics(kin.pos + dt * vel, _normalize(quat), vel, ang_vel)


def rk4_step(params, effects, kin: Kinematics, rpm, rpm_prev, dt: float) -> Kinematics:
    """Classical 4th-order Runge-Kutta on (p, q, v, ω) with the motor inputs held over the step; q renormalised."""

    def deriv(k: Kinematics) -> Kinematics:
        acc, ang_acc = accelerations(params, effects, k, rpm, rpm_prev)
        return Kinematics(k.vel, quat_derivative(k.quat, k.ang_vel), acc, ang_acc)

    def shift(k: Kinematics, d: Kinematics, h: float) -> Kinematics:
        return Kinematics(*(a + h * b for a, b in zip(k, d)))

    k1 = deriv(kin)
    k2 = deriv(shift(kin, k1, dt / 2))
    k3 = deriv(shift(kin, k2, dt / 2))
    k4 = deriv(shift(kin, k3, dt))
    out = Kinematics(*(x + dt / 6 * (a + 2 * b + 2 * c + d) for x, a, b, c, d in zip(kin, k1, k2, k3, k4)))
    return out._replace(quat=_normalize(out.quat))


INTEGRATORS = {"euler": euler_step, "rk4": rk4_step}


def ground_contact(params: DroneParams, kin: Kinematics) -> tuple[Kinematics, jax.Array]:
    """Ground plane at z = 0: the collision cylinder cannot go below it.

    Contact rule (documented, not in the paper's explicit model, which fell through the ground): when the base
    is below its resting height ``collision_height / 2`` (0.0125 m for the shipped models, where the original's
    PyBullet drones rest), it is put back at that height and the contact is perfectly inelastic and sticking:
    the velocity becomes (0, 0, max(v_z, 0)) and the angular velocity 0. Orientation is left unchanged.

    Returns:
        The corrected kinematics and bool[..., D], True where the drone touched the ground.
    """
    rest = 0.5 * params.collision_height
    touching = kin.pos[..., 2] < rest
    pos = kin.pos.at[..., 2].set(jnp.maximum(kin.pos[..., 2], rest))
    lifted = jnp.zeros_like(kin.vel).at[..., 2].set(jnp.maximum(kin.vel[..., 2], 0.0))
    vel = jnp.where(touching[..., None], lifted, kin.vel)
    ang_vel = jnp.where(touching[..., None], 0.0, kin.ang_vel)
    return Kinematics(pos, kin.quat, vel, ang_vel), touching


def _normalize(quat: jax.Array) -> jax.Array:
    return quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)
