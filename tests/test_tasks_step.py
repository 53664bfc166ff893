"""Every registered task builds with its defaults, resets and takes one step (`jd.make(task)`, jitted): the
observation, reward and flags have the documented shapes and are finite. The env layer's smoke test, in the fast
tier; `tests/test_env.py` checks each task in depth."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.envs import registered

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("task", registered())
def test_one_reset_one_step(task):
    env = jd.make(task)
    state = jax.jit(env.reset)(jax.random.key(0))
    action = jnp.zeros((env.n_drones, env.action_size), env.dtype)
    state = jax.jit(env.step)(state, action)
    obs = state.obs["state"] if isinstance(state.obs, dict) else state.obs
    assert obs.shape == (env.n_drones, env.observation_size)
    assert np.all(np.isfinite(obs)) and np.isfinite(state.reward).all()
    assert np.shape(state.reward) in ((), (env.n_drones,))
    assert int(state.steps) == 1 and not bool(state.truncated)
    assert np.all(np.isfinite(state.sim.pos)) and np.all(state.sim.pos[..., 2] >= 0)
