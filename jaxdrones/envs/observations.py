"""Observation types: what each drone sees, as stacked arrays ``f[..., D, size]`` (docs/physics.md §8).

=============  ======================  =================================================================================
name           size per drone          content
=============  ======================  =================================================================================
``kin``        12                      pos (m, world), rpy (rad, PyBullet convention), vel (m/s, world), ang_vel
                                       (rad/s, body) — SI units, unnormalised, the order of gym-pybullet-drones' KIN
``kin_norm``   12                      the paper's normalised KIN: xy/15, z/5, roll, pitch, yaw / π, vxy/3, vz/1,
                                       ang_vel as a unit vector — with vz divided by its own limit (the original
                                       divides it by the xy limit, 3, so its vz never leaves [-1/3, 1/3])
``kin_rotmat`` 21                      ``kin``, then the rotation matrix R (body→world, row-major): the attitude
                                       without the Euler angles' wrap-around at ±π (easier to learn from with any
                                       heading)
``neighbors``  12 + D + 3(D - 1)       ``kin``, then the drone's adjacency row (1 for itself and every drone within
                                       ``neighbor_radius`` m, eq. adj), then the positions of the other drones
                                       relative to it (m, world, in drone order, 0 for drones outside the radius)
               12 + 4k                 with ``max_neighbors`` (k = min(max_neighbors, D - 1)): ``kin``, then for the k
                                       drones nearest to it (3-D distance, nearest first) a flag (1 within
                                       ``neighbor_radius``), then their positions relative to it (m, world, 0 outside
                                       the radius): a size that does not grow with the team
=============  ======================  =================================================================================

With ``action_buffer=True`` the last ``ctrl_freq // 2`` actions (0.5 s, oldest first, the current step's last) are
appended, as the original's KIN does; unlike the original, the buffer is cleared at reset.

Every observation has a box (`bounds`), and is clipped to it: positions to ±`POS_BOUND` m (z to [0, `POS_BOUND`]),
velocities to ±`VEL_BOUND` m/s, body rates to ±`ANG_VEL_BOUND` rad/s. The bounds are far outside what a flying
task reaches before it terminates; the unclipped state is ``EnvState.sim``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.physics.neighbors import nearest
from jaxdrones.physics.rotations import quat_to_euler, quat_to_rotmat
from jaxdrones.physics.state import DroneState

#: Clip bounds of the observations: position (m), velocity (m/s), body rates (rad/s), relative positions (m).
POS_BOUND = 20.0
VEL_BOUND = 30.0
ANG_VEL_BOUND = 200.0
#: The paper's normalisation limits (HoverAviary._clipAndNormalizeState): xy m, z m, vxy m/s, vz m/s.
NORM_XY, NORM_Z, NORM_VXY, NORM_VZ = 15.0, 5.0, 3.0, 1.0


def kinematic_obs(sim: DroneState) -> jax.Array:
    """The kinematic observation KIN of each drone, unclipped.

    Returns:
        f[..., D, 12]: pos (m, world), rpy (rad, PyBullet convention), vel (m/s, world), ang_vel (rad/s, body).
    """
    return jnp.concatenate([sim.pos, quat_to_euler(sim.quat), sim.vel, sim.ang_vel], axis=-1)


def _kin_bounds() -> tuple[np.ndarray, np.ndarray]:
    pi = np.pi
    high = np.array([POS_BOUND] * 3 + [pi, pi / 2, pi] + [VEL_BOUND] * 3 + [ANG_VEL_BOUND] * 3, np.float32)
    low = -high
    low[2] = 0.0
    # PyBullet's yaw in the gimbal-lock branch is 2·atan2(...), within [-2π, 2π].
    low[5], high[5] = -2 * pi, 2 * pi
    return low, high


def kin_normalized(sim: DroneState) -> jax.Array:
    """The paper's normalised KIN (``_clipAndNormalizeState``), with vz normalised by its own limit.

    Returns:
        f[..., D, 12] in [-1, 1] (z in [0, 1]).
    """
    pos, rpy = sim.pos, quat_to_euler(sim.quat)
    xy = jnp.clip(pos[..., :2], -NORM_XY, NORM_XY) / NORM_XY
    z = jnp.clip(pos[..., 2:], 0.0, NORM_Z) / NORM_Z
    angles = jnp.clip(rpy, -np.pi, np.pi) / np.pi
    vxy = jnp.clip(sim.vel[..., :2], -NORM_VXY, NORM_VXY) / NORM_VXY
    vz = jnp.clip(sim.vel[..., 2:], -NORM_VZ, NORM_VZ) / NORM_VZ
    sq = jnp.sum(sim.ang_vel**2, axis=-1, keepdims=True)
    moving = sq > 0
    unit = jnp.where(moving, sim.ang_vel / jnp.sqrt(jnp.where(moving, sq, 1.0)), 0.0)
    return jnp.concatenate([xy, z, angles, vxy, vz, unit], axis=-1)


def adjacency(pos: jax.Array, radius: float) -> jax.Array:
    """The adjacency matrix of eq. adj: 1 where two drones are within ``radius`` m (3-D distance), and on the
    diagonal (gym-pybullet-drones ``_getAdjacencyMatrix``).

    Args:
        pos: f[..., D, 3] m.
        radius: m (``inf`` connects everyone).

    Returns:
        f[..., D, D] of 0 and 1.
    """
    delta = pos[..., None, :, :] - pos[..., :, None, :]
    near = jnp.sum(delta**2, axis=-1) < radius**2
    eye = jnp.eye(pos.shape[-2], dtype=bool)
    return (near | eye).astype(pos.dtype)


def relative_positions(pos: jax.Array, adj: jax.Array) -> jax.Array:
    """Positions of the other drones relative to each drone, zero for non-neighbours.

    Args:
        pos: f[..., D, 3] m, world frame.
        adj: f[..., D, D] adjacency (see `adjacency`).

    Returns:
        f[..., D, 3(D-1)] m: for drone i, p_j - p_i for every j ≠ i in increasing j.
    """
    n = pos.shape[-2]
    delta = (pos[..., None, :, :] - pos[..., :, None, :]) * adj[..., None]
    others = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int32).reshape(n, n - 1)
    picked = jnp.take_along_axis(delta, jnp.broadcast_to(others[..., None], delta.shape[:-2] + (n - 1, 3)), axis=-2)
    return jnp.clip(picked, -POS_BOUND, POS_BOUND).reshape(pos.shape[:-2] + (n, 3 * (n - 1)))


def nearest_neighbors(pos: jax.Array, radius: float, k: int) -> tuple[jax.Array, jax.Array]:
    """The k drones nearest to each drone (3-D distance, itself excluded, nearest first).

    Args:
        pos: f[..., D, 3] m, world frame.
        radius: m; drones farther away are flagged 0 and their relative position is 0.
        k: 1 ≤ k ≤ D - 1 (else ValueError).

    Returns:
        (flags f[..., D, k]: 1 within ``radius``; relative positions f[..., D, 3k] m, p_j - p_i, clipped to
        ±`POS_BOUND`).
    """
    delta = pos[..., None, :, :] - pos[..., :, None, :]  # [..., i, j]: p_j - p_i
    dist2 = jnp.sum(delta**2, axis=-1)
    indices = nearest(dist2, k)
    near = jnp.take_along_axis(dist2, indices, axis=-1) < radius**2
    rel = jnp.take_along_axis(delta, indices[..., None], axis=-2) * near[..., None]
    rel = jnp.clip(rel, -POS_BOUND, POS_BOUND)
    return near.astype(pos.dtype), rel.reshape(rel.shape[:-2] + (3 * k,))


@dataclasses.dataclass(frozen=True)
class ObsType:
    """An observation type for ``n_drones`` drones (static, hashable).

    Attributes:
        name: registered name (`OBS_TYPES`).
        n_drones: D.
        neighbor_radius: m, for ``neighbors``.
        buffer_len: actions kept in the action buffer (0: no buffer).
        action_size: entries per action in the buffer.
        max_neighbors: ``neighbors``: None (every drone, the paper's layout) or K (the min(K, D - 1) nearest).
    """

    name: str
    n_drones: int
    neighbor_radius: float = float("inf")
    buffer_len: int = 0
    action_size: int = 0
    max_neighbors: int | None = None

    @property
    def n_nearest(self) -> int | None:
        """K of the ``neighbors`` observation's nearest drones, or None for the paper's layout (every drone)."""
        return None if self.max_neighbors is None else min(self.max_neighbors, self.n_drones - 1)

    @property
    def size(self) -> int:
        """Entries per drone."""
        return _LAYOUTS[self.name].size(self) + self.buffer_len * self.action_size

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high), each f32[D, size]: the observation box."""
        low, high = _LAYOUTS[self.name].bounds(self)
        ones = np.ones(self.buffer_len * self.action_size, np.float32)
        low, high = np.concatenate([low, -ones]), np.concatenate([high, ones])
        return np.tile(low, (self.n_drones, 1)), np.tile(high, (self.n_drones, 1))

    def observe(self, sim: DroneState, buffer: jax.Array) -> jax.Array:
        """The observation f[..., D, size] of ``sim``, with the action ``buffer`` f[..., D, K, n_act] appended.

        Clipped to `bounds` (see the module docstring).
        """
        parts = _LAYOUTS[self.name].observe(self, sim)
        if self.buffer_len:
            parts.append(buffer.reshape(buffer.shape[:-2] + (-1,)))
        obs = jnp.concatenate(parts, axis=-1)
        low, high = self.bounds()
        return jnp.clip(obs, low.astype(obs.dtype), high.astype(obs.dtype))


def _norm_bounds(obs_type: ObsType) -> tuple[np.ndarray, np.ndarray]:
    low, high = -np.ones(12, np.float32), np.ones(12, np.float32)
    low[2] = 0.0
    return low, high


def _rotmat_bounds(obs_type: ObsType) -> tuple[np.ndarray, np.ndarray]:
    low, high = _kin_bounds()
    return np.concatenate([low, -np.ones(9, np.float32)]), np.concatenate([high, np.ones(9, np.float32)])


def _rotmat_obs(obs_type: ObsType, sim: DroneState) -> list:
    return [kinematic_obs(sim), quat_to_rotmat(sim.quat).reshape(sim.quat.shape[:-1] + (9,))]


def _neighbors_size(obs_type: ObsType) -> int:
    n, k = obs_type.n_drones, obs_type.n_nearest
    return 12 + (n + 3 * (n - 1) if k is None else 4 * k)


def _neighbors_bounds(obs_type: ObsType) -> tuple[np.ndarray, np.ndarray]:
    low, high = _kin_bounds()
    n, k = obs_type.n_drones, obs_type.n_nearest
    flags, others = (n, n - 1) if k is None else (k, k)
    rel = np.full(3 * others, POS_BOUND, np.float32)
    return (
        np.concatenate([low, np.zeros(flags, np.float32), -rel]),
        np.concatenate([high, np.ones(flags, np.float32), rel]),
    )


def _neighbors_obs(obs_type: ObsType, sim: DroneState) -> list:
    if obs_type.n_nearest is None:
        adj = adjacency(sim.pos, obs_type.neighbor_radius)
        return [kinematic_obs(sim), adj, relative_positions(sim.pos, adj)]
    return [kinematic_obs(sim), *nearest_neighbors(sim.pos, obs_type.neighbor_radius, obs_type.n_nearest)]


class _Layout(NamedTuple):
    size: Callable  # ObsType -> entries per drone before the action buffer
    bounds: Callable  # ObsType -> (low, high) f32[size]
    observe: Callable  # (ObsType, DroneState) -> the parts f[..., D, *] to concatenate


#: Every observation type (see the module docstring): its size, its box and its parts.
_LAYOUTS = {
    "kin": _Layout(lambda o: 12, lambda o: _kin_bounds(), lambda o, sim: [kinematic_obs(sim)]),
    "kin_norm": _Layout(lambda o: 12, _norm_bounds, lambda o, sim: [kin_normalized(sim)]),
    "kin_rotmat": _Layout(lambda o: 21, _rotmat_bounds, _rotmat_obs),
    "neighbors": _Layout(_neighbors_size, _neighbors_bounds, _neighbors_obs),
}
#: The observation types' names.
OBS_TYPES = tuple(_LAYOUTS)

#: Depth in a policy's image input: metres / DEPTH_SCALE, clipped to [0, 1] (nearer than 5 m is what a drone at a
#: few m/s must see; beyond, one value).
DEPTH_SCALE = 5.0


def policy_input(obs: jax.Array | dict[str, jax.Array]) -> jax.Array | dict[str, jax.Array]:
    """A world's observation as a policy takes it (brax's conventions; what `jaxdrones.adapters.brax.BraxEnv`
    gives its trainers and `jaxdrones.training.evaluation.act` gives a policy).

    Args:
        obs: f[D, n_obs], or with cameras the env's dict ``{"state": f[D, n], "depth": f[D, H, W], "rgb":
            u8[D, H, W, 4], "seg": i32[D, H, W]}`` (with a frame stack of K, ``f[D, K, H, W]`` and
            ``u8[D, K, H, W, 4]``: `jaxdrones.envs.config.TaskConfig.frame_stack`).

    Returns:
        f[D·n_obs]; with cameras a dict: ``"state"`` f[D·n], and per image ``"pixels/depth"`` f32[H, W, D·K]
        (depth / `DEPTH_SCALE` clipped to [0, 1]) and ``"pixels/rgb"`` f32[H, W, 3·D·K] (RGB / 255, no alpha), the
        drones and then their frames (oldest first) along the channels (brax's vision networks take keys starting
        ``pixels/``). Segmentation ids are not an image a network should read as magnitudes: they are left out.
    """
    if not isinstance(obs, dict):
        return jnp.reshape(obs, (-1,))
    out = {"state": jnp.reshape(obs["state"], (-1,))}
    if "depth" in obs:
        depth = jnp.clip(obs["depth"].astype(jnp.float32) / DEPTH_SCALE, 0.0, 1.0)
        depth = jnp.reshape(depth, (-1,) + depth.shape[-2:])  # [D·K, H, W]
        out["pixels/depth"] = jnp.moveaxis(depth, 0, -1)
    if "rgb" in obs:
        rgb = obs["rgb"][..., :3].astype(jnp.float32) / 255.0
        rgb = jnp.reshape(rgb, (-1,) + rgb.shape[-3:])  # [D·K, H, W, 3]
        out["pixels/rgb"] = jnp.concatenate(list(rgb), axis=-1)
    return out
