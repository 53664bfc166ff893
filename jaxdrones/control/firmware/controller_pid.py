"""The firmware's default controller, the PID cascade, as a pure JAX function batched over any leading axes.

bitcraze/crazyflie-firmware at 2a18fc29 (GPL-3; this is a re-implementation from its behaviour, not a copy):
``src/modules/src/controller/controller_pid.c`` (``controllerPid``: the loops' rates, the yaw setpoint, the mode
switches, the reset on a mode change and at zero thrust), ``position_controller_pid.c`` (``positionController`` and
``velocityController`` at 100 Hz: position → velocity → roll, pitch and thrust), ``attitude_pid_controller.c``
(attitude → rates → the int16 outputs at 500 Hz), with ``src/utils/src/pid.c`` (`jaxdrones.control.firmware.pid`).
The gains are ``src/platform/interface/platform_defaults_cf2.h``'s and ``platform_defaults.h``'s (the filters).

The firmware calls its controller every tick of its 1 kHz stabilizer loop with the tick's number; the position loop
runs when ``tick % 10 == 0`` and the attitude and rate loops when ``tick % 2 == 0`` (``RATE_DO_EXECUTE``); on other
ticks the control output is the previous one. `controller_pid` takes the same tick and holds the same memory in
`PidControllerState`, so one call is one firmware tick. It follows the C's float32 operations in their order: its
outputs are the C's to float32 rounding (tests/test_firmware.py checks them against the firmware's own C).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones.control.firmware import math3d as m3
from jaxdrones.control.firmware import pid as _pid
from jaxdrones.control.firmware.types import (
    MODE_ABS,
    MODE_DISABLE,
    MODE_VELOCITY,
    Control,
    FirmwareState,
    Setpoint,
    every,
    select,
)

#: The stabilizer loop's rate and the controller's loops' (stabilizer_types.h), Hz.
RATE_MAIN_LOOP, ATTITUDE_RATE, POSITION_RATE = 1000, 500, 100
#: Ticks between two runs of the position loop, and of the attitude and rate loops (``RATE_DO_EXECUTE``).
POSITION_PERIOD = RATE_MAIN_LOOP // POSITION_RATE
ATTITUDE_PERIOD = RATE_MAIN_LOOP // ATTITUDE_RATE
ATTITUDE_DT = float(np.float32(1.0) / np.float32(ATTITUDE_RATE))
POSITION_DT = float(np.float32(1.0) / np.float32(POSITION_RATE))
_F = np.float32
_PI = _F(math.pi)


@struct.dataclass
class PidControllerGains:
    """The PID cascade's constants, each loop's three axes stacked on a last axis of 3.

    Attributes:
        position: `PidGains` f32[..., 3], x and y (body-yaw frame) and z; output: velocity, m/s.
        velocity: `PidGains` f32[..., 3]; output: pitch and roll (deg) and thrust (/ ``thrust_scale``).
        attitude: `PidGains` f32[..., 3], roll, pitch, yaw (deg → deg/s).
        rate: `PidGains` f32[..., 3], roll, pitch, yaw rates (deg/s → PWM units).
        thrust_base: f32[...] PWM, the hover feed-forward (``thrustBase``).
        thrust_min: f32[...] PWM, the least thrust the velocity loop gives (``thrustMin``).
        thrust_scale: f32[...] PWM per unit of the z-velocity PID's output (``thrustScale``).
        roll_limit, pitch_limit: f32[...] deg, the velocity loop's bounds (``rLimit``, ``pLimit``).
        yaw_max_delta: f32[...] deg, how far the rate-controlled yaw setpoint may lead the yaw (0: no bound).
    """

    position: _pid.PidGains
    velocity: _pid.PidGains
    attitude: _pid.PidGains
    rate: _pid.PidGains
    thrust_base: jax.Array
    thrust_min: jax.Array
    thrust_scale: jax.Array
    roll_limit: jax.Array
    pitch_limit: jax.Array
    yaw_max_delta: jax.Array

    @classmethod
    def crazyflie(cls) -> PidControllerGains:
        """The firmware's defaults for the Crazyflie 2.x (platform_defaults_cf2.h, platform_defaults.h), with the
        output limits ``positionController`` and ``velocityController`` set (``PID_POS_VEL_*_MAX`` × 1.1, the
        roll and pitch limits × 1.1, ``UINT16_MAX / 2 / thrustScale``) and the attitude loops' integral limits."""
        vel_max = _F(1.0) * _F(1.10)  # xVelMax * velMaxOverhead; z: fmaxf(zVelMax, 0.5f) * velMaxOverhead
        rp_max = _F(20.0) * _F(1.10)  # rLimit * rpLimitOverhead
        thrust_out = _F(65535 // 2) / _F(1000.0)  # UINT16_MAX / 2 / thrustScale (integer division first)
        pos = [_pid.pid_gains(2.0, 0.0, 0.0, 0.0, POSITION_DT, POSITION_RATE, 20.0, True, output_limit=vel_max)] * 2
        pos.append(_pid.pid_gains(2.0, 0.5, 0.0, 0.0, POSITION_DT, POSITION_RATE, 20.0, True, output_limit=vel_max))
        vel = [_pid.pid_gains(25.0, 1.0, 0.0, 0.0, POSITION_DT, POSITION_RATE, 20.0, True, output_limit=rp_max)] * 2
        vel.append(
            _pid.pid_gains(25.0, 15.0, 0.0, 0.0, POSITION_DT, POSITION_RATE, 20.0, True, output_limit=thrust_out)
        )
        att = [
            _pid.pid_gains(6.0, 3.0, 0.0, 0.0, ATTITUDE_DT, ATTITUDE_RATE, 15.0, False, i_limit=20.0),
            _pid.pid_gains(6.0, 3.0, 0.0, 0.0, ATTITUDE_DT, ATTITUDE_RATE, 15.0, False, i_limit=20.0),
            _pid.pid_gains(6.0, 1.0, 0.35, 0.0, ATTITUDE_DT, ATTITUDE_RATE, 15.0, False, i_limit=360.0),
        ]
        rate = [
            _pid.pid_gains(250.0, 500.0, 2.5, 0.0, ATTITUDE_DT, ATTITUDE_RATE, 30.0, False, i_limit=33.3),
            _pid.pid_gains(250.0, 500.0, 2.5, 0.0, ATTITUDE_DT, ATTITUDE_RATE, 30.0, False, i_limit=33.3),
            _pid.pid_gains(120.0, 16.7, 0.0, 0.0, ATTITUDE_DT, ATTITUDE_RATE, 30.0, False, i_limit=166.7),
        ]
        return cls(
            position=_stack(pos),
            velocity=_stack(vel),
            attitude=_stack(att),
            rate=_stack(rate),
            thrust_base=jnp.float32(36000.0),
            thrust_min=jnp.float32(20000.0),
            thrust_scale=jnp.float32(1000.0),
            roll_limit=jnp.float32(20.0),
            pitch_limit=jnp.float32(20.0),
            yaw_max_delta=jnp.float32(0.0),
        )


def _stack(axes: list[_pid.PidGains]) -> _pid.PidGains:
    if len({g.filtered for g in axes}) != 1:
        raise ValueError("PidControllerGains: the three axes of a loop are filtered alike or not at all")
    return jax.tree.map(lambda *a: jnp.stack(a, axis=-1), *axes)


@struct.dataclass
class PidControllerState:
    """The PID cascade's memory between ticks.

    Attributes:
        position, velocity, attitude, rate: `PidState` f32[..., 3], each loop's three PIDs.
        attitude_desired: f32[..., 3] deg, roll, pitch, yaw (``attitudeDesired``).
        rate_desired: f32[..., 3] deg/s (``rateDesired``).
        actuator_thrust: f32[...] PWM (``actuatorThrust``).
        previous_mode: i32[..., 7], the last tick's ``setpoint->mode`` (a change resets the PIDs).
        control: `Control`, the last output (held on the ticks the attitude loop does not run).
    """

    position: _pid.PidState
    velocity: _pid.PidState
    attitude: _pid.PidState
    rate: _pid.PidState
    attitude_desired: jax.Array
    rate_desired: jax.Array
    actuator_thrust: jax.Array
    previous_mode: jax.Array
    control: Control


def controller_pid_init(shape: tuple[int, ...] = ()) -> PidControllerState:
    """The cascade's state after ``controllerPidInit`` (every memory zero), batch shape ``shape``."""
    loop = _pid.PidState.zeros((*shape, 3))
    zeros3 = jnp.zeros((*shape, 3), jnp.float32)
    return PidControllerState(
        position=loop,
        velocity=loop,
        attitude=loop,
        rate=loop,
        attitude_desired=zeros3,
        rate_desired=zeros3,
        actuator_thrust=jnp.zeros(shape, jnp.float32),
        previous_mode=jnp.zeros((*shape, 7), jnp.int32),
        control=Control.zeros(shape),
    )


def cap_angle(angle: jax.Array) -> jax.Array:
    """controller_pid.c ``capAngle``: ±360° until within [-180, 180] (exact for |angle| < 900°, as the C's loop)."""
    for _ in range(2):
        angle = jnp.where(angle > 180.0, angle - 360.0, angle)
    for _ in range(2):
        angle = jnp.where(angle < -180.0, angle + 360.0, angle)
    return angle


def saturate_int16(value: jax.Array) -> jax.Array:
    """attitude_pid_controller.c ``saturateSignedInt16``: bounded to ±32767, then truncated toward zero."""
    return jnp.clip(jnp.trunc(jnp.clip(value, -32767.0, 32767.0)), -32767, 32767).astype(jnp.int32)


def _reinitialize(cstate: PidControllerState, state: FirmwareState) -> PidControllerState:
    """``controllerPidReinitialize``: the position PIDs reset to the position (the velocity ones to 0) with their
    filters, the attitude PIDs to the attitude (the rate ones to 0), the desired roll and pitch to the attitude."""
    zeros = jnp.zeros_like(state.position)
    return cstate.replace(
        position=_pid.filter_reset(_pid.pid_reset(cstate.position, state.position)),
        velocity=_pid.filter_reset(_pid.pid_reset(cstate.velocity, zeros)),
        attitude=_pid.pid_reset(cstate.attitude, state.attitude),
        rate=_pid.pid_reset(cstate.rate, zeros),
        attitude_desired=cstate.attitude_desired.at[..., :2].set(state.attitude[..., :2]),
    )


def _yaw_setpoint(gains, cstate, setpoint: Setpoint, state: FirmwareState) -> jax.Array:
    """The attitude tick's desired yaw (controllerPid's first block), deg."""
    yaw = cstate.attitude_desired[..., 2]
    state_yaw = state.attitude[..., 2]
    rate_yaw = cap_angle(yaw + setpoint.attitude_rate[..., 2] * jnp.float32(ATTITUDE_DT))
    delta = cap_angle(rate_yaw - state_yaw)
    bounded = jnp.where(
        delta > gains.yaw_max_delta,
        state_yaw + gains.yaw_max_delta,
        jnp.where(delta < -gains.yaw_max_delta, state_yaw - gains.yaw_max_delta, rate_yaw),
    )
    rate_yaw = jnp.where(gains.yaw_max_delta != 0, bounded, rate_yaw)
    quat_yaw = m3.quat_yaw(setpoint.quat)
    mode_yaw, mode_quat = setpoint.mode[..., 5], setpoint.mode[..., 6]
    yaw = jnp.where(
        mode_yaw == MODE_VELOCITY,
        rate_yaw,
        jnp.where(mode_yaw == MODE_ABS, setpoint.attitude[..., 2], jnp.where(mode_quat == MODE_ABS, quat_yaw, yaw)),
    )
    return cap_angle(yaw)


def _yaw_frame(v: jax.Array, cos: jax.Array, sin: jax.Array) -> jax.Array:
    """A world vector f32[..., 3] in the yaw frame: x cos + y sin, −x sin + y cos, z (positionController)."""
    return jnp.stack([v[..., 0] * cos + v[..., 1] * sin, -v[..., 0] * sin + v[..., 1] * cos, v[..., 2]], -1)


def _position_loops(gains: PidControllerGains, cstate: PidControllerState, setpoint: Setpoint, state: FirmwareState):
    """``positionController`` and ``velocityController``: (position PIDs, velocity PIDs, thrust PWM, roll and
    pitch deg)."""
    yaw = state.attitude[..., 2] * _PI / _F(180.0)
    cos, sin = jnp.cos(yaw), jnp.sin(yaw)
    sp, pos, vel = setpoint.position, state.position, state.velocity
    sp_body, pos_body = _yaw_frame(sp, cos, sin), _yaw_frame(pos, cos, sin)
    position, vel_from_pos = _pid.pid_update(gains.position, cstate.position, sp_body, pos_body)
    absolute = setpoint.mode[..., :3] == MODE_ABS
    position = jax.tree.map(lambda new, old: jnp.where(absolute, new, old), position, cstate.position)
    gv = setpoint.velocity
    world_to_body = jnp.stack([gv[..., 0] * cos + gv[..., 1] * sin, gv[..., 1] * cos - gv[..., 0] * sin], -1)
    xy = jnp.where(setpoint.velocity_body[..., None], gv[..., :2], world_to_body)
    vel_sp = jnp.concatenate([xy, gv[..., 2:]], -1)
    vel_sp = jnp.where(absolute, vel_from_pos, vel_sp)
    vel_body = _yaw_frame(vel, cos, sin)
    velocity, out = _pid.pid_update(gains.velocity, cstate.velocity, vel_sp, vel_body)
    pitch = _pid.constrain(-out[..., 0], -gains.pitch_limit, gains.pitch_limit)
    roll = _pid.constrain(-out[..., 1], -gains.roll_limit, gains.roll_limit)
    thrust = out[..., 2] * gains.thrust_scale + gains.thrust_base
    thrust = jnp.where(thrust < gains.thrust_min, gains.thrust_min, thrust)
    thrust = _pid.constrain(thrust, 0.0, 65535.0)
    return position, velocity, thrust, roll, pitch


def controller_pid(
    gains: PidControllerGains,
    cstate: PidControllerState,
    setpoint: Setpoint,
    state: FirmwareState,
    tick: jax.Array | int,
) -> tuple[PidControllerState, Control]:
    """One tick of the firmware's ``controllerPid`` (controller_pid.c), batched over the leading axes.

    Args:
        gains: `PidControllerGains` (`PidControllerGains.crazyflie` for the firmware's).
        cstate: `PidControllerState` of batch shape ``[...]`` (`controller_pid_init`).
        setpoint: `Setpoint` ``[...]``.
        state: `FirmwareState` ``[...]`` (`jaxdrones.control.firmware.firmware_state` of a `DroneState`).
        tick: i32 (or i32[...]), the stabilizer loop's tick (1 kHz); the position loop runs on multiples of 10, the
            attitude and rate loops on multiples of 2. One tick for every drone (a scalar) runs only the loops of
            that tick (`jax.lax.cond`; a Python int compiles only those); per-drone ticks compute every loop.

    The batch axes ``[...]`` are those of ``setpoint.mode`` less its last; ``cstate`` and ``state`` have them too,
    ``gains`` none (one set for every drone).

    Returns:
        (the new `PidControllerState`, the `Control` in the legacy mode: roll, pitch, yaw in int16 PWM units and the
        thrust, for `jaxdrones.control.firmware.power_distribution_legacy`).
    """
    batch = setpoint.mode.shape[:-1]
    tick = tick if isinstance(tick, int | np.integer) else jnp.asarray(tick, jnp.int32)
    if isinstance(tick, int | np.integer) or tick.ndim == 0:  # one tick for every drone: each loop runs or not
        return _controller_pid_batch(gains, cstate, setpoint, state, tick, len(batch))
    step = _controller_pid_one
    for _ in batch:
        step = jax.vmap(step, in_axes=(None, 0, 0, 0, 0))
    return step(gains, cstate, setpoint, state, jnp.broadcast_to(tick, batch))


def batch_stage(stage: Callable, n_batch: int, in_axes: tuple = (None, 0, 0, 0)) -> Callable:
    """``stage`` (a stage of the cascade, written for one drone) vmapped over ``n_batch`` leading axes; by default
    its arguments are (gains, shared; the controller's state, the setpoint, the firmware's state)."""
    for _ in range(n_batch):
        stage = jax.vmap(stage, in_axes=in_axes)
    return stage


def _controller_pid_batch(gains, cstate, setpoint, state, tick, n_batch: int):
    """`controller_pid` with one tick for the whole batch: each stage vmapped over the batch's ``n_batch`` axes,
    the loops that do not run on the tick skipped (a Python int: not compiled; a traced scalar: `jax.lax.cond`)."""

    def batched(stage):
        stage = batch_stage(stage, n_batch)
        return lambda c: stage(gains, c, setpoint, state)

    changed = jnp.any(setpoint.mode != cstate.previous_mode)  # rare: the resets run only when a drone needs one
    cstate = jax.lax.cond(changed, batched(_mode_stage), lambda c: c, cstate)
    cstate = every(ATTITUDE_PERIOD, tick, lambda: batched(_yaw_stage)(cstate), cstate)
    cstate = every(POSITION_PERIOD, tick, lambda: batched(_position_stage)(cstate), cstate)
    cstate = every(ATTITUDE_PERIOD, tick, lambda: batched(_attitude_loops)(cstate), cstate)
    finish = batch_stage(_finish_stage, n_batch, in_axes=(0, 0))

    def running(c):
        control = c.control.replace(thrust=c.actuator_thrust)
        return c.replace(control=control), control

    return jax.lax.cond(jnp.any(cstate.actuator_thrust == 0), lambda c: finish(c, state), running, cstate)


def _controller_pid_one(
    gains: PidControllerGains,
    cstate: PidControllerState,
    setpoint: Setpoint,
    state: FirmwareState,
    tick: jax.Array,
) -> tuple[PidControllerState, Control]:
    """`controller_pid` for one drone (no leading axes) at its own tick: every loop computed, its result kept where
    it runs."""
    cstate = _mode_stage(gains, cstate, setpoint, state)
    attitude_tick = tick % ATTITUDE_PERIOD == 0
    position_tick = tick % POSITION_PERIOD == 0
    cstate = select(attitude_tick, _yaw_stage(gains, cstate, setpoint, state), cstate)
    cstate = select(position_tick, _position_stage(gains, cstate, setpoint, state), cstate)
    cstate = select(attitude_tick, _attitude_loops(gains, cstate, setpoint, state), cstate)
    return _finish_stage(cstate, state)


def _mode_stage(gains, cstate: PidControllerState, setpoint: Setpoint, state: FirmwareState) -> PidControllerState:
    """The first step of ``controllerPid``: a setpoint mode other than the last tick's resets the PIDs."""
    changed = jnp.any(setpoint.mode != cstate.previous_mode, axis=-1)
    cstate = select(changed, _reinitialize(cstate, state), cstate)
    return cstate.replace(previous_mode=jnp.broadcast_to(setpoint.mode, cstate.previous_mode.shape))


def _yaw_stage(gains, cstate: PidControllerState, setpoint: Setpoint, state: FirmwareState) -> PidControllerState:
    """The attitude tick's desired yaw."""
    yaw = _yaw_setpoint(gains, cstate, setpoint, state)
    return cstate.replace(attitude_desired=cstate.attitude_desired.at[..., 2].set(yaw))


def _position_stage(gains, cstate: PidControllerState, setpoint: Setpoint, state: FirmwareState) -> PidControllerState:
    """The position tick: the position and velocity loops set the thrust and the desired roll and pitch."""
    position, velocity, thrust, roll, pitch = _position_loops(gains, cstate, setpoint, state)
    return cstate.replace(
        position=position,
        velocity=velocity,
        actuator_thrust=thrust,
        attitude_desired=cstate.attitude_desired.at[..., 0].set(roll).at[..., 1].set(pitch),
    )


def _finish_stage(cstate: PidControllerState, state: FirmwareState) -> tuple[PidControllerState, Control]:
    """ControllerPid's last step: the control's thrust, and at zero thrust no torque and the PIDs reset."""
    control = cstate.control.replace(thrust=cstate.actuator_thrust)
    off = control.thrust == 0
    zero = Control(
        roll=jnp.zeros_like(control.roll),
        pitch=jnp.zeros_like(control.pitch),
        yaw=jnp.zeros_like(control.yaw),
        thrust=control.thrust,
    )
    control = select(off, zero, control)
    reset = _reinitialize(cstate, state)
    reset = reset.replace(attitude_desired=reset.attitude_desired.at[..., 2].set(state.attitude[..., 2]))
    cstate = select(off, reset, cstate).replace(control=control)
    return cstate, control


def _attitude_loops(gains, cstate: PidControllerState, setpoint: Setpoint, state: FirmwareState) -> PidControllerState:
    """The attitude tick after the position loop (controllerPid's third block): the manual thrust and attitude, the
    attitude PID, the rate setpoints, the rate PID and the int16 outputs (yaw negated)."""
    thrust = jnp.where(setpoint.mode[..., 2] == MODE_DISABLE, setpoint.thrust, cstate.actuator_thrust)
    manual = (setpoint.mode[..., 0] == MODE_DISABLE) | (setpoint.mode[..., 1] == MODE_DISABLE)
    desired = jnp.where(
        manual[..., None], cstate.attitude_desired.at[..., :2].set(setpoint.attitude[..., :2]), cstate.attitude_desired
    )
    attitude, rate_desired = _pid.pid_update(
        gains.attitude, cstate.attitude, desired, state.attitude, is_yaw=np.array([False, False, True])
    )
    rates = setpoint.mode[..., 3:5] == MODE_VELOCITY
    rate_desired = rate_desired.at[..., :2].set(
        jnp.where(rates, setpoint.attitude_rate[..., :2], rate_desired[..., :2])
    )
    gyro = state.gyro * jnp.array([1.0, -1.0, 1.0], jnp.float32)
    rate, out = _pid.pid_update(gains.rate, cstate.rate, rate_desired, gyro)
    out = saturate_int16(out)
    return cstate.replace(
        actuator_thrust=thrust,
        attitude_desired=desired,
        attitude=attitude,
        rate=rate,
        rate_desired=rate_desired,
        control=Control(roll=out[..., 0], pitch=out[..., 1], yaw=-out[..., 2], thrust=cstate.control.thrust),
    )
