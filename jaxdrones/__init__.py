"""jaxdrones: a JAX-vectorised, differentiable quadrotor simulator with the physics of gym-pybullet-drones."""

from jaxdrones.envs import make
from jaxdrones.params import MODELS, DroneParams, load_params
from jaxdrones.sim import SimConfig, make_step, rollout
from jaxdrones.state import DroneState, init_state

__all__ = [
    "MODELS", "make", "DroneParams", "DroneState", "SimConfig", "init_state", "load_params", "make_step", "rollout",
]
__version__ = "0.1.0"


def _register_gymnasium() -> None:
    try:
        from jaxdrones.adapters import gymnasium as _gym
    except ImportError:  # gymnasium is a dependency, but keep the core importable without it
        return
    _gym.register()


_register_gymnasium()
