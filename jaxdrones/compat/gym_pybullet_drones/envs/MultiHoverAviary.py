"""gym-pybullet-drones' ``MultiHoverAviary``: D drones, each to hover 1/(i + 1) m above its start."""

from __future__ import annotations

import numpy as np

from jaxdrones.compat.gym_pybullet_drones.envs.BaseRLAviary import BaseRLAviary
from jaxdrones.compat.gym_pybullet_drones.utils.enums import ActionType, DroneModel, ObservationType, Physics


class MultiHoverAviary(BaseRLAviary):
    """Multi-drone hover, as the original on main: drone i's target is ``INIT_XYZS[i] + (0, 0, 1/(i + 1))`` m
    (``TARGET_POS`` f[D, 3]), ``EPISODE_LEN_SEC`` = 8.

    * reward Σᵢ max(0, 2 − ‖targetᵢ − posᵢ‖⁴) per step (one number for the team, at most 2D);
    * terminated when the distances to the targets sum to less than 0.1 mm;
    * truncated when any drone has |x| > 2 m, |y| > 2 m, z > 2 m, |roll| > 0.4 rad or |pitch| > 0.4 rad, or when
      the time before the step exceeds 8 s;
    * info ``{"answer": 42}``.

    Observation f32[D, 12 + 15·size] at 30 Hz and action f32[D, size] (see `BaseRLAviary`); arguments those of
    `BaseRLAviary` (defaults ``num_drones=2``, ``ctrl_freq=30``, ``act=ActionType.RPM``).
    """

    def __init__(
        self,
        drone_model: DroneModel = DroneModel.CF2X,
        num_drones: int = 2,
        neighbourhood_radius: float = np.inf,
        initial_xyzs=None,
        initial_rpys=None,
        physics: Physics = Physics.PYB,
        pyb_freq: int = 240,
        ctrl_freq: int = 30,
        gui: bool = False,
        record: bool = False,
        obs: ObservationType = ObservationType.KIN,
        act: ActionType = ActionType.RPM,
        backend: str = "jax",
    ):
        self.EPISODE_LEN_SEC = 8
        super().__init__(
            drone_model=drone_model,
            num_drones=num_drones,
            neighbourhood_radius=neighbourhood_radius,
            initial_xyzs=initial_xyzs,
            initial_rpys=initial_rpys,
            physics=physics,
            pyb_freq=pyb_freq,
            ctrl_freq=ctrl_freq,
            gui=gui,
            record=record,
            obs=obs,
            act=act,
            backend=backend,
        )
        self.TARGET_POS = self.INIT_XYZS + np.array([[0, 0, 1 / (i + 1)] for i in range(num_drones)])

    def _computeReward(self):
        dist = np.linalg.norm(self.TARGET_POS - self.pos, axis=1)
        return float(np.sum(np.maximum(0.0, 2.0 - dist**4)))

    def _computeTerminated(self):
        return bool(np.sum(np.linalg.norm(self.TARGET_POS - self.pos, axis=1)) < 0.0001)

    def _computeTruncated(self):
        x, y, z = self.pos.T
        roll, pitch = self.rpy[:, 0], self.rpy[:, 1]
        if np.any((np.abs(x) > 2.0) | (np.abs(y) > 2.0) | (z > 2.0) | (np.abs(roll) > 0.4) | (np.abs(pitch) > 0.4)):
            return True
        return bool(self.step_counter / self.PYB_FREQ > self.EPISODE_LEN_SEC)

    def _computeInfo(self):
        return {"answer": 42}
