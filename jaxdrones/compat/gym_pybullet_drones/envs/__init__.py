"""gym-pybullet-drones' aviaries on the jaxdrones physics."""

from jaxdrones.compat.gym_pybullet_drones.envs.BaseAviary import BaseAviary
from jaxdrones.compat.gym_pybullet_drones.envs.BaseRLAviary import BaseRLAviary
from jaxdrones.compat.gym_pybullet_drones.envs.CtrlAviary import CtrlAviary
from jaxdrones.compat.gym_pybullet_drones.envs.HoverAviary import HoverAviary
from jaxdrones.compat.gym_pybullet_drones.envs.MultiHoverAviary import MultiHoverAviary

__all__ = ["BaseAviary", "BaseRLAviary", "CtrlAviary", "HoverAviary", "MultiHoverAviary"]
