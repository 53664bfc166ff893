"""gym-pybullet-drones' interface on the jaxdrones physics: the original's classes, keyword names, constants,
observation layout, rewards and ``info``, under its module paths, so that a script written for it runs with its
imports changed from ``gym_pybullet_drones`` to ``jaxdrones.compat.gym_pybullet_drones``::

    from jaxdrones.compat.gym_pybullet_drones.envs.HoverAviary import HoverAviary
    from jaxdrones.compat.gym_pybullet_drones.utils.enums import ActionType, ObservationType

    env = HoverAviary(obs=ObservationType.KIN, act=ActionType.ONE_D_RPM)   # obs f32[1, 27], action f32[1, 1]

Provided: `HoverAviary`, `MultiHoverAviary`, `CtrlAviary` (with `BaseAviary` and `BaseRLAviary` to subclass),
`DSLPIDControl`, `Logger`, `sync`, `str2bool`, and the enums `DroneModel`, `Physics`, `ActionType`,
`ObservationType`, `ImageType`. Importing this package registers the original's gymnasium ids
``hover-aviary-v0``, ``multihover-aviary-v0`` and ``ctrl-aviary-v0``. The first aviary or controller built turns
on JAX's persistent compilation cache unless one is set (`jaxdrones.io.runs.enable_compilation_cache`:
``~/.cache/jaxdrones/xla``, or ``$JAXDRONES_CACHE_DIR``), so that a script run again reads its compiled steps from
disk rather than compiling them (about 1 s). docs/migrating.md lists the differences, and how to move to
`jaxdrones.make`'s batched envs.
"""

import gymnasium as gym

from jaxdrones.compat.gym_pybullet_drones.control import BaseControl, DSLPIDControl
from jaxdrones.compat.gym_pybullet_drones.envs import (
    BaseAviary,
    BaseRLAviary,
    CtrlAviary,
    HoverAviary,
    MultiHoverAviary,
)
from jaxdrones.compat.gym_pybullet_drones.utils.enums import ActionType, DroneModel, ImageType, ObservationType, Physics
from jaxdrones.compat.gym_pybullet_drones.utils.Logger import Logger
from jaxdrones.compat.gym_pybullet_drones.utils.utils import str2bool, sync

__all__ = [
    "ActionType",
    "BaseAviary",
    "BaseControl",
    "BaseRLAviary",
    "CtrlAviary",
    "DSLPIDControl",
    "DroneModel",
    "HoverAviary",
    "ImageType",
    "Logger",
    "MultiHoverAviary",
    "ObservationType",
    "Physics",
    "str2bool",
    "sync",
]

for _id, _cls in (
    ("ctrl-aviary-v0", "CtrlAviary"),
    ("hover-aviary-v0", "HoverAviary"),
    ("multihover-aviary-v0", "MultiHoverAviary"),
):
    if _id not in gym.registry:
        gym.register(id=_id, entry_point=f"jaxdrones.compat.gym_pybullet_drones.envs:{_cls}")
