"""The firmware's Brescianini controller as a pure JAX function batched over any leading axes.

bitcraze/crazyflie-firmware at 2a18fc29 (GPL-3; a re-implementation from its behaviour, not a copy):
``src/modules/src/controller/controller_brescianini.c`` (``controllerBrescianini``, M. Hamer 2016, after Brescianini,
Hehn and D'Andrea, "Nonlinear quadrocopter attitude control", ETH Zurich 2013): at 100 Hz a second-order position
law gives the desired acceleration, its norm (bounded with a fairness rule) the collective thrust and its direction
the desired thrust axis; the attitude error (the thrust axis' tilt, then the yaw: the "full" attitude control, mixed
with the "reduced" one by ``mixing_factor``) gives body-rate setpoints, bounded after a heuristic for large rates; at
every 1 kHz tick the rate error through the Crazyflie's inertia gives the body torques. Its output is a collective
thrust in newtons and torques in N·m for `jaxdrones.control.firmware.power_distribution_force_torque`.

The C's constants are its file's statics (`BrescianiniGains.crazyflie`); its memory between ticks, the rate setpoints
and the collective acceleration of the last 100 Hz update (`BrescianiniState`). It follows the C's float32 operations
in their order (tests/test_firmware.py checks it against the firmware's own C).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones.control.firmware import math3d as m3
from jaxdrones.control.firmware import pid as _pid
from jaxdrones.control.firmware.types import MODE_DISABLE, FirmwareState, Setpoint, every, select

_F = np.float32
#: controller_brescianini.c's update rate (``RATE_100_HZ``): ticks of the 1 kHz loop between two updates.
UPDATE_PERIOD = 10
#: physicalConstants.h: ``GRAVITY_MAGNITUDE`` m/s² and ``ARCMINUTE`` rad (π / 10800).
GRAVITY_MAGNITUDE = _F(9.81)
ARCMINUTE = _F(math.pi) / _F(10800.0)


@struct.dataclass
class BrescianiniGains:
    """controller_brescianini.c's statics, f32[] (one set for every drone).

    Attributes:
        tau_xy, zeta_xy, tau_z, zeta_z: the position law's time constants (s) and damping ratios.
        tau_rp: the thrust axis' time constant, s; mixing_factor: yaw's share of the full attitude control (0: none,
            1: as roll and pitch).
        tau_rp_rate, tau_yaw_rate: the body-rate loop's time constants, s.
        coll_min, coll_max: the collective acceleration's bounds, m/s²; fairness: how a too large acceleration is cut
            (1: every axis alike, 0: z first, ``thrust_reduction_fairness``).
        omega_rp_max, omega_yaw_max: the body rates' bounds, rad/s; heuristic_rp, heuristic_yaw: above these rates
            (rad/s) a setpoint against the rotation is replaced by the largest rate along it.
        mass: kg (``CF_MASS``, platform_defaults_cf2.h); inertia: f32[3, 3] kg·m² (``CRAZYFLIE_INERTIA``).
    """

    tau_xy: jax.Array
    zeta_xy: jax.Array
    tau_z: jax.Array
    zeta_z: jax.Array
    tau_rp: jax.Array
    mixing_factor: jax.Array
    tau_rp_rate: jax.Array
    tau_yaw_rate: jax.Array
    coll_min: jax.Array
    coll_max: jax.Array
    fairness: jax.Array
    omega_rp_max: jax.Array
    omega_yaw_max: jax.Array
    heuristic_rp: jax.Array
    heuristic_yaw: jax.Array
    mass: jax.Array
    inertia: jax.Array

    @classmethod
    def crazyflie(cls) -> BrescianiniGains:
        """The C file's values, with ``CF_MASS`` = 0.029 kg (the Crazyflie 2.1 without the thrust upgrade kit)."""
        values = dict(
            tau_xy=0.3, zeta_xy=0.85, tau_z=0.3, zeta_z=0.85, tau_rp=0.25, mixing_factor=1.0, tau_rp_rate=0.015,
            tau_yaw_rate=0.0075, coll_min=1.0, coll_max=18.0, fairness=0.25, omega_rp_max=30.0, omega_yaw_max=10.0,
            heuristic_rp=12.0, heuristic_yaw=5.0, mass=0.029,
        )  # fmt: skip
        inertia = [[16.6e-6, 0.83e-6, 0.72e-6], [0.83e-6, 16.6e-6, 1.8e-6], [0.72e-6, 1.8e-6, 29.3e-6]]
        return cls(**{k: jnp.float32(v) for k, v in values.items()}, inertia=jnp.asarray(inertia, jnp.float32))


@struct.dataclass
class BrescianiniState:
    """The controller's memory between ticks (the C's function statics).

    Attributes:
        omega: f32[..., 3] rad/s, the body-rate setpoints of the last update (``control_omega``).
        thrust: f32[...] m/s², the collective acceleration of the last update (``control_thrust``).
    """

    omega: jax.Array
    thrust: jax.Array


@struct.dataclass
class ForceTorque:
    """``control_t`` in ``controlModeForceTorque``.

    Attributes:
        thrust: f32[...] N, the collective thrust (``thrustSi``).
        torque: f32[..., 3] N·m, body frame (``torque``).
    """

    thrust: jax.Array
    torque: jax.Array


def brescianini_init(shape: tuple[int, ...] = ()) -> BrescianiniState:
    """The memory at start-up (the C's statics, zero), batch shape ``shape``."""
    return BrescianiniState(omega=jnp.zeros((*shape, 3), jnp.float32), thrust=jnp.zeros(shape, jnp.float32))


def controller_brescianini(
    gains: BrescianiniGains,
    memory: BrescianiniState,
    setpoint: Setpoint,
    state: FirmwareState,
    tick: jax.Array | int,
) -> tuple[BrescianiniState, ForceTorque]:
    """One tick of the firmware's ``controllerBrescianini``, batched over the leading axes.

    Args:
        gains: `BrescianiniGains` (`BrescianiniGains.crazyflie`).
        memory: `BrescianiniState` ``[...]`` (`brescianini_init`).
        setpoint: `Setpoint` ``[...]``: position, velocity, acceleration (m, m/s, m/s², world), the yaw (deg,
            ``attitude``) and the yaw rate (deg/s, ``attitude_rate``); z modeDisable turns the output off.
        state: `FirmwareState` ``[...]``: its ``quat``, position, velocity and gyro.
        tick: i32 (or i32[...]), the stabilizer's tick: the position and attitude update runs on multiples of
            `UPDATE_PERIOD` (100 Hz), the rate loop at every tick.

    Returns:
        (the new `BrescianiniState`, the `ForceTorque` control).
    """
    omega = [m3.radians(state.gyro[..., k]) for k in range(3)]
    memory = every(UPDATE_PERIOD, tick, lambda: _update(gains, setpoint, state, omega), memory)
    taus = (gains.tau_rp_rate, gains.tau_rp_rate, gains.tau_yaw_rate)
    error = [(memory.omega[..., k] - omega[k]) / taus[k] for k in range(3)]
    inertia = gains.inertia
    torque = jnp.stack(
        [inertia[k, 0] * error[0] + inertia[k, 1] * error[1] + inertia[k, 2] * error[2] for k in range(3)], -1
    )
    off = setpoint.mode[..., 2] == MODE_DISABLE
    control = ForceTorque(
        thrust=jnp.where(off, 0.0, memory.thrust * gains.mass), torque=jnp.where(off[..., None], 0.0, torque)
    )
    return memory, control


def _half_angle_axis(alpha: jax.Array, axis: tuple) -> tuple:
    """(sin(α/2) axis, cos(α/2)) as (x, y, z, w)."""
    s, c = jnp.sin(alpha / 2.0), jnp.cos(alpha / 2.0)
    return (s * axis[0], s * axis[1], s * axis[2], c)


def _axis(alpha: jax.Array, a: tuple, b: tuple) -> tuple:
    """``vnormalize(vcross(a, b))`` where |α| exceeds an arc minute, else (1, 1, 0)."""
    axis = m3.normalize(m3.cross(a, b))
    large = jnp.abs(alpha) > ARCMINUTE
    one, zero = jnp.ones_like(alpha), jnp.zeros_like(alpha)
    return select(large, axis, (one, one, zero))


def _update(gains: BrescianiniGains, setpoint: Setpoint, state: FirmwareState, omega: list) -> BrescianiniState:
    """The 100 Hz block of ``controllerBrescianini``: the new rate setpoints and collective acceleration."""
    g = gains
    qx, qy, qz, qw = (state.quat[..., k] for k in range(4))
    r02 = 2 * qx * qz + 2 * qw * qy
    r12 = 2 * qy * qz - 2 * qw * qx
    r22 = qw * qw - qx * qx - qy * qy + qz * qz
    p_err = [setpoint.position[..., k] - state.position[..., k] for k in range(3)]
    v_err = [setpoint.velocity[..., k] - state.velocity[..., k] for k in range(3)]
    acc_sp = setpoint.acceleration

    def axis_law(k, tau, zeta, start):
        acc = start + _F(1.0) / tau / tau * p_err[k]
        acc = acc + _F(2.0) * zeta / tau * v_err[k]
        acc = acc + acc_sp[..., k]
        return _pid.constrain(acc, -g.coll_max, g.coll_max)

    acc = [
        axis_law(0, g.tau_xy, g.zeta_xy, 0.0),
        axis_law(1, g.tau_xy, g.zeta_xy, 0.0),
        axis_law(2, g.tau_z, g.zeta_z, GRAVITY_MAGNITUDE),
    ]

    # A collective acceleration beyond coll_max: every axis cut by r, z by the fairness' share of it.
    coll = acc[2] / r22
    x, y, z, grav = acc[0], acc[1], acc[2] - GRAVITY_MAGNITUDE, GRAVITY_MAGNITUDE
    f = _pid.constrain(g.fairness, 0.0, 1.0)
    a = x * x + y * y + (z * f) * (z * f)
    a = jnp.where(a < 0, 0.0, a)
    b = 2 * z * f * ((1 - f) * z + grav)
    c = g.coll_max * g.coll_max - ((1 - f) * z + grav) * ((1 - f) * z + grav)
    c = jnp.where(c < 0, 0.0, c)
    tiny = jnp.abs(a) < _F(1e-6)
    safe_a = jnp.where(tiny, 1.0, a)
    r = (-b + jnp.sqrt(b * b + _F(4.0) * safe_a * c)) / (_F(2.0) * safe_a)
    r = jnp.where(tiny, 0.0, _pid.constrain(r, 0.0, 1.0))
    cut = jnp.abs(coll) > g.coll_max
    acc = [
        jnp.where(cut, r * x, acc[0]),
        jnp.where(cut, r * y, acc[1]),
        jnp.where(cut, (r * f + (1 - f)) * z + grav, acc[2]),
    ]
    coll = _pid.constrain(acc[2] / r22, g.coll_min, g.coll_max)

    z_des = m3.normalize(tuple(acc))
    z_cur = m3.normalize((r02, r12, r22))
    zeros, ones = jnp.zeros_like(r22), jnp.ones_like(r22)
    z_inertial = (zeros, zeros, ones)

    # Reduced attitude control: the rotation from the thrust axis to the desired one.
    alpha = jnp.arccos(_pid.constrain(m3.dot(z_cur, z_des), -1.0, 1.0))
    reduced = _half_angle_axis(alpha, _axis(alpha, z_cur, z_des))
    reduced = select(jnp.cos(alpha / 2.0) < 0, tuple(-v for v in reduced), reduced)
    reduced = m3.qnormalize(reduced)

    # Full attitude control: tilt from the vertical to the desired axis, then the yaw setpoint.
    alpha = jnp.arccos(_pid.constrain(m3.dot(z_inertial, z_des), -1.0, 1.0))
    tilt = _half_angle_axis(alpha, _axis(alpha, z_inertial, z_des))
    half_yaw = m3.radians(setpoint.attitude[..., 2]) / 2.0
    desired = m3.qqmul(tilt, (zeros, zeros, jnp.sin(half_yaw), jnp.cos(half_yaw)))
    full = m3.qqmul((-qx, -qy, -qz, qw), desired)
    full = select(full[3] < 0, tuple(-v for v in full), full)
    full = m3.qnormalize(full)

    # Mixing: the rotation from the reduced to the full error, mixing_factor of it.
    between = m3.qnormalize(m3.qqmul((-reduced[0], -reduced[1], -reduced[2], reduced[3]), full))
    angle = 2.0 * jnp.arccos(_pid.constrain(between[3], -1.0, 1.0))
    sign = jnp.where(between[2] < 0, _F(-1.0), _F(1.0))
    half = angle * g.mixing_factor / 2.0
    mixed = m3.qnormalize(m3.qqmul(reduced, (zeros, zeros, jnp.sin(half) * sign, jnp.cos(half))))
    error = select(g.mixing_factor <= 0, reduced, select(g.mixing_factor >= 1, full, mixed))

    rates = [
        _F(2.0) / g.tau_rp * error[0],
        _F(2.0) / g.tau_rp * error[1],
        _F(2.0) / g.tau_rp * error[2] + m3.radians(setpoint.attitude_rate[..., 2]),
    ]
    limits = (g.omega_rp_max, g.omega_rp_max, g.omega_yaw_max)
    heuristics = (g.heuristic_rp, g.heuristic_rp, g.heuristic_yaw)
    for k in range(3):  # a setpoint against a fast rotation: the largest rate along the rotation instead
        against = (rates[k] * omega[k] < 0) & (jnp.abs(omega[k]) > heuristics[k])
        rates[k] = jnp.where(against, limits[k] * jnp.where(omega[k] < 0, _F(-1.0), _F(1.0)), rates[k])
    scaling = jnp.ones_like(r22)
    for k in range(3):
        scaling = jnp.fmax(scaling, jnp.abs(rates[k]) / limits[k])
    return BrescianiniState(omega=jnp.stack([v / scaling for v in rates], -1), thrust=coll)
