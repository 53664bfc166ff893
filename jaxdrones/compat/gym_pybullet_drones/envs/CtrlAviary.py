"""gym-pybullet-drones' ``CtrlAviary``: D drones commanded in RPM, observed as 20-entry state vectors."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from jaxdrones.compat.gym_pybullet_drones.envs.BaseAviary import BaseAviary, action_array
from jaxdrones.compat.gym_pybullet_drones.utils.enums import DroneModel, Physics


class CtrlAviary(BaseAviary):
    """An aviary for control: action f[D, 4] RPM (clipped to [0, ``MAX_RPM``]), observation f64[D, 20] (the state
    vectors of `BaseAviary._getDroneStateVector`), reward -1, never terminated or truncated, info
    ``{"answer": 42}`` (the original's). Arguments: those of `BaseAviary`.

    Raises:
        ValueError: (``step``) an action that is not D × 4 numbers, or with NaN or inf.
    """

    def __init__(
        self,
        drone_model: DroneModel = DroneModel.CF2X,
        num_drones: int = 1,
        neighbourhood_radius: float = np.inf,
        initial_xyzs=None,
        initial_rpys=None,
        physics: Physics = Physics.PYB,
        pyb_freq: int = 240,
        ctrl_freq: int = 240,
        gui: bool = False,
        record: bool = False,
        obstacles: bool = False,
        user_debug_gui: bool = True,
        output_folder: str = "results",
        backend: str = "jax",
    ):
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
            obstacles=obstacles,
            user_debug_gui=user_debug_gui,
            output_folder=output_folder,
            backend=backend,
        )

    def _actionSpace(self):
        high = np.full((self.NUM_DRONES, 4), self.MAX_RPM, np.float32)
        return spaces.Box(low=np.zeros_like(high), high=high, dtype=np.float32)

    def _observationSpace(self):
        inf, pi, r = np.inf, np.pi, self.MAX_RPM
        low = [-inf, -inf, 0.0, -1, -1, -1, -1, -pi, -pi, -pi] + [-inf] * 6 + [0.0] * 4
        high = [inf, inf, inf, 1, 1, 1, 1, pi, pi, pi] + [inf] * 6 + [r] * 4
        return spaces.Box(
            low=np.tile(np.float32(low), (self.NUM_DRONES, 1)),
            high=np.tile(np.float32(high), (self.NUM_DRONES, 1)),
            dtype=np.float32,
        )

    def _computeObs(self):
        return np.stack([self._getDroneStateVector(i) for i in range(self.NUM_DRONES)])

    def _preprocessAction(self, action):
        return np.clip(action_array(action, self.NUM_DRONES, 4, "motor speeds in RPM"), 0.0, self.MAX_RPM)

    def _computeReward(self):
        return -1

    def _computeTerminated(self):
        return False

    def _computeTruncated(self):
        return False

    def _computeInfo(self):
        return {"answer": 42}
