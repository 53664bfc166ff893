"""The helpers of the firmware's ``src/modules/interface/math3d.h`` that its controllers use, on tuples of float32
components (x, y, z) or (x, y, z, w), in the C's order of operations (bitcraze/crazyflie-firmware at 2a18fc29)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

_F = np.float32
_PI = _F(math.pi)


def radians(degrees: jax.Array) -> jax.Array:
    """``radians``: (π / 180) · degrees."""
    return (_PI / _F(180.0)) * degrees


def degrees(radians: jax.Array) -> jax.Array:
    """``degrees``: (180 / π) · radians."""
    return (_F(180.0) / _PI) * radians


def clamp(value: jax.Array, low: jax.Array | float, high: jax.Array | float) -> jax.Array:
    """``clamp``: below ``low`` gives ``low``, above ``high`` gives ``high`` (NaN stays)."""
    return jnp.where(value < low, low, jnp.where(value > high, high, value))


def cross(a: tuple, b: tuple) -> tuple:
    """``vcross``."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot(a: tuple, b: tuple) -> jax.Array:
    """``vdot``."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def normalize(v: tuple) -> tuple:
    """``vnormalize``: ``v`` times 1 / ``sqrtf(vdot(v, v))``."""
    inverse = 1.0 / jnp.sqrt(dot(v, v))
    return tuple(inverse * c for c in v)


def qqmul(q: tuple, p: tuple) -> tuple:
    """``qqmul``: the product of two (x, y, z, w) quaternions, ``qvrot(qqmul(q, p), v) == qvrot(q, qvrot(p, v))``."""
    return (
        q[3] * p[0] + q[2] * p[1] - q[1] * p[2] + q[0] * p[3],
        -q[2] * p[0] + q[3] * p[1] + q[0] * p[2] + q[1] * p[3],
        q[1] * p[0] - q[0] * p[1] + q[3] * p[2] + q[2] * p[3],
        -q[0] * p[0] - q[1] * p[1] - q[2] * p[2] + q[3] * p[3],
    )


def qnormalize(q: tuple) -> tuple:
    """``qnormalize``: s = 1 / ``sqrtf(qdot(q, q))``, then each component times s."""
    s = 1.0 / jnp.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return tuple(s * c for c in q)


def rotmat_columns(x: jax.Array, y: jax.Array, z: jax.Array, w: jax.Array) -> tuple:
    """``quat2rotmat``'s three columns, each (x, y, z)."""
    m00, m01, m02 = 1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * z * w, 2 * x * z + 2 * y * w
    m10, m11, m12 = 2 * x * y + 2 * z * w, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * x * w
    m20, m21, m22 = 2 * x * z - 2 * y * w, 2 * y * z + 2 * x * w, 1 - 2 * x * x - 2 * y * y
    return (m00, m10, m20), (m01, m11, m21), (m02, m12, m22)


def rpy2quat(r: jax.Array, p: jax.Array, y: jax.Array) -> tuple:
    """``rpy2quat``: (x, y, z, w)."""
    cr, sr = jnp.cos(r / 2.0), jnp.sin(r / 2.0)
    cp, sp = jnp.cos(p / 2.0), jnp.sin(p / 2.0)
    cy, sy = jnp.cos(y / 2.0), jnp.sin(y / 2.0)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def quat_yaw(quat: jax.Array) -> jax.Array:
    """The yaw of ``quat2rpy`` in degrees, of f32[..., 4] (x, y, z, w): what the controllers take of a quaternion
    setpoint."""
    x, y, z, w = (quat[..., k] for k in range(4))
    return degrees(jnp.arctan2(2.0 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
