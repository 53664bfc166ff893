"""A gymnasium ``Env`` over a jaxdrones env (single instance, NumPy in and out); id ``"jaxdrones/Hover-v0"``."""

from __future__ import annotations

import gymnasium as gym
import jax
import numpy as np

from jaxdrones.envs.base import Env


class GymnasiumEnv(gym.Env):
    """Wrap a functional jaxdrones env as a stateful gymnasium env.

    The wrapper owns the env state and the PRNG key (``reset(seed=...)`` re-seeds it); ``reset`` and ``step`` are
    jitted once. Observations are float32 NumPy arrays in an unbounded Box; with camera images (an env whose
    ``observation_spec`` is a dict) a ``Dict`` space of that Box (``"state"``) and the images at their own dtypes
    (rgb uint8 in [0, 255], depth float32 m, seg int32 body ids). Actions are float32 in [-1, 1].
    ``step`` returns ``(obs, reward, terminated, truncated, info)`` with ``info`` holding the env's metrics.
    `close` releases the env's backend.
    """

    metadata = {"render_modes": []}

    def __init__(self, env: Env):
        self.env = env
        spec = getattr(env, "observation_spec", None)
        if isinstance(spec, dict):
            self.observation_space = gym.spaces.Dict({k: _box(k, v) for k, v in spec.items()})
        else:
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (env.observation_size,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (env.action_size,), np.float32)
        self._reset = jax.jit(env.reset)
        self._step = jax.jit(env.step)
        self._key = jax.random.key(0)
        self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.key(seed)
        self._key, key = jax.random.split(self._key)
        self._state = self._reset(key)
        return self._obs(), self._info()

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {action.shape}")
        self._state = self._step(self._state, action)
        s = self._state
        return self._obs(), float(s.reward), bool(s.terminated), bool(s.truncated), self._info()

    def close(self) -> None:
        """Release the env's backend (PyBullet worlds); the env cannot be stepped afterwards."""
        self.env.close()

    def _obs(self):
        obs = self._state.obs
        if isinstance(self.observation_space, gym.spaces.Dict):
            return {k: np.asarray(v, self.observation_space[k].dtype) for k, v in obs.items()}
        return np.asarray(obs, np.float32)

    def _info(self) -> dict:
        return {k: float(v) for k, v in self._state.metrics.items()}


def _box(name: str, spec) -> gym.spaces.Box:
    """The gymnasium space of one entry of a dict observation."""
    if name == "rgb":
        return gym.spaces.Box(0, 255, spec.shape, np.uint8)
    if name == "seg":  # Bullet body ids, -1 where nothing is seen
        return gym.spaces.Box(-1, np.iinfo(np.int32).max, spec.shape, np.int32)
    if name == "depth":  # m along the optical axis
        return gym.spaces.Box(0.0, np.inf, spec.shape, np.float32)
    return gym.spaces.Box(-np.inf, np.inf, spec.shape, np.float32)


def make_hover(**overrides) -> GymnasiumEnv:
    """Entry point of ``gymnasium.make("jaxdrones/Hover-v0", **overrides)``; overrides are `HoverConfig` fields
    (e.g. ``backend="pybullet", vision=("rgb",)``)."""
    from jaxdrones.envs import make

    return GymnasiumEnv(make("hover", **overrides))


def register() -> None:
    """Register ``jaxdrones/Hover-v0`` with gymnasium (done on ``import jaxdrones``)."""
    if "jaxdrones/Hover-v0" not in gym.registry:
        gym.register(id="jaxdrones/Hover-v0", entry_point="jaxdrones.wrappers.gymnasium:make_hover")
