"""Termination conditions shared by the tasks: each returns ``bool[..., D]`` per drone; a task decides how they
combine into the world's ``terminated`` (usually: any drone)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxdrones.physics.rotations import quat_to_rotmat
from jaxdrones.physics.state import DroneState


def out_of_bounds(pos: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
    """Whether a drone left the box [low, high] (f[..., 3] m, world frame)."""
    low, high = (jnp.broadcast_to(b, pos.shape) for b in (low, high))
    return jnp.any((pos < low) | (pos > high), axis=-1)


def tilted(quat: jax.Array, max_tilt: jax.Array) -> jax.Array:
    """Whether the angle between body z and world z exceeds ``max_tilt`` rad (π/2: the drone is on its side)."""
    return quat_to_rotmat(quat)[..., 2, 2] < jnp.cos(max_tilt)


def not_finite(sim: DroneState) -> jax.Array:
    """Whether a drone's state holds NaN or inf."""
    parts = (sim.pos, sim.quat, sim.vel, sim.ang_vel)
    return ~jnp.all(jnp.stack([jnp.all(jnp.isfinite(x), axis=-1) for x in parts]), axis=0)


def crashed(sim: DroneState, bounds: Any, terminate_on_ground: bool) -> jax.Array:
    """Out of the arena, tilted beyond the limit, not finite or (if asked) touching the ground: bool[..., D].

    Args:
        sim: the drones' state.
        bounds: a `jaxdrones.envs.task.Bounds` (pos_low, pos_high f[3] m; max_tilt f[] rad); typed `Any` as that
            module imports this one.
        terminate_on_ground: count ground contact as a crash.
    """
    out = out_of_bounds(sim.pos, bounds.pos_low, bounds.pos_high) | tilted(sim.quat, bounds.max_tilt)
    out = out | not_finite(sim)
    if terminate_on_ground:
        out = out | sim.ground_contact
    return out
