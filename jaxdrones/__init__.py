"""jaxdrones: a JAX-vectorised, differentiable quadrotor simulator with the physics of gym-pybullet-drones."""

from jaxdrones import _fork, _xla  # noqa: F401  (_fork: refuse forked processes instead of hanging)

_xla.configure()  # before any JAX computation: see jaxdrones/_xla.py

from jaxdrones.envs import make  # noqa: E402
from jaxdrones.params import MODELS, DroneParams, load_params  # noqa: E402
from jaxdrones.sim import SimConfig, make_step, rollout  # noqa: E402
from jaxdrones.state import DroneState, init_state  # noqa: E402

__all__ = [
    "MODELS", "make", "DroneParams", "DroneState", "SimConfig", "init_state", "load_params", "make_step", "rollout",
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
