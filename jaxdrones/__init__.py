"""jaxdrones: a JAX-vectorised, differentiable quadrotor simulator with the physics of gym-pybullet-drones."""

from jaxdrones import _fork  # noqa: F401  (refuse forked processes instead of hanging)
from jaxdrones.envs import make
from jaxdrones.envs.realism import Realism
from jaxdrones.physics.params import MODELS, DroneParams, load_params
from jaxdrones.physics.state import Disturbance, DroneState, init_state
from jaxdrones.scene import Obstacle
from jaxdrones.sim import SimConfig, make_step, rollout

__all__ = [
    "MODELS",
    "make",
    "Disturbance",
    "DroneParams",
    "DroneState",
    "Obstacle",
    "Realism",
    "SimConfig",
    "init_state",
    "load_params",
    "make_step",
    "rollout",
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


#: The modules that moved into a subpackage, by subpackage: their old paths keep importing (``import
#: jaxdrones.dynamics``, ``from jaxdrones.params import load_params``, and the pickles of runs that name them).
_MOVED = {
    "physics": ("adjoint", "aerodynamics", "checks", "config", "dynamics", "kinks", "neighbors", "params",
                "rotations", "state"),
    "io": ("plotting", "runs", "video"),
    "envs": ("realism",),
}  # fmt: skip
#: Every old path (relative to the package) and the module's path now: `_MOVED`'s, and the modules that moved from
#: one subpackage to another.
_OLD_PATHS = {
    **{name: f"{package}.{name}" for package, names in _MOVED.items() for name in names},
    "physics.realism": "envs.realism",
}


def _alias_moved_modules() -> None:
    """Bind each moved module under its old path too (``import jaxdrones.<name>`` runs this file first)."""
    import importlib
    import sys

    for old, new in _OLD_PATHS.items():
        module = importlib.import_module(f"{__name__}.{new}")
        sys.modules[f"{__name__}.{old}"] = module
        parent, _, name = old.rpartition(".")
        setattr(importlib.import_module(f"{__name__}.{parent}" if parent else __name__), name, module)


_alias_moved_modules()
