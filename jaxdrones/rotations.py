"""Quaternion and Euler-angle helpers, PyBullet conventions.

Quaternions are (x, y, z, w) and rotate body to world. Euler angles are (roll, pitch, yaw) with
R = Rz(yaw)·Ry(pitch)·Rx(roll), PyBullet's ``getQuaternionFromEuler``/``getEulerFromQuaternion`` (facts §0).
All functions broadcast over leading axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

#: |ω| at or below which the exponential-map update leaves q unchanged (numpy ``isclose(|ω|, 0)``, facts §4.6).
OMEGA_EPS = 1e-8
#: |sin(pitch)| at which PyBullet's Euler conversion snaps to gimbal lock (facts §0).
GIMBAL_SNAP = 0.99999


def quat_to_rotmat(quat: jax.Array) -> jax.Array:
    """Rotation matrix of a quaternion, normalising it first as ``getMatrixFromQuaternion`` does.

    Args:
        quat: f[..., 4] (x, y, z, w), body→world.

    Returns:
        f[..., 3, 3] R with world = R @ body.
    """
    q = quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product a ⊗ b of (x, y, z, w) quaternions, f[..., 4]."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ], axis=-1)


def quat_from_euler(rpy: jax.Array) -> jax.Array:
    """Quaternion (x, y, z, w) of roll, pitch, yaw in rad (``getQuaternionFromEuler``), f[..., 3] -> f[..., 4]."""
    half = 0.5 * jnp.asarray(rpy)
    cr, cp, cy = jnp.cos(half[..., 0]), jnp.cos(half[..., 1]), jnp.cos(half[..., 2])
    sr, sp, sy = jnp.sin(half[..., 0]), jnp.sin(half[..., 1]), jnp.sin(half[..., 2])
    return jnp.stack([
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    ], axis=-1)


def quat_to_euler(quat: jax.Array) -> jax.Array:
    """Roll, pitch, yaw in rad of a unit quaternion, exactly as ``getEulerFromQuaternion`` (facts §0).

    Within about 0.26° of pitch ±90° (|sin pitch| ≥ 0.99999) PyBullet snaps to roll = 0, pitch = ±π/2, and so does
    this function.

    Args:
        quat: f[..., 4] (x, y, z, w).

    Returns:
        f[..., 3] (roll, pitch, yaw), rad.
    """
    x, y, z, w = quat[..., 0], quat[..., 1], quat[..., 2], quat[..., 3]
    s = -2.0 * (x * z - w * y)
    low, high = s <= -GIMBAL_SNAP, s >= GIMBAL_SNAP
    roll = jnp.arctan2(2 * (y * z + w * x), w * w - x * x - y * y + z * z)
    pitch = jnp.arcsin(jnp.clip(s, -GIMBAL_SNAP, GIMBAL_SNAP))
    yaw = jnp.arctan2(2 * (x * y + w * z), w * w + x * x - y * y - z * z)
    half_pi = jnp.pi / 2
    roll = jnp.where(low | high, 0.0, roll)
    pitch = jnp.where(low, -half_pi, jnp.where(high, half_pi, pitch))
    yaw = jnp.where(low, 2 * jnp.arctan2(x, -y), jnp.where(high, 2 * jnp.arctan2(-x, y), yaw))
    return jnp.stack([roll, pitch, yaw], axis=-1)


def quat_integrate(quat: jax.Array, ang_vel: jax.Array, dt: float) -> jax.Array:
    """Exact exponential-map update for a constant body rate: q ⊗ [sin(|ω|dt/2) ω/|ω|, cos(|ω|dt/2)].

    This is the paper code's explicit-dynamics quaternion update (facts §4.6); q is left unchanged when
    |ω| ≤ 1e-8 rad/s. Safe to differentiate at ω = 0.

    Args:
        quat: f[..., 4] (x, y, z, w), body→world.
        ang_vel: f[..., 3] rad/s, body frame.
        dt: s.

    Returns:
        f[..., 4] the rotated quaternion (not renormalised).
    """
    sq = jnp.sum(ang_vel * ang_vel, axis=-1, keepdims=True)
    moving = sq > OMEGA_EPS**2
    norm = jnp.sqrt(jnp.where(moving, sq, 1.0))
    theta = 0.5 * dt * norm
    axis_sin = jnp.where(moving, jnp.sin(theta) / norm, 0.5 * dt) * ang_vel
    delta = jnp.concatenate([axis_sin, jnp.where(moving, jnp.cos(theta), 1.0)], axis=-1)
    return jnp.where(moving, quat_mul(quat, delta), quat)


def quat_derivative(quat: jax.Array, ang_vel: jax.Array) -> jax.Array:
    """q̇ = ½ q ⊗ (ω, 0) for a body-frame rate ω in rad/s; f[..., 4], f[..., 3] -> f[..., 4] per second."""
    return 0.5 * quat_mul(quat, jnp.concatenate([ang_vel, jnp.zeros_like(ang_vel[..., :1])], axis=-1))


def rotate(rotmat: jax.Array, vec: jax.Array) -> jax.Array:
    """R @ v over leading axes: f[..., 3, 3], f[..., 3] -> f[..., 3]."""
    return jnp.einsum("...ij,...j->...i", rotmat, vec)
