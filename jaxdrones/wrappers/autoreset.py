"""Auto-reset with a fresh key: a finished world starts a new episode with a new start, new task params and new
domain-randomised params, drawn from the world's own key chain (``EnvState.key``).

brax's ``AutoResetWrapper`` restores each world's *first* state instead, so every world would replay one start for
a whole training run; the brax adapter, the vector env and the trainers use this wrapper.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrones.envs.base import Env, EnvState


class AutoReset(Env):
    """Wrap an env so that ``step`` resets a world whose episode ended, in the same call (brax's convention).

    The returned state of such a world is the new episode's first state, except ``reward``, ``terminated``,
    ``truncated`` and ``metrics``, which report the step that ended the old one; ``info["final_obs"]`` holds that
    step's observation (the new one is in ``obs``) and ``info["final_steps"]`` its length in control steps. The
    new episode is drawn by ``env.reset(state.key, state.task)``: its per-episode task quantities, start and
    params are new, while the task params' ranges and weights carry over.
    """

    def __init__(self, env: Env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)

    @property
    def n_drones(self) -> int:
        return self.env.n_drones

    @property
    def observation_size(self) -> int:
        return self.env.observation_size

    @property
    def action_size(self) -> int:
        return self.env.action_size

    @property
    def episode_length(self) -> int:
        return self.env.episode_length

    def close(self) -> None:
        self.env.close()

    def reset(self, key: jax.Array, task=None) -> EnvState:
        state = self.env.reset(key, task)
        return state.replace(info={**state.info, "final_obs": state.obs, "final_steps": state.steps})

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        nxt = self.env.step(state, action)
        nxt = nxt.replace(info={**nxt.info, "final_obs": nxt.obs, "final_steps": nxt.steps})
        fresh = self.env.reset(nxt.key, nxt.task)
        fresh = fresh.replace(reward=nxt.reward, terminated=nxt.terminated, truncated=nxt.truncated,
                              metrics=nxt.metrics, info={**fresh.info, **nxt.info})
        done = nxt.done
        return jax.tree.map(lambda new, old: jnp.where(done, new, old), fresh, nxt)
