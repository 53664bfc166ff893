"""JaxMARL-style adapter: a task's stacked env seen through JaxMARL's ``MultiAgentEnv`` interface, pure JAX.

``env = make("leader_follower", n_drones=3)`` gives agents ``drone_0 ... drone_2`` (agent ``drone_i`` is row ``i`` of
the stacked env) and the methods of JaxMARL's ``MultiAgentEnv``::

    obs, state = env.reset(key)
    obs, state, rewards, dones, infos = env.step(key, state, actions)

with per-agent dicts: ``obs[agent]`` f[n_obs], ``actions[agent]`` f[n_act], ``rewards[agent]`` f[],
``dones[agent]`` bool[] and ``dones["__all__"]`` bool[]. ``reset`` and ``step`` are jitted (as JaxMARL's are), pure,
and ``vmap`` over worlds. Like JaxMARL's envs, ``step`` resets a world whose episode ended in the same call, here
with `jaxdrones.wrappers.AutoReset`: the new episode is drawn from the world's own key chain (``state.key``), so a
run is reproducible from the reset key alone and ``step``'s ``key`` is accepted for the signature but not used.

JaxMARL is not a dependency: the spaces are this module's small jittable `Box` (JaxMARL's ``spaces.Box`` methods:
``sample(key)``, ``contains(x)``, ``shape``, ``dtype``, ``low``, ``high``).
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.adapters.agents import agent_names, check_agent_keys, make_multi_agent
from jaxdrones.envs.base import EnvState
from jaxdrones.envs.env import TaskEnv, clipped_per_drone, outside_box
from jaxdrones.wrappers.autoreset import AutoReset


class Box:
    """A bounded box of arrays, jittable, with JaxMARL's ``spaces.Box`` interface.

    Attributes:
        low, high: f32[shape] bounds (NumPy).
        shape: the array shape.
        dtype: float32.
    """

    def __init__(self, low, high):
        self.low = np.asarray(low, np.float32)
        self.high = np.asarray(high, np.float32)
        if self.low.shape != self.high.shape:
            raise ValueError(f"low and high must have the same shape, got {self.low.shape} and {self.high.shape}")
        self.shape = self.low.shape
        self.dtype = np.dtype(np.float32)

    def sample(self, key: jax.Array) -> jax.Array:
        """f32[shape] uniform in the box."""
        return jax.random.uniform(key, self.shape, jnp.float32, self.low, self.high)

    def contains(self, x: jax.Array) -> jax.Array:
        """bool[]: ``x`` has the box's shape and lies in it (jittable)."""
        x = jnp.asarray(x)
        if x.shape != self.shape:
            return jnp.zeros((), bool)
        return jnp.all((x >= self.low) & (x <= self.high))

    def __repr__(self) -> str:
        return f"Box(low={self.low.min():g}, high={self.high.max():g}, shape={self.shape}, dtype=float32)"


class JaxMARLEnv:
    """A `TaskEnv` of D drones with JaxMARL's ``MultiAgentEnv`` methods (see the module docstring).

    Attributes:
        env: the stacked env.
        num_agents: D.
        agents: ``["drone_0", ..., "drone_{D-1}"]``.
        observation_spaces, action_spaces: `Box` by agent: the agent's row of ``env.observation_bounds()`` and
            ``env.action_bounds()``.

    The state is the env's `EnvState` (with the auto-reset's ``info``). Actions outside their box are clipped to it
    by the env and counted per agent in ``infos["clipped_actions"]`` (f[D]); with ``strict_actions=True`` such an
    action is treated as invalid instead. An invalid action (non-finite, or out of the box when strict) terminates
    the episode with ``infos["invalid_action"]`` set, as in `TaskEnv.step` (a jitted step cannot raise).

    Raises:
        ValueError: an env with camera images in its observation (``vision``; use the PettingZoo or gymnasium
            adapter for those).
    """

    def __init__(self, env: TaskEnv, strict_actions: bool = False):
        if env.config.vision:
            raise ValueError(
                f"the JaxMARL view takes state observations only, got vision={env.config.vision}; "
                "the PettingZoo and gymnasium adapters take camera images"
            )
        self.env = env
        self.strict_actions = bool(strict_actions)
        self._auto = AutoReset(env)
        self.num_agents = env.n_drones
        self.agents = agent_names(env.n_drones)
        low, high = env.observation_bounds()
        a_low, a_high = env.action_bounds()
        self.observation_spaces = {a: Box(low[i], high[i]) for i, a in enumerate(self.agents)}
        self.action_spaces = {a: Box(a_low[i], a_high[i]) for i, a in enumerate(self.agents)}

    @property
    def name(self) -> str:
        """The task's registered name."""
        return self.env.task.name

    @partial(jax.jit, static_argnums=(0,))
    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], EnvState]:
        """Start an episode from ``key`` (typed or raw uint32); returns ``(obs, state)``."""
        state = self._auto.reset(key)
        return self.get_obs(state), state

    @partial(jax.jit, static_argnums=(0,))
    def step(
        self, key: jax.Array, state: EnvState, actions: dict[str, jax.Array]
    ) -> tuple[dict[str, jax.Array], EnvState, dict[str, jax.Array], dict[str, jax.Array], dict[str, Any]]:
        """Advance one control step, resetting the world if its episode ended.

        Args:
            key: accepted for JaxMARL's signature; unused (see the module docstring).
            state: from `reset` or `step`.
            actions: f[n_act] by agent, exactly the agents of `agents`.

        Returns:
            ``(obs, state, rewards, dones, infos)``: the new episode's first observation where a world was reset;
            ``rewards[agent]`` f[] and ``dones[agent]``, ``dones["__all__"]`` bool[] of the step that ended it;
            ``infos``: one entry per agent in every leaf, as JaxMARL's baselines expect (they reshape each leaf of a
            batch of W worlds to ``W × num_agents``): the env's metrics (f[D], the world's value for each agent),
            ``terminated`` and ``truncated`` (bool[D]), ``final_steps`` (i32[D], the ended episode's length) and
            ``clipped_actions`` (f[D], the agent's action entries outside its box at this step).
            The step's observation before a reset is ``state.info["final_obs"]`` (f[D, n_obs]).

        Raises:
            ValueError: (at trace time) missing, unknown or extra agent names, or an action of the wrong shape or
                a non-float dtype.
        """
        del key
        action = self._stack(actions)
        low, high = (jnp.asarray(b, action.dtype) for b in self.env.action_bounds())
        outside = outside_box(action, low, high)
        clipped = clipped_per_drone(action, low, high)
        if self.strict_actions:
            action = jnp.where(outside, jnp.nan, action)
        state = self._auto.step(state, action)
        done = state.done
        rewards = {a: state.reward[i] for i, a in enumerate(self.agents)}
        dones = {**dict.fromkeys(self.agents, done), "__all__": done}
        per_world = {
            **state.metrics,
            "terminated": state.terminated,
            "truncated": state.truncated,
            "final_steps": state.info["final_steps"],
        }
        infos = {k: jnp.broadcast_to(v[..., None], v.shape + (self.num_agents,)) for k, v in per_world.items()}
        infos["clipped_actions"] = clipped.astype(infos["clipped_actions"].dtype)
        return self.get_obs(state), state, rewards, dones, infos

    def get_obs(self, state: EnvState) -> dict[str, jax.Array]:
        """f[n_obs] by agent: the agent's row of ``state.obs``."""
        return self._by_agent(state.obs)

    def observation_space(self, agent: str) -> Box:
        """The observation `Box` of ``agent`` (the same object at every call)."""
        return self.observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> Box:
        """The action `Box` of ``agent`` (the same object at every call)."""
        return self.action_spaces[self._check_agent(agent)]

    def _by_agent(self, stacked: jax.Array) -> dict[str, jax.Array]:
        return {a: stacked[..., i, :] for i, a in enumerate(self.agents)}

    def _check_agent(self, agent: str) -> str:
        if agent not in self.observation_spaces:
            raise ValueError(f"unknown agent {agent!r}: expected one of {self.agents}")
        return agent

    def _stack(self, actions: dict) -> jax.Array:
        check_agent_keys(actions, self.agents)
        shape = (self.env.action_size,)
        rows = []
        for agent in self.agents:
            action = jnp.asarray(actions[agent])
            if action.shape != shape or not jnp.issubdtype(action.dtype, jnp.floating):
                raise ValueError(
                    f"action of {agent} must be a float array of shape {shape} (vmap over worlds for "
                    f"a batch), got {action.dtype}{list(action.shape)}"
                )
            rows.append(action)
        return jnp.stack(rows)


def make(task: str, strict_actions: bool = False, **options: Any) -> JaxMARLEnv:
    """A multi-agent task as a `JaxMARLEnv`, e.g. ``make("flock", n_drones=5)``.

    Args:
        task: one of `jaxdrones.envs.MULTI_AGENT` (``multi_hover``, ``leader_follower``, ``flock``, ``meetup``,
            ``crossing``).
        strict_actions: an action outside its box ends the episode as invalid (default: clipped and counted; see
            `JaxMARLEnv`).
        **options: fields of the task's config, as for `jaxdrones.make`.

    Raises:
        ValueError: a single-agent or unknown task (the message names the multi-agent tasks), an invalid option or
            value, an ``n_drones`` the task does not allow, or camera images in the observation.
    """
    return JaxMARLEnv(make_multi_agent(task, **options), strict_actions=strict_actions)
