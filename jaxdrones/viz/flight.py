"""A rollout to show (`Flight`: every drone's pose over time, the scene, the onboard camera images) and what both
views take from it: the drones' colours, the camera's view, the target file's check."""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from jaxdrones._validate import check_real, is_integer

if TYPE_CHECKING:
    from jaxdrones.envs import EnvState, TaskEnv


#: A view: (position, look_at), two (x, y, z) points in m, world frame.
View = tuple[Sequence[float], Sequence[float]]
#: Colours: (r, g, b) triples in 0-255.
Colors = Sequence[Sequence[float]]

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
        what = "the time between frames, a finite number of seconds"
        object.__setattr__(self, "dt", check_real("dt", self.dt, 0, low_open=True, what=what))
        check_real("arm", self.arm, 0, low_open=True, what="the drones' arm length, a finite number of metres")
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

        Takes the frame time ``1 / env.config.sim.ctrl_freq``, and the config's obstacles where the states carry no
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
        if not (is_integer(time_axis) and 0 <= time_axis < n_lead):
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
            1.0 / env.config.sim.ctrl_freq,
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


def wxyz(xyzw: np.ndarray) -> np.ndarray:
    """(x, y, z, w) → (w, x, y, z), viser's order."""
    return np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1)


def wxyz_from_rotmat(r: np.ndarray) -> np.ndarray:
    """A rotation matrix f[3, 3] as a unit quaternion (w, x, y, z) (SciPy's, a dependency of JAX)."""
    from scipy.spatial.transform import Rotation

    return wxyz(Rotation.from_matrix(np.asarray(r, np.float64)).as_quat())


def resolve_view(flight: Flight, offsets: np.ndarray, camera: tuple | None) -> tuple[np.ndarray, np.ndarray]:
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


def check_target(path: str, overwrite: bool, signature: bytes) -> None:
    """Raise ``ValueError`` where ``path`` is a folder or a file without ``signature`` that ``overwrite`` would
    replace (one jaxdrones did not write), ``FileExistsError`` where it is a file and ``overwrite`` is off
    (`jaxdrones.io.runs.check_replace`)."""
    from jaxdrones.io.runs import check_replace

    if os.path.isdir(path):
        raise ValueError(f"{path!r} is a folder; give a file name such as flight.html")
    check_replace(path, overwrite, signature)


def drone_palette(colors: ArrayLike | None) -> np.ndarray:
    """u8[K, 3]: ``colors`` (RGB triples in 0-255; None: `DRONE_COLORS`), checked."""
    colors = DRONE_COLORS if colors is None else colors
    try:
        palette = np.asarray(colors, np.float64)
    except (TypeError, ValueError):
        palette = np.zeros(0)
    if palette.ndim != 2 or palette.shape[1] != 3 or len(palette) == 0 or not np.all((palette >= 0) & (palette <= 255)):
        raise ValueError(f"colors must be a sequence of (r, g, b) in 0-255, got {colors!r}")
    return palette.astype(np.uint8)


def drone_colours(palette: np.ndarray, n_worlds: int, n_drones: int) -> np.ndarray:
    """u8[W, D, 3]: the palette cycled over the drones of a world, or over the worlds when each has one drone."""
    if n_drones == 1:
        return palette[np.arange(n_worlds) % len(palette)][:, None]
    return np.broadcast_to(palette[np.arange(n_drones) % len(palette)], (n_worlds, n_drones, 3))
