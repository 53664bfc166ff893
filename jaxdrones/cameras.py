"""Per-drone cameras in pure JAX: a ray caster against analytic primitives, batched, differentiable.

Each drone carries a pinhole camera (`CameraSpec`). `render` casts one ray through the centre of every pixel of
every drone's camera and intersects it, in closed form, with a `Scene` of primitives (the ground plane, boxes,
spheres, cylinders and capsules in any pose) and with the other drones of its world; it returns metric depth, a
segmentation of ids and a flat-shaded RGB image. No host callback: it is `jit`-, `vmap`- and `grad`-able, and
every array has a static shape (primitives are padded to a capacity and masked), so that scenes can be drawn per
episode without recompiling.

The camera model is the PyBullet backend's onboard camera (`jaxdrones.backends.camera`), so that both backends
give the same images of the same scene:

* the eye sits on the body +x axis just in front of the drone's collision cylinder, at p + R·(r + `EYE_MARGIN`,
  0, 0) (r = ``DroneParams.collision_radius``), unless ``CameraSpec.mount_pos`` says otherwise;
* the optical axis is body +x and the image's up body +z (the image rolls and pitches with the drone), or with
  ``CameraSpec.level`` world +z, as the original gym-pybullet-drones camera (BaseAviary._getDroneImages) keeps it;
* square pixels: the focal length in pixels is f = (H / 2) / tan(fov / 2) along both axes, fov vertical; pixel
  (column i, row j), row 0 at the top, looks along forward + ((i + ½ − W/2)·right + (H/2 − j − ½)·up) / f;
* only hits beyond the near plane count (OpenGL clips nearer geometry); nothing within ``far`` reads ``far``.

Images, for a state with leading axes [..., D]:

* ``depth``: f[..., D, H, W] in the dtype of the poses (float32 normally), metres along the optical axis (OpenGL's
  eye-space depth, what the PyBullet backend reports), ``far`` where nothing is hit; rendered without RGB, rounded
  by a few millionths of itself at most (see `render`);
* ``seg``: i32[..., D, H, W], the id of what each pixel sees, numbered as in a PyBullet world built from scratch
  (`jaxdrones.backends.pybullet.PyBulletStep.body_ids`): the ground 0, the obstacles 1..K in scene order, the drones
  K+1..K+D in state order; -1 where nothing is within ``far``;
* ``rgb``: u8[..., D, H, W, 3], each primitive's colour times ``AMBIENT + (1 − AMBIENT)·max(0, n·l)`` for the
  light direction `LIGHT` (Lambertian, no textures or shadows); black where nothing is hit.

Drones appear as the PyBullet backend draws them (`drone_primitives`): a square plate and four propeller disks; a
drone's own body is never in its own image. Depth is differentiable with respect to the drones' poses and the
primitives' poses and sizes wherever the pixel sees the same surface of the same primitive under a small change;
at silhouette edges, where a small change swaps what a pixel sees, depth jumps and its derivative is that of the
surface seen (it ignores the jump). Segmentation and RGB colours are piecewise constant.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones.physics.rotations import quat_to_rotmat

#: Gap between the front of a drone's collision cylinder and its camera's eye, m.
EYE_MARGIN = 0.005
#: Direction towards the light (world frame, unit) and the ambient share of the shading of `render`'s RGB.
LIGHT = tuple(np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0]))
AMBIENT = 0.35
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
#: Image rows traced per block by `render` (see there).
ROWS_PER_BLOCK = 4
#: Slots of a shape traced per step of `render`'s scan over a scene's primitives (see there).
SLOTS_PER_STEP = 4
#: The primitive types of a `Scene`, in the order `render` numbers them.
SHAPES = ("box", "sphere", "cylinder", "capsule")
#: The images `render` gives.
IMAGE_KINDS = ("rgb", "depth", "seg")


@dataclasses.dataclass(frozen=True)
class ImageKind:
    """How an env (either backend) and the PyBullet backend's `camera_images` hold one kind of camera image.

    Attributes:
        dtype: the pixels' dtype.
        channels: the per-pixel shape (RGBA for rgb, as Bullet's; none for depth and seg).
        blank: a pixel of a drone whose pose is not finite (nothing rendered).
        low, high: the pixels' range (gymnasium's Box).
    """

    dtype: type
    channels: tuple[int, ...]
    blank: float
    low: float
    high: float


#: The camera images of the envs' observations and of the PyBullet backend, by name (see `TaskConfig.vision`).
ENV_IMAGES = {"rgb": ImageKind(np.uint8, (4,), 0, 0, 255),
              "depth": ImageKind(np.float32, (), np.nan, 0.0, np.inf),  # m along the optical axis
              "seg": ImageKind(np.int32, (), -1, -1, np.iinfo(np.int32).max)}  # body ids, -1: nothing seen


def image_shapes(lead: tuple[int, ...], width: int, height: int, kinds=tuple(ENV_IMAGES)) -> dict:
    """``{kind: jax.ShapeDtypeStruct(lead + (height, width) + channels, dtype)}`` of `ENV_IMAGES`' ``kinds``."""
    return {k: jax.ShapeDtypeStruct(tuple(lead) + (height, width) + ENV_IMAGES[k].channels, ENV_IMAGES[k].dtype)
            for k in kinds}


# --------------------------------------------------------------------------------------------- the camera spec
def check_image_size(width, height) -> tuple[int, int]:
    """Width and height as positive ints (pixels), or ValueError."""
    for name, value in (("width", width), ("height", height)):
        if not isinstance(value, numbers.Integral) or isinstance(value, bool) or not 1 <= value <= 8192:
            raise ValueError(f"{name} must be an integer number of pixels in [1, 8192], got {value!r}")
    return int(width), int(height)


def real(name: str, value) -> float:
    """``value`` as a Python float, or ValueError naming ``name`` if it is not a real scalar."""
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, np.ndarray, jax.Array)) or np.ndim(value):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    return float(value)


def check_camera_args(width, height, fov, near, far) -> tuple[int, int, float, float | None, float]:
    """Validate an onboard camera's settings; returns them as Python numbers.

    Raises:
        ValueError: width/height not an int in [1, 8192], fov not in (0, 180) degrees, far not finite and > 0, near
            not None or finite with 0 < near < far.
    """
    width, height = check_image_size(width, height)
    fov, far = real("fov", fov), real("far", far)
    if not 0.0 < fov < 180.0:
        raise ValueError(f"fov must be the vertical field of view in degrees, in (0, 180), got {fov}")
    if not (math.isfinite(far) and far > 0.0):
        raise ValueError(f"far must be a positive finite distance in m, got {far}")
    if near is not None:
        near = real("near", near)
        if not (math.isfinite(near) and 0.0 < near < far):
            raise ValueError(f"near must be None (the drone's arm) or a distance in m with 0 < near < far={far}, "
                             f"got {near}")
    return width, height, fov, near, far


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """A drone's onboard camera (static: part of a compiled program's shape).

    The defaults are the PyBullet backend's onboard camera (`jaxdrones.backends.camera`): the paper's 64 × 48
    image and 60° vertical field of view (gym-pybullet-drones BaseAviary: IMG_RES, fov=60), near plane the drone's
    arm, far plane 100 m.

    Attributes:
        width, height: pixels, in [1, 8192].
        fov: vertical field of view, degrees, in (0, 180).
        near: near plane, m; None: the drone's arm (``DroneParams.arm``), as the original.
        far: far plane, m, > near.
        mount_pos: the eye in the body frame, m; None: (collision_radius + `EYE_MARGIN`, 0, 0).
        mount_rpy: the camera's rotation in the body frame (roll, pitch, yaw; rad, the URDF convention): the
            optical axis is R_mount e_x, the image's up R_mount e_z.
        level: keep world +z as the image's up (the original's camera; the optical axis still follows the body)
            instead of rolling and pitching with the body.

    Raises:
        ValueError: a size, field of view or plane out of range, or a mount of the wrong length.
    """

    width: int = 64
    height: int = 48
    fov: float = 60.0
    near: float | None = None
    far: float = 100.0
    mount_pos: tuple[float, float, float] | None = None
    mount_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    level: bool = False

    def __post_init__(self):
        _, _, fov, near, far = check_camera_args(self.width, self.height, self.fov, self.near, self.far)
        object.__setattr__(self, "fov", fov)
        object.__setattr__(self, "far", far)
        object.__setattr__(self, "near", near)
        for name in ("mount_pos", "mount_rpy"):
            value = getattr(self, name)
            if value is None and name == "mount_pos":
                continue
            try:
                value = tuple(float(v) for v in value)
            except (TypeError, ValueError):
                value = ()
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ValueError(f"CameraSpec.{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)

    @property
    def focal(self) -> float:
        """The focal length in pixels, f = (H / 2) / tan(fov / 2)."""
        return (self.height / 2) / math.tan(math.radians(self.fov) / 2)

    def pixel_rays(self) -> np.ndarray:
        """f32[H, W, 3]: each pixel's ray in camera coordinates (forward, left, up), forward component 1, so
        that a hit at ray parameter t lies at depth t along the optical axis."""
        f = self.focal
        right = (np.arange(self.width) + 0.5 - self.width / 2) / f
        up = (self.height / 2 - np.arange(self.height) - 0.5) / f
        up, right = np.meshgrid(up, right, indexing="ij")
        return np.stack([np.ones_like(up), -right, up], -1).astype(np.float32)


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
    PyBullet's convention, as `jaxdrones.rotations.quat_from_euler`."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def check_obstacles(obstacles) -> tuple:
    """The obstacles as a tuple, or ValueError if one is not a primitive the JAX cameras draw (a URDF mesh: only
    Bullet draws those)."""
    obstacles = tuple(obstacles)
    for k, o in enumerate(obstacles):
        shape = getattr(o, "shape", None)
        if shape == "urdf":
            raise ValueError(f"obstacle {k} is a URDF mesh ({o.urdf!r}): the JAX cameras draw only boxes, spheres, "
                             f"cylinders and capsules; use backend='pybullet' for meshes")
        if shape not in SHAPES:
            raise ValueError(f"obstacle {k}: shape must be one of {SHAPES}, got {shape!r}")
    return obstacles


def _size(shape: str, size) -> tuple:
    """An `Obstacle`'s size as `Primitives.size`: box half extents; (radius, 0, 0); (radius, half length, 0)."""
    if shape == "box":
        return tuple(x / 2 for x in size)
    return (size[0], 0.0, 0.0) if shape == "sphere" else (size[0], size[1] / 2, 0.0)


def make_scene(obstacles=(), capacity: dict | int | None = None, ground: bool = True,
               dtype=jnp.float32) -> Scene:
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
            raise ValueError(f"the scene holds {len(by_shape[shape])} {shape} obstacles, more than its capacity "
                             f"of {n}: raise capacity[{shape!r}]")
        pos, rot, size = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
        seg, rgb, valid = np.full(n, -1, np.int32), np.zeros((n, 3)), np.zeros(n, bool)
        for i, (sid, o) in enumerate(by_shape[shape]):
            pos[i], rot[i], seg[i], rgb[i], valid[i] = o.pos, _rotmat_from_rpy(o.rpy), sid, o.rgba[:3], True
            size[i] = _size(shape, o.size)
        parts[shape] = Primitives(pos=jnp.asarray(pos, dtype), rot=jnp.asarray(rot, dtype),
                                  size=jnp.asarray(size, dtype), seg=jnp.asarray(seg), rgb=jnp.asarray(rgb, dtype),
                                  valid=jnp.asarray(valid))
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
    out = jnp.full(points.shape[:-1], jnp.inf, points.dtype)
    for shape in SHAPES:
        prims = getattr(scene, shape)
        if prims.valid.shape[-1] == 0:
            continue
        rel = points[..., :, None, :] - prims.pos[..., None, :, :]  # [..., P, N, 3]
        local = jnp.einsum("...nji,...pnj->...pni", prims.rot, rel)  # Rᵀ (p − c), the shape's frame
        size = prims.size[..., None, :, :]
        d = _SDF[shape](local, size)
        out = jnp.minimum(out, jnp.min(jnp.where(prims.valid[..., None, :], d, jnp.inf), axis=-1))
    return out


def _sdf_box(p, size):
    q = jnp.abs(p) - size
    outside = jnp.linalg.norm(jnp.maximum(q, 0.0) + 1e-30, axis=-1)
    return jnp.where(jnp.all(q <= 0, axis=-1), jnp.max(q, axis=-1), outside)


def _sdf_sphere(p, size):
    return jnp.linalg.norm(p, axis=-1) - size[..., 0]


def _sdf_cylinder(p, size):
    q = jnp.stack([jnp.linalg.norm(p[..., :2], axis=-1) - size[..., 0], jnp.abs(p[..., 2]) - size[..., 1]], -1)
    outside = jnp.linalg.norm(jnp.maximum(q, 0.0) + 1e-30, axis=-1)
    return jnp.where(jnp.all(q <= 0, axis=-1), jnp.max(q, axis=-1), outside)


def _sdf_capsule(p, size):
    axis = jnp.clip(p[..., 2], -size[..., 1], size[..., 1])
    return jnp.linalg.norm(p - jnp.stack([jnp.zeros_like(axis), jnp.zeros_like(axis), axis], -1), axis=-1) - \
        size[..., 0]


_SDF = {"box": _sdf_box, "sphere": _sdf_sphere, "cylinder": _sdf_cylinder, "capsule": _sdf_capsule}


# --------------------------------------------------------------------------------------------- ray intersections
def _safe_sqrt(x, ok):
    return jnp.sqrt(jnp.where(ok, x, 1.0))


def _slab(o, d, half):
    """Entry and exit t of the ray o + t d through |x| ≤ half (one axis)."""
    inv = 1.0 / jnp.where(d == 0, 1e-30, d)
    t0, t1 = (-half - o) * inv, (half - o) * inv
    return jnp.minimum(t0, t1), jnp.maximum(t0, t1)


def _hit_box(o, d, size):
    lo, hi = zip(*(_slab(o[i], d[i], size[..., i]) for i in range(3)))
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
    pieces = [_hit_cylinder(o, d, size)] + [_hit_sphere_at((o[0], o[1], o[2] - end), d, radius)
                                            for end in (half, -half)]
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


def drone_primitives(params, pos: jax.Array, rot: jax.Array, first_seg: int | jax.Array) -> dict:
    """The drones' visual shapes as primitives: per drone a box (the plate) and four cylinders (the propeller
    disks), with the drone's segmentation id ``first_seg + d``.

    Args:
        params: `jaxdrones.params.DroneParams` broadcastable to [..., D] (arm, prop_pos, prop_radius).
        pos: f[..., D, 3] m; rot: f[..., D, 3, 3], body → world (`jaxdrones.rotations.quat_to_rotmat`).
        first_seg: the id of drone 0.

    Returns:
        ``{"box": Primitives [..., D], "cylinder": Primitives [..., 4D]}``.
    """
    dtype = pos.dtype
    n = pos.shape[-2]
    arm = jnp.broadcast_to(jnp.asarray(params.arm, dtype), pos.shape[:-1])
    seg = jnp.broadcast_to(first_seg + jnp.arange(n, dtype=jnp.int32), pos.shape[:-1])
    side = BODY_SIDE_PER_ARM * arm / 2
    plate = Primitives(pos=pos, rot=rot, size=jnp.stack([side, side, jnp.full_like(side, BODY_THICKNESS / 2)], -1),
                       seg=seg, rgb=jnp.broadcast_to(jnp.asarray(BODY_RGBA[:3], dtype), pos.shape),
                       valid=jnp.ones(pos.shape[:-1], bool))
    prop_pos = jnp.broadcast_to(jnp.asarray(params.prop_pos, dtype), pos.shape[:-1] + (4, 3))
    prop_pos = prop_pos + jnp.asarray([0.0, 0.0, PROP_Z], dtype)
    centres = pos[..., None, :] + jnp.einsum("...ij,...kj->...ki", rot, prop_pos)  # [..., D, 4, 3]
    radius = jnp.broadcast_to(jnp.asarray(params.prop_radius, dtype), pos.shape[:-1])
    lead = pos.shape[:-2]
    props = Primitives(
        pos=centres.reshape(lead + (4 * n, 3)),
        rot=jnp.repeat(rot, 4, axis=-3),
        size=jnp.repeat(jnp.stack([radius, jnp.full_like(radius, PROP_THICKNESS / 2), jnp.zeros_like(radius)],
                                  -1), 4, axis=-2),
        seg=jnp.repeat(seg, 4, axis=-1), rgb=jnp.broadcast_to(jnp.asarray(PROP_RGBA[:3], dtype), lead + (4 * n, 3)),
        valid=jnp.ones(lead + (4 * n,), bool))
    return {"box": plate, "cylinder": props}


def camera_frames(spec: CameraSpec, params, pos: jax.Array, rot: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each drone's eye f[..., D, 3] (m, world) and camera axes f[..., D, 3, 3] (world; columns forward, left, up),
    from its position, body → world rotation f[..., D, 3, 3] and ``spec`` (see the module docstring)."""
    dtype = pos.dtype
    if spec.mount_pos is None:
        ahead = jnp.broadcast_to(jnp.asarray(params.collision_radius, dtype), pos.shape[:-1]) + EYE_MARGIN
        mount = jnp.stack([ahead, jnp.zeros_like(ahead), jnp.zeros_like(ahead)], -1)
    else:
        mount = jnp.broadcast_to(jnp.asarray(spec.mount_pos, dtype), pos.shape)
    eye = pos + jnp.einsum("...ij,...j->...i", rot, mount)
    axes = rot @ jnp.asarray(_rotmat_from_rpy(spec.mount_rpy), dtype)
    if spec.level:
        forward = axes[..., 0]
        left = jnp.cross(jnp.asarray([0.0, 0.0, 1.0], dtype), forward)
        left = left / jnp.maximum(jnp.linalg.norm(left, axis=-1, keepdims=True), 1e-12)
        axes = jnp.stack([forward, left, jnp.cross(forward, left)], -1)
    return eye, axes


def render(spec: CameraSpec, scene: Scene, params, pos: jax.Array, quat: jax.Array,
           kinds: tuple[str, ...] = ("rgb", "depth", "seg")) -> dict:
    """Every drone's onboard camera images (see the module docstring for the camera model and the images).

    Each pixel's ray meets the primitives one after the other (the ground, then each slot of each shape), keeping
    the nearest hit so far: one elementwise pass over the pixels that XLA fuses and vectorises across them, and
    whose derivative is that of the hit kept. Without RGB, the nearest hit is kept as one integer per pixel, the
    depth's bits with the primitive's slot in the lowest few (`_pack`): a single chain of minimums, about 2 to 6
    times faster on CPU than keeping depth and id apart (`benchmarks/cameras.py`), whose depth is rounded by less
    than 2^(b − 24) of itself in float32 (2^(b − 53) in float64) for a scene of fewer than 2^b − 1 primitives
    (drones' included); with RGB depth is exact. Derivatives are those of the exact depth either way.

    Args:
        spec: the `CameraSpec`.
        scene: a `Scene` (`make_scene`), unbatched or with the state's leading world axes.
        params: `jaxdrones.params.DroneParams` broadcastable to [..., D] (collision_radius, arm, prop_pos,
            prop_radius).
        pos: f[..., D, 3] m, world frame; quat: f[..., D, 4] (x, y, z, w), body → world.
        kinds: which images to return, a subset of ``("rgb", "depth", "seg")``.

    Returns:
        dict of the ``kinds``: ``depth`` f[..., D, H, W] m (the poses' dtype), ``seg`` i32[..., D, H, W], ``rgb``
        u8[..., D, H, W, 3].

    Raises:
        ValueError: an unknown image kind, or pos/quat not f[..., D, 3] / f[..., D, 4].
    """
    if not kinds or set(kinds) - set(IMAGE_KINDS):
        raise ValueError(f"kinds must be a non-empty subset of {IMAGE_KINDS}, got {kinds!r}")
    if pos.ndim < 2 or pos.shape[-1] != 3 or quat.shape != pos.shape[:-1] + (4,):
        raise ValueError(f"render needs pos f[..., D, 3] and quat f[..., D, 4], got {pos.shape} and {quat.shape}")
    dtype = pos.dtype if jnp.issubdtype(pos.dtype, jnp.floating) else jnp.float32
    kinds = tuple(k for k in IMAGE_KINDS if k in kinds)
    if "rgb" in kinds:
        return _images(spec, kinds, scene, params, pos.astype(dtype), quat.astype(dtype), fast=False)
    return _depth_seg(spec, kinds, scene, params, pos.astype(dtype), quat.astype(dtype))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _depth_seg(spec, kinds, scene, params, pos, quat) -> dict:
    """`render` without RGB: each pixel's nearest hit as one packed key (`_pack`), a single chain of minimums."""
    return _images(spec, kinds, scene, params, pos, quat, fast=True)


@_depth_seg.defjvp
def _depth_seg_jvp(spec, kinds, primals, tangents):
    """The derivative of the surface each pixel sees: that of `_trace`'s nearest hit, which keeps t unrounded."""
    _, tangent = jax.jvp(functools.partial(_images, spec, kinds, fast=False), primals, tangents)
    return _depth_seg(spec, kinds, *primals), tangent


def _images(spec, kinds, scene, params, pos, quat, fast: bool) -> dict:
    """`render`'s images (its arguments checked); ``fast``: the nearest hits by `_trace_keys`, else `_trace`."""
    dtype = pos.dtype
    rot = quat_to_rotmat(quat)  # normalised, as the PyBullet backend's getMatrixFromQuaternion
    eye, axes = camera_frames(spec, params, pos, rot)
    near = jnp.broadcast_to(jnp.asarray(params.arm if spec.near is None else spec.near, dtype), pos.shape[:-1])
    near = near[..., None, None]
    drones = drone_primitives(params, pos, rot, scene.drone_seg()[..., None])
    shading = "rgb" in kinds

    def rows(rays):  # the images' rows of rays f[h, W, 3] (camera frame): dict of [..., D, h, W(, 3)]
        ray = tuple(jnp.einsum("hwk,...k->...hw", rays, axes[..., i, :]) for i in range(3))  # world
        if fast:
            return {"key": _trace_keys(spec, scene, drones, eye, ray, near)}
        return _trace(spec, scene, drones, eye, ray, near, shading)

    # Row by row blocks (`ROWS_PER_BLOCK`), so that a pass over a block's pixels stays in the CPU's cache however
    # many worlds are vmapped (on 2 cores, 1024 worlds, 16 primitives: 3,300 against 2,300 frames/s for the
    # whole image at once; 1 to 12 rows a block measured alike within the machine's noise).
    rays = spec.pixel_rays()
    blocks = -(-spec.height // ROWS_PER_BLOCK)
    rays = np.concatenate([rays, np.repeat(rays[-1:], blocks * ROWS_PER_BLOCK - spec.height, 0)])
    best = jax.lax.map(rows, jnp.asarray(rays.reshape(blocks, ROWS_PER_BLOCK, spec.width, 3), dtype))
    n_lead = pos.ndim - 2

    def image(x):  # [B, ..., D, h, W, *C] -> [..., D, H, W, *C]
        x = jnp.moveaxis(x, 0, n_lead + 1)
        x = x.reshape(x.shape[:n_lead + 1] + (blocks * ROWS_PER_BLOCK,) + x.shape[n_lead + 3:])
        return jax.lax.slice_in_dim(x, 0, spec.height, axis=n_lead + 1)

    best = {k: image(v) for k, v in best.items()}
    if fast:
        best = _unpack(spec, scene, drones, best["key"])

    out = {}
    if "depth" in kinds:
        out["depth"] = best["t"]
    if "seg" in kinds:
        out["seg"] = best["seg"]
    if shading:
        normal = best["normal"]
        normal = normal / jnp.maximum(jnp.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        shade = AMBIENT + (1 - AMBIENT) * jnp.maximum(0.0, normal @ jnp.asarray(LIGHT, dtype))
        out["rgb"] = jnp.clip(jnp.round(255 * best["rgb"] * shade[..., None]), 0, 255).astype(jnp.uint8)
    return out


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
    2^bits (a relative change below 2^(bits − 24) in float32, 2^(bits − 53) in float64), the slot in the low bits.
    (The bits of positive floats are ordered as the floats.)"""
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
    primitives: 64 primitives ran 20 times slower than 16; one slot a step, the chain of passes runs about 3 times
    slower per primitive than a few unrolled.)
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
            _nearer(shape, jax.tree.map(lambda x: x[u], prims), seen_by, eye, ray, near, best, shading)
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
        hit = hit & seen_by[:, None, None]
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
        n_local = _normal(shape, tuple(oc + t_safe * dc for oc, dc in zip(o, d)), size)
        normal = tuple(sum(n_local[k] * rot[..., i, k, None, None] for k in range(3)) for i in range(3))
        best["normal"] = jnp.where(hit[..., None], jnp.stack(normal, -1), best["normal"])
        best["rgb"] = jnp.where(hit[..., None], prim.rgb[..., None, None, None, :], best["rgb"])
