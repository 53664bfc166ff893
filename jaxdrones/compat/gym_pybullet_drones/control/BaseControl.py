"""gym-pybullet-drones' ``BaseControl``: the controllers' interface (``computeControlFromState``)."""

from __future__ import annotations

import abc

import numpy as np

from jaxdrones.compat.gym_pybullet_drones._common import KeywordHints
from jaxdrones.compat.gym_pybullet_drones.utils.enums import DroneModel
from jaxdrones.physics.params import load_params


class BaseControl(KeywordHints, metaclass=abc.ABCMeta):
    """A controller of one drone of ``drone_model``: `computeControl` (per subclass) maps the drone's state and a
    target to four motor speeds, RPM.

    Attributes:
        DRONE_MODEL: the `DroneModel`.
        GRAVITY: m·g, N (``g`` m/s², the mass from the model's URDF).
        KF, KM: the thrust and torque coefficients of the URDF (N/RPM², N·m/RPM²).
        control_counter: calls since the last `reset`.
    """

    def __init__(self, drone_model: DroneModel, g: float = 9.8):
        self.DRONE_MODEL = DroneModel(drone_model)
        self._params = load_params(self.DRONE_MODEL.value)
        self.GRAVITY = g * float(self._params.mass)
        self.KF = float(self._params.kf)
        self.KM = float(self._params.km)
        self.reset()

    def reset(self) -> None:
        """Zero the call counter (subclasses also zero their memory)."""
        self.control_counter = 0

    def computeControlFromState(
        self,
        control_timestep,
        state,
        target_pos,
        target_rpy=np.zeros(3),  # noqa: B008
        target_vel=np.zeros(3),
        target_rpy_rates=np.zeros(3),
    ):  # noqa: B008
        """`computeControl` from a 20-entry state vector (the aviaries' observation row: pos 0:3, quat 3:7, vel
        10:13, angular velocity 13:16)."""
        state = np.asarray(state)
        return self.computeControl(
            control_timestep=control_timestep,
            cur_pos=state[0:3],
            cur_quat=state[3:7],
            cur_vel=state[10:13],
            cur_ang_vel=state[13:16],
            target_pos=target_pos,
            target_rpy=target_rpy,
            target_vel=target_vel,
            target_rpy_rates=target_rpy_rates,
        )

    @abc.abstractmethod
    def computeControl(
        self,
        control_timestep,
        cur_pos,
        cur_quat,
        cur_vel,
        cur_ang_vel,
        target_pos,
        target_rpy=np.zeros(3),
        target_vel=np.zeros(3),
        target_rpy_rates=np.zeros(3),
    ):  # noqa: B008
        """(rpm f[4], ...) for one drone; each controller defines it."""
