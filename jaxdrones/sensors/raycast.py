"""Ray casting for `jaxdrones.sensors.camera.render`: closed-form ray–primitive hits, their normals, and the nearest hit
per pixel over a `jaxdrones.scene.primitives.Scene` and the drones, found by a scan over the scene's slots that
packs depth and slot into one sortable integer key (see `render` for the two passes)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.scene.primitives import (
    GROUND_RGB,
    SHAPES,
    Primitives,
    _safe_sqrt,
)

__all__ = ["ROWS_PER_BLOCK", "SLOTS_PER_STEP"]

#: Image rows traced per block by `render` (see there).
ROWS_PER_BLOCK = 4

#: Slots of a shape traced per step of `render`'s scan over a scene's primitives (see there).
SLOTS_PER_STEP = 4


def _slab(o, d, half):
    """Entry and exit t of the ray o + t d through |x| ≤ half (one axis)."""
    inv = 1.0 / jnp.where(d == 0, 1e-30, d)
    t0, t1 = (-half - o) * inv, (half - o) * inv
    return jnp.minimum(t0, t1), jnp.maximum(t0, t1)


def _hit_box(o, d, size):
    lo, hi = zip(*(_slab(o[i], d[i], size[..., i]) for i in range(3)), strict=True)
    t_in = jnp.maximum(jnp.maximum(lo[0], lo[1]), lo[2])
    t_out = jnp.minimum(jnp.minimum(hi[0], hi[1]), hi[2])
    return t_in, t_out


def _hit_sphere_at(o, d, radius):
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
    c = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - radius * radius
    disc = b * b - a * c
    ok = disc >= 0
    root = _safe_sqrt(disc, ok)
    return jnp.where(ok, (-b - root) / a, jnp.inf), jnp.where(ok, (-b + root) / a, -jnp.inf)


def _hit_sphere(o, d, size):
    return _hit_sphere_at(o, d, size[..., 0])


def _hit_cylinder(o, d, size):
    radius, half = size[..., 0], size[..., 1]
    a = d[0] * d[0] + d[1] * d[1]
    b = o[0] * d[0] + o[1] * d[1]
    c = o[0] * o[0] + o[1] * o[1] - radius * radius
    disc = b * b - a * c
    parallel = a < 1e-12
    ok = (disc >= 0) & ~parallel
    root = _safe_sqrt(disc, ok)
    a_safe = jnp.where(parallel, 1.0, a)
    side_in = jnp.where(ok, (-b - root) / a_safe, jnp.where(parallel & (c <= 0), -jnp.inf, jnp.inf))
    side_out = jnp.where(ok, (-b + root) / a_safe, jnp.where(parallel & (c <= 0), jnp.inf, -jnp.inf))
    cap_in, cap_out = _slab(o[2], d[2], half)
    return jnp.maximum(side_in, cap_in), jnp.minimum(side_out, cap_out)


def _hit_capsule(o, d, size):
    """The union of the cylinder and its two end spheres: the first entry and last exit among the pieces hit."""
    radius, half = size[..., 0], size[..., 1]
    pieces = [_hit_cylinder(o, d, size)] + [
        _hit_sphere_at((o[0], o[1], o[2] - end), d, radius) for end in (half, -half)
    ]
    t_in = functools.reduce(jnp.minimum, [jnp.where(a <= b, a, jnp.inf) for a, b in pieces])
    t_out = functools.reduce(jnp.maximum, [jnp.where(a <= b, b, -jnp.inf) for a, b in pieces])
    return t_in, t_out


_HIT = {"box": _hit_box, "sphere": _hit_sphere, "cylinder": _hit_cylinder, "capsule": _hit_capsule}


def _normal(shape, p, size):
    """The outward normal (shape frame, not normalised) at the surface point p of the shape."""
    x, y, z = p
    if shape == "box":
        rel = [jnp.abs(c) / jnp.maximum(size[..., i], 1e-12) for i, c in enumerate(p)]
        face = [(rel[i] >= rel[(i + 1) % 3]) & (rel[i] >= rel[(i + 2) % 3]) for i in range(3)]
        return tuple(jnp.where(face[i], jnp.sign(c), 0.0) for i, c in enumerate(p))
    if shape == "sphere":
        return x, y, z
    radius, half = size[..., 0], size[..., 1]
    if shape == "cylinder":
        cap = jnp.abs(z) >= half - 1e-5 * jnp.maximum(radius, half)
        return jnp.where(cap, 0.0, x), jnp.where(cap, 0.0, y), jnp.where(cap, jnp.sign(z), 0.0)
    axis_z = jnp.clip(z, -half, half)  # capsule: from the nearest point of the axis segment
    return x, y, z - axis_z


def _slots(scene, drones) -> list:
    """The primitives in the order the rays meet them after the ground (`_trace_keys` numbers them so): per shape
    the scene's, then the drones' (`drone_primitives`); as (shape, primitives, owner), ``owner`` i[N] the drone
    each of the drones' primitives belongs to (its own camera skips it), None for the scene's."""
    out = []
    n_drones = drones["box"].seg.shape[-1]
    for shape in SHAPES:
        out.append((shape, getattr(scene, shape), None))
        if shape in drones:
            per_drone = drones[shape].seg.shape[-1] // n_drones
            out.append((shape, drones[shape], np.repeat(np.arange(n_drones), per_drone)))
    return out


def _key_bits(scene, drones) -> int:
    """Bits of a packed key that hold the slot: enough for every slot, the ground and 'nothing hit'."""
    n = 2 + sum(p.seg.shape[-1] for _, p, _ in _slots(scene, drones))
    return max(1, (n - 1).bit_length())


def _int_type(dtype):
    return jnp.int64 if jnp.dtype(dtype).itemsize == 8 else jnp.int32


def _pack(t, slot, bits: int):
    """A hit at t > 0 of slot as one integer whose order is that of t: t's bits rounded to the nearest multiple of
    2^bits (a relative change below 2^(bits − 24) in float32, 2^(bits − 53) in float64), the slot in the low bits;
    the bits of positive floats are ordered as the floats."""
    key = jax.lax.bitcast_convert_type(t, _int_type(t.dtype))
    return ((key + (1 << (bits - 1))) & ~((1 << bits) - 1)) | slot


def _trace_keys(spec, scene, drones, eye, ray, near) -> jax.Array:
    """The nearest hit of each ray (as `_trace`) as a packed key (`_pack`), i[..., D, h, W]: one minimum after
    another over the ground and every slot, all unrolled, which XLA fuses into one pass over the pixels."""
    dtype = eye.dtype
    bits = _key_bits(scene, drones)
    far = jnp.asarray(spec.far, dtype)
    nothing = _pack(far, (1 << bits) - 1, bits)
    height = eye[..., 2, None, None]
    down = ray[2] < 0
    t_ground = -height / jnp.where(down, ray[2], -1.0)
    seen = down & (height > 0) & jnp.asarray(scene.ground)[..., None, None, None] & (t_ground >= near)
    key = jnp.where(seen & (t_ground < far), _pack(t_ground, 0, bits), nothing)
    slot = 1
    own = jnp.arange(eye.shape[-2])
    for shape, prims, owner in _slots(scene, drones):
        for u in range(prims.seg.shape[-1]):
            seen_by = None if owner is None else own != owner[u]
            t_in, hit, _ = _hit(shape, _slot(prims, u), seen_by, eye, ray, near)
            key = jnp.minimum(key, jnp.where(hit & (t_in < far), _pack(t_in, slot, bits), nothing))
            slot += 1
    return key


def _slot(prims: Primitives, u: int) -> Primitives:
    """Slot u of padded primitives (fields [..., N, ...] → [..., ...])."""
    return jax.tree.map(lambda x, k: jnp.take(x, u, axis=x.ndim - 1 - k), prims, Primitives(**_TRAILING))


def _unpack(spec, scene, drones, key) -> dict:
    """`_trace_keys`' keys i[..., D, H, W] as `_trace`'s t and seg (-1 and ``far`` where nothing is hit)."""
    bits = _key_bits(scene, drones)
    mask = (1 << bits) - 1
    slot = key & mask
    lead = key.shape[:-3]
    ids = [jnp.zeros(lead + (1,), jnp.int32)]
    ids += [jnp.broadcast_to(p.seg, lead + p.seg.shape[-1:]).astype(jnp.int32) for _, p, _ in _slots(scene, drones)]
    ids.append(jnp.full(lead + (mask + 1 - sum(i.shape[-1] for i in ids),), -1, jnp.int32))  # up to "nothing"
    table = jnp.concatenate(ids, -1)
    seg = jnp.take_along_axis(table, slot.reshape(lead + (-1,)), axis=-1)
    t = jax.lax.bitcast_convert_type(key & ~mask, _float_type(key.dtype))
    return {"t": jnp.where(slot == mask, jnp.asarray(spec.far, t.dtype), t), "seg": seg.reshape(key.shape)}


def _float_type(itype):
    return jnp.float64 if jnp.dtype(itype).itemsize == 8 else jnp.float32


def _trace(spec, scene, drones, eye, ray, near, shading) -> dict:
    """The nearest hit of each ray (3-tuple f[..., D, h, W], world frame) from the eyes f[..., D, 3]: dict of
    t, seg and, with ``shading``, rgb and the world normal, per pixel (see `render`)."""
    dtype = eye.dtype
    far = jnp.asarray(spec.far, dtype)
    # The ground plane z = 0, seen from above.
    height = eye[..., 2, None, None]
    down = ray[2] < 0
    t_ground = -height / jnp.where(down, ray[2], -1.0)
    seen = down & (height > 0) & jnp.asarray(scene.ground)[..., None, None, None] & (t_ground >= near)
    seen = seen & (t_ground < far)
    best = {"t": jnp.where(seen, t_ground, far), "seg": jnp.where(seen, 0, -1)}
    if shading:
        best["rgb"] = jnp.where(seen[..., None], jnp.asarray(GROUND_RGB, dtype), 0.0)
        best["normal"] = jnp.where(seen[..., None], jnp.asarray([0.0, 0.0, 1.0], dtype), 0.0)

    for shape, prims, owner in _slots(scene, drones):
        best = _nearest(shape, prims, owner, eye, ray, near, best, shading)
    return best


def _nearest(shape, prims, owner, eye, ray, near, best, shading) -> dict:
    """``best`` updated with the padded primitives ``prims`` of one shape (fields [..., N, ...]); ``owner`` i[N]
    gives the drone each belongs to (its camera skips it), or is None (a scene's, seen by every drone).

    A scan over the slots, `SLOTS_PER_STEP` at a time: each step a few fused passes over the block's pixels. (All
    slots unrolled, XLA fuses the chain of nearest hits so that its cost grows faster than the number of
    primitives; one slot a step, the chain of passes runs slower per primitive than a few unrolled:
    `benchmarks/speed/cameras.py`.)
    """
    n_slots = prims.seg.shape[-1]
    if not n_slots:
        return best
    unroll = min(n_slots, SLOTS_PER_STEP)
    steps = -(-n_slots // unroll)
    pad = steps * unroll - n_slots  # padding slots: valid False, never hit

    def blocks(x, k):  # [..., N, *F] -> [steps, unroll, ..., *F]
        x = jnp.moveaxis(x, x.ndim - 1 - k, 0)
        x = jnp.concatenate([x, jnp.zeros((pad,) + x.shape[1:], x.dtype)]) if pad else x
        return x.reshape((steps, unroll) + x.shape[1:])

    slots = jax.tree.map(blocks, prims, Primitives(**_TRAILING))
    # NumPy when unrolled, so that XLA folds the test of a drone's own body.
    owners = None if owner is None else np.concatenate([owner, np.full(pad, -1)]).reshape(steps, unroll)
    own = jnp.arange(eye.shape[-2])

    def update(best, block):
        best = dict(best)
        prims, owners = block
        for u in range(unroll):
            seen_by = None if owners is None else own != owners[u]
            _nearer(shape, jax.tree.map(lambda x, u=u: x[u], prims), seen_by, eye, ray, near, best, shading)
        return best, None

    if steps == 1:
        return update(best, (jax.tree.map(lambda x: x[0], slots), None if owners is None else owners[0]))[0]
    return jax.lax.scan(update, best, (slots, None if owners is None else jnp.asarray(owners)))[0]


#: The trailing axes of each `Primitives` field after its slot axis.
_TRAILING = {"pos": 1, "rot": 2, "size": 1, "seg": 0, "rgb": 1, "valid": 0}


def _dot3(a: jax.Array, b: jax.Array) -> jax.Array:
    """Σ_k a[..., k] b[..., k] over a last axis of 3, written out: an elementwise expression that XLA fuses into
    its consumers (a reduction over an axis of 3 compiles on CPU to a separate, slow kernel)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _hit(shape, prim, seen_by, eye, ray, near):
    """Where each ray first enters one primitive (see `_nearer` for the shapes): t_in f[..., D, H, W], whether it
    is a hit the camera sees (in front of the near plane, a valid slot, not the camera's own drone) and the ray
    and primitive in the shape's frame (o, d, size, rot)."""
    rot = prim.rot[..., None, :, :]  # [..., 1, 3, 3], columns the shape's axes
    rel = eye - prim.pos[..., None, :]  # [..., D, 3]
    o = tuple(_dot3(rel, rot[..., i])[..., None, None] for i in range(3))  # Rᵀ (eye − c)
    d = tuple(sum(ray[k] * rot[..., k, i, None, None] for k in range(3)) for i in range(3))
    size = prim.size[..., None, None, None, :]
    t_in, t_out = _HIT[shape](o, d, size)
    hit = (t_in <= t_out) & (t_in >= near) & prim.valid[..., None, None, None]
    if seen_by is not None:
        hit = hit & jnp.broadcast_to(seen_by[:, None, None], hit.shape)
    return t_in, hit, (o, d, size, rot)


def _nearer(shape, prim, seen_by, eye, ray, near, best, shading):
    """Update ``best`` (t, seg and, with ``shading``, rgb and the world normal, per pixel [..., D, H, W]) with one
    primitive (fields [..., ...], per world or shared) where its hit is nearer.

    Shapes: eye f[..., D, 3]; ray 3-tuple f[..., D, H, W] (world); near f[..., D, 1, 1]; ``seen_by`` bool[D]
    (False for the drone the primitive belongs to), or None (a scene's primitive, seen by all).
    """
    t_in, hit, (o, d, size, rot) = _hit(shape, prim, seen_by, eye, ray, near)
    hit = hit & (t_in < best["t"])
    best["t"] = jnp.where(hit, t_in, best["t"])
    best["seg"] = jnp.where(hit, prim.seg[..., None, None, None], best["seg"])
    if shading:
        t_safe = jnp.where(hit, t_in, 0.0)
        n_local = _normal(shape, tuple(oc + t_safe * dc for oc, dc in zip(o, d, strict=True)), size)
        normal = tuple(sum(n_local[k] * rot[..., i, k, None, None] for k in range(3)) for i in range(3))
        best["normal"] = jnp.where(hit[..., None], jnp.stack(normal, -1), best["normal"])
        best["rgb"] = jnp.where(hit[..., None], prim.rgb[..., None, None, None, :], best["rgb"])
