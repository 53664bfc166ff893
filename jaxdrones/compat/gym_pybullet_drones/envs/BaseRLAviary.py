"""gym-pybullet-drones' ``BaseRLAviary``: the RL aviaries' actions (`ActionType`), the KIN observation with its
action buffer, on the jaxdrones action mappings (`jaxdrones.envs.actions`)."""

from __future__ import annotations

import functools
from collections import deque

import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces

from jaxdrones.compat.gym_pybullet_drones.envs.BaseAviary import BaseAviary, action_array
from jaxdrones.compat.gym_pybullet_drones.utils.enums import ActionType, DroneModel, ObservationType, Physics
from jaxdrones.envs.actions import Reference, make_action
from jaxdrones.physics.params import broadcast_params


class BaseRLAviary(BaseAviary):
    """The base of the RL aviaries (the original's, on main).

    Args: those of `BaseAviary` (without ``obstacles``, ``user_debug_gui``, ``vision_attributes``), and
        obs: ``ObservationType.KIN`` (or ``"kin"``): per drone pos (m), roll/pitch/yaw (rad), vel (m/s), angular
            velocity (rad/s, world frame), then the last ``ACTION_BUFFER_SIZE = ctrl_freq // 2`` actions, oldest
            first: f32[D, 12 + ACTION_BUFFER_SIZE · size] (27 for one-dimensional actions at 30 Hz).
        act: an `ActionType` (or its value), mapped to RPM as the original does: ``RPM`` hover_rpm·(1 + 0.05 a),
            ``ONE_D_RPM`` the same for the four motors, ``PID`` the DSL PID to the target a (m, at most 1 m from the
            drone), ``VEL`` the PID to the velocity 0.25 m/s·|a₃|·unit(a₀:₃), ``ONE_D_PID`` the PID to
            pos + (0, 0, 0.1 a).

    Actions: f[D, size] in [-1, 1] (the Box ``action_space``); entries outside are clipped before the mapping, and
    the buffer holds the actions as given, as the original's.

    Raises:
        ValueError: ``ObservationType.RGB`` (no cameras here; `jaxdrones.make`'s ``vision`` has them), and
            (``step``) an action that is not D × size numbers, or with NaN or inf.
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
        obs: ObservationType = ObservationType.KIN,
        act: ActionType = ActionType.RPM,
        backend: str = "jax",
    ):
        self.OBS_TYPE, self.ACT_TYPE = ObservationType(obs), ActionType(act)
        if self.OBS_TYPE is ObservationType.RGB:
            raise ValueError(
                "ObservationType.RGB: the compat aviaries observe KIN only; camera observations are "
                "jaxdrones.make(task, vision=('rgb',)) (pure JAX, batched)"
            )
        self.ACTION_BUFFER_SIZE = int(ctrl_freq // 2)
        self.action_buffer = deque(maxlen=self.ACTION_BUFFER_SIZE)
        self._action = make_action(self.ACT_TYPE.value, pid_target="absolute")
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
            obstacles=False,
            user_debug_gui=False,
            backend=backend,
        )
        if self.ACT_TYPE is ActionType.VEL:
            self.SPEED_LIMIT = 0.03 * self.MAX_SPEED_KMH * (1000 / 3600)

    def _set_constants(self, params) -> None:
        super()._set_constants(params)
        self._drone_params = broadcast_params(params, (self.NUM_DRONES,))

    def _housekeeping(self) -> None:
        super()._housekeeping()
        self._carry = self._action.init(self._drone_params, self._state)

    def _actionSpace(self):
        size = self._action.size
        for _ in range(self.ACTION_BUFFER_SIZE):
            self.action_buffer.append(np.zeros((self.NUM_DRONES, size)))
        ones = np.ones((self.NUM_DRONES, size), np.float32)
        return spaces.Box(low=-ones, high=ones, dtype=np.float32)

    def _observationSpace(self):
        n, width = self.NUM_DRONES, self.ACTION_BUFFER_SIZE * self._action.size
        low = np.concatenate([np.full((n, 12), -np.inf), -np.ones((n, width))], axis=1)
        low[:, 2] = 0.0
        high = np.concatenate([np.full((n, 12), np.inf), np.ones((n, width))], axis=1)
        return spaces.Box(low=low.astype(np.float32), high=high.astype(np.float32), dtype=np.float32)

    def _preprocessAction(self, action):
        action = action_array(action, self.NUM_DRONES, self._action.size, f"for {self.ACT_TYPE}", np.float32)
        self.action_buffer.append(action)
        rpm, self._carry = _to_rpm(
            self._action, self._drone_params, self._state, self._carry, np.clip(action, -1.0, 1.0), self.CTRL_TIMESTEP
        )
        return np.asarray(rpm, np.float64)

    def _computeObs(self):
        kin = np.concatenate([self.pos, self.rpy, self.vel, self.ang_v], axis=1)
        return np.concatenate([kin, *self.action_buffer], axis=1).astype(np.float32)


@functools.partial(jax.jit, static_argnums=0)
def _to_rpm(action_type, params, sim, carry, action, ctrl_dt):
    ref = Reference(pos=sim.pos, vel=jnp.zeros_like(sim.vel))
    return action_type.to_rpm(params, sim, carry, action.astype(sim.pos.dtype), ref, ctrl_dt)
