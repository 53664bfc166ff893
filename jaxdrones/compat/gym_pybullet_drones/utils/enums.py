"""gym-pybullet-drones' enums (``gym_pybullet_drones/utils/enums.py``), with the same members and values."""

from __future__ import annotations

from enum import Enum


class DroneModel(Enum):
    """Drone models: the value is the URDF's name in ``jaxdrones/assets`` (`jaxdrones.physics.params.MODELS`)."""

    CF2X = "cf2x"  # Crazyflie 2.x, X configuration
    CF2P = "cf2p"  # Crazyflie 2.x, + configuration
    RACE = "racer"  # a racer, X configuration


class Physics(Enum):
    """Physics updates. Every member runs the paper's explicit update (the original's ``DYN``) on the JAX core,
    with the aerodynamics its name gives; ``PYB`` members are not PyBullet's own integrator there (pass
    ``backend="pybullet"`` to an aviary for PyBullet's, with collisions)."""

    PYB = "pyb"
    DYN = "dyn"
    PYB_GND = "pyb_gnd"
    PYB_DRAG = "pyb_drag"
    PYB_DW = "pyb_dw"
    PYB_GND_DRAG_DW = "pyb_gnd_drag_dw"


class ImageType(Enum):
    """Camera image types."""

    RGB = 0
    DEP = 1
    SEG = 2
    BW = 3


class ActionType(Enum):
    """RL action types; the value is `jaxdrones.envs.actions`' name of the same mapping."""

    RPM = "rpm"
    PID = "pid"
    VEL = "vel"
    ONE_D_RPM = "one_d_rpm"
    ONE_D_PID = "one_d_pid"


class ObservationType(Enum):
    """RL observation types (``RGB``: see `jaxdrones.make`'s ``vision`` for cameras)."""

    KIN = "kin"
    RGB = "rgb"


#: The aerodynamic effects of each `Physics` member: (drag, ground_effect, downwash).
PHYSICS_EFFECTS = {
    Physics.PYB: (False, False, False),
    Physics.DYN: (False, False, False),
    Physics.PYB_GND: (False, True, False),
    Physics.PYB_DRAG: (True, False, False),
    Physics.PYB_DW: (False, False, True),
    Physics.PYB_GND_DRAG_DW: (True, True, True),
}
