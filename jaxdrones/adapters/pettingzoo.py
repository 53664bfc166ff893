"""PettingZoo adapters: a multi-agent task as a ``pettingzoo.ParallelEnv`` (`parallel_env`) or, turn by turn, an
``AECEnv`` (`env`); NumPy in and out, one dict per agent.

``parallel_env("leader_follower", n_drones=3)`` gives agents ``drone_0 ... drone_2``; agent ``drone_i`` is row ``i``
of the stacked env (`jaxdrones.envs.TaskEnv`): its observation is row ``i`` of ``obs f[D, n_obs]``, its action row
``i`` of ``action f[D, n_act]``, its reward ``reward[i]``. Each ``reset``/``step`` is one jitted call of the whole
stacked env (the per-agent dicts are built only here, at the boundary). All drones of a world end their episode
together: the world's ``terminated``/``truncated`` apply to every agent, and ``agents`` is then empty until the next
``reset``. ``env(...)`` is PettingZoo's ``parallel_to_aec`` of it: the drones act in turn, and the world steps once
the last of them has.

This module has PettingZoo's environment-module layout (``parallel_env`` and ``env`` taking keyword arguments), so
that PettingZoo's tutorials take it where they take one of PettingZoo's own, e.g. with SuperSuit and
Stable-Baselines3::

    from jaxdrones.adapters import pettingzoo as env_fn
    env = env_fn.parallel_env(task="multi_hover", n_drones=2)
    env = supersuit.pettingzoo_env_to_vec_env_v1(env)
    env = supersuit.concat_vec_envs_v1(env, 8, num_cpus=0, base_class="stable_baselines3")

``num_cpus > 1`` starts worker processes, which multiprocessing forks by default on Linux (before Python 3.14);
JAX hangs in a process forked after it started, so the workers then raise a `RuntimeError` naming the fixes
(``num_cpus=0``, or ``multiprocessing.set_start_method("spawn")``; `jaxdrones._fork`). The env pickles as its
task, config and render mode (a copy is built anew, with no episode running), so ``spawn`` workers work.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import jax
import numpy as np
from gymnasium.utils import seeding
from numpy.typing import ArrayLike
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from jaxdrones._fork import check_not_forked
from jaxdrones.adapters._host import RENDER_MODES, HumanView, OneWorldRendering, check_torch_threads, host_metrics
from jaxdrones.adapters.agents import agent_names, check_agent_keys, make_multi_agent
from jaxdrones.adapters.gymnasium import check_action, compiled, spaces
from jaxdrones.envs.env import TaskEnv, clipped_per_drone


class PettingZooEnv(OneWorldRendering, ParallelEnv):
    """A `TaskEnv` of D drones as a PettingZoo ``ParallelEnv``; the adapter owns the env state and the PRNG key.

    * Spaces per agent (`observation_space`, `action_space`, the same object at every call): float32 Boxes, the
      agent's row of ``env.observation_bounds()`` and ``env.action_bounds()`` (a ``Dict`` with that drone's camera
      images under ``vision``).
    * ``reset(seed=..., options=None) -> (observations, infos)``: a seed makes the episode sequence reproducible,
      ``reset()`` without one continues it; ``options`` is accepted and ignored.
    * ``step(actions) -> (observations, rewards, terminations, truncations, infos)``: ``actions`` holds one action
      f32[n_act] per live agent. Entries outside its box are clipped to it, and ``infos[agent]["clipped_actions"]``
      counts those of that agent at this step; ``strict_actions=True`` raises a ``ValueError`` instead. NaN or inf
      entries always raise a ``ValueError``. Rewards are floats, the drone's ``reward[i]``; ``infos[agent]`` holds
      the world's metrics (floats, means over the drones).
    * ``render()`` returns an RGB frame u8[H, W, 3] with ``render_mode="rgb_array"`` (else None); with
      ``render_mode="human"`` every ``reset`` and ``step`` shows the frame in a window
      (`jaxdrones.adapters.gymnasium.HumanView`). `close` releases the backend.
    """

    metadata = {"render_modes": list(RENDER_MODES), "name": "jaxdrones", "is_parallelizable": True, "render_fps": 30}

    def __init__(self, env: TaskEnv, render_mode: str | None = None, strict_actions: bool = False):
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")
        check_not_forked()
        self._init_args = (env, render_mode, strict_actions)
        self.env = env
        self.render_mode = render_mode
        self.strict_actions = bool(strict_actions)
        self.metadata = {
            **self.metadata,
            "name": f"jaxdrones_{env.task.name}_v0",
            "render_fps": env.config.sim.ctrl_freq,
        }
        self.possible_agents = agent_names(env.n_drones)
        self.agents = []
        obs_space, action_space = spaces(env)
        stacked = env.n_drones > 1  # `spaces` drops the drone axis of a single drone
        self.observation_spaces = {a: _agent_space(obs_space, i, stacked) for i, a in enumerate(self.possible_agents)}
        self.action_spaces = {a: _agent_space(action_space, i, stacked) for i, a in enumerate(self.possible_agents)}
        self._reset, self._step = compiled(env)
        self._state = None
        self.np_random = None
        self._view = HumanView.for_mode(env, render_mode)

    def observation_space(self, agent: str) -> gym.Space:
        """The observation space of ``agent`` (cached: the same object at every call)."""
        return self.observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> gym.Space:
        """The action space of ``agent`` (cached: the same object at every call)."""
        return self.action_spaces[self._check_agent(agent)]

    def __reduce__(self):
        return type(self), self._init_args

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
        """Start an episode; returns ``(observations, infos)``, one entry per agent."""
        check_not_forked()
        check_torch_threads()
        if seed is not None or self.np_random is None:
            self.np_random, _ = seeding.np_random(seed)
        key = jax.random.key(int(self.np_random.integers(2**31)))
        self._state = self._reset(key)
        self.agents = list(self.possible_agents)
        self._show()
        return self._observations(self.agents), self._infos(self.agents)

    def step(
        self, actions: dict[str, ArrayLike]
    ) -> tuple[dict[str, Any], dict[str, float], dict[str, bool], dict[str, bool], dict[str, dict[str, Any]]]:
        """Advance every drone one control step.

        Returns:
            Per-agent dicts ``(observations, rewards, terminations, truncations, infos)`` over the agents that were
            live (all of them: the drones of a world end their episode together); ``agents`` is empty after the
            episode's last step.

        Raises:
            ValueError: unknown, missing or extra agent names, or an action of the wrong shape or not finite (or,
                with ``strict_actions``, outside its box).
            RuntimeError: no episode is running (``reset`` not called, or the episode has ended), or a process
                forked after JAX started (`jaxdrones._fork`).
        """
        check_not_forked()
        if self._state is None or not self.agents:
            raise RuntimeError("no episode is running: call reset() first (agents is empty after an episode ends)")
        agents = self.agents
        check_agent_keys(actions, agents)
        action = np.stack(
            [
                check_action(actions[a], self.action_spaces[a], strict=self.strict_actions, name=f"action of {a}")
                for a in agents
            ]
        )
        space = self.action_spaces[agents[0]]
        clipped = clipped_per_drone(action, space.low, space.high)
        self._state = self._step(self._state, action)
        self._show()
        s = self._state
        reward = np.asarray(s.reward, np.float32)
        terminated, truncated = bool(s.terminated), bool(s.truncated)
        out = (
            self._observations(agents),
            {a: float(reward[i]) for i, a in enumerate(agents)},
            dict.fromkeys(agents, terminated),
            dict.fromkeys(agents, truncated),
            self._infos(agents, clipped),
        )
        if terminated or truncated:
            self.agents = []
        return out

    def _check_agent(self, agent: str) -> str:
        if agent not in self.observation_spaces:
            raise ValueError(f"unknown agent {agent!r}: expected one of {self.possible_agents}")
        return agent

    def _observations(self, agents: list[str]) -> dict:
        obs = jax.tree.map(np.asarray, self._state.obs)
        return {a: _agent_obs(obs, self.observation_spaces[a], i) for i, a in enumerate(agents)}

    def _infos(self, agents: list[str], clipped: np.ndarray | None = None) -> dict:
        """The world's metrics for each agent, with ``clipped_actions`` that agent's own count (0 at a reset)."""
        metrics = host_metrics(self._state.metrics)
        return {
            a: {**metrics, "clipped_actions": 0 if clipped is None else int(clipped[i])} for i, a in enumerate(agents)
        }


def _agent_space(space: gym.Space, i: int, stacked: bool) -> gym.Space:
    """Drone ``i``'s part of a one-world space (``stacked``: its arrays have the drone axis first)."""
    if isinstance(space, gym.spaces.Dict):
        return gym.spaces.Dict({k: _agent_space(v, i, stacked) for k, v in space.items()})
    low, high = (space.low[i], space.high[i]) if stacked else (space.low, space.high)
    return gym.spaces.Box(low, high, dtype=space.dtype)


def _agent_obs(obs, space: gym.Space, i: int):
    """Drone ``i``'s row of the stacked observation, in ``space``'s dtypes: a writable copy (a view of JAX's buffer
    is read-only, and ``torch.from_numpy`` warns on one)."""
    if isinstance(space, gym.spaces.Dict):
        return {k: _agent_obs(obs[k], space[k], i) for k in space}
    return np.array(obs[i], space.dtype)


def parallel_env(
    task: str, render_mode: str | None = None, strict_actions: bool = False, **options: Any
) -> PettingZooEnv:
    """A multi-agent task as a PettingZoo ``ParallelEnv``, e.g. ``parallel_env("flock", n_drones=5)``.

    Args:
        task: one of `jaxdrones.envs.MULTI_AGENT` (``multi_hover``, ``leader_follower``, ``flock``, ``meetup``,
            ``crossing``).
        render_mode: None, ``"human"`` or ``"rgb_array"``.
        strict_actions: refuse actions outside their box with a ``ValueError`` (default: clip and count them in
            ``infos[agent]["clipped_actions"]``).
        **options: fields of the task's config (``n_drones``, ``action_type``, ``obs_type``, ``episode_len_s``,
            ``backend``, ...), as for `jaxdrones.make`.

    Raises:
        ValueError: a single-agent or unknown task (the message names the multi-agent tasks), an invalid option or
            value, an ``n_drones`` the task does not allow, or an unknown render mode.
        RuntimeError: in a process forked after JAX started (see the module docstring).
    """
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")
    return PettingZooEnv(make_multi_agent(task, **options), render_mode=render_mode, strict_actions=strict_actions)


def env(task: str, render_mode: str | None = None, strict_actions: bool = False, **options: Any) -> AECEnv:
    """A multi-agent task as a PettingZoo ``AECEnv`` (agents act in turn): PettingZoo's ``parallel_to_aec`` of
    `parallel_env` (same arguments and errors). The world steps once every live agent has acted; ``last()`` gives
    each agent its observation and the reward of the last world step.
    """
    return parallel_to_aec(parallel_env(task, render_mode=render_mode, strict_actions=strict_actions, **options))
