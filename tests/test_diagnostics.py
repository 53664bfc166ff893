"""`jaxdrones.diagnostics`: the gradient statistics of a task's return against a direct computation, and their
growth with the horizon (backpropagation through a long rollout of an unstable system)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.diagnostics import episode_return, return_gradient_stats


def linear_policy(params, obs):
    return jnp.tanh(obs @ params["w"])


def test_gradient_stats_match_a_direct_computation_and_grow_with_the_horizon():
    env = jd.make("hover", reward="paper")
    params = {"w": 0.05 * jax.random.normal(jax.random.key(1), (env.observation_size, env.action_size))}
    key = jax.random.key(0)
    short, long = return_gradient_stats(env, linear_policy, params, key, horizons=(5, 40), n_starts=4)
    # Direct: one gradient per start, in a Python loop.
    starts = jax.vmap(env.reset)(jax.random.split(key, 4))
    value_and_grad = jax.jit(jax.value_and_grad(lambda p, s: episode_return(env, linear_policy, p, s, 5)))
    grads, returns = [], []
    for i in range(4):
        value, grad = value_and_grad(params, jax.tree.map(lambda x, i=i: x[i], starts))
        returns.append(float(value))
        grads.append(np.ravel(np.asarray(grad["w"], np.float64)))
    grads = np.array(grads)
    mean = grads.mean(axis=0)
    assert short["horizon"] == 5 and short["nonfinite"] == 0
    assert short["return_mean"] == pytest.approx(np.mean(returns), rel=1e-5)
    assert short["mean_grad_norm"] == pytest.approx(np.linalg.norm(mean), rel=1e-4)
    assert short["grad_norm_mean"] == pytest.approx(np.linalg.norm(grads, axis=1).mean(), rel=1e-4)
    assert short["grad_variance"] == pytest.approx(np.mean(np.sum((grads - mean) ** 2, axis=1)), rel=1e-4)
    # 1.3 s instead of 0.17 s of an unstable system: the gradients are orders of magnitude larger.
    assert long["nonfinite"] == 0 and long["grad_norm_mean"] > 100 * short["grad_norm_mean"]


def test_gradient_stats_bad_input():
    env = jd.make("hover")
    with pytest.raises(ValueError, match="n_starts must be >= 2"):
        return_gradient_stats(env, linear_policy, {"w": jnp.zeros((21, 4))}, jax.random.key(0), n_starts=1)
