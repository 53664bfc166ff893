"""The firmware's PID cascade in the loop with jaxdrones' physics, one firmware tick (1 ms) at a time.

Each tick does what the firmware's stabilizer loop does between two of its ticks: the controller reads the state
(`firmware_state`: a perfect estimator), its control goes through the power distribution and the cap to the motors'
commands, the motor map turns them into speeds (`motor_rpm`), and the physics advances 1 ms at those speeds. The
physics step must advance 1 ms per call: ``jaxdrones.make_step(SimConfig(sim_freq=1000, ctrl_freq=1000))``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jaxdrones.control.firmware.controller_pid import (
    RATE_MAIN_LOOP,
    PidControllerGains,
    PidControllerState,
    controller_pid,
    controller_pid_init,
)
from jaxdrones.control.firmware.motors import motor_rpm
from jaxdrones.control.firmware.power import power_distribution_cap, power_distribution_legacy
from jaxdrones.control.firmware.types import Setpoint, firmware_state
from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.state import DroneState
from jaxdrones.physics.step import StepFn


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
    step: StepFn, params: DroneParams, gains: PidControllerGains, loop: PidLoopState, setpoint: Setpoint
) -> tuple[PidLoopState, jax.Array]:
    """One firmware tick of the PID cascade driving the physics.

    Args:
        step: a physics step of 1 ms (see the module's docstring).
        params: `DroneParams` of the drones.
        gains: `PidControllerGains` (`PidControllerGains.crazyflie`).
        loop: `PidLoopState` ``[..., D]``.
        setpoint: `Setpoint` ``[..., D]``.

    Returns:
        (the loop after the tick, the motors' commands i32[..., D, 4] in PWM units).

    Raises:
        ValueError: a ``step`` of a `SimConfig` whose step is not 1 ms (`check_tick_step`).
    """
    check_tick_step(step)
    controller, control = controller_pid(gains, loop.controller, setpoint, firmware_state(loop.drone), loop.tick)
    pwm = power_distribution_cap(power_distribution_legacy(control))
    drone = step(params, loop.drone, motor_rpm(params, pwm))
    return PidLoopState(drone=drone, controller=controller, tick=loop.tick + 1), pwm
