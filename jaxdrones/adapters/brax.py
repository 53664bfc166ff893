"""Adapter from a jaxdrones env to ``brax.envs.Env``, for ``brax.training``'s trainers (PPO, APG, SAC).

brax's trainers take an env and a ``wrap_env_fn``; give them `BraxEnv` and `wrap_for_brax_training`::

    from brax.training.agents.ppo import train as ppo
    from jaxdrones.adapters.brax import BraxEnv, wrap_for_brax_training

    env = jd.make("hover")
    make_policy, params, _ = ppo.train(environment=BraxEnv(env), wrap_env_fn=wrap_for_brax_training,
                                       episode_length=env.episode_length, num_timesteps=1_000_000, ...)

(`jaxdrones.training.brax_ppo.train` does this.) Importing this module also makes brax's trainers run on JAX releases
without ``jax.device_put_replicated`` (removed in jax 0.10; brax 0.14 still calls it): see `patch_brax`.

Passing ``jd.make("hover")`` itself as brax's ``environment`` does not
work: brax's own wrappers expect its ``State`` with a physics ``pipeline_state``.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

# brax imports MuJoCo, whose optional GPU plugins print "Failed to import warp" on a machine without them.
with contextlib.redirect_stdout(io.StringIO()):
    from brax.envs.base import Env as BraxBaseEnv
    from brax.envs.base import State as BraxState
    from brax.envs.base import Wrapper as BraxWrapper
    from brax.envs.wrappers import training as brax_training
    from brax.training.agents.ppo import networks, train  # noqa: F401  (imported here, quietly, for patch_brax)

from jaxdrones.envs.base import Env, EnvState, world_axes
from jaxdrones.envs.observations import policy_input
from jaxdrones.wrappers.autoreset import AutoReset, VmapAutoReset

#: brax's modules that call ``jax.device_put_replicated`` (brax 0.14.2): `patch_brax` gives them a stand-in.
BRAX_REPLICATING_MODULES = (
    "brax.training.pmap",
    "brax.training.agents.ppo.train",
    "brax.training.agents.apg.train",
    "brax.training.agents.sac.train",
)


def device_put_replicated(x: Any, devices: Sequence[jax.Device]) -> Any:
    """A copy of every leaf of ``x`` on each of ``devices``, stacked on a new leading axis that ``jax.pmap`` splits
    over them: what ``jax.device_put_replicated`` did before jax 0.10 removed it. ``x``: a pytree of arrays; returns
    the same pytree, each leaf f[len(devices), ...]."""
    import numpy as np

    devices = list(devices)
    sharding = jax.sharding.NamedSharding(
        jax.sharding.Mesh(np.array(devices), ("devices",)), jax.sharding.PartitionSpec("devices")
    )

    def put(leaf):
        leaf = jnp.asarray(leaf)
        shards = [jax.device_put(leaf[None], device) for device in devices]
        return jax.make_array_from_single_device_arrays((len(devices),) + leaf.shape, sharding, shards)

    return jax.tree.map(put, x)


class _JaxWithReplicated:
    """The ``jax`` module as brax's trainers see it after `patch_brax`: every attribute is jax's, plus
    `device_put_replicated`."""

    device_put_replicated = staticmethod(device_put_replicated)

    def __getattr__(self, name):
        return getattr(jax, name)


def patch_brax() -> list[str]:
    """Give brax's modules that call ``jax.device_put_replicated`` (`BRAX_REPLICATING_MODULES`) a ``jax`` that has
    it, where the installed JAX does not (jax >= 0.10); returns the modules patched. Nothing else of brax or of
    ``jax`` changes: the stand-in (`device_put_replicated`) is seen by those modules only, and what it builds is
    what the removed function built (tested: brax's PPO trains on jax 0.10 as on 0.9). Idempotent; a no-op on a
    JAX that still has the function."""
    import importlib

    if hasattr(jax, "device_put_replicated"):
        return []
    patched = []
    for name in BRAX_REPLICATING_MODULES:
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                module = importlib.import_module(name)
        except ImportError:  # a brax without this trainer
            continue
        if getattr(module, "jax", None) is jax:
            module.jax = _JaxWithReplicated()
            patched.append(name)
    return patched


patch_brax()


def privileged_shape(env: Env) -> tuple[int, ...] | None:
    """The shape of ``env.privileged`` of a state (f[D, k]; `jaxdrones.envs.base.Env.privileged`), or None when the
    env has no privileged observation. Traced abstractly: nothing runs."""
    out = jax.eval_shape(env.privileged, jax.eval_shape(env.reset, jax.random.key(0)))
    return None if out is None else tuple(out.shape)


class BraxEnv(BraxBaseEnv):
    """A jaxdrones env seen as a brax env with flat observation and action vectors.

    The observation is ``obs`` f[D, n_obs] flattened (D·n_obs), or with cameras the dict of brax's vision trainers
    (``"state"`` and ``"pixels/depth"``, ``"pixels/rgb"``: `jaxdrones.envs.observations.policy_input`; train with
    ``vision=True`` and brax's ``networks_vision``); the action f[D·n_act] is reshaped to f[D, n_act],
    the reward is the sum over drones (a team reward; the drone's own for D = 1). The jaxdrones `EnvState` travels
    as brax's ``pipeline_state``. ``done`` is ``terminated | truncated`` and ``info["truncation"]`` marks the time
    limit, so that PPO bootstraps there; ``info["steps"]`` is the episode's length so far (brax's evaluator
    reads it), and ``info["episode_metrics"]``/``info["episode_done"]`` hold the running episode sums that brax's
    trainer logs. Episodes are reset by `AutoReset` (a fresh start per episode), not by
    brax's wrappers.

    With ``privileged=True`` the observation dict also holds ``"privileged_state"`` f[D·k], the env's privileged
    observation (`jaxdrones.envs.base.Env.privileged`), for a critic that reads it (MuJoCo Playground's key and
    convention; brax's networks take it as ``value_obs_key``).

    Keys: brax passes raw uint32 keys; typed ``jax.random.key`` keys work too.

    Raises:
        ValueError: ``privileged=True`` on an env without camera images or without a privileged observation.
    """

    def __init__(self, env: Env, auto_reset: bool = True, privileged: bool = False):
        if privileged and not (isinstance(env.observation_spec, dict) and privileged_shape(env)):
            raise ValueError(
                "privileged=True needs an env with camera images (vision=...) and a privileged "
                "observation (Task.privileged: e.g. avoid, fly_thru_gate)"
            )
        self.env = env
        self.privileged = privileged
        self.auto_reset = auto_reset
        self._inner = AutoReset(env) if auto_reset else env

    def reset(self, rng: jax.Array) -> BraxState:
        return self.start(self._inner.reset(rng))

    def step(self, state: BraxState, action: jax.Array) -> BraxState:
        action = jnp.reshape(action, (self.env.n_drones, self.env.action_size))
        return self.advance(state, self._inner.step(state.pipeline_state, action))

    def start(self, state: EnvState) -> BraxState:
        """The brax state of a world's first jaxdrones state ``state``."""
        zero = jnp.zeros((), state.reward.dtype)
        episode = {k: zero for k in ("sum_reward", "length", *state.metrics)}
        info = {"truncation": zero, "steps": zero, "episode_done": zero, "episode_metrics": episode}
        return BraxState(
            pipeline_state=state, obs=self._flat(state), reward=zero, done=zero, metrics=dict(state.metrics), info=info
        )

    def advance(self, state: BraxState, new: EnvState) -> BraxState:
        """The brax state after ``state`` of a world whose jaxdrones state stepped (and reset, where its episode
        ended) to ``new``."""
        dtype = new.reward.dtype
        metrics = {**state.metrics, **new.metrics}
        steps = new.info["final_steps"] if "final_steps" in new.info else new.steps  # the episode's length so far
        reward, done = jnp.sum(new.reward), new.done.astype(dtype)
        # Running sums over the current episode, restarted after one ends (what brax's training metrics read).
        keep = 1 - state.info["episode_done"]
        values = {"sum_reward": reward, "length": jnp.ones((), dtype), **new.metrics}
        episode = {k: v * keep + values[k] for k, v in state.info["episode_metrics"].items()}
        info = {
            **state.info,
            "truncation": new.truncated.astype(dtype),
            "steps": steps.astype(dtype),
            "episode_done": done,
            "episode_metrics": episode,
        }
        return BraxState(pipeline_state=new, obs=self._flat(new), reward=reward, done=done, metrics=metrics, info=info)

    def _flat(self, state):
        obs = policy_input(state.obs)
        if self.privileged:
            obs["privileged_state"] = jnp.reshape(self.env.privileged(state), (-1,))
        return obs

    @property
    def observation_size(self) -> int | dict[str, tuple[int, ...]]:
        """D·n_obs, or with cameras the shape of each key of the observation dict (brax's vision convention)."""
        spec = self.env.observation_spec
        if not isinstance(spec, dict):
            return self.env.n_drones * self.env.observation_size
        zeros = {k: jnp.zeros(v.shape, v.dtype) for k, v in spec.items()}
        sizes = {k: v.shape for k, v in jax.eval_shape(policy_input, zeros).items()}
        if self.privileged:
            sizes["privileged_state"] = (int(np.prod(privileged_shape(self.env))),)
        return sizes

    @property
    def action_size(self) -> int:
        return self.env.n_drones * self.env.action_size

    @property
    def backend(self) -> str:
        return "jaxdrones"


class BatchedBraxEnv(BraxWrapper):
    """A `BraxEnv` over a batch of worlds, as brax's ``VmapWrapper`` of it gives, but reset by `VmapAutoReset`:
    only the worlds whose episode ended compute a reset, where ``vmap`` of `AutoReset` computes one for every world
    at every step (with cameras a reset renders the first images, so that nearly doubles a step's cost).

    ``reset(rng)`` takes keys [W] (raw uint32 [W, 2] or typed); ``step(state, action)`` actions f[W, D·n_act]. The
    states are those of ``VmapWrapper(env)``, except that the jaxdrones state in ``pipeline_state`` holds the drones'
    params once (batch shape [D]) when the env does not randomise them (`VmapAutoReset`).
    """

    def __init__(self, env: BraxEnv):
        super().__init__(env)
        self._worlds = VmapAutoReset(env.env)
        self._axes = world_axes(self._worlds.params_shared)
        self._state_axes = BraxState(pipeline_state=self._axes, obs=0, reward=0, done=0, metrics=0, info=0)

    def reset(self, rng: jax.Array) -> BraxState:
        start = jax.vmap(self.env.start, in_axes=(self._axes,), out_axes=self._state_axes)
        return start(self._worlds.reset(rng))

    def step(self, state: BraxState, action: jax.Array) -> BraxState:
        inner = self.env.env
        new = self._worlds.step(
            state.pipeline_state, jnp.reshape(action, (action.shape[0], inner.n_drones, inner.action_size))
        )
        advance = jax.vmap(self.env.advance, in_axes=(self._state_axes, self._axes), out_axes=self._state_axes)
        return advance(state, new)


def wrap_for_brax_training(
    env: BraxEnv | Env,
    episode_length: int | None = None,
    action_repeat: int = 1,
    randomization_fn: Callable | None = None,
) -> BatchedBraxEnv | brax_training.VmapWrapper:
    """``wrap_env_fn`` for brax's trainers: a `BraxEnv` over a batch of worlds, `BatchedBraxEnv` (brax's
    ``VmapWrapper`` of it when it does not reset, ``auto_reset=False``).

    Args:
        env: a `BraxEnv` or a jaxdrones env.
        episode_length: ignored: the env truncates at its own ``episode_length``.
        action_repeat: must be 1 (the env's control rate sets the step).
        randomization_fn: unsupported: domain randomisation is the task option ``randomize``, drawn at every reset.

    Raises:
        ValueError: ``action_repeat`` ≠ 1 or a ``randomization_fn``.
    """
    if randomization_fn is not None:
        raise ValueError(
            "brax's randomization_fn is not supported: pass randomize={'mass': 0.1, ...} to "
            "jd.make(...) to draw randomised drone params at every reset"
        )
    if action_repeat != 1:
        raise ValueError(f"action_repeat must be 1 (set the env's ctrl_freq instead), got {action_repeat}")
    if not isinstance(env, BraxEnv):
        env = BraxEnv(env)
    return BatchedBraxEnv(env) if env.auto_reset else brax_training.VmapWrapper(env)
