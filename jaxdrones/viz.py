"""Flight viewer: a rollout as one self-contained HTML file that plays offline, or as a GIF/MP4 through the JAX
cameras.

`write_html` records a `Flight` (positions and attitudes of every drone of one world or many, the scene's
obstacles and gates, and the onboard camera images when the env has cameras) with viser's scene serializer and
writes viser's static client with the recording embedded: one ``.html`` file that opens from ``file://`` with no
server and no network, with play/pause, a time slider, playback speed, trails behind the drones and a 3D view to
orbit. It needs viser (the ``viewer`` extra: ``pip install ".[viewer]"`` from a clone; viser's
``ViserServer.get_scene_serializer`` and ``StateSerializer.as_html``, https://viser.studio): the scene is built in
a viser server bound to localhost, which no client ever joins, and recorded message by message.

`write_video` draws the same flight from a chase or fixed camera with the JAX ray caster
(`jaxdrones.cameras.render`, no PyBullet) and writes a GIF or MP4 (`jaxdrones.video.VideoWriter`).

    import jaxdrones as jd
    from jaxdrones.viz import Flight, write_html

    flight = Flight.from_states(env, states)      # states: EnvState with a leading time axis (rollout_policy)
    write_html("flight.html", flight)

Frames: positions are m in the world frame, z up; quaternions (x, y, z, w) rotate body to world, as everywhere in
jaxdrones (`jaxdrones.DroneState`).
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import io
import math
import numbers
import os
import socket
from collections.abc import Sequence
from contextlib import redirect_stdout
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from jaxdrones.envs import EnvState, TaskEnv

#: A view: (position, look_at), two (x, y, z) points in m, world frame.
View = tuple[Sequence[float], Sequence[float]]
#: Colours: (r, g, b) triples in 0-255.
Colors = Sequence[Sequence[float]]

#: What installs viser (the HTML viewer's only optional dependency): the ``viewer`` extra, from a clone of the project.
VIEWER_INSTALL = 'pip install ".[viewer]" from a clone of jaxdrones, or pip install viser "websockets<17"'
#: Drone colours (RGB 0-255), cycled over the drones of a world: distinct hues that stand out on a white scene.
DRONE_COLORS = (
    (31, 119, 180),
    (214, 39, 40),
    (44, 160, 44),
    (148, 103, 189),
    (255, 127, 14),
    (23, 190, 207),
    (227, 119, 194),
    (188, 189, 34),
)
#: The cf2x's arm length, m (its URDF): the drones' drawn size when a `Flight` does not say.
CF2X_ARM = 0.0397
#: The HTML viewer's initial vertical field of view, degrees.
VIEW_FOV = 50.0
#: Camera presets of `write_video`.
VIDEO_CAMERAS = ("chase", "fixed")


def _viser():
    """Import viser, or raise one ModuleNotFoundError that names the extra to install."""
    try:
        import viser
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(f"the flight viewer needs viser: {VIEWER_INSTALL}", name="viser") from err
    return viser


def viewer_available() -> bool:
    """Whether viser (the ``viewer`` extra) is installed, so that `write_html` can run."""
    import importlib.util

    return importlib.util.find_spec("viser") is not None


# --------------------------------------------------------------------------------------------- the flight
@dataclasses.dataclass(frozen=True, eq=False)
class Flight:
    """A rollout to show: every drone's pose over time, the scene, and optionally the onboard camera images.

    Build it from arrays (checked and flattened here) or from env states with `Flight.from_states`.

    Attributes:
        pos: f[T, ..., D, 3] m, world frame, z up: T frames, any leading world axes, D drones. Stored as
            f64[T, W, D, 3] with the world axes flattened (W = 1 without world axes).
        quat: f[T, ..., D, 4] (x, y, z, w), body → world, same leading axes; stored normalised as f64[T, W, D, 4].
        dt: time between frames, s (> 0).
        scene: the static obstacles and gates: None, a sequence of `jaxdrones.scene.Obstacle` (or anything
            `jaxdrones.scene.resolve_obstacles` takes; URDF meshes are not drawn), or a `jaxdrones.cameras.Scene`
            (a task's ``TaskParams.scene``: the gate of ``fly_thru_gate``, the obstacles of ``avoid``), unbatched
            or with the flight's world axes (one scene per world). Stored as a `jaxdrones.cameras.Scene` of NumPy
            arrays, unbatched or with one world axis [W], or None.
        images: onboard camera frames: u8[T, ..., D, H, W, 3 or 4] (RGB or RGBA), or depth f[T, ..., D, H, W] m
            (drawn grey, near bright); stored as u8[T, W, D, H, W, 3]. None: no camera.
        arm: the drones' arm length, m (their drawn size); default the cf2x's.

    Raises:
        ValueError: arrays of the wrong shape (the message names the expected one), non-finite values, a zero
            quaternion, a dt that is not a positive number, a scene whose world axes differ from the flight's, or
            images whose leading axes differ from the positions'.
    """

    pos: np.ndarray
    quat: np.ndarray
    dt: float
    scene: Any = None
    images: np.ndarray | None = None
    arm: float = CF2X_ARM

    def __post_init__(self):
        pos = _finite_array("pos", self.pos, "f[T, ..., D, 3] (m, world frame)", last=(3,))
        quat = _finite_array("quat", self.quat, "f[T, ..., D, 4] (x, y, z, w)", last=(4,))
        if quat.shape[:-1] != pos.shape[:-1]:
            raise ValueError(
                f"quat must be f[T, ..., D, 4] with the leading axes of pos f{list(pos.shape)}, that is "
                f"f{list(pos.shape[:-1]) + [4]}; got f{list(quat.shape)}"
            )
        norm = np.linalg.norm(quat, axis=-1, keepdims=True)
        if np.any(norm < 1e-9):
            raise ValueError("quat: every quaternion must be non-zero (x, y, z, w), body → world")
        lead = pos.shape[1:-2]
        n_worlds = math.prod(lead)
        t, d = pos.shape[0], pos.shape[-2]
        object.__setattr__(self, "pos", pos.reshape(t, n_worlds, d, 3))
        object.__setattr__(self, "quat", (quat / norm).reshape(t, n_worlds, d, 4))
        if isinstance(self.dt, bool) or not isinstance(self.dt, numbers.Real) or not (0 < self.dt < math.inf):
            raise ValueError(f"dt must be the time between frames, a finite number of seconds > 0, got {self.dt!r}")
        object.__setattr__(self, "dt", float(self.dt))
        if isinstance(self.arm, bool) or not isinstance(self.arm, numbers.Real) or not (0 < self.arm < math.inf):
            raise ValueError(f"arm must be the drones' arm length, a finite number of metres > 0, got {self.arm!r}")
        object.__setattr__(self, "scene", _check_scene(self.scene, lead))
        object.__setattr__(self, "images", _check_images(self.images, pos.shape[:-1]))

    @property
    def n_frames(self) -> int:
        """T, the number of frames."""
        return self.pos.shape[0]

    @property
    def n_worlds(self) -> int:
        """W, the number of worlds (the leading world axes flattened)."""
        return self.pos.shape[1]

    @property
    def n_drones(self) -> int:
        """D, the drones per world."""
        return self.pos.shape[2]

    @classmethod
    def from_states(cls, env: TaskEnv, states: EnvState, time_axis: int = 0) -> Flight:
        """The flight of env states with a time axis, e.g. `jaxdrones.training.rollout_policy`'s (time first) or
        those of several episodes vmapped (``time_axis=1``): `from_data` of `flight_data`.

        Args:
            env: the `jaxdrones.envs.TaskEnv` the states come from.
            states: `jaxdrones.envs.EnvState` with leading axes holding a time axis at ``time_axis``.
            time_axis: the time axis among the leading axes.

        Raises:
            ValueError: as `Flight`, or a ``time_axis`` beyond the states' leading axes.
        """
        return cls.from_data(env, flight_data(states), time_axis)

    @classmethod
    def from_data(cls, env: TaskEnv, data: dict, time_axis: int = 0) -> Flight:
        """The flight of `flight_data`'s arrays (taken inside a compiled program, e.g. an evaluation's).

        Takes the frame time ``1 / env.config.ctrl_freq``, and the config's obstacles where the states carry no
        scene (URDF meshes are not drawn).

        Args:
            env: the `jaxdrones.envs.TaskEnv` the states come from.
            data: `flight_data`'s dict (JAX or NumPy arrays).
            time_axis: the time axis among the leading axes of ``data["pos"]`` f[..., D, 3].

        Raises:
            ValueError: as `Flight`, or a ``time_axis`` beyond the leading axes.
        """
        import jax

        pos = np.asarray(data["pos"])
        n_lead = pos.ndim - 2
        if isinstance(time_axis, bool) or not isinstance(time_axis, numbers.Integral) or not 0 <= time_axis < n_lead:
            raise ValueError(
                f"time_axis must index a leading axis of pos f{list(pos.shape)} (0 <= time_axis < "
                f"{n_lead}), got {time_axis!r}"
            )

        def first_time(x):
            return np.moveaxis(np.asarray(x), time_axis, 0)

        scene = data.get("scene")
        if scene is not None:  # constant over an episode: the first frame's
            scene = jax.tree.map(lambda x: first_time(x)[0], scene)
        else:
            scene = tuple(o for o in _resolve(env.config.obstacles) if o.shape != "urdf")
        images = None if data.get("images") is None else first_time(data["images"])
        return cls(
            first_time(pos),
            first_time(data["quat"]),
            1.0 / env.config.ctrl_freq,
            scene=scene,
            images=images,
            arm=float(np.max(np.asarray(data["arm"]))),
        )


def flight_data(states: EnvState) -> dict:
    """What a `Flight` needs from env states, as a dict of arrays; traceable, so that a compiled program (an
    evaluation) can return it: ``pos`` f[..., D, 3], ``quat`` f[..., D, 4], ``arm`` f[..., D] m, ``scene`` (the task
    params' `jaxdrones.cameras.Scene`, or None) and ``images`` (the observation's camera frames: RGB u8[..., D, H, W,
    4], else depth f[..., D, H, W]; the newest frame of a frame stack; None without cameras).

    Args:
        states: `jaxdrones.envs.EnvState` with any leading axes (time, episodes, worlds).
    """
    pos = states.sim.pos
    images = None
    if isinstance(states.obs, dict):
        name = "rgb" if "rgb" in states.obs else "depth" if "depth" in states.obs else None
        if name is not None:
            images = states.obs[name]
            if images.ndim == pos.ndim + (3 if name == "rgb" else 2):  # [..., D, K, H, W(, C)]: the newest frame
                images = images[(slice(None),) * (pos.ndim - 1) + (-1,)]
    return {
        "pos": pos,
        "quat": states.sim.quat,
        "arm": states.params.arm,
        "scene": getattr(states.task, "scene", None),
        "images": images,
    }


def _finite_array(name: str, value, expected: str, last: tuple[int, ...]) -> np.ndarray:
    """``value`` as a finite f64 array with at least 3 axes (T, D and the last) ending in ``last``."""
    try:
        x = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a numeric array {expected}, got {type(value).__name__}") from None
    if x.ndim < 3 or x.shape[-len(last) :] != last or 0 in x.shape:
        raise ValueError(f"{name} must be {expected} with T >= 1 frames and D >= 1 drones, got shape {list(x.shape)}")
    if not np.all(np.isfinite(x)):
        bad = np.argwhere(~np.isfinite(x))[0]
        raise ValueError(f"{name} must be finite; entry {tuple(int(i) for i in bad)} is {x[tuple(bad)]}")
    return x


def _resolve(obstacles) -> tuple:
    from jaxdrones.scene import resolve_obstacles

    return resolve_obstacles(obstacles)


def _check_scene(scene, lead: tuple[int, ...]):
    """The `Flight.scene` argument as a `jaxdrones.cameras.Scene` of NumPy arrays, unbatched or [W], or None."""
    import jax

    from jaxdrones.scene.primitives import Scene, make_scene

    if scene is None or (isinstance(scene, (tuple, list)) and len(scene) == 0):
        return None
    if not isinstance(scene, Scene):
        obstacles = tuple(o for o in _resolve(scene) if o.shape != "urdf")  # meshes: Bullet's alone
        return jax.tree.map(np.asarray, make_scene(obstacles, ground=True)) if obstacles else None
    scene = jax.tree.map(np.asarray, scene)
    scene_lead = scene.box.pos.shape[:-2]
    if scene_lead == ():
        return scene
    if scene_lead != lead:
        raise ValueError(
            f"scene: a jaxdrones.cameras.Scene unbatched or with the flight's world axes {list(lead)} "
            f"(box.pos f[..., N, 3]), got world axes {list(scene_lead)}"
        )
    n = math.prod(lead)
    return jax.tree.map(lambda x: x.reshape((n,) + x.shape[len(lead) :]), scene)


def _check_images(images, lead: tuple[int, ...]):
    """Camera frames as u8[T, W, D, H, W, 3] (RGB; depth drawn grey), or None; ``lead`` is pos's [T, ..., D]."""
    if images is None:
        return None
    x = np.asarray(images)
    n = len(lead)
    expected = f"u8[T, ..., D, H, W, 3 or 4] (RGB/RGBA) or depth f[T, ..., D, H, W] m with T, ..., D = {list(lead)}"
    rgb = x.dtype == np.uint8 and x.ndim == n + 3 and x.shape[-1] in (3, 4)
    depth = np.issubdtype(x.dtype, np.floating) and x.ndim == n + 2
    if x.shape[:n] != lead or not (rgb or depth) or 0 in x.shape:
        raise ValueError(f"images must be {expected}; got {x.dtype}{list(x.shape)}")
    if depth:
        finite = np.isfinite(x)
        far = np.max(x[finite]) if finite.any() else 1.0
        x = np.where(finite, x, far)
        grey = np.round(255 * (1 - np.clip(x / max(far, 1e-9), 0, 1))).astype(np.uint8)
        x = np.repeat(grey[..., None], 3, -1)
    x = x[..., :3]
    n_worlds = math.prod(lead[1:-1])
    return np.ascontiguousarray(x.reshape((lead[0], n_worlds, lead[-1]) + x.shape[n:]))


# --------------------------------------------------------------------------------------------- geometry helpers
def _wxyz(xyzw: np.ndarray) -> np.ndarray:
    """(x, y, z, w) → (w, x, y, z), viser's order."""
    return np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1)


def _wxyz_from_rotmat(r: np.ndarray) -> np.ndarray:
    """A rotation matrix f[3, 3] as a unit quaternion (w, x, y, z) (SciPy's, a dependency of JAX)."""
    from scipy.spatial.transform import Rotation

    return _wxyz(Rotation.from_matrix(np.asarray(r, np.float64)).as_quat())


def _primitives(scene, world: int) -> list[tuple]:
    """The valid primitives of world ``world`` of a `Flight.scene`: (shape, centre, rotation, size, rgb) with
    `jaxdrones.cameras.Primitives`' size convention (half extents; radius; radius and half length)."""
    if scene is None:
        return []
    out = []
    for shape in ("box", "sphere", "cylinder", "capsule"):
        p = getattr(scene, shape)
        if p.valid.ndim == 2:  # one scene per world: this world's
            p = type(p)(**{f.name: getattr(p, f.name)[world] for f in dataclasses.fields(p)})
        out += [(shape, p.pos[i], p.rot[i], p.size[i], p.rgb[i]) for i in np.flatnonzero(p.valid)]
    return out


def _drone_mesh(arm: float) -> tuple[np.ndarray, np.ndarray]:
    """A quadrotor of arm length ``arm`` m as one triangle mesh (vertices f[V, 3] m, body frame; faces i32[F, 3]):
    a square plate, four rotor disks on the diagonals (the cf2x's X layout) and a nose along body +x that shows the
    heading."""
    import trimesh

    side = 1.13 * arm  # `jaxdrones.cameras.BODY_SIDE_PER_ARM`, as the cameras draw the plate
    d = arm / math.sqrt(2)
    parts = [trimesh.creation.box((side, side, 0.012))]
    nose = trimesh.creation.box((0.9 * arm, 0.25 * arm, 0.012))
    nose.apply_translation((side / 2 + 0.3 * arm, 0.0, 0.0))
    parts.append(nose)
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        disk = trimesh.creation.cylinder(radius=0.58 * arm, height=0.004, sections=20)
        disk.apply_translation((sx * d, sy * d, 0.008))
        parts.append(disk)
    mesh = trimesh.util.concatenate(parts)
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


def _world_offsets(flight: Flight, spacing: float | None) -> np.ndarray:
    """f[W, 3]: where each world is drawn, m: all at the origin (``spacing`` 0), or on a square grid of that pitch."""
    n = flight.n_worlds
    if spacing is None:
        per_world = flight.scene is not None and flight.scene.box.pos.ndim == 3 and n > 1
        if not per_world:
            return np.zeros((n, 3))
        span = float(np.ptp(flight.pos[..., :2], axis=(0, 2)).max())
        reach = [
            np.abs(c[:2] - flight.pos[0, w, :, :2].mean(0)).max() + 2 * np.max(s)
            for w in range(n)
            for _, c, _, s, _ in _primitives(flight.scene, w)
        ]
        spacing = 2 * max([span, *reach]) + 1.0
    cols = math.ceil(math.sqrt(n))
    w = np.arange(n)
    return np.stack([(w % cols) * spacing, -(w // cols) * spacing, np.zeros(n)], -1)


def _view(flight: Flight, offsets: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """The initial camera (position, look-at point), m: ``camera`` if given, else looking at the centre of the
    drones' paths from the front left and above, far enough to see them all."""
    if camera is not None:
        eye, target = (np.asarray(v, np.float64) for v in camera)
        if eye.shape != (3,) or target.shape != (3,) or not np.all(np.isfinite([*eye, *target])):
            raise ValueError(f"camera must be (position, look_at), two finite (x, y, z) points in m, got {camera!r}")
        if np.allclose(eye, target):
            raise ValueError("camera: position and look_at must differ")
        return eye, target
    pts = (flight.pos + offsets[None, :, None, :]).reshape(-1, 3)
    lo, hi = pts.min(0), pts.max(0)
    target = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 0.5)
    direction = np.array([-0.55, -1.0, 0.6])
    return target + direction / np.linalg.norm(direction) * radius * 2.6, target


# --------------------------------------------------------------------------------------------- HTML viewer
def write_html(
    path: str | os.PathLike,
    flight: Flight,
    *,
    overwrite: bool = False,
    trail_s: float | None = 2.0,
    max_fps: float = 30.0,
    spacing: float | None = None,
    camera: View | None = None,
    drone_scale: float = 1.0,
    colors: Colors | None = None,
    dark_mode: bool = False,
) -> str:
    """Write ``flight`` as one self-contained HTML file that plays offline (from ``file://``, no server).

    The file is viser's static client with the recorded scene embedded (no URL is fetched): the ground grid, the
    scene's boxes, spheres, cylinders and capsules, the drones as small quadrotors (a nose marks body +x) in a colour
    per drone index, or per world for flights of one drone (`DRONE_COLORS`), their trails, and with
    ``flight.images`` a panel per drone of world 0 (`MAX_PANELS` at most) showing its camera frames beside the
    flight, facing the initial view. The page has play/pause (also the space bar), a time slider, playback speed and
    a view to orbit, pan and zoom. Worlds are drawn at the same place unless the scene differs per world, where they
    are laid out on a grid (see ``spacing``).

    Args:
        path: the file to write (``.html``); parent folders are created.
        flight: the `Flight`.
        overwrite: replace an existing file (otherwise FileExistsError).
        trail_s: how far back each trail reaches, s; None: the whole flight; 0: no trails.
        max_fps: the recording's frame rate at most, Hz: frames are skipped to stay at or below it (the time axis
            is kept: playback runs at real time).
        spacing: the pitch, m, of the grid the worlds are laid out on; 0: all at the origin; None: at the origin
            unless the scene is per world, then a pitch that keeps the worlds apart.
        camera: the initial view, ``(position, look_at)`` in m (world frame), z up, `VIEW_FOV` vertically; None:
            from the front left and above, framing the drones' paths.
        drone_scale: draw the drones this many times their size (> 0), e.g. to see small drones in a large arena.
        colors: RGB 0-255 per drone index (per world with one drone), a sequence of (r, g, b), cycled; default
            `DRONE_COLORS`.
        dark_mode: the viewer's dark theme.

    Returns:
        The path written.

    Raises:
        TypeError: ``flight`` is not a `Flight`.
        ModuleNotFoundError: viser is not installed (`VIEWER_INSTALL`).
        FileExistsError: ``path`` exists and not ``overwrite``.
        ValueError: a bad option (a negative trail, a frame rate or scale that is not positive, a camera that is not
            two points, colours that are not RGB triples).
    """
    if not isinstance(flight, Flight):
        raise TypeError(
            f"flight must be a jaxdrones.viz.Flight (e.g. Flight(pos, quat, dt)), got {type(flight).__name__}"
        )
    path = os.fspath(path)
    _check_target(path, overwrite)
    if trail_s is not None and not (isinstance(trail_s, numbers.Real) and 0 <= trail_s < math.inf):
        raise ValueError(f"trail_s must be None or a finite number of seconds >= 0, got {trail_s!r}")
    for name, value in (("max_fps", max_fps), ("drone_scale", drone_scale)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < value < math.inf:
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    if spacing is not None and not (isinstance(spacing, numbers.Real) and 0 <= spacing < math.inf):
        raise ValueError(f"spacing must be None or a finite number of metres >= 0, got {spacing!r}")
    palette = _palette(colors)
    offsets = _world_offsets(flight, spacing)
    eye, target = _view(flight, offsets, camera)
    viser = _viser()
    html = _record(viser, flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode)
    folder = os.path.dirname(path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    with open(path, "w" if overwrite else "x", encoding="utf-8") as f:
        f.write(html)
    return path


def _check_target(path: str, overwrite: bool) -> None:
    if os.path.isdir(path):
        raise ValueError(f"{path!r} is a folder; give a file name such as flight.html")
    if os.path.exists(path) and not overwrite:
        raise FileExistsError(errno.EEXIST, "exists; pass overwrite=True to replace it", path)


def _palette(colors) -> np.ndarray:
    colors = DRONE_COLORS if colors is None else colors
    try:
        palette = np.asarray(colors, np.float64)
    except (TypeError, ValueError):
        palette = np.zeros(0)
    if palette.ndim != 2 or palette.shape[1] != 3 or len(palette) == 0 or not np.all((palette >= 0) & (palette <= 255)):
        raise ValueError(f"colors must be a sequence of (r, g, b) in 0-255, got {colors!r}")
    return palette.astype(np.uint8)


def _colours(palette: np.ndarray, n_worlds: int, n_drones: int) -> np.ndarray:
    """u8[W, D, 3]: the palette cycled over the drones of a world, or over the worlds when each has one drone."""
    if n_drones == 1:
        return palette[np.arange(n_worlds) % len(palette)][:, None]
    return np.broadcast_to(palette[np.arange(n_drones) % len(palette)], (n_worlds, n_drones, 3))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _record(viser, flight: Flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode) -> str:
    """Build the scene in a viser server bound to localhost (no client ever connects), record the frames with its
    scene serializer and return the static client with the recording embedded."""
    quiet = io.StringIO()  # viser prints a banner on start and a line on stop
    with redirect_stdout(quiet):
        server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        return _build(server, flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode)
    finally:
        with redirect_stdout(quiet):
            server.stop()


def _build(server, flight: Flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode) -> str:
    scene = server.scene
    scene.set_up_direction("+z")
    n_w, n_d = flight.n_worlds, flight.n_drones
    pos = flight.pos + offsets[None, :, None, :]  # [T, W, D, 3]
    n = n_w * n_d
    colours = _colours(palette, n_w, n_d).reshape(n, 3)
    corners = [pos.reshape(-1, 3), target[None]]
    corners += [
        (c + offsets[w] + np.abs(r) @ h)[None] for w in range(n_w) for _, c, r, h, _ in _primitives(flight.scene, w)
    ]
    corners += [
        (c + offsets[w] - np.abs(r) @ h)[None] for w in range(n_w) for _, c, r, h, _ in _primitives(flight.scene, w)
    ]
    lo, hi = np.concatenate(corners).min(0) - 0.5, np.concatenate(corners).max(0) + 0.5
    size = float(np.ceil(max(hi[0] - lo[0], hi[1] - lo[1], 2.0)))
    scene.add_grid(
        "/ground",
        width=size,
        height=size,
        plane="xy",
        cell_size=0.25,
        section_size=1.0,
        position=(float(round((lo[0] + hi[0]) / 2)), float(round((lo[1] + hi[1]) / 2)), 0.0),
        shadow_opacity=0.0,
    )
    for w in range(n_w):
        if w > 0 and (flight.scene is None or flight.scene.box.pos.ndim == 2) and not np.any(offsets[w]):
            break  # one scene for all worlds drawn at one place: once
        for k, (shape, centre, rot, half, rgb) in enumerate(_primitives(flight.scene, w)):
            _add_primitive(
                scene,
                f"/scene/w{w}/{shape}{k}",
                shape,
                centre + offsets[w],
                rot,
                half,
                tuple(int(c) for c in np.round(255 * np.clip(rgb, 0, 1))),
            )
    vertices, faces = _drone_mesh(flight.arm * drone_scale)
    drones = scene.add_batched_meshes_simple(
        "/drones",
        vertices,
        faces,
        batched_wxyzs=_wxyz(flight.quat[0]).reshape(n, 4),
        batched_positions=pos[0].reshape(n, 3),
        batched_colors=colours,
        lod="off",
        material="toon3",
        cast_shadow=False,
        receive_shadow=False,
    )  # toon: saturated colours under viser's bright default lights
    server.initial_camera.position = tuple(eye)
    server.initial_camera.look_at = tuple(target)
    server.initial_camera.up = (0.0, 0.0, 1.0)
    server.initial_camera.fov = math.radians(VIEW_FOV)
    panels = _add_panels(scene, flight, eye, target, lo, hi)
    stride = max(1, math.ceil(1.0 / (flight.dt * max_fps)))
    frames = list(range(0, flight.n_frames, stride))
    if frames[-1] != flight.n_frames - 1:
        frames.append(flight.n_frames - 1)
    keep = None if trail_s is None else math.ceil(trail_s / (stride * flight.dt))
    serializer = server.get_scene_serializer()
    trails = []
    for i, t in enumerate(frames):
        if i > 0:
            serializer.insert_sleep((t - frames[i - 1]) * flight.dt)
            drones.batched_positions = pos[t].reshape(n, 3)
            drones.batched_wxyzs = _wxyz(flight.quat[t]).reshape(n, 4)
            if keep != 0:
                segment = np.stack([pos[frames[i - 1]], pos[t]], axis=-2).reshape(n, 2, 3)
                trails.append(
                    scene.add_line_segments(
                        f"/trails/{i}",
                        segment,
                        colors=np.repeat(colours[:, None], 2, 1),
                        thickness=1.5,
                        thickness_units="screen",
                    )
                )
                if keep is not None and len(trails) > keep:
                    trails.pop(0).remove()
        for d, panel in enumerate(panels):
            if i == 0 or not np.array_equal(flight.images[t, 0, d], flight.images[frames[i - 1], 0, d]):
                panel.image = flight.images[t, 0, d]
    if len(frames) == 1:  # a single frame: a still scene
        serializer.insert_sleep(flight.dt)
    return serializer.as_html(dark_mode=dark_mode)


def _add_primitive(scene, name: str, shape: str, centre, rot, half, rgb) -> None:
    """One obstacle (`jaxdrones.cameras.Primitives` conventions) as a viser shape."""
    wxyz = _wxyz_from_rotmat(rot)
    centre = tuple(float(c) for c in centre)
    if shape == "box":
        scene.add_box(name, color=rgb, dimensions=tuple(2 * float(h) for h in half), wxyz=wxyz, position=centre)
    elif shape == "sphere":
        scene.add_icosphere(name, radius=float(half[0]), color=rgb, position=centre)
    elif shape == "cylinder":
        scene.add_cylinder(
            name, radius=float(half[0]), height=2 * float(half[1]), color=rgb, wxyz=wxyz, position=centre
        )
    else:
        import trimesh

        mesh = trimesh.creation.capsule(height=2 * float(half[1]), radius=float(half[0]))  # along z, centred
        scene.add_mesh_simple(
            name,
            np.asarray(mesh.vertices, np.float32),
            np.asarray(mesh.faces, np.int32),
            color=rgb,
            wxyz=wxyz,
            position=centre,
        )


#: Camera panels drawn at most (world 0's first drones).
MAX_PANELS = 4


def _add_panels(scene, flight: Flight, eye, target, lo, hi) -> list:
    """Image panels for world 0's drones' camera frames: upright, facing the initial view, in a column beside the
    flight (to its right as seen from the initial view)."""
    if flight.images is None:
        return []
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= max(np.linalg.norm(right), 1e-9)
    up = np.cross(right, forward)
    rot = np.stack([right, -up, forward], axis=1)  # the image plane's x right, y down, z away from the viewer
    wxyz = _wxyz_from_rotmat(rot)
    h, w = flight.images.shape[3:5]
    extent = float(np.linalg.norm(hi - lo))
    height = max(0.5 * extent / MAX_PANELS, 0.15)
    width = height * w / h
    centre = (lo + hi) / 2
    half = float(np.abs(right) @ (hi - lo)) / 2  # the box [lo, hi]'s half extent along the view's right
    panels = []
    count = min(flight.n_drones, MAX_PANELS)
    middle = centre + right * (half + 0.2 + width / 2)
    middle[2] = target[2]
    middle[2] = max(middle[2], 1.1 * height * count / 2 + 0.05)  # the lowest panel above the ground
    for d in range(count):
        centre = middle + up * (height * 1.1 * ((count - 1) / 2 - d))
        panels.append(
            scene.add_image(
                f"/cameras/drone{d}",
                flight.images[0, 0, d],
                width,
                height,
                format="png",
                wxyz=wxyz,
                position=tuple(centre),
                cast_shadow=False,
                receive_shadow=False,
            )
        )
    return panels


#: Evaluation episodes ``jaxdrones view`` flies by default, and ``jaxdrones train`` shows in its flight.html.
VIEW_EPISODES = 4


# --------------------------------------------------------------------------------------------- video
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
    MP4 or GIF (`jaxdrones.video.VideoWriter`).

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
        overwrite: replace an existing file.

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
    _check_target(path, overwrite)
    for name, value, n in (("world", world, flight.n_worlds), ("drone", drone, flight.n_drones)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 0 <= value < n:
            raise ValueError(f"{name} must be an index in [0, {n}), got {value!r}")
    if isinstance(max_fps, bool) or not isinstance(max_fps, numbers.Real) or not 0 < max_fps < math.inf:
        raise ValueError(f"max_fps must be a finite number > 0, got {max_fps!r}")
    if trail_s is not None and not (isinstance(trail_s, numbers.Real) and 0 <= trail_s < math.inf):
        raise ValueError(f"trail_s must be None or a finite number of seconds >= 0, got {trail_s!r}")
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
    colours = _colours(_palette(colors), 1, flight.n_drones)[0]
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
        eye, target = _view(one, np.zeros((1, 3)), None)
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
    eye, target = _view(flight, np.zeros((flight.n_worlds, 3)), camera)
    return np.tile(eye, (n, 1)), np.tile(_look(eye, target), (n, 1, 1))


def _xyzw_from_rotmat(r: np.ndarray) -> np.ndarray:
    """A rotation matrix f[3, 3] as a unit quaternion (x, y, z, w)."""
    w, x, y, z = _wxyz_from_rotmat(r)
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
