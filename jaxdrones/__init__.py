"""jaxdrones: a JAX-vectorised, differentiable quadrotor simulator with the physics of gym-pybullet-drones."""

from jaxdrones import _fork  # noqa: F401  (refuse forked processes instead of hanging)
from jaxdrones.envs import make
from jaxdrones.params import MODELS, DroneParams, load_params
from jaxdrones.realism import Realism
from jaxdrones.scene import Obstacle
from jaxdrones.sim import SimConfig, make_step, rollout
from jaxdrones.state import Disturbance, DroneState, init_state

__all__ = [
    "MODELS", "make", "Disturbance", "DroneParams", "DroneState", "Obstacle", "Realism", "SimConfig", "init_state",
    "load_params", "make_step", "rollout",
]
__version__ = "0.1.0"


def _register_gymnasium() -> None:
    try:
        import gymnasium  # noqa: F401
    except ModuleNotFoundError as e:  # a dependency, but the core stays importable without it
        if e.name != "gymnasium":
            raise
        return
    from jaxdrones.adapters import gymnasium as _gym

    _gym.register()


_register_gymnasium()
