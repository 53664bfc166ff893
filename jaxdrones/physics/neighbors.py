"""Neighbour lists, which bound the cost of the pairwise couplings of a team of D drones: the k nearest drones of
each drone (`nearest`, for the ``neighbors`` observation) and the drones within a radius found with a cell list
(`cell_candidates`, for the downwash), whose cost grows as D rather than D²."""

from __future__ import annotations

import math

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
    """``x`` f[..., D] at the drones of a neighbour list i32[..., D, k]: f[..., D, k]."""
    return jnp.take_along_axis(x[..., None, :], indices, axis=-1)


def _flat_batch(fn, *arrays):
    """``fn`` on one world's f[D] arrays, mapped over any leading axes."""
    lead = arrays[0].shape[:-1]
    flat = [a.reshape((-1, a.shape[-1])) for a in arrays]
    out = jax.vmap(fn)(*flat)
    return out.reshape(lead + out.shape[1:])


#: The 3 × 3 block of cells around a drone's cell.
_BLOCK = tuple((dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1))


def cell_candidates(x: jax.Array, y: jax.Array, radius: float, capacity: int) -> jax.Array:
    """The drones that may lie within ``radius`` horizontally of each drone, found with a cell list (Allen &
    Tildesley, "Computer Simulation of Liquids", §5.3): the plane is cut into square cells of side ``radius``, and a
    drone's candidates are the drones of the 3 × 3 cells around its own, at most ``capacity`` per cell. It costs
    O(D log D) per world (a sort of the drones by cell), not D²: every drone within ``radius`` is found unless its cell
    holds more than ``capacity`` drones.

    Cells map to a periodic table of at least 2D buckets (cell (i, j) to bucket (i mod s, j mod s)): cells s apart
    share a bucket, which only adds candidates (the caller keeps those within ``radius``), and a bucket met twice in
    one 3 × 3 block is counted once.

    Args:
        x, y: f[..., D] m, horizontal positions. No gradient flows through the choice.
        radius: cell side, m (> 0).
        capacity: slots per cell (≥ 1).

    Returns:
        i32[..., D, 9·capacity] drone indices; free slots hold the drone itself.
    """
    n = x.shape[-1]
    side = 1 << max(2, math.ceil(math.log2(math.sqrt(2 * n))))  # a periodic side × side table of ≥ 2D cells
    buckets = side * side

    def bucket(cx, cy):  # cells side apart share a bucket
        return jnp.bitwise_and(cx, side - 1) * side + jnp.bitwise_and(cy, side - 1)

    def one_world(x, y):
        cx, cy = (jnp.floor(jax.lax.stop_gradient(v) / radius).astype(jnp.int32) for v in (x, y))
        own = bucket(cx, cy)
        order = jnp.argsort(own)
        count = jnp.zeros(buckets, jnp.int32).at[own].add(1)
        start = jnp.cumsum(count) - count
        block = jnp.stack([bucket(cx + dx, cy + dy) for dx, dy in _BLOCK], -1)  # [D, 9]
        seen_before = jnp.any((block[:, :, None] == block[:, None, :]) & jnp.tri(9, k=-1, dtype=bool)[None], -1)
        slot = jnp.arange(capacity)
        valid = (slot[None, None] < count[block][..., None]) & ~seen_before[..., None]  # [D, 9, C]
        index = order[jnp.minimum(start[block][..., None] + slot[None, None], n - 1)]
        self_index = jnp.arange(n)[:, None, None]
        return jnp.where(valid, index, self_index).reshape(n, 9 * capacity)

    return _flat_batch(one_world, x, y)
