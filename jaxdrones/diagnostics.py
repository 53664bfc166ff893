"""Diagnostics of gradients through rollouts: how the gradient of a task's return behaves as the horizon grows.

Backpropagation through long rollouts of a chaotic or unstable system (a quadrotor is open-loop unstable) gives
gradients whose norm and variance grow with the horizon until they carry no useful direction (Metz et al.,
"Gradients are Not All You Need", 2021; Suh et al., "Do Differentiable Simulators Give Better Policy Gradients?",
ICML 2022). `return_gradient_stats` measures this for any task and policy, so that a horizon (or a truncation,
as in short-horizon actor-critic) can be chosen from data.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs.base import Env, EnvState


def episode_return(env: Env, policy: Callable, policy_params: Any, state: EnvState, horizon: int) -> jax.Array:
    """Sum over ``horizon`` control steps of the drones' summed reward, the policy acting on the observation.

    Args:
        env: a jaxdrones env (one world).
        policy: ``policy(policy_params, obs f[D, n_obs]) -> action f[D, n_act]``, differentiable.
        policy_params: a pytree of arrays.
        state: the start, from ``env.reset``.
        horizon: control steps (static).

    Returns:
        f[] the return (no discount, no auto-reset: the env keeps stepping after a termination).
    """

    def body(s, _):
        s = env.step(s, policy(policy_params, s.obs))
        return s, jnp.sum(s.reward)

    return jnp.sum(jax.lax.scan(body, state, None, length=horizon)[1])


def return_gradient_stats(
    env: Env,
    policy: Callable,
    policy_params: Any,
    key: jax.Array,
    horizons: Sequence[int] = (10, 30, 100, 300),
    n_starts: int = 64,
) -> list[dict]:
    """Statistics of the gradient of the return w.r.t. the policy's params, over random starts, per horizon.

    For each horizon H, the return of H steps from each of ``n_starts`` starts (``env.reset`` with keys split from
    ``key``) is differentiated w.r.t. ``policy_params`` (one jitted, vmapped call per horizon).

    Args:
        env: a jaxdrones env (one world).
        policy: ``policy(policy_params, obs) -> action`` (see `episode_return`).
        policy_params: a pytree of arrays.
        key: PRNG key of the starts (the same starts for every horizon).
        horizons: control-step horizons to measure.
        n_starts: starts (samples) per horizon, ≥ 2.

    Returns:
        One dict per horizon: ``horizon``, ``return_mean`` and ``return_std`` of the return, ``grad_norm_mean``
        (mean over starts of ‖∇‖), ``mean_grad_norm`` (‖mean ∇‖, the signal), ``grad_variance`` (mean over starts
        of ‖∇ − mean ∇‖², the noise), ``snr`` (``mean_grad_norm`` / √``grad_variance``), ``nonfinite`` (starts
        whose gradient has a NaN or inf; excluded from the other figures).

    Raises:
        ValueError: ``n_starts`` < 2 or a horizon < 1.
    """
    if n_starts < 2 or min(horizons) < 1:
        raise ValueError(
            f"n_starts must be >= 2 and every horizon >= 1, got n_starts={n_starts}, horizons={tuple(horizons)}"
        )
    states = jax.vmap(env.reset)(jax.random.split(key, n_starts))
    flat = lambda tree: jnp.concatenate([jnp.ravel(x) for x in jax.tree.leaves(tree)])  # noqa: E731
    stats = []
    for horizon in horizons:

        def value_and_flat_grad(state, horizon=horizon):
            value, grad = jax.value_and_grad(lambda p: episode_return(env, policy, p, state, horizon))(policy_params)
            return value, flat(grad)

        values, grads = jax.jit(jax.vmap(value_and_flat_grad))(states)
        values, grads = np.asarray(values, np.float64), np.asarray(grads, np.float64)
        finite = np.all(np.isfinite(grads), axis=1) & np.isfinite(values)
        g = grads[finite]
        mean = g.mean(axis=0) if len(g) else np.full(grads.shape[1], np.nan)
        variance = float(np.mean(np.sum((g - mean) ** 2, axis=1))) if len(g) else float("nan")
        signal = float(np.linalg.norm(mean))
        stats.append(
            {
                "horizon": int(horizon),
                "return_mean": float(values[finite].mean()),
                "return_std": float(values[finite].std()),
                "grad_norm_mean": float(np.linalg.norm(g, axis=1).mean()) if len(g) else float("nan"),
                "mean_grad_norm": signal,
                "grad_variance": variance,
                "snr": float(signal / np.sqrt(variance)) if variance > 0 else float("inf"),
                "nonfinite": int((~finite).sum()),
            }
        )
    return stats
