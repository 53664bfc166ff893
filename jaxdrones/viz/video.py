"""A `jaxdrones.viz.Flight` drawn from a chase or fixed camera with the JAX ray caster (`jaxdrones.cameras.render`,
no PyBullet), written as a GIF or MP4 (`jaxdrones.io.video.VideoWriter`)."""

from __future__ import annotations

import functools
import math
import os

import numpy as np

from jaxdrones._validate import check_real, is_integer
from jaxdrones.io.video import SIGNATURE
from jaxdrones.viz.flight import (
    CF2X_ARM,
    Colors,
    Flight,
    View,
    check_target,
    drone_colours,
    drone_palette,
    resolve_view,
    wxyz_from_rotmat,
)

#: Camera presets of `write_video`.
VIDEO_CAMERAS = ("chase", "fixed")

#: Sky colour of `write_video` (RGB 0-255), where a ray meets nothing.
SKY_RGB = (200, 222, 240)


def write_video(
    path: str | os.PathLike,
    flight: Flight,
    *,
    camera: str | View = "chase",
    world: int = 0,
    drone: int = 0,
    width: int = 320,
    height: int = 240,
    fov: float = 60.0,
    max_fps: float = 30.0,
    trail_s: float | None = 2.0,
    chase: tuple[float, float] = (1.0, 0.4),
    colors: Colors | None = None,
    overwrite: bool = False,
) -> str:
    """Draw one world of ``flight`` with the JAX cameras (`jaxdrones.cameras.render`, no PyBullet) and write it as an
    MP4 or GIF (`jaxdrones.io.video.VideoWriter`).

    The view is a pinhole camera (the cameras' model, `jaxdrones.cameras.CameraSpec`) placed by ``camera``; it sees
    the ground, the scene's primitives in their colours, and the drones as the cameras draw them (dark plates and
    propeller disks). Each drone's trail is drawn over the image as a line in its colour (`DRONE_COLORS`; not hidden
    behind obstacles); the sky is `SKY_RGB`. Frames are skipped to stay at or below ``max_fps`` and the video plays in
    real time.

    Args:
        path: ``.mp4`` or ``.gif``; parent folders are created.
        flight: the `Flight`.
        camera: ``"chase"``: ``chase[0]`` m behind drone ``drone`` along its heading (body +x in the horizontal
            plane, smoothed over about 0.5 s) and ``chase[1]`` m above it, looking at it; ``"fixed"``: one view of the
            whole flight from the front left and above; or ``(position, look_at)``, two points in m (world frame).
        world: the world to draw.
        drone: the drone the chase camera follows.
        width, height: pixels.
        fov: vertical field of view, degrees.
        max_fps: the video's frame rate at most, Hz.
        trail_s: how far back the trails reach, s; None: the whole flight; 0: no trails.
        chase: (distance behind, height above) of the chase camera, m.
        colors: the trails' RGB 0-255 per drone index, as `write_html`'s.
        overwrite: replace an existing video that jaxdrones wrote (`jaxdrones.io.video.SIGNATURE`; any other file
            is refused with ``ValueError`` and kept).

    Returns:
        The path written.

    Raises:
        FileExistsError: ``path`` exists and not ``overwrite``.
        ValueError: an extension other than .mp4/.gif, a world or drone out of range, an unknown camera, or a bad
            size, field of view or frame rate.
    """
    import jax
    import jax.numpy as jnp

    from jaxdrones.io.video import VideoWriter, video_format
    from jaxdrones.physics.params import load_params
    from jaxdrones.physics.rotations import quat_to_rotmat
    from jaxdrones.scene.primitives import drone_primitives, make_scene
    from jaxdrones.sensors.camera import CameraSpec, render

    if not isinstance(flight, Flight):
        raise TypeError(f"flight must be a jaxdrones.viz.Flight, got {type(flight).__name__}")
    path = os.fspath(path)
    video_format(path)
    check_target(path, overwrite, SIGNATURE)
    for name, value, n in (("world", world, flight.n_worlds), ("drone", drone, flight.n_drones)):
        if not (is_integer(value) and 0 <= value < n):
            raise ValueError(f"{name} must be an index in [0, {n}), got {value!r}")
    check_real("max_fps", max_fps, 0, low_open=True, what="a finite number")
    if trail_s is not None:
        check_real("trail_s", trail_s, 0, what="None or a finite number of seconds")
    spec = CameraSpec(width=width, height=height, fov=fov, near=0.05, far=100.0, mount_pos=(0.0, 0.0, 0.0))
    frames, stride = _frames(flight, max_fps)
    pos = flight.pos[:, world]  # [T, D, 3]
    eyes, axes = _video_cameras(flight, world, drone, camera, chase, frames)
    scale = flight.arm / CF2X_ARM
    base = load_params("cf2x")
    params = base.replace(
        arm=base.arm * scale,
        prop_pos=base.prop_pos * scale,
        prop_radius=base.prop_radius * scale,
        collision_radius=base.collision_radius * scale,
    )
    scene = flight.scene
    if scene is None:
        scene = make_scene(())
    elif scene.box.pos.ndim == 3:
        scene = jax.tree.map(lambda x: x[world], scene)
    scene = jax.tree.map(jnp.asarray, scene)
    cam_quat = np.stack([_xyzw_from_rotmat(r) for r in axes]).astype(np.float32)

    def frame(p, q, eye, cam):  # the drones join the scene as primitives; the camera is the one body rendering
        drones = drone_primitives(params, p, quat_to_rotmat(q), DRONE_SEG)
        join = functools.partial(jax.tree.map, lambda a, b: jnp.concatenate([a, b.astype(a.dtype)]))
        seen = scene.replace(box=join(scene.box, drones["box"]), cylinder=join(scene.cylinder, drones["cylinder"]))
        return render(spec, seen, params, eye[None], cam[None], kinds=("depth", "seg"))

    draw = jax.jit(jax.vmap(frame))
    drone_pos = pos[frames].astype(np.float32)
    drone_quat = flight.quat[frames, world].astype(np.float32)
    eyes32 = eyes.astype(np.float32)
    colours = drone_colours(drone_palette(colors), 1, flight.n_drones)[0]
    lookup = _seg_colours(scene, colours)
    keep = None if trail_s is None else math.ceil(trail_s / (stride * flight.dt))
    with VideoWriter(path, fps=1.0 / (stride * flight.dt), overwrite=overwrite) as video:
        for start in range(0, len(frames), 16):
            chunk = slice(start, start + 16)
            out = draw(drone_pos[chunk], drone_quat[chunk], eyes32[chunk], cam_quat[chunk])
            depth, seg = np.asarray(out["depth"][:, 0]), np.asarray(out["seg"][:, 0])
            for k in range(len(seg)):
                i = start + k
                image = _shade(spec, depth[k], seg[k], eyes[i], axes[i], lookup)
                if keep != 0:
                    first = 0 if keep is None else max(0, i - keep)
                    image = _draw_trails(image, pos[frames[first : i + 1]], eyes[i], axes[i], spec, colours)
                video.append(image)
    return path


#: The segmentation id of drone 0 in `write_video`'s renders (above any obstacle's).
DRONE_SEG = 1 << 20


def _seg_colours(scene, colours: np.ndarray) -> dict:
    """Colour (RGB 0-1) of each segmentation id of `write_video`'s renders: the ground (0) `GROUND_RGB`, the
    scene's primitives their own, drone d (`DRONE_SEG` + d) its trail's colour."""
    from jaxdrones.scene.primitives import GROUND_RGB, SHAPES

    lookup = {0: np.asarray(GROUND_RGB)}
    for shape in SHAPES:
        p = getattr(scene, shape)
        for i in np.flatnonzero(np.asarray(p.valid)):
            lookup[int(p.seg[i])] = np.asarray(p.rgb[i], np.float64)
    for d, c in enumerate(colours):
        lookup[DRONE_SEG + d] = np.asarray(c) / 255.0
    return lookup


def _shade(spec, depth: np.ndarray, seg: np.ndarray, eye, axes, lookup: dict) -> np.ndarray:
    """u8[H, W, 3]: a depth and segmentation render coloured by id (``lookup``), Lambert-shaded with the normals of
    the depth map's surface (the cameras' `LIGHT` and `AMBIENT`), the ground with lines every 0.5 m up to 6 m, the sky
    `SKY_RGB`; depth and ids are `render`'s fast path, many times faster than its RGB path."""
    from jaxdrones.sensors.camera import AMBIENT, LIGHT

    rays = spec.pixel_rays().astype(np.float64) @ np.asarray(axes).T  # [H, W, 3] world, forward component 1
    points = eye + depth[..., None] * rays
    normal = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    normal *= np.where(np.sum(normal * rays, -1, keepdims=True) > 0, -1.0, 1.0)  # facing the camera
    shade = AMBIENT + (1 - AMBIENT) * np.maximum(0.0, normal @ np.asarray(LIGHT))
    base = np.zeros(depth.shape + (3,))
    for sid in np.unique(seg):
        if sid >= 0:
            base[seg == sid] = lookup.get(int(sid), (0.5, 0.5, 0.5))
    ground = seg == 0
    shade = np.where(ground, 1.0, shade)  # flat ground: its lines give the depth cue
    cell = points[..., :2] / 0.5
    near = np.min(np.abs(cell - np.round(cell)), axis=-1) * 0.5 < 0.004 * np.maximum(depth, 1.0)
    lines = ground & near & (depth < 6.0)  # farther, lines every 0.5 m alias into moiré
    base[lines] *= 0.75
    image = np.clip(np.round(255 * base * shade[..., None]), 0, 255).astype(np.uint8)
    image[seg < 0] = SKY_RGB
    return image


def _frames(flight: Flight, max_fps: float) -> tuple[list[int], int]:
    """The frames kept at ``max_fps`` at most (the last one always), and the stride between them."""
    stride = max(1, math.ceil(1.0 / (flight.dt * max_fps)))
    frames = list(range(0, flight.n_frames, stride))
    if frames[-1] != flight.n_frames - 1:
        frames.append(flight.n_frames - 1)
    return frames, stride


def _look(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """f[3, 3]: camera axes (columns forward, left, up; world frame) looking from ``eye`` at ``target``, z up."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    left = np.cross((0.0, 0.0, 1.0), forward)
    if np.linalg.norm(left) < 1e-6:  # looking straight up or down: any horizontal left
        left = np.array([0.0, 1.0, 0.0])
    left = left / np.linalg.norm(left)
    return np.stack([forward, left, np.cross(forward, left)], axis=1)


def _video_cameras(flight: Flight, world: int, drone: int, camera, chase, frames) -> tuple[np.ndarray, np.ndarray]:
    """Eyes f[F, 3] m and camera axes f[F, 3, 3] of `write_video`'s frames."""
    n = len(frames)
    if isinstance(camera, str) and camera not in VIDEO_CAMERAS:
        raise ValueError(f"camera must be one of {VIDEO_CAMERAS} or (position, look_at), got {camera!r}")
    if isinstance(camera, str) and camera == "fixed":
        one = Flight(flight.pos[:, world : world + 1], flight.quat[:, world : world + 1], flight.dt)
        eye, target = resolve_view(one, np.zeros((1, 3)), None)
        return np.tile(eye, (n, 1)), np.tile(_look(eye, target), (n, 1, 1))
    if isinstance(camera, str) and camera == "chase":
        try:
            behind, above = (float(v) for v in chase)
        except (TypeError, ValueError):
            behind = above = math.nan
        if not (math.isfinite(behind) and math.isfinite(above) and (behind > 0 or above > 0)):
            raise ValueError(
                f"chase must be (distance behind, height above) in m, finite, not both <= 0, got {chase!r}"
            )
        target = flight.pos[frames, world, drone]
        x, y, z, w = np.moveaxis(flight.quat[frames, world, drone], -1, 0)
        heading = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z)], -1)  # body x in the horizontal plane
        smooth = np.zeros(2)
        alpha = min(1.0, (frames[1] - frames[0]) * flight.dt / 0.5) if n > 1 else 1.0
        eyes, axes = np.zeros((n, 3)), np.zeros((n, 3, 3))
        for i in range(n):
            smooth = heading[i] if i == 0 else (1 - alpha) * smooth + alpha * heading[i]
            h = smooth / np.linalg.norm(smooth) if np.linalg.norm(smooth) > 1e-6 else np.array([1.0, 0.0])
            eyes[i] = target[i] - behind * np.array([h[0], h[1], 0.0]) + (0.0, 0.0, above)
            axes[i] = _look(eyes[i], target[i])
        return eyes, axes
    eye, target = resolve_view(flight, np.zeros((flight.n_worlds, 3)), camera)
    return np.tile(eye, (n, 1)), np.tile(_look(eye, target), (n, 1, 1))


def _xyzw_from_rotmat(r: np.ndarray) -> np.ndarray:
    """A rotation matrix f[3, 3] as a unit quaternion (x, y, z, w)."""
    w, x, y, z = wxyz_from_rotmat(r)
    return np.array([x, y, z, w])


def _draw_trails(image: np.ndarray, path: np.ndarray, eye, axes, spec, colours) -> np.ndarray:
    """``image`` with each drone's ``path`` f[K, D, 3] (m, world) drawn as a line, projected with the cameras'
    pinhole model (`jaxdrones.cameras`: pixel (i, j) looks along forward plus
    ((i + ½ − W/2)·right + (H/2 − j − ½)·up) / f); segments with an end behind the near plane are left out."""
    if len(path) < 2:
        return image
    from PIL import Image, ImageDraw

    rel = (path - eye) @ axes  # [K, D, 3]: forward, left, up
    f = spec.focal
    ahead = rel[..., 0] > spec.near
    depth = np.where(ahead, rel[..., 0], 1.0)
    col = spec.width / 2 - 0.5 - f * rel[..., 1] / depth
    row = spec.height / 2 - 0.5 - f * rel[..., 2] / depth
    picture = Image.fromarray(image)
    pen = ImageDraw.Draw(picture)
    for d in range(path.shape[1]):
        colour = tuple(int(c) for c in colours[d])
        for k in range(len(path) - 1):
            if ahead[k, d] and ahead[k + 1, d]:
                pen.line([(col[k, d], row[k, d]), (col[k + 1, d], row[k + 1, d])], fill=colour, width=2)
    return np.asarray(picture)
