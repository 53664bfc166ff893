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
from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxdrones._validate import check_int, check_real
from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.rotations import quat_to_rotmat
from jaxdrones.scene.primitives import (
    Scene,
    _rotmat_from_rpy,
    drone_primitives,
)
from jaxdrones.sensors.raycast import (
    ROWS_PER_BLOCK,
    _trace,
    _trace_keys,
    _unpack,
)

__all__ = [
    "AMBIENT",
    "CameraSpec",
    "ENV_IMAGES",
    "EYE_MARGIN",
    "IMAGE_KINDS",
    "ImageKind",
    "LIGHT",
    "camera_frames",
    "check_camera_args",
    "check_image_size",
    "image_shapes",
    "real",
    "render",
]

#: Gap between the front of a drone's collision cylinder and its camera's eye, m.
EYE_MARGIN = 0.005

#: Direction towards the light (world frame, unit) and the ambient share of the shading of `render`'s RGB.
LIGHT = tuple(np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0]))

AMBIENT = 0.35

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
ENV_IMAGES = {
    "rgb": ImageKind(np.uint8, (4,), 0, 0, 255),
    "depth": ImageKind(np.float32, (), np.nan, 0.0, np.inf),  # m along the optical axis
    "seg": ImageKind(np.int32, (), -1, -1, np.iinfo(np.int32).max),
}  # body ids, -1: nothing seen


def image_shapes(
    lead: tuple[int, ...], width: int, height: int, kinds: Iterable[str] = tuple(ENV_IMAGES)
) -> dict[str, jax.ShapeDtypeStruct]:
    """``{kind: jax.ShapeDtypeStruct(lead + (height, width) + channels, dtype)}`` of `ENV_IMAGES`' ``kinds``."""
    return {
        k: jax.ShapeDtypeStruct(tuple(lead) + (height, width) + ENV_IMAGES[k].channels, ENV_IMAGES[k].dtype)
        for k in kinds
    }


# --------------------------------------------------------------------------------------------- the camera spec
def check_image_size(width: int, height: int) -> tuple[int, int]:
    """Width and height as positive ints (pixels), or ValueError."""
    return tuple(check_int(name, value, 1, 8192) for name, value in (("width", width), ("height", height)))


def real(name: str, value: ArrayLike) -> float:
    """``value`` as a Python float, or ValueError naming ``name`` if it is not a real scalar."""
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, np.ndarray, jax.Array)) or np.ndim(value):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    return float(value)


def check_camera_args(
    width: int, height: int, fov: float, near: float | None, far: float
) -> tuple[int, int, float, float | None, float]:
    """Validate an onboard camera's settings; returns them as Python numbers.

    Raises:
        ValueError: width/height not an int in [1, 8192], fov not in (0, 180) degrees, far not finite and > 0, near
            not None or finite with 0 < near < far.
    """
    width, height = check_image_size(width, height)
    what = "the vertical field of view in degrees,"
    fov = check_real("fov", real("fov", fov), 0, 180, low_open=True, high_open=True, what=what)
    far = check_real("far", real("far", far), 0, low_open=True, what="a finite distance in m")
    if near is not None:
        what = "None (the drone's arm) or a distance in m below far,"
        near = check_real("near", real("near", near), 0, far, low_open=True, high_open=True, what=what)
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


def camera_frames(spec: CameraSpec, params: DroneParams, pos: jax.Array, rot: jax.Array) -> tuple[jax.Array, jax.Array]:
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


def render(
    spec: CameraSpec,
    scene: Scene,
    params: DroneParams,
    pos: jax.Array,
    quat: jax.Array,
    kinds: tuple[str, ...] = ("rgb", "depth", "seg"),
) -> dict[str, jax.Array]:
    """Every drone's onboard camera images (see the module docstring for the camera model and the images).

    Each pixel's ray meets the primitives one after the other (the ground, then each slot of each shape), keeping
    the nearest hit so far: one elementwise pass over the pixels that XLA fuses and vectorises across them, and whose
    derivative is that of the hit kept. Without RGB, the nearest hit is kept as one integer per pixel, the depth's bits
    with the primitive's slot in the lowest few (`_pack`): a single chain of minimums, faster on CPU than keeping depth
    and id apart (`benchmarks/speed/cameras.py`, docs/benchmarks.md, "Cameras"), whose depth is rounded by less than
    2^(b − 24) of itself in float32 (2^(b − 53) in float64) for a scene of fewer than 2^b − 1 primitives (drones'
    included); with RGB depth is exact. Derivatives are those of the exact depth either way.

    Args:
        spec: the `CameraSpec`.
        scene: a `Scene` (`make_scene`), unbatched or with the state's leading world axes.
        params: `jaxdrones.physics.params.DroneParams` broadcastable to [..., D] (collision_radius, arm, prop_pos,
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
    # many worlds are vmapped (docs/benchmarks.md, "Cameras").
    rays = spec.pixel_rays()
    blocks = -(-spec.height // ROWS_PER_BLOCK)
    rays = np.concatenate([rays, np.repeat(rays[-1:], blocks * ROWS_PER_BLOCK - spec.height, 0)])
    best = jax.lax.map(rows, jnp.asarray(rays.reshape(blocks, ROWS_PER_BLOCK, spec.width, 3), dtype))
    n_lead = pos.ndim - 2

    def image(x):  # [B, ..., D, h, W, *C] -> [..., D, H, W, *C]
        x = jnp.moveaxis(x, 0, n_lead + 1)
        x = x.reshape(x.shape[: n_lead + 1] + (blocks * ROWS_PER_BLOCK,) + x.shape[n_lead + 3 :])
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
