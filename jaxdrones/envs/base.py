"""The functional environment protocol (brax's shape): ``reset(key) -> EnvState``, ``step(state, action)``."""

from __future__ import annotations

import abc
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from jaxdrones.params import DroneParams
from jaxdrones.rotations import quat_to_euler
from jaxdrones.state import DroneState


@struct.dataclass
class EnvState:
    """State of one (or, with leading axes, many) environment instances.

    Attributes:
        sim: DroneState of the task's drones, f[..., D, ...].
        params: DroneParams used by this episode (sampled at reset; differentiable).
        key: PRNG key for the episode's randomness.
        obs: f[..., obs_size] observation after the last reset/step; for a task with camera images, a dict of
            arrays (see the task's ``observation_spec``).
        reward: f[...] reward of the last step (0 after reset).
        terminated: bool[...] the episode ended in a terminal state (crash, left the arena, invalid action).
        truncated: bool[...] the episode hit its time limit without terminating.
        steps: i32[...] control steps taken since reset.
        metrics: dict of f[...] per-step diagnostics.
        info: dict of extra per-step data.
    """

    sim: DroneState
    params: DroneParams
    key: jax.Array
    obs: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    steps: jax.Array
    metrics: dict[str, jax.Array] = struct.field(default_factory=dict)
    info: dict[str, Any] = struct.field(default_factory=dict)

    @property
    def done(self) -> jax.Array:
        """bool[...] terminated or truncated."""
        return self.terminated | self.truncated


class Env(abc.ABC):
    """A jittable environment over a physics backend: pure ``reset`` and ``step``, batched by ``vmap``.

    `close` releases what the backend holds (PyBullet worlds); an env is also a context manager that closes it.
    """

    def close(self) -> None:
        """Release the backend's resources (nothing to do for the JAX backend)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @abc.abstractmethod
    def reset(self, key: jax.Array) -> EnvState:
        """Start an episode from a PRNG key (typed ``jax.random.key`` or raw uint32)."""

    @abc.abstractmethod
    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Advance one control step with ``action`` f[action_size] in [-1, 1]."""

    @property
    @abc.abstractmethod
    def observation_size(self) -> int:
        """Length of the flat observation."""

    @property
    @abc.abstractmethod
    def action_size(self) -> int:
        """Length of the flat action."""

    @property
    @abc.abstractmethod
    def episode_length(self) -> int:
        """Control steps before truncation."""


def kinematic_obs(sim: DroneState) -> jax.Array:
    """The paper's kinematic observation (eq. obs, facts §8 KIN without the action buffer) of each drone.

    Returns:
        f[..., D, 12]: position (m, world), roll/pitch/yaw (rad, PyBullet convention), velocity (m/s, world) and
        angular velocity (rad/s, body frame).
    """
    return jnp.concatenate([sim.pos, quat_to_euler(sim.quat), sim.vel, sim.ang_vel], axis=-1)
