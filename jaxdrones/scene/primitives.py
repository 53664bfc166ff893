"""The scene the JAX cameras see, backend-neutral: primitives (the ground plane, boxes, spheres, cylinders and
capsules in any pose) padded to a static capacity (`Scene`, `make_scene`), their signed distance (`distance`), and
the drones drawn as the PyBullet backend draws them (`drone_primitives`). See `jaxdrones.sensors.camera`."""

from __future__ import annotations

import numbers
from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.typing import DTypeLike

from jaxdrones.physics.params import DroneParams
from jaxdrones.scene.obstacles import Obstacle

__all__ = [
    "BODY_RGBA",
    "BODY_SIDE_PER_ARM",
    "BODY_THICKNESS",
    "GROUND_RGB",
    "PROP_RGBA",
    "PROP_THICKNESS",
    "PROP_Z",
    "Primitives",
    "SHAPES",
    "Scene",
    "check_obstacles",
    "distance",
    "drone_primitives",
    "make_scene",
]

#: Colour of the ground (RGB in [0, 1]).
GROUND_RGB = (0.72, 0.72, 0.72)

#: The drones' visual shape, as the PyBullet backend builds it (`jaxdrones.backends.scene.create_drone`): a square
#: plate of side ``BODY_SIDE_PER_ARM * arm`` and ``BODY_THICKNESS`` m, centred on the body origin, and four
#: propeller disks of the propeller radius, ``PROP_THICKNESS`` m thick, ``PROP_Z`` m above each propeller position.
BODY_SIDE_PER_ARM = 1.13

BODY_THICKNESS = 0.012

PROP_THICKNESS = 0.002

PROP_Z = 0.004

BODY_RGBA = (0.15, 0.15, 0.15, 1.0)

PROP_RGBA = (0.55, 0.55, 0.6, 1.0)

#: The primitive types of a `Scene`, in the order `render` numbers them.
SHAPES = ("box", "sphere", "cylinder", "capsule")


# --------------------------------------------------------------------------------------------- the scene
@struct.dataclass
class Primitives:
    """N primitives of one shape, padded: arrays f[..., N, ...] (leading axes: worlds, if drawn per world).

    Attributes:
        pos: f[..., N, 3] m, world frame, the shape's centre.
        rot: f[..., N, 3, 3], shape frame → world frame (columns: the shape's axes).
        size: f[..., N, 3] m: box half extents (x, y, z); sphere (radius, 0, 0); cylinder and capsule (radius, half
            length of the axis segment along the shape's z, 0).
        seg: i32[..., N], the segmentation id.
        rgb: f[..., N, 3] in [0, 1].
        valid: bool[..., N]; False for padding, never hit.
    """

    pos: jax.Array
    rot: jax.Array
    size: jax.Array
    seg: jax.Array
    rgb: jax.Array
    valid: jax.Array


@struct.dataclass
class Scene:
    """What the cameras see besides the drones: the ground plane z = 0 (seg id 0) and padded primitives per shape.

    Build it with `make_scene` (from `jaxdrones.scene.Obstacle` descriptions, as the PyBullet backend
    takes them); the capacity of each shape is its arrays' N, so scenes of one capacity share a compiled program.
    """

    box: Primitives
    sphere: Primitives
    cylinder: Primitives
    capsule: Primitives
    ground: jax.Array  #: bool[...], whether the ground plane is there.

    def drone_seg(self) -> jax.Array:
        """i32[...]: the segmentation id of drone 0, one more than the largest obstacle id (K + 1 for the K
        obstacles of `make_scene`, numbered 1..K), 1 with no obstacle."""
        ids = [jnp.where(p.valid, p.seg, 0) for p in (self.box, self.sphere, self.cylinder, self.capsule)]
        return jnp.max(jnp.concatenate(ids, axis=-1), axis=-1, initial=0) + 1


def _rotmat_from_rpy(rpy) -> np.ndarray:
    """R(roll, pitch, yaw) = Rz(yaw) Ry(pitch) Rx(roll), in NumPy (host-side scene building): the URDF's and
    PyBullet's convention, as `jaxdrones.physics.rotations.quat_from_euler`."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def check_obstacles(obstacles: Iterable[Obstacle]) -> tuple[Obstacle, ...]:
    """The obstacles as a tuple, or ValueError if one is not a primitive the JAX cameras draw (a URDF mesh: only
    Bullet draws those)."""
    obstacles = tuple(obstacles)
    for k, o in enumerate(obstacles):
        shape = getattr(o, "shape", None)
        if shape == "urdf":
            raise ValueError(
                f"obstacle {k} is a URDF mesh ({o.urdf!r}): the JAX cameras draw only boxes, spheres, "
                f"cylinders and capsules; use backend='pybullet' for meshes"
            )
        if shape not in SHAPES:
            raise ValueError(f"obstacle {k}: shape must be one of {SHAPES}, got {shape!r}")
    return obstacles


def _size(shape: str, size) -> tuple:
    """An `Obstacle`'s size as `Primitives.size`: box half extents; (radius, 0, 0); (radius, half length, 0)."""
    if shape == "box":
        return tuple(x / 2 for x in size)
    return (size[0], 0.0, 0.0) if shape == "sphere" else (size[0], size[1] / 2, 0.0)


def make_scene(
    obstacles: Iterable[Obstacle] = (),
    capacity: dict[str, int] | int | None = None,
    ground: bool = True,
    dtype: DTypeLike = jnp.float32,
) -> Scene:
    """A `Scene` from static obstacles, as the PyBullet backend takes them.

    Args:
        obstacles: a sequence of `jaxdrones.scene.Obstacle` (``"box"``, ``"sphere"``, ``"cylinder"`` or
            ``"capsule"``); obstacle k gets the segmentation id k + 1 (the ground is 0), as in a PyBullet world.
        capacity: slots per shape, ``{"box": 8, ...}`` or one int for every shape; default: as many as the
            obstacles of each shape. Unused slots are padding (never hit).
        ground: include the ground plane z = 0.
        dtype: float dtype of the arrays.

    Raises:
        ValueError: a URDF obstacle (only Bullet draws meshes: use ``backend="pybullet"``), an unknown shape, or more
            obstacles of a shape than its capacity.
    """
    obstacles = check_obstacles(obstacles)
    by_shape = {s: [] for s in SHAPES}
    for k, o in enumerate(obstacles):
        by_shape[o.shape].append((k + 1, o))
    if capacity is None:
        capacity = {s: len(v) for s, v in by_shape.items()}
    elif isinstance(capacity, numbers.Integral) and not isinstance(capacity, bool):
        capacity = dict.fromkeys(SHAPES, int(capacity))
    if not isinstance(capacity, dict) or set(capacity) - set(SHAPES):
        raise ValueError(f"capacity must be an int or a dict with keys in {SHAPES}, got {capacity!r}")
    parts = {}
    for shape in SHAPES:
        n = capacity.get(shape, len(by_shape[shape]))
        if not isinstance(n, numbers.Integral) or n < len(by_shape[shape]):
            raise ValueError(
                f"the scene holds {len(by_shape[shape])} {shape} obstacles, more than its capacity "
                f"of {n}: raise capacity[{shape!r}]"
            )
        pos, rot, size = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
        seg, rgb, valid = np.full(n, -1, np.int32), np.zeros((n, 3)), np.zeros(n, bool)
        for i, (sid, o) in enumerate(by_shape[shape]):
            pos[i], rot[i], seg[i], rgb[i], valid[i] = o.pos, _rotmat_from_rpy(o.rpy), sid, o.rgba[:3], True
            size[i] = _size(shape, o.size)
        parts[shape] = Primitives(
            pos=jnp.asarray(pos, dtype),
            rot=jnp.asarray(rot, dtype),
            size=jnp.asarray(size, dtype),
            seg=jnp.asarray(seg),
            rgb=jnp.asarray(rgb, dtype),
            valid=jnp.asarray(valid),
        )
    return Scene(**parts, ground=jnp.asarray(ground))


def distance(scene: Scene, points: jax.Array) -> jax.Array:
    """Distance from each point to the nearest obstacle of ``scene`` (not the ground), m: f[..., P].

    Signed: negative inside a primitive (minus the depth to its surface), ``inf`` with no valid primitive. Exact for
    boxes, spheres, cylinders and capsules in any pose (their signed distance functions; for a box and a cylinder
    outside, the distance to the nearest point of the solid, inside, to the nearest face). A drone whose centre is
    closer than its collision radius touches an obstacle (how the ``avoid`` task detects collisions).

    Args:
        scene: a `Scene` with leading axes [...] (or none, shared by every point).
        points: f[..., P, 3] m, world frame.
    """
    # The component axis first ([3, ..., P, N] arrays), so that each step is one elementwise operation over every
    # point and primitive: with the 3 components last, the rotation and the norms were 3-wide reductions.
    point = jnp.moveaxis(points, -1, 0)[..., :, None]  # [3, ..., P, 1]
    out = jnp.full(points.shape[:-1], jnp.inf, points.dtype)
    for shape in SHAPES:
        prims = getattr(scene, shape)
        if prims.valid.shape[-1] == 0:
            continue
        extra = (1,) * max(0, points.ndim - 1 - prims.valid.ndim)  # a scene shared by every point: [1..., N]
        prims = jax.tree.map(lambda x, extra=extra: jnp.reshape(x, extra + x.shape), prims)
        rel = point - jnp.moveaxis(prims.pos, -1, 0)[..., None, :]  # p − c: [3, ..., P, N]
        rot = jnp.moveaxis(prims.rot, (-2, -1), (0, 1))[..., None, :]  # R[j, i]: [3, 3, ..., 1, N]
        local = jnp.sum(rot * rel[:, None], axis=0)  # Rᵀ (p − c), the shape's frame: [3, ..., P, N]
        size = jnp.moveaxis(prims.size, -1, 0)[..., None, :]
        d = _SDF[shape](local, size)
        out = jnp.minimum(out, jnp.min(jnp.where(prims.valid[..., None, :], d, jnp.inf), axis=-1))
    return out


# Signed distance functions of a point p f[3, ...] in the shape's frame and its size f[k, ...] (component axis first).
def _sdf_box(p, size):
    q = jnp.abs(p) - size
    outside = jnp.linalg.norm(jnp.maximum(q, 0.0) + 1e-30, axis=0)
    return jnp.where(jnp.all(q <= 0, axis=0), jnp.max(q, axis=0), outside)


def _sdf_sphere(p, size):
    return jnp.linalg.norm(p, axis=0) - size[0]


def _sdf_cylinder(p, size):
    q = jnp.stack([jnp.linalg.norm(p[:2], axis=0) - size[0], jnp.abs(p[2]) - size[1]])
    outside = jnp.linalg.norm(jnp.maximum(q, 0.0) + 1e-30, axis=0)
    return jnp.where(jnp.all(q <= 0, axis=0), jnp.max(q, axis=0), outside)


def _sdf_capsule(p, size):
    axis = jnp.clip(p[2], -size[1], size[1])
    return jnp.linalg.norm(jnp.stack([p[0], p[1], p[2] - axis]), axis=0) - size[0]


_SDF = {"box": _sdf_box, "sphere": _sdf_sphere, "cylinder": _sdf_cylinder, "capsule": _sdf_capsule}


# --------------------------------------------------------------------------------------------- ray intersections
def _safe_sqrt(x, ok):
    return jnp.sqrt(jnp.where(ok, x, 1.0))


def drone_primitives(params: DroneParams, pos: jax.Array, rot: jax.Array, first_seg: int | jax.Array) -> dict:
    """The drones' visual shapes as primitives: per drone a box (the plate) and four cylinders (the propeller
    disks), with the drone's segmentation id ``first_seg + d``.

    Args:
        params: `jaxdrones.physics.params.DroneParams` broadcastable to [..., D] (arm, prop_pos, prop_radius).
        pos: f[..., D, 3] m; rot: f[..., D, 3, 3], body → world (`jaxdrones.physics.rotations.quat_to_rotmat`).
        first_seg: the id of drone 0.

    Returns:
        ``{"box": Primitives [..., D], "cylinder": Primitives [..., 4D]}``.
    """
    dtype = pos.dtype
    n = pos.shape[-2]
    arm = jnp.broadcast_to(jnp.asarray(params.arm, dtype), pos.shape[:-1])
    seg = jnp.broadcast_to(first_seg, pos.shape[:-1]) + jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), pos.shape[:-1])
    side = BODY_SIDE_PER_ARM * arm / 2
    plate = Primitives(
        pos=pos,
        rot=rot,
        size=jnp.stack([side, side, jnp.full_like(side, BODY_THICKNESS / 2)], -1),
        seg=seg,
        rgb=jnp.broadcast_to(jnp.asarray(BODY_RGBA[:3], dtype), pos.shape),
        valid=jnp.ones(pos.shape[:-1], bool),
    )
    prop_pos = jnp.broadcast_to(jnp.asarray(params.prop_pos, dtype), pos.shape[:-1] + (4, 3))
    prop_pos = prop_pos.at[..., 2].add(PROP_Z)
    centres = pos[..., None, :] + jnp.einsum("...ij,...kj->...ki", rot, prop_pos)  # [..., D, 4, 3]
    radius = jnp.broadcast_to(jnp.asarray(params.prop_radius, dtype), pos.shape[:-1])
    lead = pos.shape[:-2]
    props = Primitives(
        pos=centres.reshape(lead + (4 * n, 3)),
        rot=jnp.repeat(rot, 4, axis=-3),
        size=jnp.repeat(
            jnp.stack([radius, jnp.full_like(radius, PROP_THICKNESS / 2), jnp.zeros_like(radius)], -1), 4, axis=-2
        ),
        seg=jnp.repeat(seg, 4, axis=-1),
        rgb=jnp.broadcast_to(jnp.asarray(PROP_RGBA[:3], dtype), lead + (4 * n, 3)),
        valid=jnp.ones(lead + (4 * n,), bool),
    )
    return {"box": plate, "cylinder": props}
