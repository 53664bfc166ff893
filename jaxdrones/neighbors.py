"""Neighbour lists: the k nearest drones of each drone, which bound the cost of pairwise couplings (downwash, the
``neighbors`` observation) to D·k pairs."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def nearest(dist2: jax.Array, k: int) -> jax.Array:
    """The ``k`` drones nearest to each drone, itself excluded, nearest first.

    Args:
        dist2: f[..., D, D], squared distances between drones (any metric; row i for drone i). No gradient flows
            through the choice.
        k: 1 ≤ k ≤ D - 1.

    Returns:
        i32[..., D, k], drone indices.

    Raises:
        ValueError: k out of range.
    """
    n = dist2.shape[-1]
    if not isinstance(k, int) or not 1 <= k <= n - 1:
        raise ValueError(f"nearest: k must be an integer in [1, D - 1] = [1, {n - 1}], got {k!r}")
    dist2 = jnp.where(jnp.eye(n, dtype=bool), jnp.inf, jax.lax.stop_gradient(dist2))
    return jax.lax.top_k(-dist2, k)[1]


def gather(x: jax.Array, indices: jax.Array) -> jax.Array:
    """``x`` f[..., D] (or f[..., D, n]) at the drones of a neighbour list i32[..., D, k]: f[..., D, k] (or
    f[..., D, k, n])."""
    if x.ndim == indices.ndim - 1:
        return jnp.take_along_axis(x[..., None, :], indices, axis=-1)
    return jnp.take_along_axis(x[..., None, :, :], indices[..., None], axis=-2)
