"""Controllers: the paper's DSL PID (position/attitude cascade) and its desired-velocity interface."""

from jaxdrones.control.pid import (
    PIDGains,
    PIDInfo,
    PIDState,
    mixer_matrix,
    pid_compute,
    pid_control,
    pid_init,
    speed_limit,
    velocity_control,
    velocity_targets,
)

__all__ = [
    "PIDGains", "PIDInfo", "PIDState", "mixer_matrix", "pid_compute", "pid_control", "pid_init", "speed_limit",
    "velocity_control", "velocity_targets",
]
