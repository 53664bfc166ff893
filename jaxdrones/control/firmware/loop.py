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
    """
    controller, control = controller_pid(gains, loop.controller, setpoint, firmware_state(loop.drone), loop.tick)
    pwm = power_distribution_cap(power_distribution_legacy(control))
    drone = step(params, loop.drone, motor_rpm(params, pwm))
    return PidLoopState(drone=drone, controller=controller, tick=loop.tick + 1), pwm
