"""A scripted camera scene: a drone hovering in front of a box, seen by its onboard camera (``jaxdrones camera``).

One drone is level and at rest at `DRONE_POS` (0.5 m above the ground, facing world +x). A cube of side
`BOX_SIDE` stands straight ahead on its optical axis, its front face ``distance`` m in front of the camera's eye
(default `BOX_DISTANCE` = 1 m), centred at the eye's height; a sphere stands off-axis, ahead and to the left. The
onboard camera (`jaxdrones.backends.camera`) then sees, by the pinhole model with f = (H/2)/tan(fov/2) pixels:

* the box's front face as a square of side f·BOX_SIDE/distance pixels centred in the image, at depth ``distance``
  (the face is perpendicular to the optical axis, so every pixel on it reads the same depth), in the box's colour;
* the ground below the horizon (the image's middle row) and nothing (segmentation -1) above it, except the objects.

`save_camera_images` writes ``rgb.png`` (8-bit RGB), ``depth.png`` (16-bit, millimetres, 0 where nothing is within
the far plane), ``seg.png`` (8-bit palette image whose index is body id + 1, 0 = nothing; 16-bit grey if an id
exceeds 254) and ``scene.json`` (body ids and camera settings).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

from jaxdrones._validate import check_real
from jaxdrones.io.runs import write_json
from jaxdrones.physics.params import DroneParams
from jaxdrones.scene import Obstacle

if TYPE_CHECKING:
    from PIL import Image

#: The drone's position, m, world frame (level, yaw 0: the camera looks along world +x).
DRONE_POS = (0.0, 0.0, 0.5)
#: Distance from the camera's eye to the box's front face, m; the box's side, m; its colour (RGBA in [0, 1]).
BOX_DISTANCE = 1.0
BOX_SIDE = 0.2
BOX_RGBA = (0.8, 0.3, 0.2, 1.0)
#: The off-axis sphere: centre (m, world frame), radius (m) and colour.
SPHERE_POS = (1.6, 0.6, 0.35)
SPHERE_RADIUS = 0.15
SPHERE_RGBA = (0.2, 0.7, 0.3, 1.0)
#: Files written by `save_camera_images`.
FILES = ("rgb.png", "depth.png", "seg.png", "scene.json")
#: Colours of seg.png's palette: nothing, then body ids 0, 1, ... (cycled).
_SEG_COLOURS = (
    (0, 0, 0),
    (128, 128, 128),
    (230, 90, 50),
    (60, 180, 80),
    (70, 110, 230),
    (240, 200, 40),
    (170, 80, 200),
    (40, 200, 200),
    (250, 250, 250),
)


def eye_position(params: DroneParams) -> np.ndarray:
    """The camera's eye, f[3] m, world frame: `DRONE_POS` + (collision_radius + EYE_MARGIN, 0, 0)."""
    from jaxdrones.sensors.camera import EYE_MARGIN

    return np.asarray(DRONE_POS) + np.array([float(params.collision_radius) + EYE_MARGIN, 0.0, 0.0])


def scene_obstacles(params: DroneParams, distance: float = BOX_DISTANCE) -> tuple[Obstacle, Obstacle]:
    """The box (front face ``distance`` m ahead of the eye, centred on the optical axis) and the sphere.

    Raises:
        ValueError: if ``distance`` is not a positive finite number.
    """
    check_real("distance", distance, 0, low_open=True, what="a finite number of metres")
    eye = eye_position(params)
    box = Obstacle("box", size=(BOX_SIDE,) * 3, pos=(eye[0] + distance + BOX_SIDE / 2, eye[1], eye[2]), rgba=BOX_RGBA)
    sphere = Obstacle("sphere", size=(SPHERE_RADIUS,), pos=SPHERE_POS, rgba=SPHERE_RGBA)
    return box, sphere


def camera_scene(
    model: str = "cf2x",
    width: int = 320,
    height: int = 240,
    fov: float = 60.0,
    distance: float = BOX_DISTANCE,
    renderer: str = "tiny",
) -> dict:
    """Build the scene in a PyBullet step and render the drone's onboard camera.

    Args:
        model: airframe name or URDF path (`jaxdrones.load_params`).
        width, height: image size, pixels.
        fov: vertical field of view, degrees.
        distance: eye-to-box-face distance, m.
        renderer: ``"tiny"`` or ``"egl"``.

    Returns:
        dict with ``rgb`` uint8[H, W, 4], ``depth`` float32[H, W] m, ``seg`` int32[H, W] (the drone's images),
        ``body_ids`` (`PyBulletStep.body_ids`: ground, obstacles = (box, sphere), drones), ``eye`` f[3] m and
        ``settings`` (model, width, height, fov, near, far, distance, renderer).

    Raises:
        ValueError: on a bad model, image size, fov, distance or renderer.
        RuntimeError: if the renderer cannot be used on this machine (``"egl"`` without the EGL plugin).
        ModuleNotFoundError: without pybullet installed (the ``pybullet`` extra).
    """
    import jax

    from jaxdrones.physics.params import load_params
    from jaxdrones.physics.state import init_state
    from jaxdrones.sim import SimConfig, make_step

    params = load_params(model)
    config = SimConfig(n_drones=1)
    state = jax.tree.map(np.asarray, init_state(config, pos=np.array([DRONE_POS])))
    with make_step(config, backend="pybullet", obstacles=scene_obstacles(params, distance), renderer=renderer) as step:
        images = step.camera_images(params, state, width=width, height=height, fov=fov)
        ids = step.body_ids(0)
    return {
        **{k: v[0] for k, v in images.items()},
        "body_ids": ids,
        "eye": eye_position(params),
        "settings": {
            "model": model,
            "width": width,
            "height": height,
            "fov_deg": fov,
            "near_m": float(params.arm),
            "far_m": 100.0,
            "box_distance_m": distance,
            "renderer": renderer,
        },
    }


def save_camera_images(scene: dict, out_dir: str | os.PathLike, overwrite: bool = False) -> dict:
    """Write `FILES` of a `camera_scene` result into ``out_dir`` (created if missing).

    Returns:
        dict file name → path written.

    Raises:
        FileExistsError: if one of the files exists and not ``overwrite`` (nothing is written then).
    """
    from PIL import Image

    out_dir = os.fspath(out_dir)
    paths = {name: os.path.join(out_dir, name) for name in FILES}
    existing = [p for p in paths.values() if os.path.exists(p)]
    if existing and not overwrite:
        raise FileExistsError(f"{existing} exist; pass overwrite=True (CLI: --overwrite) or another folder")
    os.makedirs(out_dir, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(scene["rgb"][..., :3])).save(paths["rgb.png"])
    Image.fromarray(depth_to_mm(scene["depth"], scene["settings"]["far_m"])).save(paths["depth.png"])
    seg_image(scene["seg"]).save(paths["seg.png"])
    scene_file = {
        "body_ids": scene["body_ids"],
        "eye_m": np.asarray(scene["eye"]).tolist(),
        "settings": scene["settings"],
        "files": {
            "depth.png": "uint16 depth along the optical axis in mm, 0 = nothing within far",
            "seg.png": "pixel value = Bullet body id + 1, 0 = nothing",
        },
    }
    write_json(paths["scene.json"], scene_file)
    return paths


def depth_to_mm(depth: np.ndarray, far: float) -> np.ndarray:
    """Depth f[H, W] m → uint16 millimetres (rounded, clipped at 65 535), 0 where depth ≥ far or not finite."""
    depth = np.asarray(depth, np.float64)
    mm = np.clip(np.round(np.nan_to_num(depth, nan=0.0) * 1000.0), 0, 65535)
    return np.where(np.isfinite(depth) & (depth < far * (1 - 1e-6)), mm, 0).astype(np.uint16)


def seg_image(seg: np.ndarray) -> Image.Image:
    """A Pillow image of segmentation ids int[H, W]: value id + 1 (0 = nothing), 8-bit palette if ids ≤ 254."""
    from PIL import Image

    index = np.asarray(seg).astype(np.int64) + 1
    if index.max(initial=0) <= 255:
        image = Image.fromarray(index.astype(np.uint8), "L").convert("P")
        palette = [
            c
            for i in range(256)
            for c in (_SEG_COLOURS[0] if i == 0 else _SEG_COLOURS[1 + (i - 1) % (len(_SEG_COLOURS) - 1)])
        ]
        image.putpalette(palette)
        return image
    return Image.fromarray(index.astype(np.uint16))
