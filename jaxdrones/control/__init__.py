"""Controllers: the paper's DSL PID, its desired-velocity interface, the wrench mixer and a body-rate loop.

The mixer is the paper's DYN action conversion (exact NNLS); the body-rate loop serves collective thrust and body
rates commands.
"""

from jaxdrones.control.mixer import (
    RateGains,
    allocation_matrix,
    body_rate_control,
    body_rate_torque,
    mixer_matrix,
    nnls_rpm_squared,
    wrench_scale,
    wrench_to_rpm,
)
from jaxdrones.control.pid import (
    PIDGains,
    PIDInfo,
    PIDState,
    pid_compute,
    pid_control,
    pid_init,
    speed_limit,
    velocity_control,
    velocity_targets,
)

__all__ = [
    "PIDGains",
    "PIDInfo",
    "PIDState",
    "RateGains",
    "allocation_matrix",
    "body_rate_control",
    "body_rate_torque",
    "mixer_matrix",
    "nnls_rpm_squared",
    "pid_compute",
    "pid_control",
    "pid_init",
    "speed_limit",
    "velocity_control",
    "velocity_targets",
    "wrench_scale",
    "wrench_to_rpm",
]
