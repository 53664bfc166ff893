"""Adapter from a jaxdrones `Env` to ``brax.envs.Env`` for ``brax.training`` agents (PPO, APG, SAC)."""

from __future__ import annotations

import jax
from brax.envs.base import Env as BraxBaseEnv
from brax.envs.base import State as BraxState
from brax.envs.wrappers import training as brax_training

from jaxdrones.envs.base import Env, EnvState


class BraxEnv(BraxBaseEnv):
    """A jaxdrones env seen as a brax env.

    The jaxdrones `EnvState` travels as brax's ``pipeline_state``. brax's ``done`` is ``terminated`` only: the
    time limit is applied by brax's ``EpisodeWrapper`` (see `wrap_for_brax_training`), which marks it as
    ``info["truncation"]`` so that PPO bootstraps instead of treating it as a terminal state.
    """

    def __init__(self, env: Env):
        self.env = env

    def reset(self, rng: jax.Array) -> BraxState:
        state = self.env.reset(rng)
        return self._to_brax(state)

    def step(self, state: BraxState, action: jax.Array) -> BraxState:
        new = self.env.step(state.pipeline_state, action)
        return self._to_brax(new, state.info, state.metrics)

    @staticmethod
    def _to_brax(state: EnvState, info: dict | None = None, metrics: dict | None = None) -> BraxState:
        # brax's wrappers add their own entries to info and metrics; keep them across steps.
        merged = dict(metrics or {})
        merged.update(state.metrics)
        return BraxState(pipeline_state=state, obs=state.obs, reward=state.reward,
                         done=state.terminated.astype(state.reward.dtype), metrics=merged,
                         info={} if info is None else info)

    @property
    def observation_size(self) -> int:
        return self.env.observation_size

    @property
    def action_size(self) -> int:
        return self.env.action_size

    @property
    def backend(self) -> str:
        return "jaxdrones"


def wrap_for_brax_training(env, episode_length: int, action_repeat: int = 1, randomization_fn=None):
    """``wrap_env_fn`` for brax's trainers: vmap, brax's episode time limit and auto-reset.

    Args:
        env: a `BraxEnv`.
        episode_length: control steps per episode (use the task's ``episode_length``).
        action_repeat: brax's action repeat (1 for the paper's tasks).
        randomization_fn: unsupported (domain randomisation belongs in the task's ``reset``); must be None.

    Raises:
        ValueError: if ``randomization_fn`` is given.
    """
    if randomization_fn is not None:
        raise ValueError("jaxdrones envs randomise in reset(); brax's randomization_fn is not supported")
    env = brax_training.VmapWrapper(env)
    env = brax_training.EpisodeWrapper(env, episode_length, action_repeat)
    return brax_training.AutoResetWrapper(env)
