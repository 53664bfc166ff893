"""gym-pybullet-drones' controllers."""

from jaxdrones.compat.gym_pybullet_drones.control.BaseControl import BaseControl
from jaxdrones.compat.gym_pybullet_drones.control.DSLPIDControl import DSLPIDControl

__all__ = ["BaseControl", "DSLPIDControl"]
