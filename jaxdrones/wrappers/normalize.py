"""Observation standardisation with running statistics, per world, in pure JAX: gymnasium's
``NormalizeObservation`` (each env keeps its own running mean and variance) for the functional envs.

The statistics live in the state (``EnvState.info["obs_norm"]``), so the wrapper is as pure as the env: ``jit`` and
``vmap`` over worlds, each world with its own statistics. Wrap an env that auto-resets (`AutoReset`), so that the
statistics run on across episodes; a `reset` starts them anew.

Why: PPO without observation normalisation failed on the multi-agent tasks with RPM actions, with every trainer
tried. Measured on ``multi_hover`` (2 drones), 3.04 M env steps: `jaxdrones.training.mappo`'s independent PPO
reached 0.8 cm on two seeds of three with its running statistics and failed on all three without them (53-216 cm);
JaxMARL's IPPO (``ippo_ff_mabrax.py``, 10 M steps) kept both drones on the ground without normalisation whatever
else was changed, and moved them only with it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jaxdrones.envs.base import EnvState
from jaxdrones.wrappers.autoreset import _Wrapper

#: Standardised observations are clipped to ±CLIP (gymnasium's and brax's PPO examples use 10 or 5).
CLIP = 10.0
#: The prior's weight in samples (gymnasium's ``RunningMeanStd`` epsilon): mean 0, variance 1 until data arrive.
PRIOR_COUNT = 1e-4


@struct.dataclass
class RunningStats:
    """Running mean and variance of each observation entry, pooled over the drones of a world.

    Attributes:
        mean: f[n_obs].
        var: f[n_obs] (population variance).
        count: f[], samples seen (drone-steps), plus `PRIOR_COUNT`.
    """

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def prior(cls, n_obs: int, dtype) -> RunningStats:
        """Mean 0, variance 1, weight `PRIOR_COUNT`."""
        return cls(jnp.zeros(n_obs, dtype), jnp.ones(n_obs, dtype), jnp.asarray(PRIOR_COUNT, dtype))

    def update(self, batch: jax.Array) -> RunningStats:
        """The statistics with ``batch`` f[..., n_obs] added (Chan et al.'s parallel update, as gymnasium's
        ``RunningMeanStd.update_from_moments``)."""
        batch = batch.reshape(-1, batch.shape[-1]).astype(self.mean.dtype)
        n = batch.shape[0]
        mean, var = jnp.mean(batch, axis=0), jnp.var(batch, axis=0)
        total = self.count + n
        delta = mean - self.mean
        new_mean = self.mean + delta * (n / total)
        m2 = self.var * self.count + var * n + delta**2 * (self.count * n / total)
        return RunningStats(new_mean, m2 / total, total)

    def normalize(self, obs: jax.Array) -> jax.Array:
        """``obs`` standardised, (obs − mean) / √(var + 1e-8), clipped to ±`CLIP`."""
        scaled = (obs - self.mean) / jnp.sqrt(self.var + 1e-8)
        return jnp.clip(scaled, -CLIP, CLIP).astype(obs.dtype)


class NormalizeObservation(_Wrapper):
    """Standardise ``state.obs`` f[D, n_obs] with running statistics of this world's observations (see the module
    docstring), updated at every `reset` and `step` before the observation is standardised.

    ``state.info["obs_norm"]`` holds the `RunningStats`; ``state.info["final_obs"]`` (from `AutoReset`) stays
    unstandardised. Observations with camera images are not supported.

    Raises:
        ValueError: an env whose observation is a dict (``vision``).
    """

    def __init__(self, env):
        if isinstance(env.observation_spec, dict):
            raise ValueError("NormalizeObservation standardises state observations f[D, n_obs]; this env's "
                             "observation has camera images (vision)")
        super().__init__(env)

    def reset(self, key: jax.Array, task=None) -> EnvState:
        state = self.env.reset(key, task)
        stats = RunningStats.prior(state.obs.shape[-1], state.obs.dtype)
        return self._normalize(state, stats)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        stats = state.info["obs_norm"]
        return self._normalize(self.env.step(state, action), stats)

    @staticmethod
    def _normalize(state: EnvState, stats: RunningStats) -> EnvState:
        stats = stats.update(state.obs)
        return state.replace(obs=stats.normalize(state.obs), info={**state.info, "obs_norm": stats})
