"""The firmware's PID cascade in the loop with jaxdrones' physics, one firmware tick (1 ms) at a time.

Each tick does what the firmware's stabilizer loop does between two of its ticks: the controller reads the state
(`firmware_state`: a perfect estimator), its control goes through the power distribution and the cap to the motors'
commands, the motor map turns them into speeds (`motor_rpm`), and the physics advances 1 ms at those speeds. The
physics step must advance 1 ms per call: ``jaxdrones.make_step(SimConfig(sim_freq=1000, ctrl_freq=1000))``.

`pid_tick` runs one tick; `pid_ticks` runs many with one setpoint, the firmware's schedule of loops written into the
program (which loop runs on which tick, for a loop that starts on a multiple of 10 ticks) rather than decided tick by
tick: the same results at about twice the speed on 2 CPU cores and 13 times on a GPU (docs/benchmarks.md, "The
firmware's PID in the loop").
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones.control.firmware.controller_pid import (
    ATTITUDE_PERIOD,
    POSITION_PERIOD,
    RATE_MAIN_LOOP,
    PidControllerGains,
    PidControllerState,
    _attitude_loops,
    _mode_stage,
    _position_stage,
    _yaw_stage,
    batch_stage,
    controller_pid,
    controller_pid_init,
)
from jaxdrones.control.firmware.motors import motor_rpm
from jaxdrones.control.firmware.power import power_distribution_cap, power_distribution_legacy
from jaxdrones.control.firmware.types import MODE_DISABLE, Control, Setpoint, firmware_state
from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.state import Disturbance, DroneState
from jaxdrones.physics.step import JaxStep, StepFn


@struct.dataclass
class PidLoopState:
    """The drones, their controllers' memory and the firmware's tick.

    Attributes:
        drone: `DroneState` ``[..., D]``.
        controller: `PidControllerState` ``[..., D]``.
        tick: i32[], the next tick's number (the stabilizer's ``stabilizerStep``).
    """

    drone: DroneState
    controller: PidControllerState
    tick: jax.Array


def check_tick_step(step: StepFn) -> None:
    """Raise ``ValueError`` unless ``step`` (a `jaxdrones.make_step` step, whose ``config`` is its `SimConfig`)
    advances one firmware tick, 1 ms: ``sim_freq`` and ``ctrl_freq`` 1000. A step without a ``config`` is taken as
    the caller says."""
    config = getattr(step, "config", None)
    if config is not None and (config.sim_freq, config.ctrl_freq) != (RATE_MAIN_LOOP, RATE_MAIN_LOOP):
        raise ValueError(
            f"the firmware's loop needs a physics step of one 1 ms tick: SimConfig(sim_freq={RATE_MAIN_LOOP}, "
            f"ctrl_freq={RATE_MAIN_LOOP}, ...), got sim_freq={config.sim_freq}, ctrl_freq={config.ctrl_freq}"
        )


def pid_loop_init(drone: DroneState, tick: int = 0) -> PidLoopState:
    """The loop at ``drone`` with fresh controllers (`controller_pid_init`), starting at ``tick``."""
    return PidLoopState(drone=drone, controller=controller_pid_init(drone.pos.shape[:-1]), tick=jnp.int32(tick))


def pid_tick(
    step: StepFn,
    params: DroneParams,
    gains: PidControllerGains,
    loop: PidLoopState,
    setpoint: Setpoint,
    disturbance: Disturbance | None = None,
) -> tuple[PidLoopState, jax.Array]:
    """One firmware tick of the PID cascade driving the physics.

    Args:
        step: a physics step of 1 ms (see the module's docstring).
        params: `DroneParams` of the drones.
        gains: `PidControllerGains` (`PidControllerGains.crazyflie`).
        loop: `PidLoopState` ``[..., D]``.
        setpoint: `Setpoint` ``[..., D]``.
        disturbance: a `jaxdrones.physics.state.Disturbance` held over the tick (None: none).

    Returns:
        (the loop after the tick, the motors' commands i32[..., D, 4] in PWM units).

    Raises:
        ValueError: a ``step`` of a `SimConfig` whose step is not 1 ms (`check_tick_step`).
    """
    check_tick_step(step)
    controller, control = controller_pid(gains, loop.controller, setpoint, firmware_state(loop.drone), loop.tick)
    pwm = _motors(control)
    drone = step(params, loop.drone, motor_rpm(params, pwm), disturbance)
    return PidLoopState(drone=drone, controller=controller, tick=loop.tick + 1), pwm


def _motors(control: Control) -> jax.Array:
    """The motors' commands i32[..., 4] of a `Control`: the legacy power distribution and its cap."""
    return power_distribution_cap(power_distribution_legacy(control))


def pid_ticks(
    step: StepFn,
    params: DroneParams,
    gains: PidControllerGains,
    loop: PidLoopState,
    setpoint: Setpoint,
    ticks: int,
    disturbance: Disturbance | None = None,
) -> tuple[PidLoopState, jax.Array]:
    """``ticks`` firmware ticks of the PID cascade driving the physics with one setpoint: the loop after ``ticks``
    calls of `pid_tick`.

    Where the loop starts on a multiple of `POSITION_PERIOD` ticks, ``ticks`` is one too, and every drone's thrust is
    sure to stay above 0 (z controlled with a positive ``gains.thrust_min``, or z modeDisable with a positive manual
    thrust), the firmware's reset at zero thrust cannot happen and the schedule of its loops is known when the
    program is traced:
    `pid_schedule` runs them without deciding anything per tick. Elsewhere (a `jax.lax.cond`, once per call) it is
    a scan of `pid_tick`. Both give `pid_tick`'s results (to float32 rounding: XLA may fuse the arithmetic
    differently). Under `jax.vmap` over worlds with a per-world ``loop.tick``, the ``cond`` computes both: call
    `pid_schedule` where the start is known to be on the schedule (as `jaxdrones.envs` does).

    Args:
        step: a physics step of 1 ms (`check_tick_step`), called as ``step(params, drone, rpm, disturbance)``.
        params: `DroneParams` of the drones.
        gains: `PidControllerGains`.
        loop: `PidLoopState` ``[..., D]``.
        setpoint: `Setpoint` ``[..., D]``, held for every tick.
        ticks: how many ticks, ≥ 1 (a Python int).
        disturbance: a `jaxdrones.physics.state.Disturbance` held over every tick (None: none).

    Returns:
        (the loop after the ticks, the motors' commands of the last tick i32[..., D, 4] in PWM units).

    Raises:
        ValueError: ``ticks`` not a positive int, or a ``step`` not of 1 ms.
    """
    check_tick_step(step)
    if isinstance(ticks, bool) or not isinstance(ticks, int | np.integer) or ticks < 1:
        raise ValueError(f"pid_ticks: ticks must be a positive int, got {ticks!r}")
    ticks = int(ticks)

    def general(loop):
        pwm = jnp.zeros(loop.drone.rpm.shape, jnp.int32)

        def one(carry, _):
            return pid_tick(step, params, gains, carry[0], setpoint, disturbance), None

        return jax.lax.scan(one, (loop, pwm), None, length=ticks)[0]

    if ticks % POSITION_PERIOD:
        return general(loop)

    def scheduled(loop):
        drone, controller, pwm = pid_schedule(
            step, params, gains, loop.drone, loop.controller, setpoint, ticks, disturbance
        )
        return PidLoopState(drone=drone, controller=controller, tick=loop.tick + ticks), pwm

    manual = setpoint.mode[..., 2] == MODE_DISABLE
    thrust_above_0 = jnp.where(manual, setpoint.thrust > 0, gains.thrust_min > 0)
    on_schedule = (loop.tick % POSITION_PERIOD == 0) & jnp.all(thrust_above_0)
    return jax.lax.cond(on_schedule, scheduled, general, loop)


def pid_schedule(
    step: StepFn,
    params: DroneParams,
    gains: PidControllerGains,
    drone: DroneState,
    controller: PidControllerState,
    setpoint: Setpoint,
    ticks: int,
    disturbance: Disturbance | None = None,
) -> tuple[DroneState, PidControllerState, jax.Array]:
    """`pid_ticks` from a tick that is a multiple of `POSITION_PERIOD`, with the loops of each tick chosen when the
    program is traced: per `POSITION_PERIOD` ticks, the position loop once, then five times the attitude and rate
    loops followed by two ticks of physics at the motors' commands they set (the firmware's odd ticks change nothing
    but the physics; the JAX core's two substeps in one call). The caller vouches for what `pid_ticks` checks: the
    start on the schedule, ``ticks`` a multiple of `POSITION_PERIOD`, and a thrust that stays above 0 (z controlled
    with ``gains.thrust_min`` > 0, or a positive manual thrust; at zero thrust the firmware resets its PIDs, and this
    path does not).

    Args and raises: see `pid_ticks` (``drone`` and ``controller`` the loop's); ``ticks`` must be a positive
    multiple of `POSITION_PERIOD`.

    Returns:
        (the drones after the ticks, the controller's state, the motors' commands of the last tick i32[..., D, 4]).
    """
    if isinstance(ticks, bool) or not isinstance(ticks, int | np.integer) or ticks < 1 or ticks % POSITION_PERIOD:
        raise ValueError(f"pid_schedule: ticks must be a positive multiple of {POSITION_PERIOD}, got {ticks!r}")
    n_batch = setpoint.mode.ndim - 1
    stages = {
        name: batch_stage(stage, n_batch)
        for name, stage in (
            ("mode", _mode_stage),
            ("yaw", _yaw_stage),
            ("position", _position_stage),
            ("attitude", _attitude_loops),
        )
    }
    hold, calls = _held_step(step)
    # The setpoint is held: only the first tick can see a change of mode (controllerPid's reset).
    controller = stages["mode"](gains, controller, setpoint, firmware_state(drone))

    def attitude_tick(carry, position: bool):
        drone, controller = carry
        state = firmware_state(drone)
        controller = stages["yaw"](gains, controller, setpoint, state)
        if position:
            controller = stages["position"](gains, controller, setpoint, state)
        controller = stages["attitude"](gains, controller, setpoint, state)
        control = controller.control.replace(thrust=controller.actuator_thrust)
        controller = controller.replace(control=control)
        pwm = _motors(control)
        rpm = motor_rpm(params, pwm)
        for _ in range(calls):  # the attitude tick and the ticks that hold its control
            drone = hold(params, drone, rpm, disturbance)
        return (drone, controller), pwm

    def block(carry, _):
        for k in range(_ATTITUDE_TICKS):
            carry, pwm = attitude_tick(carry, k == 0)
        return carry, pwm

    (drone, controller), pwm = jax.lax.scan(block, (drone, controller), None, length=ticks // POSITION_PERIOD)
    return drone, controller, pwm[-1]


def _held_step(step: StepFn) -> tuple[StepFn, int]:
    """(a physics step, calls of it) that advance `ATTITUDE_PERIOD` ticks at one command: the JAX core's step of that
    many substeps for a JAX core's 1 ms step (one call: 1.2 times the loop's speed on 2 CPU cores, docs/benchmarks.md,
    "The firmware's PID in the loop"), else ``step`` that many times."""
    config = getattr(step, "config", None)
    if isinstance(step, JaxStep) and config.ctrl_freq == config.sim_freq:
        return JaxStep(dataclasses.replace(config, ctrl_freq=config.sim_freq // ATTITUDE_PERIOD)), 1
    return step, ATTITUDE_PERIOD


#: Attitude ticks per position tick.
_ATTITUDE_TICKS = POSITION_PERIOD // ATTITUDE_PERIOD
