"""Quaternion and Euler-angle helpers, PyBullet conventions, and the component form of small vectors.

Quaternions are (x, y, z, w) and rotate body to world. Euler angles are (roll, pitch, yaw) with
R = Rz(yaw)·Ry(pitch)·Rx(roll), PyBullet's ``getQuaternionFromEuler``/``getEulerFromQuaternion`` (docs/physics.md
§0.3-0.4). All functions broadcast over leading axes.

Component form. The physics is written on tuples of per-component arrays (a position is ``(x, y, z)``, each
f[..., D]) rather than on f[..., D, 3] arrays; `split` and `join` convert. Every operation then runs over the
contiguous world and drone axes, which XLA vectorises on CPU, where a trailing axis of 3 or 4 gives strided loops,
stacks and small dot products. Matrices stay arrays (f[..., 3, 3]) and `matvec` reads their entries. The
array-form functions (``quat_mul``, ``quat_integrate``, ``quat_to_rotmat``) wrap the component form (``*_c``).

The array-form conversions users call from Python loops (`quat_to_euler`, `quat_from_euler`, `quat_to_rotmat`,
`quat_mul`) are jitted: one call is one dispatch (about 10 µs) rather than a few dozen eager operations (ms).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

#: |ω| at or below which the exponential-map update leaves q unchanged (numpy ``isclose(|ω|, 0)``;
#: docs/physics.md §4.6).
OMEGA_EPS = 1e-8
#: |sin(pitch)| at which PyBullet's Euler conversion snaps to gimbal lock (docs/physics.md §0.4).
GIMBAL_SNAP = 0.99999

#: A small vector in component form: a tuple of same-shaped arrays, e.g. (x, y, z) or (x, y, z, w).
Components = tuple


def split(x: jax.Array, contiguous: bool = False) -> Components:
    """Array f[..., k] -> component form, a k-tuple of f[...], bit for bit.

    Differentiated, the tangent of component i is the sum over the last axis of the tangent masked to entry i, so
    the cotangents of the k components are gathered back into f[..., k] by a masked sum of broadcasts, which XLA
    on CPU compiles into a loop over the array. (The transpose of the slices ``x[..., i]``, a sum of k padded
    arrays, is one that XLA:CPU's fusion emitters (jaxlib's default) compile into a loop that recomputes the
    shared cotangents of the components for every element: the gradient of a user's scan over the control step
    then cost over 200 times its forward pass.)

    Args:
        x: f[..., k].
        contiguous: on CPU, compute the components as one integer matrix product on the bits of ``x`` (the k x k
            identity times the rows: exact, NaN payloads and signed zeros included), which XLA does not fuse
            into the consumers of the components: they become contiguous arrays, read at unit stride by the
            physics, instead of strided reads of ``x`` repeated in every loop that uses them. For a state or
            command split once per control step (see `jaxdrones.sim`).
    """
    if isinstance(x, np.ndarray) and x.dtype == object:  # entry by entry (`jaxdrones.experimental.pallas`'s params)
        return _slices(x)
    return _split(x, bool(contiguous))


def _slices(x: jax.Array) -> Components:
    return tuple(x[..., i] for i in range(x.shape[-1]))


def _rows_of_product(x: jax.Array) -> Components:
    """The components of x f[..., k] as the rows of I_k · bits(x)ᵀ, an integer matrix product (exact)."""
    bits_type = {4: jnp.int32, 8: jnp.int64}[x.dtype.itemsize]
    bits = jax.lax.bitcast_convert_type(x, bits_type)
    rows = jnp.einsum("jk,...k->j...", jnp.eye(x.shape[-1], dtype=bits_type), bits)
    return tuple(jax.lax.bitcast_convert_type(row, x.dtype) for row in rows)


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _split(x: jax.Array, contiguous: bool) -> Components:
    x = jnp.asarray(x)
    if contiguous and x.dtype in (jnp.float32, jnp.float64) and x.ndim > 1:
        return jax.lax.platform_dependent(x, cpu=_rows_of_product, default=_slices)
    return _slices(x)


@_split.defjvp
def _split_jvp(contiguous, primals, tangents):
    (x,), (t,) = primals, tangents
    entry = np.arange(x.shape[-1])
    if t.dtype == jax.dtypes.float0:  # integer input
        return _split(x, contiguous), tuple(np.zeros(x.shape[:-1], jax.dtypes.float0) for _ in entry)
    return _split(x, contiguous), tuple(jnp.sum(jnp.where(entry == i, t, 0), axis=-1) for i in entry)


def join(c: Components, contiguous: bool = False) -> jax.Array:
    """Component form (k-tuple of f[...]) -> array f[..., k], bit for bit.

    Args:
        c: k-tuple of f[...].
        contiguous: differentiated on CPU, take the tangent as the product of the stacked component tangents with
            the k x k identity, so that the backward pass splits an incoming cotangent f[..., k] into its
            components with one matrix product, which XLA does not fuse, rather than with strided slices fused
            into every loop that reads a component (loops that XLA:CPU's fusion emitters leave unvectorised, with
            the cotangent's own computation repeated in each). For a state joined at every control step (see
            `jaxdrones.sim`). The product is exact for finite tangents; a NaN or infinite tangent makes the whole
            vector's NaN.
    """
    if contiguous:
        return _join(tuple(jnp.broadcast_arrays(*c)))
    return jnp.stack(c, axis=-1)


@jax.custom_jvp
def _join(c: Components) -> jax.Array:
    return jnp.stack(c, axis=-1)


def _join_by_product(t: Components) -> jax.Array:
    eye = jnp.eye(len(t), dtype=t[0].dtype)
    return jnp.einsum("kj,j...->...k", eye, jnp.stack(t), precision=jax.lax.Precision.HIGHEST)


@_join.defjvp
def _join_jvp(primals, tangents):
    (c,), (t,) = primals, tangents
    if t[0].ndim == 0:
        return _join(c), jnp.stack(t, axis=-1)
    return _join(c), jax.lax.platform_dependent(t, cpu=_join_by_product, default=lambda t: jnp.stack(t, axis=-1))


def dot(a: Components, b: Components) -> jax.Array:
    """Σ_i a_i b_i, summed pairwise: (a0 b0 + a1 b1) + (a2 b2 + a3 b3).

    XLA on CPU contracts a product and a sum into one fused multiply-add, which rounds one product but not the
    other; summing in pairs keeps sums of equal and opposite products exactly zero (e.g. the roll torque of a
    hovering drone, or of a + frame raising a motor on its x axis), as a dot product does.
    """
    terms = [ai * bi for ai, bi in zip(a, b, strict=True)]
    while len(terms) > 1:
        pairs = [terms[i : i + 2] for i in range(0, len(terms), 2)]
        terms = [pair[0] + pair[1] if len(pair) == 2 else pair[0] for pair in pairs]
    return terms[0]


def matvec(m: jax.Array, v: Components) -> Components:
    """M v with M an array f[..., n, k] (e.g. a params matrix) and v a k-tuple; returns an n-tuple."""
    return tuple(dot(split(m[..., i, :]), v) for i in range(m.shape[-2]))


def cross(a: Components, b: Components) -> Components:
    """A × b of 3-vectors, as ``jnp.cross``."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def normalize_c(v: Components) -> Components:
    """V / |v| in component form."""
    norm = jnp.sqrt(dot(v, v))
    return tuple(vi / norm for vi in v)


@jax.jit
def quat_to_rotmat(quat: jax.Array) -> jax.Array:
    """Rotation matrix of a quaternion, normalising it first as ``getMatrixFromQuaternion`` does.

    Args:
        quat: f[..., 4] (x, y, z, w), body→world.

    Returns:
        f[..., 3, 3] R with world = R @ body.
    """
    return jnp.stack([join(row) for row in quat_to_rotmat_c(split(quat, contiguous=True))], axis=-2)


def quat_to_rotmat_c(quat: Components, unit: bool = False) -> tuple[Components, Components, Components]:
    """`quat_to_rotmat` in component form: (x, y, z, w) -> rows ((R00, R01, R02), (R10, ...), (R20, ...)).

    ``unit=True`` skips the normalisation, for a quaternion already known to be of unit norm.
    """
    x, y, z, w = quat if unit else normalize_c(quat)
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )


@jax.jit
def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product a ⊗ b of (x, y, z, w) quaternions, f[..., 4]."""
    return join(quat_mul_c(split(a), split(b)))


def quat_mul_c(a: Components, b: Components) -> Components:
    """`quat_mul` in component form."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


@jax.jit
def quat_from_euler(rpy: jax.Array) -> jax.Array:
    """Quaternion (x, y, z, w) of roll, pitch, yaw in rad (``getQuaternionFromEuler``), f[..., 3] -> f[..., 4]."""
    half = 0.5 * jnp.asarray(rpy)
    cr, cp, cy = jnp.cos(half[..., 0]), jnp.cos(half[..., 1]), jnp.cos(half[..., 2])
    sr, sp, sy = jnp.sin(half[..., 0]), jnp.sin(half[..., 1]), jnp.sin(half[..., 2])
    return jnp.stack(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ],
        axis=-1,
    )


#: Coefficients of Cephes' ``atanf`` polynomial: atan(z) ≈ z + z³ (p0 z⁶ + p1 z⁴ + p2 z² + p3) for |z| ≤ tan(π/8).
_ATANF = (8.05374449538e-2, -1.38776856032e-1, 1.99777106478e-1, -3.33329491539e-1)
_TAN_PI_8 = 0.4142135623730950


def atan2(y: jax.Array, x: jax.Array) -> jax.Array:
    """The angle of the point (x, y) in rad, in [-π, π], with the signed-zero conventions of C's two-argument
    arctangent.

    XLA on CPU computes ``jnp.arctan2`` with a scalar library call per element; in float32 this uses Cephes' ``atanf``
    instead (octant reduction to [0, 1], a second one at tan(π/8), a degree-9 odd polynomial; S. L. Moshier, Cephes Math
    Library, 1984-1992), which XLA vectorises (docs/benchmarks.md, "Throughput of the JAX core"), within 3e-7 rad of the
    float64 result, as ``jnp.arctan2`` is. Other dtypes use ``jnp.arctan2``. In float32 its derivative is atan2's own,
    (x dy - y dx) / (x² + y²) (not the polynomial's, whose backward pass costs several times more), taken as 0 at (0,
    0), where atan2 has none.
    """
    if jnp.result_type(y, x) != jnp.float32:
        return jnp.arctan2(y, x)
    return _atan2_f32(*jnp.broadcast_arrays(jnp.asarray(y, jnp.float32), jnp.asarray(x, jnp.float32)))


@jax.custom_jvp
def _atan2_f32(y: jax.Array, x: jax.Array) -> jax.Array:
    ax, ay = jnp.abs(x), jnp.abs(y)
    big, small = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    a = small / jnp.where(big > 0, big, 1.0)  # in [0, 1]
    far = a > _TAN_PI_8
    z = jnp.where(far, (a - 1.0) / (a + 1.0), a)
    z2 = z * z
    p0, p1, p2, p3 = _ATANF
    r = (((p0 * z2 + p1) * z2 + p2) * z2 + p3) * z2 * z + z
    r = jnp.where(far, r + jnp.pi / 4, r)
    r = jnp.where(ay > ax, jnp.pi / 2 - r, r)
    r = jnp.where(jnp.signbit(x), jnp.pi - r, r)
    return jnp.where(jnp.signbit(y), -r, r)


@_atan2_f32.defjvp
def _atan2_f32_jvp(primals, tangents):
    (y, x), (dy, dx) = primals, tangents
    r2 = x * x + y * y
    return _atan2_f32(y, x), (x * dy - y * dx) / jnp.where(r2 > 0, r2, 1.0)


def asin(x: jax.Array) -> jax.Array:
    """arcsin(x) for x in (-1, 1), rad: `atan2` (x, √(1 − x²)), vectorised on CPU in float32 as `atan2` is."""
    return atan2(x, jnp.sqrt((1.0 - x) * (1.0 + x)))


@jax.jit
def quat_to_euler(quat: jax.Array) -> jax.Array:
    """Roll, pitch, yaw in rad of a unit quaternion, exactly as ``getEulerFromQuaternion`` (docs/physics.md §0.4).

    Within about 0.26° of pitch ±90° (|sin pitch| ≥ 0.99999) PyBullet snaps to roll = 0, pitch = ±π/2, and so does
    this function.

    Args:
        quat: f[..., 4] (x, y, z, w).

    Returns:
        f[..., 3] (roll, pitch, yaw), rad.
    """
    x, y, z, w = split(quat, contiguous=True)
    s = -2.0 * (x * z - w * y)
    low, high = s <= -GIMBAL_SNAP, s >= GIMBAL_SNAP
    snap = low | high
    # Each angle is one atan2 of arguments chosen per branch (the snapped yaw is 2·atan2(x, -y) at pitch -π/2 and
    # 2·atan2(-x, y) at +π/2, the snapped roll atan2(0, 1) = 0): half the atan2 calls of evaluating both branches,
    # and the branch not taken cannot put a NaN into the derivative (atan2(0, 0) at a level attitude).
    sign = jnp.where(low, 1.0, -1.0)
    roll = atan2(jnp.where(snap, 0.0, 2 * (y * z + w * x)), jnp.where(snap, 1.0, w * w - x * x - y * y + z * z))
    pitch = asin(jnp.clip(s, -GIMBAL_SNAP, GIMBAL_SNAP))
    pitch = jnp.where(low, -jnp.pi / 2, jnp.where(high, jnp.pi / 2, pitch))
    yaw = atan2(
        jnp.where(snap, sign * x, 2 * (x * y + w * z)), jnp.where(snap, -sign * y, w * w + x * x - y * y - z * z)
    )
    yaw = jnp.where(snap, 2 * yaw, yaw)
    return jnp.stack([roll, pitch, yaw], axis=-1)


def quat_integrate(quat: jax.Array, ang_vel: jax.Array, dt: float) -> jax.Array:
    """Exact exponential-map update for a constant body rate: q ⊗ [sin(|ω|dt/2) ω/|ω|, cos(|ω|dt/2)].

    This is the paper code's explicit-dynamics quaternion update (docs/physics.md §4.6); q is left unchanged when
    |ω| ≤ 1e-8 rad/s; there its derivative is that of the first-order update q ⊗ (½ dt ω, 1), so gradients
    with respect to ω do not vanish at rest.

    Args:
        quat: f[..., 4] (x, y, z, w), body→world.
        ang_vel: f[..., 3] rad/s, body frame.
        dt: s.

    Returns:
        f[..., 4] the rotated quaternion (not renormalised).
    """
    return join(quat_integrate_c(split(quat), split(ang_vel), dt))


def quat_integrate_c(quat: Components, ang_vel: Components, dt: float) -> Components:
    """`quat_integrate` in component form."""
    sq = dot(ang_vel, ang_vel)
    moving = sq > OMEGA_EPS**2
    norm = jnp.sqrt(jnp.where(moving, sq, 1.0))
    theta = 0.5 * dt * norm
    sin_over_norm = jnp.where(moving, jnp.sin(theta) / norm, 0.5 * dt)
    delta = (*(sin_over_norm * w for w in ang_vel), jnp.where(moving, jnp.cos(theta), 1.0))
    # Below the threshold q is returned unchanged, but with the gradient of the first-order update q ⊗ (½dt ω, 1)
    # (which is what `delta` is there), so that attitude gradients flow through a drone at rest: the value is
    # q + 0 exactly, the derivative r's alone (it already holds q's own, through q ⊗ delta).
    rotated = quat_mul_c(quat, delta)
    stop = jax.lax.stop_gradient
    return tuple(jnp.where(moving, r, stop(q) + (r - stop(r))) for r, q in zip(rotated, quat, strict=True))


def quat_derivative_c(quat: Components, ang_vel: Components) -> Components:
    """q̇ = ½ q ⊗ (ω, 0) for a body-frame rate ω in rad/s: (x, y, z, w), (ωx, ωy, ωz) -> q̇ per second."""
    return tuple(0.5 * c for c in quat_mul_c(quat, (*ang_vel, jnp.zeros_like(ang_vel[0]))))


#: |sin(pitch)| above which the intrinsic 'XYZ' conversion treats the attitude as gimbal-locked (third angle 0,
#: as scipy does).
_XYZ_GIMBAL_EPS = 1e-7


def rotmat_from_euler_xyz(angles: jax.Array) -> jax.Array:
    """Rotation matrix of *intrinsic* 'XYZ' Euler angles (scipy ``from_euler('XYZ')``): R = Rx(a)·Ry(b)·Rz(c).

    Args:
        angles: f[..., 3] rad (a, b, c).

    Returns:
        f[..., 3, 3].
    """
    ca, cb, cc = jnp.cos(angles[..., 0]), jnp.cos(angles[..., 1]), jnp.cos(angles[..., 2])
    sa, sb, sc = jnp.sin(angles[..., 0]), jnp.sin(angles[..., 1]), jnp.sin(angles[..., 2])
    rows = [
        [cb * cc, -cb * sc, sb],
        [sa * sb * cc + ca * sc, -sa * sb * sc + ca * cc, -sa * cb],
        [-ca * sb * cc + sa * sc, ca * sb * sc + sa * cc, ca * cb],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def euler_xyz_from_rotmat(rotmat: jax.Array) -> jax.Array:
    """*Intrinsic* 'XYZ' Euler angles of a rotation matrix (scipy ``as_euler('XYZ')``), the inverse of
    `rotmat_from_euler_xyz`.

    Angles: a, c ∈ (−π, π], b ∈ [−π/2, π/2]. At gimbal lock (|sin b| > 1 − 1e-7) the third angle is set to 0 as
    scipy does (scipy also warns; this function does not).

    Args:
        rotmat: f[..., 3, 3], a rotation matrix.

    Returns:
        f[..., 3] rad (a, b, c).
    """
    r = rotmat
    cos_b = jnp.sqrt(r[..., 0, 0] ** 2 + r[..., 0, 1] ** 2)
    b = jnp.arctan2(r[..., 0, 2], cos_b)
    a = jnp.arctan2(-r[..., 1, 2], r[..., 2, 2])
    c = jnp.arctan2(-r[..., 0, 1], r[..., 0, 0])
    locked = jnp.abs(r[..., 0, 2]) > 1.0 - _XYZ_GIMBAL_EPS
    # With b = ±π/2, R[1,0] and R[1,1] are sin and cos of (a ± c); c = 0 leaves a.
    a_locked = jnp.arctan2(jnp.sign(r[..., 0, 2]) * r[..., 1, 0], r[..., 1, 1])
    a = jnp.where(locked, a_locked, a)
    c = jnp.where(locked, 0.0, c)
    return jnp.stack([a, b, c], axis=-1)
