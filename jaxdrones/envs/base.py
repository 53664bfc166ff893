"""The functional environment protocol (brax's shape): ``reset(key) -> EnvState``, ``step(state, action)``."""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Any

import jax
from flax import struct

from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.state import DroneState

if TYPE_CHECKING:
    import numpy as np

    from jaxdrones.envs.task import TaskParams


@struct.dataclass
class EnvState:
    """State of one (or, with leading axes, many) environment worlds of ``D`` drones.

    Attributes:
        sim: DroneState of the drones, f[..., D, ...].
        params: DroneParams of this episode, batch shape [..., D] (sampled at reset with domain randomisation;
            differentiable).
        task: the task's params of this episode (`jaxdrones.envs.task.TaskParams`: targets, references, start
            ranges, termination bounds, reward weights), sampled at reset.
        ctrl: the action type's carry (the DSL PID's state for the PID-based actions, else ``()``).
        history: f[..., D, K, n_act] the last K actions, oldest first (K = 0 without an action buffer).
        integral: f[..., D, 3] the integral of the task's tracking error (f[..., D, 0] without
            ``config.error_integral``; `jaxdrones.envs.config.TaskConfig.error_integral`).
        key: PRNG key of the world, from which an auto-reset draws the next episode.
        obs: f[..., D, n_obs] observation after the last reset/step; with camera images, a dict of arrays (see the
            env's ``observation_spec``).
        reward: f[..., D] per-drone reward of the last step (0 after reset).
        terminated: bool[...] the episode ended in a terminal state (crash, left the arena, invalid action).
        truncated: bool[...] the episode hit its time limit without terminating.
        steps: i32[...] control steps taken since reset.
        metrics: dict of f[...] per-step diagnostics (per world: means over the drones).
        info: dict of extra per-step data (wrappers add theirs, e.g. the auto-reset's final observation).
        realism: the sim-to-real options' `jaxdrones.envs.realism.RealismState` (drawn values, delay buffers, wind and
            disturbance processes), or None when the config has no ``realism``.
    """

    sim: DroneState
    params: DroneParams
    task: Any
    ctrl: Any
    history: jax.Array
    integral: jax.Array
    key: jax.Array
    obs: Any
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    steps: jax.Array
    metrics: dict[str, jax.Array] = struct.field(default_factory=dict)
    info: dict[str, Any] = struct.field(default_factory=dict)
    realism: Any = None

    @property
    def done(self) -> jax.Array:
        """bool[...] terminated or truncated."""
        return self.terminated | self.truncated


def world_axes(shared_params: bool) -> EnvState:
    """The ``vmap`` axes (``in_axes``/``out_axes``) of an `EnvState` batched over worlds: every field on axis 0,
    except ``params`` on none when every world shares them (``shared_params``; see `Env.shared_params`)."""
    return EnvState(
        sim=0,
        params=None if shared_params else 0,
        task=0,
        ctrl=0,
        history=0,
        integral=0,
        key=0,
        obs=0,
        reward=0,
        terminated=0,
        truncated=0,
        steps=0,
        metrics=0,
        info=0,
        realism=0,
    )


class Env(abc.ABC):
    """A jittable environment over a physics backend: pure ``reset`` and ``step``, batched by ``vmap``.

    `close` releases what the backend holds (PyBullet worlds); an env is also a context manager that closes it.
    """

    def close(self) -> None:  # noqa: B027  (a default: the JAX backend holds nothing to release)
        """Release the backend's resources (nothing to do for the JAX backend)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def shared_params(self) -> DroneParams | None:
        """The `DroneParams` (batch shape [D]) that every world and episode uses, or None when ``reset`` draws them
        (domain randomisation). Batched wrappers keep shared params once rather than once per world: a step that
        reads them per world is about a fifth slower on CPU."""
        return None

    def render_world(
        self, params: DroneParams, sim: DroneState, width: int = 480, height: int = 360
    ) -> np.ndarray | None:
        """One world's frame u8[H, W, 3] from the backend's renderer, or None where the backend has none (the
        default; the JAX backend: `jaxdrones.viz` and `jaxdrones.io.plotting` draw its flights).

        Args:
            params: one world's drone params, batch shape [D].
            sim: one world's state, pos f[D, 3] m, world frame.
            width, height: the frame's size, pixels.
        """
        return None

    def privileged(self, state: EnvState) -> jax.Array | None:
        """f[D, k]: what a critic may read of ``state`` and the policy does not (`jaxdrones.envs.task.Task.privileged`),
        or None when the env has nothing of the kind (the default)."""
        return None

    @abc.abstractmethod
    def reset(self, key: jax.Array, task: TaskParams | None = None) -> EnvState:
        """Start an episode from a PRNG key (typed ``jax.random.key`` or raw uint32)."""

    @abc.abstractmethod
    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Advance one control step with ``action`` f[D, action_size]."""

    @property
    @abc.abstractmethod
    def n_drones(self) -> int:
        """Drones per world, D."""

    @property
    @abc.abstractmethod
    def observation_size(self) -> int:
        """Length of one drone's observation."""

    @property
    @abc.abstractmethod
    def action_size(self) -> int:
        """Length of one drone's action."""

    @property
    @abc.abstractmethod
    def episode_length(self) -> int:
        """Control steps before truncation."""
