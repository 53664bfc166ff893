"""gym-pybullet-drones' ``HoverAviary``: one drone to hover at (0, 0, 1) m."""

from __future__ import annotations

import numpy as np

from jaxdrones.compat.gym_pybullet_drones.envs.BaseRLAviary import BaseRLAviary
from jaxdrones.compat.gym_pybullet_drones.utils.enums import ActionType, DroneModel, ObservationType, Physics


class HoverAviary(BaseRLAviary):
    """Single-agent hover, as the original on main: target ``TARGET_POS`` = (0, 0, 1) m, ``EPISODE_LEN_SEC`` = 8.

    * reward max(0, 2 − ‖target − pos‖⁴) per step (at most 2);
    * terminated when the drone is within 0.1 mm of the target;
    * truncated when |x| > 1.5 m, |y| > 1.5 m, z > 2 m, |roll| > 0.4 rad or |pitch| > 0.4 rad, or when the time
      before the step exceeds 8 s (so an episode lasts 242 steps at 30 Hz);
    * info ``{"answer": 42}``.

    Observation f32[1, 12 + 15·size] at 30 Hz and action f32[1, size] (see `BaseRLAviary`); arguments those of
    `BaseRLAviary` without ``num_drones`` and ``neighbourhood_radius`` (defaults: ``ctrl_freq=30``,
    ``act=ActionType.RPM``).
    """

    def __init__(
        self,
        drone_model: DroneModel = DroneModel.CF2X,
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
        self.TARGET_POS = np.array([0, 0, 1])
        self.EPISODE_LEN_SEC = 8
        super().__init__(
            drone_model=drone_model,
            num_drones=1,
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

    def _computeReward(self):
        return max(0.0, 2.0 - float(np.linalg.norm(self.TARGET_POS - self.pos[0])) ** 4)

    def _computeTerminated(self):
        return bool(np.linalg.norm(self.TARGET_POS - self.pos[0]) < 0.0001)

    def _computeTruncated(self):
        (x, y, z), (roll, pitch, _) = self.pos[0], self.rpy[0]
        if abs(x) > 1.5 or abs(y) > 1.5 or z > 2.0 or abs(roll) > 0.4 or abs(pitch) > 0.4:
            return True
        return bool(self.step_counter / self.PYB_FREQ > self.EPISODE_LEN_SEC)

    def _computeInfo(self):
        return {"answer": 42}
