"""The Crazyflie firmware's controllers as pure JAX functions, batched over any leading axes (e.g. ``[W, D]``).

Re-implemented from bitcraze/crazyflie-firmware at 2a18fc29 (each module cites the file it follows) and checked against
the firmware's own C through its Python bindings (tests/test_firmware.py): the default PID cascade (`controller_pid`,
one call per 1 kHz tick), the Mellinger controller (`controller_mellinger`), the Brescianini controller
(`controller_brescianini`), the quadrotor power distribution
(`power_distribution_legacy`, `power_distribution_force_torque`, `power_distribution_cap`) and the Crazyflie 2.1's motor
map (`motor_thrust`, `motor_rpm`), with the firmware's state, setpoint and control types (`Setpoint`, `FirmwareState`,
`Control`) and `firmware_state`, the firmware's view of a `DroneState`. `pid_tick` runs the cascade in the loop with the
physics, one 1 ms tick per call; `pid_ticks` many ticks per call, its loops' schedule written into the program.
"""

from jaxdrones.control.firmware.brescianini import (
    BrescianiniGains,
    BrescianiniState,
    ForceTorque,
    brescianini_init,
    controller_brescianini,
)
from jaxdrones.control.firmware.controller_pid import (
    ATTITUDE_RATE,
    POSITION_RATE,
    RATE_MAIN_LOOP,
    PidControllerGains,
    PidControllerState,
    controller_pid,
    controller_pid_init,
)
from jaxdrones.control.firmware.loop import (
    PidLoopState,
    check_tick_step,
    pid_loop_init,
    pid_schedule,
    pid_tick,
    pid_ticks,
)
from jaxdrones.control.firmware.mellinger import MellingerGains, MellingerState, controller_mellinger, mellinger_init
from jaxdrones.control.firmware.motors import CRAZYFLIE_MOTOR_TAU, THRUST_MIN, motor_rpm, motor_thrust
from jaxdrones.control.firmware.pid import PidGains, PidState, pid_update
from jaxdrones.control.firmware.power import (
    power_distribution_cap,
    power_distribution_force_torque,
    power_distribution_legacy,
)
from jaxdrones.control.firmware.types import (
    MODE_ABS,
    MODE_DISABLE,
    MODE_VELOCITY,
    Control,
    FirmwareState,
    Setpoint,
    firmware_state,
)

__all__ = [
    "BrescianiniGains",
    "BrescianiniState",
    "ForceTorque",
    "brescianini_init",
    "controller_brescianini",
    "ATTITUDE_RATE",
    "CRAZYFLIE_MOTOR_TAU",
    "MODE_ABS",
    "MODE_DISABLE",
    "MODE_VELOCITY",
    "POSITION_RATE",
    "RATE_MAIN_LOOP",
    "THRUST_MIN",
    "Control",
    "MellingerGains",
    "MellingerState",
    "FirmwareState",
    "PidControllerGains",
    "PidControllerState",
    "PidGains",
    "PidLoopState",
    "PidState",
    "Setpoint",
    "check_tick_step",
    "controller_mellinger",
    "controller_pid",
    "controller_pid_init",
    "firmware_state",
    "mellinger_init",
    "motor_rpm",
    "motor_thrust",
    "pid_loop_init",
    "pid_schedule",
    "pid_tick",
    "pid_ticks",
    "pid_update",
    "power_distribution_cap",
    "power_distribution_force_torque",
    "power_distribution_legacy",
]
