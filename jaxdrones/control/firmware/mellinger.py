"""The firmware's Mellinger controller (``src/modules/src/controller/controller_mellinger.c``, bitcraze/crazyflie-
firmware at 2a18fc29, after Mellinger and Kumar, "Minimum snap trajectory generation and control for quadrotors",
ICRA 2011) as a pure JAX function, batched over any leading axes: a position PID to a desired thrust vector, the
rotation error from the attitude it asks for, and moments from that error, the body rates and their integral, at the
attitude loop's 500 Hz. It follows the C's float32 operations in their order, the math3d.h helpers included
(``vnormalize``, ``vcross``, ``quat2rotmat``, ``rpy2quat``), so its outputs are the C's to float32 rounding
(tests/test_firmware.py).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones.control.firmware import math3d as m3
from jaxdrones.control.firmware.controller_pid import ATTITUDE_DT, ATTITUDE_PERIOD
from jaxdrones.control.firmware.types import (
    MODE_ABS,
    MODE_DISABLE,
    MODE_VELOCITY,
    Control,
    FirmwareState,
    Setpoint,
    every,
)

_F = np.float32
_PI = _F(math.pi)
#: physicalConstants.h, m/s².
GRAVITY_MAGNITUDE = 9.81


@struct.dataclass
class MellingerGains:
    """The Mellinger controller's constants (``controllerMellinger_t``'s defaults, controller_mellinger.c), f32[].

    Attributes:
        mass: kg (``CF_MASS``, platform_defaults_cf2.h); mass_thrust: PWM per newton of the thrust vector.
        kp_xy, kd_xy, ki_xy, i_range_xy: the horizontal position PID and its integral's bound (m·s).
        kp_z, kd_z, ki_z, i_range_z: the vertical one.
        kR_xy, kw_xy, ki_m_xy, i_range_m_xy: roll and pitch: attitude error, rate error, integral and its bound.
        kR_z, kw_z, ki_m_z, i_range_m_z: yaw's.
        kd_omega_rp: the roll and pitch rates' derivative gain.
    """

    mass: jax.Array
    mass_thrust: jax.Array
    kp_xy: jax.Array
    kd_xy: jax.Array
    ki_xy: jax.Array
    i_range_xy: jax.Array
    kp_z: jax.Array
    kd_z: jax.Array
    ki_z: jax.Array
    i_range_z: jax.Array
    kR_xy: jax.Array  # noqa: N815 (the firmware's name)
    kw_xy: jax.Array
    ki_m_xy: jax.Array
    i_range_m_xy: jax.Array
    kR_z: jax.Array  # noqa: N815
    kw_z: jax.Array
    ki_m_z: jax.Array
    i_range_m_z: jax.Array
    kd_omega_rp: jax.Array

    @classmethod
    def crazyflie(cls) -> MellingerGains:
        """controller_mellinger.c's ``g_self`` with ``CF_MASS`` = 0.029 kg (the Crazyflie 2.1 without the thrust
        upgrade kit)."""
        values = dict(
            mass=0.029, mass_thrust=132000, kp_xy=0.4, kd_xy=0.2, ki_xy=0.05, i_range_xy=2.0, kp_z=1.25, kd_z=0.4,
            ki_z=0.05, i_range_z=0.4, kR_xy=70000, kw_xy=20000, ki_m_xy=0.0, i_range_m_xy=1.0, kR_z=60000,
            kw_z=12000, ki_m_z=500, i_range_m_z=1500, kd_omega_rp=200,
        )  # fmt: skip
        return cls(**{k: jnp.float32(v) for k, v in values.items()})


@struct.dataclass
class MellingerState:
    """The controller's memory: the position integral f32[..., 3] (x, y, z), the attitude error's integral
    f32[..., 3], the last roll and pitch rates and their setpoints, f32[..., 2] each (rad/s, legacy pitch), and the
    last `Control` (held on the ticks the controller does not run)."""

    i_error: jax.Array
    i_error_m: jax.Array
    prev_omega: jax.Array
    prev_setpoint_omega: jax.Array
    control: Control


def mellinger_init(shape: tuple[int, ...] = ()) -> MellingerState:
    """The state after ``controllerMellingerInit``: every memory zero, batch shape ``shape``."""
    zeros3, zeros2 = jnp.zeros((*shape, 3), jnp.float32), jnp.zeros((*shape, 2), jnp.float32)
    return MellingerState(
        i_error=zeros3, i_error_m=zeros3, prev_omega=zeros2, prev_setpoint_omega=zeros2, control=Control.zeros(shape)
    )


def controller_mellinger(
    gains: MellingerGains, mstate: MellingerState, setpoint: Setpoint, state: FirmwareState, tick: jax.Array | int
) -> tuple[MellingerState, Control]:
    """One tick of the firmware's ``controllerMellinger`` (controller_mellinger.c), batched over the leading axes.

    Args:
        gains: `MellingerGains` (`MellingerGains.crazyflie`), one set for every drone.
        mstate: `MellingerState` ``[...]`` (`mellinger_init`).
        setpoint: `Setpoint` ``[...]`` (position, velocity, acceleration, attitude, rates, modes).
        state: `FirmwareState` ``[...]``.
        tick: i32 (or i32[...]), the stabilizer's tick: the controller runs when it is even (500 Hz), else holds its
            last control.

    Returns:
        (the new `MellingerState`, the `Control` in the legacy mode).
    """
    new_state = every(ATTITUDE_PERIOD, tick, lambda: _mellinger(gains, mstate, setpoint, state)[0], mstate)
    return new_state, new_state.control


def _mellinger(gains: MellingerGains, mstate: MellingerState, setpoint: Setpoint, state: FirmwareState):
    """The attitude tick's computation of ``controllerMellinger``."""
    g = gains
    dt = jnp.float32(ATTITUDE_DT)
    sp_pos, sp_vel = setpoint.position, setpoint.velocity
    r_error = [sp_pos[..., k] - state.position[..., k] for k in range(3)]
    v_error = [sp_vel[..., k] - state.velocity[..., k] for k in range(3)]
    ranges = (g.i_range_xy, g.i_range_xy, g.i_range_z)
    i_error = [m3.clamp(mstate.i_error[..., k] + r_error[k] * dt, -ranges[k], ranges[k]) for k in range(3)]

    mode = setpoint.mode
    quat_yaw = m3.quat_yaw(setpoint.quat)
    desired_yaw = jnp.where(
        mode[..., 5] == MODE_VELOCITY,
        state.attitude[..., 2] + setpoint.attitude_rate[..., 2] * dt,
        jnp.where(
            mode[..., 5] == MODE_ABS, setpoint.attitude[..., 2], jnp.where(mode[..., 6] == MODE_ABS, quat_yaw, 0.0)
        ),
    )

    x, y, z, w = (state.quat[..., k] for k in range(4))
    z_axis = m3.rotmat_columns(x, y, z, w)[2]
    zero = jnp.zeros_like(x)

    # position mode
    accel = tuple(setpoint.acceleration[..., k] for k in range(3))
    thrust_vec = (
        g.mass * accel[0] + g.kp_xy * r_error[0] + g.kd_xy * v_error[0] + g.ki_xy * i_error[0],
        g.mass * accel[1] + g.kp_xy * r_error[1] + g.kd_xy * v_error[1] + g.ki_xy * i_error[1],
        g.mass * (accel[2] + _F(GRAVITY_MAGNITUDE)) + g.kp_z * r_error[2] + g.kd_z * v_error[2] + g.ki_z * i_error[2],
    )

    def axes_from(target, yaw_deg):
        z_des = m3.normalize(target)
        yaw = m3.radians(yaw_deg)
        x_c = (jnp.cos(yaw), jnp.sin(yaw), zero)
        y_des = m3.normalize(m3.cross(z_des, x_c))
        return m3.cross(y_des, z_des), y_des, z_des

    pos_axes = axes_from(thrust_vec, desired_yaw)
    pos_thrust = m3.dot(thrust_vec, z_axis)
    # manual attitude mode
    cmd = m3.rpy2quat(
        m3.radians(setpoint.attitude[..., 0]), -m3.radians(setpoint.attitude[..., 1]), m3.radians(desired_yaw)
    )
    manual_axes = m3.rotmat_columns(*cmd)
    # any other mode: hold the height at the state's yaw
    hold_vec = (
        zero,
        zero,
        g.mass * _F(GRAVITY_MAGNITUDE) + g.kp_z * r_error[2] + g.kd_z * v_error[2] + g.ki_z * i_error[2],
    )
    hold_axes = axes_from(hold_vec, state.attitude[..., 2])
    hold_thrust = m3.dot(hold_vec, z_axis)

    position_mode = mode[..., 0] == MODE_ABS
    manual_mode = (mode[..., 4] == MODE_ABS) & (mode[..., 3] == MODE_ABS) & (mode[..., 2] == MODE_DISABLE)

    def choose(a, b, c):
        return jnp.where(position_mode, a, jnp.where(manual_mode, b, c))

    x_des, y_des, z_des = (
        tuple(choose(p, m, h) for p, m, h in zip(*axes, strict=True))
        for axes in zip(pos_axes, manual_axes, hold_axes, strict=True)
    )
    current_thrust = choose(pos_thrust, zero, hold_thrust)

    e_r = _rotation_error(x, y, z, w, x_des, y_des, z_des)
    e_r = (e_r[0], -e_r[1], e_r[2])

    rate = (m3.radians(state.gyro[..., 0]), -m3.radians(state.gyro[..., 1]), m3.radians(state.gyro[..., 2]))
    sp_rate = setpoint.attitude_rate
    e_w = (
        m3.radians(sp_rate[..., 0]) - rate[0],
        -m3.radians(sp_rate[..., 1]) - rate[1],
        m3.radians(sp_rate[..., 2]) - rate[2],
    )
    prev, prev_sp = mstate.prev_omega, mstate.prev_setpoint_omega
    started = prev[..., 0] == prev[..., 0]
    err_d_roll = jnp.where(
        started, ((m3.radians(sp_rate[..., 0]) - prev_sp[..., 0]) - (rate[0] - prev[..., 0])) / dt, 0.0
    )
    err_d_pitch = jnp.where(
        started, (-(m3.radians(sp_rate[..., 1]) - prev_sp[..., 1]) - (rate[1] - prev[..., 1])) / dt, 0.0
    )
    m_ranges = (g.i_range_m_xy, g.i_range_m_xy, g.i_range_m_z)
    i_error_m = [m3.clamp(mstate.i_error_m[..., k] + (-e_r[k]) * dt, -m_ranges[k], m_ranges[k]) for k in range(3)]
    moment = (
        -g.kR_xy * e_r[0] + g.kw_xy * e_w[0] + g.ki_m_xy * i_error_m[0] + g.kd_omega_rp * err_d_roll,
        -g.kR_xy * e_r[1] + g.kw_xy * e_w[1] + g.ki_m_xy * i_error_m[1] + g.kd_omega_rp * err_d_pitch,
        -g.kR_z * e_r[2] + g.kw_z * e_w[2] + g.ki_m_z * i_error_m[2],
    )
    thrust = jnp.where(mode[..., 2] == MODE_DISABLE, setpoint.thrust, g.mass_thrust * current_thrust)
    on = thrust > 0
    to_int = lambda v: jnp.where(on, jnp.trunc(m3.clamp(v, -32000.0, 32000.0)), 0.0).astype(jnp.int32)  # noqa: E731
    control = Control(roll=to_int(moment[0]), pitch=to_int(moment[1]), yaw=to_int(-moment[2]), thrust=thrust)
    keep = lambda v: jnp.where(on, v, 0.0)  # noqa: E731  (zero thrust: the integrals reset)
    new_state = MellingerState(
        i_error=jnp.stack([keep(v) for v in i_error], -1),
        i_error_m=jnp.stack([keep(v) for v in i_error_m], -1),
        prev_omega=jnp.stack([rate[0], rate[1]], -1),
        prev_setpoint_omega=jnp.stack([m3.radians(sp_rate[..., 0]), m3.radians(sp_rate[..., 1])], -1),
        control=control,
    )
    return new_state, control


def _rotation_error(x, y, z, w, x_des, y_des, z_des):
    """controller_mellinger.c's eR ("fast version", generated with Mathematica), before its y is negated."""
    xd, yd, zd = x_des, y_des, z_des
    sq = lambda v: v * v  # noqa: E731  (math3d.h fsqr)
    ex = (
        (-1 + 2 * sq(x) + 2 * sq(y)) * yd[2]
        + zd[1]
        - 2 * (x * yd[0] * z + y * yd[1] * z - x * y * zd[0] + sq(x) * zd[1] + sq(z) * zd[1] - y * z * zd[2])
        + 2 * w * (-(y * yd[0]) - z * zd[0] + x * (yd[1] + zd[2]))
    )
    ey = (
        xd[2]
        - zd[0]
        - 2
        * (
            sq(x) * xd[2]
            + y * (xd[2] * y - xd[1] * z)
            - (sq(y) + sq(z)) * zd[0]
            + x * (-(xd[0] * z) + y * zd[1] + z * zd[2])
            + w * (x * xd[1] + z * zd[1] - y * (xd[0] + zd[2]))
        )
    )
    ez = (
        yd[0]
        - 2 * (y * (x * xd[0] + y * yd[0] - x * yd[1]) + w * (x * xd[2] + y * yd[2]))
        + 2 * (-(xd[2] * y) + w * (xd[0] + yd[1]) + x * yd[2]) * z
        - 2 * yd[0] * sq(z)
        + xd[1] * (-1 + 2 * sq(x) + 2 * sq(z))
    )
    return ex, ey, ez
