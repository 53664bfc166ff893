"""Cameras of the PyBullet backend: one onboard camera per drone, and a third-person view of a world for videos.

Onboard camera (`camera_images`, ``step.camera_images(...)``)
-------------------------------------------------------------

The original (gym-pybullet-drones main, envs/BaseAviary.py:565-617; docs/physics.md §8.5) puts the eye at p + (0, 0, L)
(L = the arm, a world-frame offset above the drone), looks at p + R·(1000, 0, 0), keeps the world +z as the up
vector, and renders a 64 × 48 image with a 60° vertical field of view, aspect 1.0, near plane L and far plane 1000.
Here the camera is rigidly mounted on the body:

* eye at p + R·(r + `EYE_MARGIN`, 0, 0): on the body +x axis, just in front of the drone's collision cylinder
  (radius r = ``DroneParams.collision_radius``, which covers the propellers), so that no part of the drone is in
  front of the lens and the drone never sees itself. (The original's eye above the drone sees its own propellers
  when the drone pitches.)
* optical axis along body +x, image up along body +z: the image rolls and pitches with the drone, as a camera
  fixed to the frame does;
* ``fov``: the vertical field of view; aspect = W / H, so pixels are square and the focal length in pixels is the
  same along both image axes: f = (H / 2) / tan(fov / 2). (The original's aspect 1.0 on a 64 × 48 image stretches
  the image horizontally by 4/3.)
* near plane: ``near`` m, by default the drone's arm L (the original's near plane); far plane ``far`` m (default
  100; the original's 1000 wastes depth-buffer precision).

A point at camera coordinates (right, up, forward Z) lands at the pixel (column, row)
= (W/2 + f·right/Z, H/2 − f·up/Z), with pixel (i, j) covering [i, i+1) × [j, j+1) and row 0 at the top, as in
OpenGL after Bullet's flip of the rows. (TinyRenderer's rasterisation sits up to a pixel off this model at object edges,
e.g. a box face predicted 42 × 42 pixels renders 41 × 41, and its rows sample about half a pixel low; the EGL
renderer matches the model exactly.)
Bullet's pixel values:

* ``rgb``: uint8 RGBA, as ``pybullet.getCameraImage`` returns it (alpha 255);
* ``depth``: Bullet's normalised z-buffer z ∈ [0, 1] (OpenGL's, for the projection matrix of `projection_matrix`)
  converted to metres along the optical axis, depth = far·near / (far − (far − near)·z) (the inverse of OpenGL's
  perspective depth mapping); pixels where nothing is within ``far`` read ``far``;
* ``seg``: the Bullet body id seen at each pixel, -1 where nothing is. Map ids to objects with
  ``step.body_ids(world)``: the ground plane, the obstacles (in the order of ``step.obstacles``) and the drones
  (in state order). In a world built from scratch the load order gives ground 0, obstacles 1..K, drones K+1..K+D,
  but ids change when a drone's geometry changes, so use `body_ids`.

Renderers: ``renderer="tiny"`` uses ``pybullet.ER_TINY_RENDERER`` (CPU, always available), ``renderer="egl"`` uses
``pybullet.ER_BULLET_HARDWARE_OPENGL`` through Bullet's EGL plugin (headless OpenGL, loaded in every world).
Shadows are off (the original turns them on; they cost a second render pass in TinyRenderer).
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import jax
import numpy as np
from numpy.typing import ArrayLike

from jaxdrones.backends import require_pybullet
from jaxdrones.physics.checks import check_params_batch, check_state_shape
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.params import DroneParams, broadcast_params, pack_params
from jaxdrones.physics.state import DroneState
from jaxdrones.sensors.camera import ENV_IMAGES, EYE_MARGIN, check_camera_args, check_image_size, image_shapes
from jaxdrones.sensors.camera import real as _real

pybullet = require_pybullet()

#: Vertical field of view (deg), near and far planes (m) of the third-person view `render`.
RENDER_FOV = 60.0
RENDER_NEAR = 0.01
RENDER_FAR = 100.0
#: Bullet renderer per ``renderer`` option of the backend.
_BULLET_RENDERER = {"tiny": pybullet.ER_TINY_RENDERER, "egl": pybullet.ER_BULLET_HARDWARE_OPENGL}


# --------------------------------------------------------------------------------------------- pure camera math
def projection_matrix(fov: float, aspect: float, near: float | np.ndarray, far: float) -> np.ndarray:
    """OpenGL perspective projection matrices, as ``pybullet.computeProjectionMatrixFOV`` builds them.

    Args:
        fov: vertical field of view, degrees.
        aspect: width / height.
        near: f[...] m, near plane distance(s).
        far: far plane distance, m.

    Returns:
        f64[..., 16], column-major (OpenGL order, the layout ``getCameraImage`` takes): with t = 1/tan(fov/2),
        P = [[t/aspect, 0, 0, 0], [0, t, 0, 0], [0, 0, (far+near)/(near−far), 2·far·near/(near−far)], [0, 0, −1, 0]]
        (gluPerspective).
    """
    near = np.asarray(near, np.float64)
    t = 1.0 / math.tan(math.radians(fov) / 2.0)
    out = np.zeros(near.shape + (16,))
    out[..., 0] = t / aspect
    out[..., 5] = t
    out[..., 10] = (far + near) / (near - far)
    out[..., 11] = -1.0
    out[..., 14] = 2.0 * far * near / (near - far)
    return out


def onboard_view_matrices(pos: np.ndarray, quat: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """View matrices of cameras looking along body +x with body +z up, the eye at ``offset`` m along body +x.

    Args:
        pos: f[..., 3] m, world frame.
        quat: f[..., 4] (x, y, z, w) body → world, unit norm.
        offset: f[...] m, eye distance from the body origin along body +x.

    Returns:
        f64[..., 16] column-major, equal to ``pybullet.computeViewMatrix(eye, eye + R e_x, R e_z)`` (gluLookAt):
        rows s = f × u = −R e_y, u = R e_z, −f = −R e_x, translated by −(s·eye, u·eye, −f·eye).
    """
    x, y, z, w = np.moveaxis(np.asarray(quat, np.float64), -1, 0)
    fwd = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], -1)  # R e_x
    left = np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], -1)  # R e_y
    up = np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)  # R e_z
    eye = np.asarray(pos, np.float64) + np.asarray(offset, np.float64)[..., None] * fwd
    side = -left
    out = np.zeros(fwd.shape[:-1] + (16,))
    out[..., 0:12:4] = side
    out[..., 1:12:4] = up
    out[..., 2:12:4] = -fwd
    out[..., 12] = -np.sum(side * eye, -1)
    out[..., 13] = -np.sum(up * eye, -1)
    out[..., 14] = np.sum(fwd * eye, -1)
    out[..., 15] = 1.0
    return out


def zbuffer_to_depth(z: np.ndarray, near: float | np.ndarray, far: float) -> np.ndarray:
    """Bullet's normalised z-buffer z ∈ [0, 1] → distance along the optical axis, m.

    depth = far·near / (far − (far − near)·z), the inverse of OpenGL's perspective depth mapping (z = 0 at the near
    plane, z = 1 at the far plane). ``near`` broadcasts against ``z``.
    """
    return far * near / (far - (far - near) * z)


# --------------------------------------------------------------------------------------------- argument checks
def check_pose(config: SimConfig, state: DroneState) -> tuple[int, ...]:
    """Check that ``state`` has real pos f[..., D, 3] and quat f[..., D, 4] with D = n_drones; returns [..., D].

    Raises:
        ValueError: on other shapes (`jaxdrones.physics.checks.check_state_shape`), or a non-numeric dtype.
    """
    lead = check_state_shape(config, state)
    for name, x in (("pos", state.pos), ("quat", state.quat)):
        kind = np.dtype(x.dtype).kind if hasattr(x, "dtype") else np.asarray(x).dtype.kind
        if kind not in "fiu":
            raise ValueError(f"state.{name} must be a real array, got dtype {getattr(x, 'dtype', None)}")
    return lead


def _is_traced(*xs) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in xs)


# --------------------------------------------------------------------------------------------- onboard cameras
def camera_images(
    step: Any,
    params: DroneParams,
    state: DroneState,
    *,
    width: int = 64,
    height: int = 48,
    fov: float = 60.0,
    near: float | None = None,
    far: float = 100.0,
) -> dict:
    """The onboard camera images of every drone; see ``PyBulletStep.camera_images`` (``step``: that
    `jaxdrones.backends.pybullet.PyBulletStep`, which imports this module)."""
    step.check_open()
    width, height, fov, near, far = check_camera_args(width, height, fov, near, far)
    lead = check_pose(step.config, state)
    check_params_batch(params, state)
    settings = (width, height, fov, near, far)
    if _is_traced(state.pos, state.quat, params.mass, params.collision_radius, params.arm):
        return _traced_images(step, params, state, lead, settings)
    pos, quat = np.asarray(state.pos, np.float64), np.asarray(state.quat, np.float64)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise ValueError("state.pos or state.quat contains NaN or inf")
    if np.any(np.sum(quat * quat, -1) == 0.0):
        raise ValueError("state.quat has a zero quaternion")
    return _host_images(step, step.host_params(params, state.pos), pos, quat, settings)


def _traced_images(step, params: DroneParams, state: DroneState, lead: tuple[int, ...], settings) -> dict:
    """`camera_images` inside jit/vmap/scan: a host callback; drones with a non-finite pose read nothing there."""
    packed_params, unpack_params = pack_params(broadcast_params(params, lead), lead)

    def callback(packed_params, pos, quat):
        host = step.host_params(unpack_params(packed_params), pos, by_value=True)
        return _host_images(step, host, np.asarray(pos, np.float64), np.asarray(quat, np.float64), settings)

    return jax.pure_callback(
        callback,
        image_shapes(lead, settings[0], settings[1]),
        packed_params,
        state.pos,
        state.quat,
        vmap_method="broadcast_all",
    )


def _host_images(step, host: dict, pos: np.ndarray, quat: np.ndarray, settings) -> dict:
    """Render NumPy poses pos f[*L, D, 3], quat f[*L, D, 4] with host params (one Bullet world per world).

    A drone whose pose is not finite (or has a zero quaternion) gets rgb 0, depth NaN and seg -1.
    """
    width, height, fov, near, far = settings
    lead = pos.shape[:-1]
    n_drones, n_worlds = lead[-1], math.prod(lead[:-1])
    arrays = host["arrays"]
    near_d = arrays["arm"] if near is None else np.full((n_worlds, n_drones), near)  # [W, D]
    pos = pos.reshape(n_worlds, n_drones, 3)
    norm = np.sqrt(np.sum(quat * quat, -1, keepdims=True)).reshape(n_worlds, n_drones, 1)
    quat = quat.reshape(n_worlds, n_drones, 4) / np.where(norm > 0, norm, 1.0)
    ok = np.all(np.isfinite(pos), -1) & np.all(np.isfinite(quat), -1) & (norm[..., 0] > 0)  # [W, D]
    views = onboard_view_matrices(
        np.where(ok[..., None], pos, 0.0), np.where(ok[..., None], quat, 1.0), arrays["collision_radius"] + EYE_MARGIN
    ).tolist()
    projections = projection_matrix(fov, width / height, near_d, far).tolist()
    rgb, zbuf, seg = (
        np.full(s.shape, ENV_IMAGES[k].blank, s.dtype)
        for k, s in image_shapes((n_worlds, n_drones), width, height).items()
    )
    step._ensure_worlds(n_worlds, host)
    renderer = _BULLET_RENDERER[step.renderer]
    pos_l, quat_l, ok_l = pos.tolist(), quat.tolist(), ok.tolist()
    for w in range(n_worlds):
        for attempt in (0, 1):
            try:
                _capture_world(
                    step._worlds[w],
                    pos_l[w],
                    quat_l[w],
                    ok_l[w],
                    views[w],
                    projections[w],
                    (width, height, renderer),
                    rgb[w],
                    zbuf[w],
                    seg[w],
                )
                break
            except pybullet.error:
                if attempt:
                    raise RuntimeError(
                        f"PyBullet failed to render world {w} twice (its client was rebuilt in between)"
                    ) from None
                step._rebuild_world(w, host)
    # in float64: far − (far − near)·z cancels to ~near at z ≈ 1, which float32 would resolve only to ~1e-4 relative
    depth = zbuffer_to_depth(zbuf.astype(np.float64), near_d[..., None, None], far).astype(np.float32)
    return {
        "rgb": rgb.reshape(lead + rgb.shape[2:]),
        "depth": depth.reshape(lead + depth.shape[2:]),
        "seg": seg.reshape(lead + seg.shape[2:]),
    }


def _capture_world(world, pos, quat, ok, views, projections, image, rgb, zbuf, seg) -> None:
    """Pose the drones of one world and fill rgb [D, H, W, 4], zbuf [D, H, W] and seg [D, H, W] in place.

    A drone with ``ok[d]`` false is moved far away (1e6 m below the ground), so that the others do not see it at a
    stale pose, and its images are left as they are.
    """
    client, bodies = world.client, world.drones
    width, height, renderer = image
    for d, body in enumerate(bodies):
        where = (pos[d], quat[d]) if ok[d] else ((0.0, 0.0, -1e6), (0.0, 0.0, 0.0, 1.0))
        pybullet.resetBasePositionAndOrientation(body, *where, physicsClientId=client)
    for d in range(len(bodies)):
        if not ok[d]:
            continue
        _, _, pixels, depth, ids = pybullet.getCameraImage(
            width,
            height,
            viewMatrix=views[d],
            projectionMatrix=projections[d],
            renderer=renderer,
            shadow=0,
            physicsClientId=client,
        )
        rgb[d] = np.reshape(pixels, (height, width, 4))
        zbuf[d] = np.reshape(depth, (height, width))
        seg[d] = np.reshape(ids, (height, width))


# --------------------------------------------------------------------------------------------- third-person view
def render(
    step: Any,
    params: DroneParams,
    state: DroneState,
    *,
    world: int = 0,
    width: int = 640,
    height: int = 480,
    target: ArrayLike | None = None,
    distance: float = 1.5,
    yaw: float = -30.0,
    pitch: float = -30.0,
) -> np.ndarray:
    """A third-person image of one world; see ``PyBulletStep.render`` (``step``: that `PyBulletStep`)."""
    step.check_open()
    width, height = check_image_size(width, height)
    lead = check_pose(step.config, state)
    check_params_batch(params, state)
    if _is_traced(state.pos, state.quat, params.mass):
        raise ValueError(
            "render takes concrete arrays (NumPy or JAX), not traced ones: call it outside jit/vmap, "
            "e.g. on the states of a rollout"
        )
    n_worlds = math.prod(lead[:-1])
    if not isinstance(world, numbers.Integral) or isinstance(world, bool) or not 0 <= world < n_worlds:
        raise ValueError(f"world must be an int in [0, {n_worlds}) (the state's worlds, flattened), got {world!r}")
    distance, yaw, pitch = (_real(name, v) for name, v in (("distance", distance), ("yaw", yaw), ("pitch", pitch)))
    if not (math.isfinite(distance) and distance > 0.0):
        raise ValueError(f"distance must be a positive finite distance in m, got {distance}")
    if not (math.isfinite(yaw) and math.isfinite(pitch)):
        raise ValueError(f"yaw and pitch must be finite angles in degrees, got {yaw} and {pitch}")
    pos = np.asarray(state.pos, np.float64).reshape(n_worlds, lead[-1], 3)[world]
    quat = np.asarray(state.quat, np.float64).reshape(n_worlds, lead[-1], 4)[world]
    norm = np.sqrt(np.sum(quat * quat, -1, keepdims=True))
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat)) and np.all(norm > 0)):
        raise ValueError(f"world {world}: state.pos or state.quat is not finite (or a quaternion is zero)")
    if target is None:
        target = pos.mean(0)
    target = np.asarray(target, np.float64)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise ValueError(f"target must be None or a finite point (x, y, z) in m, got {target!r}")
    host = step.host_params(params, state.pos)
    step._ensure_worlds(world + 1, host)
    client, bodies = step._worlds[world].client, step._worlds[world].drones
    for body, p, q in zip(bodies, pos.tolist(), (quat / norm).tolist(), strict=True):
        pybullet.resetBasePositionAndOrientation(body, p, q, physicsClientId=client)
    view = pybullet.computeViewMatrixFromYawPitchRoll(target.tolist(), distance, yaw, pitch, 0.0, 2)
    projection = projection_matrix(RENDER_FOV, width / height, RENDER_NEAR, RENDER_FAR).tolist()
    _, _, pixels, _, _ = pybullet.getCameraImage(
        width,
        height,
        viewMatrix=view,
        projectionMatrix=projection,
        renderer=_BULLET_RENDERER[step.renderer],
        shadow=0,
        flags=pybullet.ER_NO_SEGMENTATION_MASK,
        physicsClientId=client,
    )
    return np.ascontiguousarray(np.reshape(pixels, (height, width, 4))[:, :, :3], dtype=np.uint8)


def held_images(
    step: Any,
    params: DroneParams,
    sim: DroneState,
    due: jax.Array,
    held: dict,
    width: int,
    height: int,
    fov: float = 60.0,
) -> dict:
    """One world's camera images on the PyBullet backend, as an env holds them (`jaxdrones.envs.env.TaskEnv`):
    `camera_images` (``step``: the `PyBulletStep`) if the render is ``due`` (bool[]), else ``held`` (the last
    images, [D, H, W(, 4)]), in one host callback, with vertical field of view ``fov`` (degrees). Under ``vmap``
    (where `jax.lax.cond` runs both branches) only the due worlds are rendered, and a world whose pose is not finite
    reads the blank images of `ENV_IMAGES` (rgb 0, depth NaN, seg -1)."""
    spec = image_shapes(np.shape(sim.pos)[:-1], width, height, tuple(held))

    def render(params, sim, due, held):
        lead = np.shape(due)

        def flat(x):
            x = np.asarray(x)
            return x.reshape((-1,) + x.shape[len(lead) :])

        out = {k: flat(v).copy() for k, v in held.items()}
        pos, quat = flat(sim.pos), flat(sim.quat)
        finite = (
            np.all(np.isfinite(pos), axis=(-2, -1))
            & np.all(np.isfinite(quat), axis=(-2, -1))
            & np.all(np.sum(quat * quat, -1) > 0, axis=-1)
        )
        due = flat(due)
        for k in out:
            out[k][due & ~finite] = ENV_IMAGES[k].blank
        index = np.flatnonzero(due & finite)
        if index.size:
            images = step.camera_images(
                jax.tree.map(lambda x: flat(x)[index], params),
                jax.tree.map(lambda x: flat(x)[index], sim),
                width=width,
                height=height,
                fov=fov,
            )
            for k in out:
                out[k][index] = images[k]
        return {k: v.reshape(lead + spec[k].shape) for k, v in out.items()}

    return jax.pure_callback(render, spec, params, sim, due, held, vmap_method="broadcast_all")
