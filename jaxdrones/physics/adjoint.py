"""The Euler physics substep with a hand-written reverse-mode derivative (vector-Jacobian product).

`euler_substep_c` computes what `jaxdrones.physics.dynamics.euler_step_c` followed by
`jaxdrones.physics.dynamics.ground_contact_c` compute (the paper's explicit update with drag and ground effect,
docs/physics.md §3-§6, and the ground contact), value for value, and gives ``jax.grad``, ``jax.vjp`` and everything
built on them the derivative written out below (`substep_vjp`) instead of the one JAX derives. Forward-mode derivatives
(``jax.jvp``, ``jax.jacfwd``) are not defined for it (a ``jax.custom_vjp`` has none); `jaxdrones.sim` keeps the derived
path for configs that ask for them (see `supported`).

Why: JAX derives the reverse pass one operation at a time, and XLA:CPU then compiles each of the many small
cotangent terms into loops that recompute what the forward pass shares between components (the rotation matrix,
the exponential map). The hand-written pass recomputes the forward quantities once from the substep's input and
transposes the update equation by equation, so the control step needs no rematerialisation (``jax.checkpoint``).
The gradient's cost over the forward pass, before and after, through `jaxdrones.rollout`, a user's own
``lax.scan`` and the hover env's ``step``: `benchmarks/gradients/gradients.py`, docs/benchmarks.md, "Gradients".

tests/test_adjoint.py checks it against JAX's derived derivative to float64 rounding. Two parts keep JAX's
derivative: the downwash (the paper's force, or the per-rotor thrust changes, which enter the lifts) is computed
outside the substep (an input of it, differentiated by JAX), and a gradient with respect to the drone's params
(system identification) makes the rule fall back to JAX's derived pass for that substep.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from jax.custom_derivatives import CustomVJPPrimal, SymbolicZero

from jaxdrones.physics import dynamics
from jaxdrones.physics.dynamics import Effects, Kinematics, Motors
from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.rotations import (
    GIMBAL_SNAP,
    OMEGA_EPS,
    Components,
    cross,
    dot,
    matvec,
    quat_mul_c,
    quat_to_rotmat_c,
    split,
)
from jaxdrones.physics.state import Disturbance

if TYPE_CHECKING:
    from jaxdrones.physics.config import SimConfig


def supported(config: SimConfig) -> bool:
    """Whether a `jaxdrones.physics.config.SimConfig` steps with `euler_substep_c` (`SimConfig.hand_written_adjoint`):
    ``adjoint=True`` with the Euler integrator and the kinks treated exactly (the defaults). Smooth and
    straight-through kinks (`jaxdrones.physics.kinks`) and RK4 keep JAX's derived derivatives."""
    return config.hand_written_adjoint


def euler_substep_c(
    params: DroneParams,
    effects: Effects,
    kin: Kinematics,
    motors: Motors,
    rpm_prev: Components,
    dt: float,
    neighbors: jax.Array | None = None,
    disturbance: Disturbance | None = None,
) -> tuple[Kinematics, jax.Array]:
    """One Euler physics substep of ``dt`` s and the ground contact, in component form, as
    ``dynamics.ground_contact_c(params, dynamics.euler_step_c(params, effects, kin, motors, rpm_prev, dt, True,
    neighbors, None, disturbance))`` (``kin.quat`` of unit norm), with the reverse-mode derivative of
    `substep_vjp`.

    Args:
        params: DroneParams.
        effects: the static `dynamics.Effects`, with ``kinks.mode == "exact"`` (see `supported`).
        kin: `dynamics.Kinematics` in component form (each field a tuple of f[..., D]); ``kin.quat`` of unit norm.
        motors: `dynamics.Motors` of the held command.
        rpm_prev: 4-tuple of f[..., D] RPM, the previous substep's command (drag).
        dt: the substep, s.
        neighbors: the downwash's neighbour list (`dynamics.Effects.downwash_neighbors`), or None.
        disturbance: a `jaxdrones.physics.state.Disturbance` in component form (its given fields 3-tuples of f[..., D]),
            or None.

    Returns:
        The kinematics after the substep and bool[..., D], True where the drone touched the ground.
    """
    downwash = dynamics.downwash_c(params, effects, kin, motors, neighbors, unit_quat=True)
    return _substep(params, effects, kin, motors, rpm_prev, downwash, disturbance, dt)


def _reference(params, effects, kin, motors, rpm_prev, downwash, disturbance, dt):
    kin = dynamics.euler_step_c(params, effects, kin, motors, rpm_prev, dt, True, None, downwash, disturbance)
    return dynamics.ground_contact_c(params, kin, effects.kinks)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 7))
def _substep(params, effects, kin, motors, rpm_prev, downwash, disturbance, dt):
    return _reference(params, effects, kin, motors, rpm_prev, downwash, disturbance, dt)


def _substep_fwd(params, effects, kin, motors, rpm_prev, downwash, disturbance, dt):
    is_primal = lambda x: isinstance(x, CustomVJPPrimal)  # noqa: E731
    params_perturbed = any(x.perturbed for x in jax.tree.leaves(params, is_leaf=is_primal))
    inputs = jax.tree.map(lambda x: x.value, (params, kin, motors, rpm_prev, downwash, disturbance), is_leaf=is_primal)
    out = _reference(inputs[0], effects, *inputs[1:], dt)
    # The residuals are the inputs; their structure tells the backward pass whether params need a cotangent.
    return out, (*inputs, (None,) if params_perturbed else ())


def _substep_bwd(effects, dt, residuals, cotangent):
    params, kin, motors, rpm_prev, downwash, disturbance, params_perturbed = residuals
    ct_kin = jax.tree.map(_instantiate, cotangent[0], is_leaf=lambda x: isinstance(x, SymbolicZero))
    if params_perturbed:  # JAX's derived derivative, params included (system identification)
        _, vjp = jax.vjp(
            lambda *args: _reference(args[0], effects, *args[1:], dt)[0],
            params,
            kin,
            motors,
            rpm_prev,
            downwash,
            disturbance,
        )
        return vjp(ct_kin)
    kin_b, motors_b, rpm_prev_b, downwash_b, disturbance_b = substep_vjp(
        params, effects, kin, motors, rpm_prev, downwash, dt, ct_kin, disturbance
    )
    rpm_prev_b = rpm_prev_b if effects.drag else None  # unread without drag: a symbolic zero
    return None, kin_b, motors_b, rpm_prev_b, None if downwash is None else downwash_b, disturbance_b


def _instantiate(x):
    return jnp.zeros(x.aval.shape, x.aval.dtype) if isinstance(x, SymbolicZero) else x


_substep.defvjp(_substep_fwd, _substep_bwd, symbolic_zeros=True)


def _max_weight(x: jax.Array, floor) -> jax.Array:
    """D max(x, floor) / dx as ``jnp.maximum`` defines it: 1 above the floor, ½ at it, 0 below."""
    return jnp.where(x > floor, 1.0, jnp.where(x == floor, 0.5, 0.0)).astype(x.dtype)


def _conj(q: Components) -> Components:
    return (-q[0], -q[1], -q[2], q[3])


def _matvec_t(m: jax.Array, v: Components) -> Components:
    """Mᵀ v for M f[..., n, k] and v an n-tuple: a k-tuple."""
    return tuple(dot(split(m[..., :, j]), v) for j in range(m.shape[-1]))


def substep_vjp(
    params: DroneParams,
    effects: Effects,
    kin: Kinematics,
    motors: Motors,
    rpm_prev: Components,
    downwash: jax.Array | None,
    dt: float,
    ct: Kinematics,
    disturbance: Disturbance | None = None,
) -> tuple[Kinematics, Motors, Components, jax.Array, Disturbance | None]:
    """The cotangents of the substep's inputs (``kin``, ``motors``, ``rpm_prev``, ``downwash``: None, the paper's
    force f[..., D] N along body z or the per-rotor thrust changes, a 4-tuple of f[..., D] N, as
    `dynamics.downwash_c` returns them, and ``disturbance``, None or a `Disturbance` in component form) for the
    cotangent ``ct`` of its output kinematics; the others as in `euler_substep_c`.

    The forward quantities are recomputed from the inputs, then each equation of the substep is transposed in the
    reverse order (docs/physics.md: ground contact §5.6, position and exponential-map updates §4.5-4.6, Euler's
    equation and the gyroscopic term §3.1, thrust, torques, drag §6.2 and ground effect §6.1). Where the forward
    pass has a kink the derivative is JAX's: ``max`` passes ½ to each side at a tie, a ``where`` the branch taken.
    """
    p, q, v, w = kin
    thrust, yaw = motors
    given = Disturbance() if disturbance is None else disturbance
    wind = given.wind
    # The forward pass (dynamics.accelerations_c, euler_step_c, ground_contact_c), keeping what the reverse pass uses.
    rot = quat_to_rotmat_c(q, unit=True)
    lift = thrust
    if effects.ground_effect:
        rot_z = rot[2]
        upright = (rot_z[2] > 0) & (jnp.abs(rot_z[0]) < GIMBAL_SNAP)
        height = [p[2] + dot(rot_z, split(params.prop_pos[..., i, :])) for i in range(4)]
        clipped = [jnp.maximum(h, params.gnd_eff_h_clip) for h in height]
        gain = [params.gnd_eff_coeff * (params.prop_radius / (4 * c)) ** 2 for c in clipped]
        lift = tuple(t + jnp.where(upright, t * g, 0.0) for t, g in zip(thrust, gain, strict=True))
    lift, body_z_downwash = dynamics.add_downwash_c(lift, downwash)
    body_z_force = sum(lift[1:], lift[0])
    if body_z_downwash is not None:
        body_z_force = body_z_force + body_z_downwash
    force = [rot[k][2] * body_z_force for k in range(3)]
    force[2] = force[2] + -params.mass * params.gravity
    if effects.drag:
        omega_sum = sum(rpm_prev[1:], rpm_prev[0]) * (2 * jnp.pi / 60)
        v_air = v if wind is None else tuple(vk - wk for vk, wk in zip(v, wind, strict=True))
        force = [f - omega_sum * params.drag_coeff[..., k] * v_air[k] for k, f in enumerate(force)]
    if given.force is not None:
        force = [f + e for f, e in zip(force, given.force, strict=True)]
    torque = (*matvec(params.torque_arm, lift), yaw)
    if given.torque is not None:
        torque = tuple(t + e for t, e in zip(torque, given.torque, strict=True))
    inertia_w = matvec(params.inertia, w)
    gyro = cross(w, inertia_w)
    ang_acc = matvec(params.inertia_inv, tuple(t - g for t, g in zip(torque, gyro, strict=True)))
    vel = tuple(vk + dt * (f / params.mass) for vk, f in zip(v, force, strict=True))
    ang_vel = tuple(wk + dt * a for wk, a in zip(w, ang_acc, strict=True))
    sq = dot(ang_vel, ang_vel)
    moving = sq > OMEGA_EPS**2
    norm = jnp.sqrt(jnp.where(moving, sq, 1.0))
    theta = 0.5 * dt * norm
    sin, cos = jnp.sin(theta), jnp.cos(theta)
    sin_over_norm = jnp.where(moving, sin / norm, 0.5 * dt)
    delta = (*(sin_over_norm * wk for wk in ang_vel), jnp.where(moving, cos, 1.0))
    # The quaternion normalised at the end: q ⊗ delta, or q itself below OMEGA_EPS (with q ⊗ delta's derivative).
    unnormalised = tuple(jnp.where(moving, r, qk) for r, qk in zip(quat_mul_c(q, delta), q, strict=True))
    length = jnp.sqrt(dot(unnormalised, unnormalised))
    z_new = p[2] + dt * vel[2]
    rest = 0.5 * params.collision_height
    touching = z_new < rest

    # The reverse pass. Ground contact: z ← max(z, rest); while touching v ← (0, 0, max(v_z, 0)), ω ← 0.
    pos_b, quat_b, vel_b, ang_vel_b = ct
    pos_b = (pos_b[0], pos_b[1], pos_b[2] * _max_weight(z_new, rest))
    vel_b = (
        jnp.where(touching, 0.0, vel_b[0]),
        jnp.where(touching, 0.0, vel_b[1]),
        jnp.where(touching, vel_b[2] * _max_weight(vel[2], 0.0), vel_b[2]),
    )
    ang_vel_b = tuple(jnp.where(touching, 0.0, b) for b in ang_vel_b)
    # p ← p + dt v.
    vel_b = tuple(a + dt * b for a, b in zip(vel_b, pos_b, strict=True))
    # q ← normalise(q ⊗ delta(ω)), delta = (sin(θ) ω / |ω|, cos θ), θ = ½ dt |ω| (½ dt ω, 1 below OMEGA_EPS).
    # One reciprocal rather than a division per component: XLA:CPU runs each division that several loops read as
    # a loop of its own.
    inv_length = 1 / length
    unit = tuple(u * inv_length for u in unnormalised)
    along = dot(unit, quat_b)
    unnormalised_b = tuple((b - u * along) * inv_length for b, u in zip(quat_b, unit, strict=True))
    q_b = quat_mul_c(unnormalised_b, _conj(delta))  # the transpose of q ↦ q ⊗ delta
    delta_b = quat_mul_c(_conj(q), unnormalised_b)  # the transpose of delta ↦ q ⊗ delta
    radial = jnp.where(
        moving,
        (dot(delta_b[:3], ang_vel) * (0.5 * dt * cos * norm - sin) / norm**2 - delta_b[3] * 0.5 * dt * sin) / norm,
        0.0,
    )
    ang_vel_b = tuple(
        a + sin_over_norm * d + radial * wk for a, d, wk in zip(ang_vel_b, delta_b[:3], ang_vel, strict=True)
    )
    # ω ← ω + dt J⁻¹ (τ - ω × Jω); v ← v + dt F / m.
    tau_b = _matvec_t(params.inertia_inv, tuple(dt * b for b in ang_vel_b))
    gyro_b = tuple(-b for b in tau_b)
    w_b = tuple(
        a + b + c
        for a, b, c in zip(
            ang_vel_b, cross(inertia_w, gyro_b), _matvec_t(params.inertia, cross(gyro_b, w)), strict=True
        )
    )
    dt_over_mass = dt / params.mass
    force_b = tuple(dt_over_mass * b for b in vel_b)
    v_b = vel_b
    # τ = (torque_arm @ lift, yaw); F = R (0, 0, Σ lift + downwash) - m g e_z + drag.
    lift_b = tuple(params.torque_arm[..., 0, i] * tau_b[0] + params.torque_arm[..., 1, i] * tau_b[1] for i in range(4))
    rpm_prev_b = tuple(jnp.zeros_like(r) for r in rpm_prev)
    wind_b = None
    if effects.drag:
        drag_b = tuple(omega_sum * params.drag_coeff[..., k] * f for k, f in enumerate(force_b))
        v_b = tuple(a - b for a, b in zip(v_b, drag_b, strict=True))
        wind_b = None if wind is None else drag_b
        omega_sum_b = -dot(tuple(params.drag_coeff[..., k] * v_air[k] for k in range(3)), force_b)
        rpm_prev_b = tuple(jnp.broadcast_to(omega_sum_b * (2 * jnp.pi / 60), r.shape) for r in rpm_prev)
    if wind is not None and wind_b is None:  # no drag: the wind does not act
        wind_b = tuple(jnp.zeros_like(x) for x in wind)
    disturbance_b = (
        None
        if disturbance is None
        else Disturbance(
            force=None if given.force is None else force_b, torque=None if given.torque is None else tau_b, wind=wind_b
        )
    )
    body_z_force_b = dot(tuple(rot[k][2] for k in range(3)), force_b)
    lift_b = tuple(b + body_z_force_b for b in lift_b)
    downwash_b = lift_b if isinstance(downwash, tuple) else body_z_force_b  # per-rotor changes add to the lifts
    rot_b = [[0.0] * 3 for _ in range(3)]  # the cotangents of R's entries that the substep reads
    for k in range(3):
        rot_b[k][2] = force_b[k] * body_z_force
    thrust_b = lift_b
    if effects.ground_effect:
        # lift_i = f_i (1 + gain_i) while upright, gain_i = C (r / 4 h_i)², h_i = max(z + R[2] · prop_i, h_clip).
        thrust_b = tuple(b * (1 + jnp.where(upright, g, 0.0)) for b, g in zip(lift_b, gain, strict=True))
        height_b = [
            jnp.where(upright, b * t * (-2 * g / c), 0.0) * _max_weight(h, params.gnd_eff_h_clip)
            for b, t, g, c, h in zip(lift_b, thrust, gain, clipped, height, strict=True)
        ]
        pos_b = (pos_b[0], pos_b[1], pos_b[2] + sum(height_b[1:], height_b[0]))
        for k in range(3):
            rot_b[2][k] = rot_b[2][k] + sum(height_b[i] * params.prop_pos[..., i, k] for i in range(4))
    # R(q) for a unit q (quat_to_rotmat_c): the entries read above are column 2 and row 2.
    x, y, z, s = q
    b02, b12, b22 = rot_b[0][2], rot_b[1][2], rot_b[2][2]
    b20, b21 = rot_b[2][0], rot_b[2][1]
    q_b = (
        q_b[0] + 2 * (z * b02 - s * b12 - 2 * x * b22 + z * b20 + s * b21),
        q_b[1] + 2 * (s * b02 + z * b12 - 2 * y * b22 - s * b20 + z * b21),
        q_b[2] + 2 * (x * b02 + y * b12 + x * b20 + y * b21),
        q_b[3] + 2 * (y * b02 - x * b12 - y * b20 + x * b21),
    )
    return Kinematics(pos_b, q_b, v_b, w_b), Motors(thrust_b, tau_b[2]), rpm_prev_b, downwash_b, disturbance_b
