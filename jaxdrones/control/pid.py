"""The paper's DSLPIDControl in pure JAX, with its state carried explicitly.

A cascaded PID (gym-pybullet-drones ``control/DSLPIDControl.py`` on ``main``; docs/physics.md §12): a position loop
computes a desired force, hence a collective thrust in PWM units and a desired attitude; an attitude loop turns
the rotation error into roll/pitch/yaw "torques" in PWM units; a mixer and the Crazyflie's PWM→RPM map give the
four motor speeds. Everything here is a pure function of arrays, so it runs under ``jit``, ``vmap`` and ``grad``
and broadcasts over any leading axes ``[..., D]`` (worlds, drones). The gains are data (`PIDGains`), so they can
be tuned, batched per world, or differentiated.

Reproduced exactly, quirks included (docs/physics.md §12.2-12.4, §14.9):

* only the target *yaw* of ``target_rpy`` is used; the target roll and pitch are ignored;
* the measured angular velocity is never used: the rate error is the finite difference of PyBullet Euler angles
  over the control period, with no angle wrapping, and ``last_rpy`` starts at 0 (so the first call after
  `pid_init` sees a derivative spike whenever the attitude is not level);
* the desired attitude is converted to *intrinsic* 'XYZ' Euler angles (scipy's convention, not PyBullet's) and
  back before the attitude loop, and the returned yaw error mixes the two conventions;
* outputs always lie in [9440.3, 21666.45] RPM (PWM clipped to [20000, 65535]).

The mixer is derived from the airframe (`mixer_matrix`), so it equals the original's for ``cf2x`` (main-branch
motor order) and ``cf2p``. The original accepts only those two; here the ``racer`` (or any URDF) is accepted as
well, but the gains are tuned for the 27 g Crazyflie and are far too weak for a heavier airframe (the 0.83 kg
racer drifts tens of centimetres off the circle example's path). The original's RL/VEL environments always build
the cf2x controller, even for a cf2p airframe (docs/physics.md §10.1); pass cf2x params here to reproduce that.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.typing import DTypeLike
from numpy.typing import ArrayLike

from jaxdrones.control.mixer import mixer_matrix
from jaxdrones.physics.params import DroneParams, align_params
from jaxdrones.physics.rotations import (
    euler_xyz_from_rotmat,
    quat_to_euler,
    quat_to_rotmat,
    rotmat_from_euler_xyz,
)
from jaxdrones.physics.state import DroneState

#: PWM→RPM map of the Crazyflie: rpm = PWM2RPM_SCALE·pwm + PWM2RPM_CONST (docs/physics.md §12.1).
PWM2RPM_SCALE = 0.2685
#: RPM, see `PWM2RPM_SCALE`.
PWM2RPM_CONST = 4070.3
#: Motor PWM limits (docs/physics.md §12.1); the output RPM therefore lies in [9440.3, 21666.45].
MIN_PWM = 20000.0
MAX_PWM = 65535.0
#: Limit of the roll/pitch/yaw torques, PWM units (docs/physics.md §12.3, step 5).
MAX_TORQUE_PWM = 3200.0
#: Per-axis limits of the position-error integral, m·s: ±2 in x/y, ±0.15 in z (docs/physics.md §12.2, step 2).
POS_INTEGRAL_LIMIT = (2.0, 2.0, 0.15)
#: Per-axis limits of the attitude-error integral, s: ±1 roll/pitch, ±1500 yaw (docs/physics.md §12.3, step 4).
ATT_INTEGRAL_LIMIT = (1.0, 1.0, 1500.0)


#: The DSL gains of the paper's controller by `PIDGains` field (docs/physics.md §12.1; DSLPIDControl.py's
#: ``P_COEFF_FOR`` ... ``D_COEFF_TOR``).
DSL_GAINS = dict(
    p_pos=(0.4, 0.4, 1.25),
    i_pos=(0.05, 0.05, 0.05),
    d_pos=(0.2, 0.2, 0.5),
    p_att=(70000.0, 70000.0, 60000.0),
    i_att=(0.0, 0.0, 500.0),
    d_att=(20000.0, 20000.0, 12000.0),
)


@struct.dataclass
class PIDGains:
    """Gains of DSLPIDControl, per axis (x, y, z) or (roll, pitch, yaw), as arrays.

    Each leaf is f[..., 3] and broadcasts against the controlled drones' ``[..., D, 3]``: f[3] for one gain set,
    f[W, 1, 3] or f[W, D, 3] for per-world or per-drone gains.

    Attributes:
        p_pos: N/m, position P (``P_COEFF_FOR``), acting on the world-frame position error.
        i_pos: N/(m·s), position I (``I_COEFF_FOR``).
        d_pos: N·s/m, position D (``D_COEFF_FOR``), acting on the world-frame velocity error.
        p_att: PWM, attitude P (``P_COEFF_TOR``), acting on the rotation-matrix error (dimensionless).
        i_att: PWM/s, attitude I (``I_COEFF_TOR``).
        d_att: PWM·s/rad, attitude D (``D_COEFF_TOR``), acting on the Euler-rate error.
    """

    p_pos: jax.Array
    i_pos: jax.Array
    d_pos: jax.Array
    p_att: jax.Array
    i_att: jax.Array
    d_att: jax.Array

    @classmethod
    def dsl(cls, dtype: DTypeLike | None = None) -> PIDGains:
        """The DSL gains of the paper's controller (docs/physics.md §12.1), in JAX's default float or ``dtype``."""
        dtype = jnp.result_type(float) if dtype is None else dtype
        return cls(**{k: jnp.asarray(v, dtype=dtype) for k, v in DSL_GAINS.items()})


@struct.dataclass
class PIDState:
    """The controller's memory (``reset()`` zeroes it), for drones with leading shape ``[..., D]``.

    Attributes:
        integral_pos_e: f[..., D, 3] m·s, clipped integral of the world-frame position error.
        integral_rpy_e: f[..., D, 3] s, clipped integral of minus the rotation error.
        last_rpy: f[..., D, 3] rad, PyBullet roll/pitch/yaw seen at the previous call (0 after reset).
    """

    integral_pos_e: jax.Array
    integral_rpy_e: jax.Array
    last_rpy: jax.Array


class PIDInfo(NamedTuple):
    """Intermediate values of one `pid_compute` call.

    Attributes:
        pos_err: f[..., D, 3] m, world frame, target − current position (the original's ``pos_e``).
        yaw_err: f[..., D] rad, intrinsic-'XYZ' target yaw minus PyBullet yaw (the original's third output).
        target_euler: f[..., D, 3] rad, desired attitude as intrinsic 'XYZ' Euler angles.
        thrust_pwm: f[..., D], collective thrust in PWM units before mixing (may be negative).
    """

    pos_err: jax.Array
    yaw_err: jax.Array
    target_euler: jax.Array
    thrust_pwm: jax.Array


def pid_init(shape_or_state: DroneState | int | tuple[int, ...], dtype: DTypeLike | None = None) -> PIDState:
    """A zeroed `PIDState`, as after the original's ``reset()``.

    Args:
        shape_or_state: a `DroneState` (its ``pos`` gives the shape and dtype), or the leading shape ``(..., D)``,
            e.g. ``(4,)`` for 4 drones or ``(W, D)``.
        dtype: float dtype; default the state's, else JAX's default float.

    Returns:
        PIDState with leaves f[..., D, 3].

    Raises:
        ValueError: if a shape is empty or has non-positive entries.
    """
    if isinstance(shape_or_state, DroneState):
        shape = tuple(shape_or_state.pos.shape)
        dtype = shape_or_state.pos.dtype if dtype is None else dtype
    else:
        lead = tuple(int(n) for n in np.atleast_1d(shape_or_state))
        if not lead or any(n < 1 for n in lead):
            raise ValueError(
                f"pid_init: expected a DroneState or a leading shape (..., n_drones) of positive "
                f"sizes, got {shape_or_state!r}"
            )
        shape = lead + (3,)
    dtype = jnp.result_type(float) if dtype is None else dtype
    zeros = jnp.zeros(shape, dtype=dtype)
    return PIDState(integral_pos_e=zeros, integral_rpy_e=zeros, last_rpy=zeros)


def pid_control(
    params: DroneParams,
    gains: PIDGains,
    pid_state: PIDState,
    state: DroneState,
    target_pos: ArrayLike,
    *,
    target_vel: ArrayLike | None = None,
    target_rpy: ArrayLike | None = None,
    target_rpy_rates: ArrayLike | None = None,
    ctrl_dt: float | jax.Array,
) -> tuple[jax.Array, PIDState]:
    """One call of DSLPIDControl ``computeControl`` for every drone: motor speeds and the updated controller state.

    Same as `pid_compute` without the intermediate values; see there for arguments, units and errors.

    Returns:
        (rpm f[..., D, 4] in RPM, new PIDState).
    """
    rpm, new_state, _ = pid_compute(
        params,
        gains,
        pid_state,
        state,
        target_pos,
        target_vel=target_vel,
        target_rpy=target_rpy,
        target_rpy_rates=target_rpy_rates,
        ctrl_dt=ctrl_dt,
    )
    return rpm, new_state


def pid_compute(
    params: DroneParams,
    gains: PIDGains,
    pid_state: PIDState,
    state: DroneState,
    target_pos: ArrayLike,
    *,
    target_vel: ArrayLike | None = None,
    target_rpy: ArrayLike | None = None,
    target_rpy_rates: ArrayLike | None = None,
    ctrl_dt: float | jax.Array,
) -> tuple[jax.Array, PIDState, PIDInfo]:
    """DSLPIDControl ``computeControl`` (docs/physics.md §12), batched.

    Source: gym-pybullet-drones main, control/DSLPIDControl.py:82-145, 187-208, 240-259.

    Position loop: e_p = p* − p, e_v = v* − v; I_p ← clip(I_p + e_p·dt); F = P∘e_p + I∘I_p + D∘e_v + (0, 0, m g);
    thrust_pwm = (√(max(0, F·R e_z)/(4 kf)) − 4070.3)/0.2685; desired attitude R_d = [x_d y_d z_d] with
    z_d = F/|F| and the heading of the target yaw, as intrinsic 'XYZ' Euler angles. Attitude loop: rebuild R_d from
    those angles; e_R = vee(R_dᵀR − RᵀR_d); rate error = rates* − (rpy − last_rpy)/dt with PyBullet Euler angles;
    I_R ← clip(I_R − e_R·dt); τ = clip(−P∘e_R + D∘rate_err + I∘I_R, ±3200); pwm = clip(thrust_pwm + M τ, 20000,
    65535); rpm = 0.2685·pwm + 4070.3.

    Args:
        params: DroneParams (``mass``, ``gravity``, ``kf``, ``torque_arm``, ``prop_spin``), unbatched or with
            leading axes that broadcast against ``[..., D]``.
        gains: PIDGains, e.g. ``PIDGains.dsl()``.
        pid_state: PIDState with leaves f[..., D, 3] (from `pid_init` or a previous call).
        state: DroneState with ``pos`` f[..., D, 3] m (world), ``quat`` f[..., D, 4] (x, y, z, w) body→world and
            ``vel`` f[..., D, 3] m/s (world). ``ang_vel`` is not used, as in the original.
        target_pos: f[..., D, 3] m, world frame (anything broadcastable to ``state.pos``, e.g. f[3]).
        target_vel: f[..., D, 3] m/s, world frame; default 0.
        target_rpy: f[..., D, 3] rad; only the yaw (last component) is used; default 0.
        target_rpy_rates: f[..., D, 3] rad/s, target Euler-angle rates; default 0.
        ctrl_dt: control period in s (the original's ``control_timestep``, e.g. 1/48), a positive scalar.

    Returns:
        (rpm f[..., D, 4] in RPM, new PIDState, PIDInfo). Arrays have the state's float dtype.

    Raises:
        ValueError: if ``gains`` or ``pid_state`` has the wrong type, if ``state.pos``/``state.quat`` are not
            [..., D, 3]/[..., D, 4] with the same leading shape, if a target or the PID state does not broadcast to
            ``state.pos``'s shape, or if a concrete ``ctrl_dt`` is not positive.
    """
    _check_state(state)
    if not isinstance(pid_state, PIDState) or not isinstance(gains, PIDGains):
        raise ValueError(
            f"expected a PIDGains and a PIDState (see PIDGains.dsl() and pid_init()), got "
            f"{type(gains).__name__} and {type(pid_state).__name__}"
        )
    targets = tuple(_host_array(t) for t in (target_pos, target_vel, target_rpy, target_rpy_rates))
    return _pid_checked(params, gains, pid_state, state, *targets, _check_dt(ctrl_dt, state.pos.dtype))


@jax.jit
def _pid_checked(params, gains, pid_state, state, target_pos, target_vel, target_rpy, target_rpy_rates, ctrl_dt):
    """`pid_compute` after its host checks: the shape checks run once per compilation (a ValueError at trace time),
    so that a call from a Python loop costs one dispatch."""
    shape, dtype = state.pos.shape, state.pos.dtype
    pid_state = jax.tree_util.tree_map(lambda x: _as_shape("pid_state", x, shape, dtype), pid_state)
    target_pos = _as_shape("target_pos", target_pos, shape, dtype)
    target_vel = _as_shape("target_vel", target_vel, shape, dtype)
    target_rpy = _as_shape("target_rpy", target_rpy, shape, dtype)
    target_rpy_rates = _as_shape("target_rpy_rates", target_rpy_rates, shape, dtype)
    return _pid_compute(params, gains, pid_state, state, target_pos, target_vel, target_rpy, target_rpy_rates, ctrl_dt)


def _host_array(value):
    """A target as a jit argument: None (0) and JAX arrays as they are, anything else (lists, NumPy, floats) as
    NumPy, so that a Python list is one argument and not one per element."""
    return value if value is None or isinstance(value, jax.Array) else np.asarray(value)


def _pid_compute(params, gains, pid_state, state, target_pos, target_vel, target_rpy, target_rpy_rates, ctrl_dt):
    """`pid_compute` on validated, broadcast inputs."""
    shape = state.pos.shape
    params = align_params(params, len(shape) - 1)
    gains = jax.tree.map(lambda g: jnp.broadcast_to(g, shape), gains)
    rotmat = quat_to_rotmat(state.quat)
    with jax.named_scope("pid_position"):
        thrust_pwm, target_euler, pos_err, integral_pos_e = _position_loop(
            params, gains, pid_state.integral_pos_e, rotmat, state, target_pos, target_vel, target_rpy, ctrl_dt
        )
    with jax.named_scope("pid_attitude"):
        rpm, rpy, integral_rpy_e = _attitude_loop(
            params, gains, pid_state, rotmat, state.quat, thrust_pwm, target_euler, target_rpy_rates, ctrl_dt
        )
    new_state = PIDState(integral_pos_e=integral_pos_e, integral_rpy_e=integral_rpy_e, last_rpy=rpy)
    info = PIDInfo(
        pos_err=pos_err, yaw_err=target_euler[..., 2] - rpy[..., 2], target_euler=target_euler, thrust_pwm=thrust_pwm
    )
    return rpm, new_state, info


def _position_loop(params, gains, integral_pos_e, rotmat, state, target_pos, target_vel, target_rpy, dt):
    """``_dslPIDPositionControl`` (docs/physics.md §12.2; main, control/DSLPIDControl.py:187-208)."""
    pos_err = target_pos - state.pos
    vel_err = target_vel - state.vel
    limit = jnp.broadcast_to(jnp.asarray(POS_INTEGRAL_LIMIT, dtype=pos_err.dtype), pos_err.shape)
    integral = jnp.clip(integral_pos_e + pos_err * dt, -limit, limit)
    weight = params.mass * params.gravity
    gravity = jnp.stack([jnp.zeros_like(weight), jnp.zeros_like(weight), weight], axis=-1)
    force = gains.p_pos * pos_err + gains.i_pos * integral + gains.d_pos * vel_err + gravity
    scalar = jnp.maximum(0.0, jnp.sum(force * rotmat[..., :, 2], axis=-1))
    positive = scalar > 0
    rpm = jnp.where(positive, jnp.sqrt(jnp.where(positive, scalar, 1.0) / (4 * params.kf)), 0.0)
    thrust_pwm = (rpm - PWM2RPM_CONST) / PWM2RPM_SCALE

    z_d = force / jnp.linalg.norm(force, axis=-1, keepdims=True)
    yaw = target_rpy[..., 2]
    x_c = jnp.stack([jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw)], axis=-1)
    y_d = jnp.cross(z_d, x_c)
    y_d = y_d / jnp.linalg.norm(y_d, axis=-1, keepdims=True)
    x_d = jnp.cross(y_d, z_d)
    target_rotmat = jnp.stack([x_d, y_d, z_d], axis=-1)
    return thrust_pwm, euler_xyz_from_rotmat(target_rotmat), pos_err, integral


def _attitude_loop(params, gains, pid_state, rotmat, quat, thrust_pwm, target_euler, target_rpy_rates, dt):
    """``_dslPIDAttitudeControl`` (docs/physics.md §12.3; main, control/DSLPIDControl.py:240-259)."""
    rpy = quat_to_euler(quat)
    target_rotmat = rotmat_from_euler_xyz(target_euler)
    err = jnp.swapaxes(target_rotmat, -1, -2) @ rotmat - jnp.swapaxes(rotmat, -1, -2) @ target_rotmat
    rot_err = jnp.stack([err[..., 2, 1], err[..., 0, 2], err[..., 1, 0]], axis=-1)
    rate_err = target_rpy_rates - (rpy - pid_state.last_rpy) / dt
    limit = jnp.broadcast_to(jnp.asarray(ATT_INTEGRAL_LIMIT, dtype=rot_err.dtype), rot_err.shape)
    integral = jnp.clip(pid_state.integral_rpy_e - rot_err * dt, -limit, limit)
    torque = -gains.p_att * rot_err + gains.d_att * rate_err + gains.i_att * integral
    torque = jnp.clip(torque, -MAX_TORQUE_PWM, MAX_TORQUE_PWM)
    mixed = (mixer_matrix(params).astype(torque.dtype) @ torque[..., None])[..., 0]
    pwm = jnp.clip(thrust_pwm[..., None] + mixed, MIN_PWM, MAX_PWM)
    return PWM2RPM_SCALE * pwm + PWM2RPM_CONST, rpy, integral


def speed_limit(params: DroneParams) -> jax.Array:
    """The VEL action's speed limit, m/s: 3 % of the airframe's maximum speed (docs/physics.md §10.1).

    SPEED_LIMIT = 0.03 · max_speed_kmh · 1000/3600 (gym-pybullet-drones main, envs/BaseRLAviary.py:93-95), i.e.
    0.25 m/s for cf2x/cf2p. Returns f[...] like ``params.max_speed_kmh``.
    """
    return 0.03 * params.max_speed_kmh * (1000.0 / 3600.0)


def velocity_targets(
    state: DroneState, action: ArrayLike, speed_limit: ArrayLike
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Map a desired-velocity action (vx, vy, vz, s) to PID targets (the VEL action, docs/physics.md §10.1-10.2).

    target position = current position; target velocity = speed_limit · |s| · (vx, vy, vz)/‖(vx, vy, vz)‖
    (0 when the direction is 0); target rpy = (0, 0, current PyBullet yaw). Target rates are 0.

    Args:
        state: DroneState with ``pos`` f[..., D, 3] and ``quat`` f[..., D, 4].
        action: f[..., D, 4]: a direction (any length) and a speed fraction s (the box is [−1, 1]³ × [0, 1]; only
            |s| is used). Broadcastable to the state's ``[..., D, 4]``.
        speed_limit: m/s, a scalar or f[..., D] (see `speed_limit`).

    Returns:
        (target_pos f[..., D, 3] m, target_vel f[..., D, 3] m/s, target_rpy f[..., D, 3] rad), all world frame.

    Raises:
        ValueError: if ``action`` does not broadcast to [..., D, 4] with the state's leading shape.
    """
    shape, dtype = _check_state(state)
    action = _as_shape("action", action, shape[:-1] + (4,), dtype)
    return _velocity_targets(state, action, jnp.asarray(speed_limit, dtype=dtype))


@jax.jit
def _velocity_targets(state, action, limit):
    """`velocity_targets` on validated inputs."""
    direction = action[..., :3]
    sq = jnp.sum(direction**2, axis=-1, keepdims=True)
    nonzero = sq > 0
    unit = jnp.where(nonzero, direction / jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)
    target_vel = jnp.broadcast_to(limit, action.shape[:-1])[..., None] * jnp.abs(action[..., 3:4]) * unit
    yaw = quat_to_euler(state.quat)[..., 2]
    target_rpy = jnp.stack([jnp.zeros_like(yaw), jnp.zeros_like(yaw), yaw], axis=-1)
    return state.pos, target_vel, target_rpy


def velocity_control(
    params: DroneParams,
    gains: PIDGains,
    pid_state: PIDState,
    state: DroneState,
    action: ArrayLike,
    *,
    ctrl_dt: float | jax.Array,
    limit: ArrayLike | None = None,
) -> tuple[jax.Array, PIDState]:
    """Desired-velocity control (the paper's VEL action): `velocity_targets` followed by `pid_control`.

    Args:
        params, gains, pid_state, state: as for `pid_compute`.
        action: f[..., D, 4] (vx, vy, vz, s), see `velocity_targets`.
        ctrl_dt: control period, s.
        limit: speed limit in m/s; default `speed_limit` of ``params`` (0.25 m/s for the Crazyflies).

    Returns:
        (rpm f[..., D, 4] in RPM, new PIDState).

    Raises:
        ValueError: as `velocity_targets` and `pid_compute`.
    """
    limit = speed_limit(params) if limit is None else limit
    target_pos, target_vel, target_rpy = velocity_targets(state, action, limit)
    return pid_control(
        params, gains, pid_state, state, target_pos, target_vel=target_vel, target_rpy=target_rpy, ctrl_dt=ctrl_dt
    )


def _check_state(state: DroneState) -> tuple[tuple[int, ...], jnp.dtype]:
    if not isinstance(state, DroneState):
        raise ValueError(f"expected a DroneState, got {type(state).__name__}")
    pos_shape, quat_shape = tuple(state.pos.shape), tuple(state.quat.shape)
    if (
        len(pos_shape) < 2
        or pos_shape[-1] != 3
        or quat_shape != pos_shape[:-1] + (4,)
        or tuple(state.vel.shape) != pos_shape
    ):
        raise ValueError(
            f"state must have pos/vel f[..., D, 3] and quat f[..., D, 4] with the same leading shape, "
            f"got pos {pos_shape}, vel {tuple(state.vel.shape)}, quat {quat_shape}"
        )
    return pos_shape, state.pos.dtype


def _as_shape(name: str, value, shape: tuple[int, ...], dtype) -> jax.Array:
    """``value`` (None meaning 0) as an array of ``shape``, or a ValueError naming the shapes."""
    if value is None:
        return jnp.zeros(shape, dtype=dtype)
    value = jnp.asarray(value, dtype=dtype)
    try:
        ok = np.broadcast_shapes(value.shape, shape) == shape
    except ValueError:
        ok = False
    if not ok or value.ndim == 0 or value.shape[-1] != shape[-1]:
        raise ValueError(
            f"{name} must broadcast to shape {shape} ([..., n_drones, {shape[-1]}] with the state's "
            f"leading shape), got {value.shape}"
        )
    return jnp.broadcast_to(value, shape)


def _check_dt(ctrl_dt, dtype):
    """``ctrl_dt`` checked (when concrete) and as a scalar of ``dtype``: NumPy on the host, a tracer under a trace."""
    if isinstance(ctrl_dt, jax.core.Tracer):
        return ctrl_dt.astype(dtype)
    values = np.asarray(ctrl_dt, dtype=np.float64)
    if values.ndim != 0 or not math.isfinite(float(values)) or float(values) <= 0:
        raise ValueError(f"ctrl_dt must be a positive finite scalar in seconds (e.g. 1/48), got {ctrl_dt!r}")
    return np.asarray(values, dtype=dtype)
