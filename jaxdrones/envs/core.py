"""The composable env layer: a static task config, traced task params, and one env that runs any task.

Three tiers (docs/physics.md §11):

* `TaskConfig` (frozen, hashable; a change recompiles): drone count, models, action and observation types, rates,
  effects, backend, and the defaults of the task params.
* `TaskParams` (a pytree in `EnvState.task`, sampled at ``reset``): targets, references, start ranges, termination
  bounds and reward weights, so every world and every episode can differ without recompiling.
* `DroneParams` (in `EnvState.params`, sampled at ``reset`` with `DomainRandomization`).

A `Task` supplies only its start sampling, its reward terms and its termination rule (plus its success metrics and,
for tasks with a moving reference, the reference); `TaskEnv` does the rest with the shared action
(`jaxdrones.envs.actions`), observation (`jaxdrones.envs.observations`), reward (`jaxdrones.envs.rewards`) and
termination (`jaxdrones.envs.terminations`) modules. Every env holds ``D ≥ 1`` drones with stacked arrays: obs
``f[D, n_obs]``, action ``f[D, n_act]``, reward ``f[D]``; ``terminated``/``truncated`` are per world.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones._fork import check_not_forked
from jaxdrones.backends import BACKENDS, RENDERERS
from jaxdrones.cameras import ENV_IMAGES, image_shapes
from jaxdrones.envs import rewards, terminations
from jaxdrones.envs.actions import ACTION_TYPES, PID_MAX_STEP, PID_TARGETS, Reference, make_action
from jaxdrones.envs.base import Env, EnvState
from jaxdrones.envs.observations import OBS_TYPES, ObsType
from jaxdrones.params import MODELS, DroneParams, broadcast_params, load_params, stack_params, with_derived
from jaxdrones.rotations import quat_from_euler
from jaxdrones.sim import SimConfig, make_step
from jaxdrones.state import DroneState

#: Camera images a vision observation can hold (see `TaskConfig.vision`; their dtypes and per-pixel shapes in
#: `jaxdrones.cameras.ENV_IMAGES`).
VISION = tuple(ENV_IMAGES)
#: Reward variants: ``"shaped"`` (ours, for fast RL) and ``"paper"`` (the original's).
REWARDS = ("shaped", "paper")


@dataclasses.dataclass(frozen=True)
class DomainRandomization:
    """Relative half-widths of per-drone parameter randomisation, drawn anew at every reset (per world, episode
    and drone): each field's value is multiplied by a factor uniform in [1 − r, 1 + r].

    The derived quantities (hover and max RPM, max thrust and torques, J⁻¹) are recomputed from the sampled values
    by `jaxdrones.params.with_derived`.

    Attributes:
        mass: of ``mass``.
        inertia: of the inertia matrix (one factor for the whole matrix, which stays positive definite).
        kf: of the thrust coefficient.
        km: of the torque coefficient.
        drag: of the drag coefficients.

    Raises:
        ValueError: a range that is not finite or not in [0, 1) (1 or more would allow a non-positive value).
    """

    mass: float = 0.0
    inertia: float = 0.0
    kf: float = 0.0
    km: float = 0.0
    drag: float = 0.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 <= value < 1):
                raise ValueError(f"randomize.{f.name} must be a relative half-width in [0, 1) (a factor in "
                                 f"[1 - r, 1 + r]; r >= 1 allows a non-positive {f.name}), got {value!r}")

    def sample(self, key: jax.Array, params: DroneParams) -> DroneParams:
        """Randomised ``params`` (batch shape [..., D]), with the derived fields recomputed."""
        fields = {"mass": "mass", "inertia": "inertia", "kf": "kf", "km": "km", "drag": "drag_coeff"}
        lead = params.mass.shape
        new = {}
        for k, (name, attr) in zip(jax.random.split(key, len(fields)), fields.items(), strict=False):
            r = getattr(self, name)
            if r == 0:
                continue
            factor = jax.random.uniform(k, lead, params.mass.dtype, 1.0 - r, 1.0 + r)
            value = getattr(params, attr)
            new[attr] = value * factor.reshape(lead + (1,) * (value.ndim - len(lead)))
        return with_derived(params.replace(**new)) if new else params


@struct.dataclass
class StartRanges:
    """Where episodes start: uniform around a centre (m, rad, m/s, rad/s; world frame except ``ang_vel``).

    Attributes:
        pos: f[D, 3] centre of the start positions, m.
        pos_range: f[3] half-widths in x, y, z, m (z is kept above the ground).
        rpy: f[D, 3] centre attitude, rad.
        tilt: f[] largest random tilt, rad: roll = t cos φ, pitch = t sin φ, t ~ U[0, tilt], φ ~ U[0, 2π).
        yaw: f[] half-width of the random yaw, rad (π: any heading).
        vel: f[3] half-widths of the start velocity, m/s.
        ang_vel: f[3] half-widths of the start body rates, rad/s.
    """

    pos: jax.Array
    pos_range: jax.Array
    rpy: jax.Array
    tilt: jax.Array
    yaw: jax.Array
    vel: jax.Array
    ang_vel: jax.Array


@struct.dataclass
class Bounds:
    """Termination bounds: the arena box and the largest tilt.

    Attributes:
        pos_low: f[3] m, world frame.
        pos_high: f[3] m.
        max_tilt: f[] rad, angle between body z and world z.
    """

    pos_low: jax.Array
    pos_high: jax.Array
    max_tilt: jax.Array


@struct.dataclass
class TaskParams:
    """The traced params of a task's episode (see the module docstring).

    Attributes:
        target: f[D, 3] m, each drone's position target (world frame).
        start: `StartRanges`.
        bounds: `Bounds`.
        weights: reward weight by term name, f[].
        data: task-specific arrays (e.g. ``"target_vel"`` f[D, 3], ``"waypoints"`` f[K, D, 3]).
        scene: what the JAX backend's cameras see besides the drones, a `jaxdrones.cameras.Scene` (`Task.scene`;
            a task may draw it per episode in `Task.sample`, e.g. the ``avoid`` task's obstacles), or None without
            cameras.
    """

    target: jax.Array
    start: StartRanges
    bounds: Bounds
    weights: dict[str, jax.Array]
    data: dict[str, jax.Array] = struct.field(default_factory=dict)
    scene: Any = None


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """Static settings shared by every task (hashable; a change recompiles). Tasks subclass it with their own
    fields and defaults.

    Attributes:
        n_drones: drones per world, D (the task says which D it allows).
        model: drone model name or URDF path for all drones, or a tuple with one per drone (heterogeneous team,
            e.g. ``("cf2x", "racer")``).
        action_type: one of `jaxdrones.envs.actions.ACTION_TYPES`.
        obs_type: one of `jaxdrones.envs.observations.OBS_TYPES`; default ``"kin_rotmat"`` (the paper's KIN followed
            by the rotation matrix: with random headings, the Euler angles' wrap at ±π makes learning much slower
            — PPO on 3-D hover reached 14 cm with ``"kin"`` and 1.2 cm with ``"kin_rotmat"`` in the same 4.4 M
            steps); ``"kin"`` is the paper's.
        action_buffer: append the last ``ctrl_freq // 2`` actions to the observation (the original's KIN).
        pid_target: ``pid`` action: ``"absolute"`` (main) or ``"relative"`` (the paper).
        pid_scale: ``pid`` with relative targets: target = pos + pid_scale · a, m, in (0, 1]; the paper's 0.1 m,
            which the DSL PID flies at up to about 0.5 m/s (0.3 m: about 1 m/s).
        sim_freq: physics rate, Hz.
        ctrl_freq: control (env step) rate, Hz.
        episode_len_s: episode length, s.
        drag, ground_effect, downwash: aerodynamic effects of the physics (docs/physics.md §6).
        kinks: the treatment of the physics' kinks for gradients (`SimConfig.kinks`, `jaxdrones.kinks`):
            ``"exact"`` (default), ``"smooth"`` or ``"straight_through"``, or a `jaxdrones.kinks.Kinks`.
        adjoint: reverse-mode derivatives of the physics through its hand-written adjoint (`SimConfig.adjoint`;
            default True); False for forward-mode derivatives (``jax.jvp``, ``jax.jacfwd``) through ``step``.
        reward: ``"shaped"`` (the task's shaped reward) or ``"paper"`` (the original's reward).
        init_pos: f[D, 3] m, fixed start positions (the original's ``initial_xyzs``): they override the random
            start ranges; the drones start at rest and level (unless ``init_rpy`` is given).
        init_rpy: f[D, 3] rad, fixed start attitudes (``initial_rpys``), overriding the random attitude.
        start_pos_range: (x, y, z) half-widths of random start positions around the task's start centre, m
            (None: the task's default).
        start_tilt: largest random start tilt, rad (None: the task's default).
        start_yaw: half-width of the random start yaw, rad (None: the task's default).
        start_vel: half-width of each random start velocity component, m/s (None: the task's default).
        start_ang_vel: half-width of each random start body-rate component, rad/s (None: the task's default).
        arena_xy: an episode terminates when a drone's |x| or |y| exceeds this, m.
        arena_z: ... or its z exceeds this, m.
        max_tilt: ... or its tilt exceeds this, rad.
        terminate_on_ground: a touch of the ground terminates the episode as a crash.
        randomize: `DomainRandomization` (or a dict of its fields) applied at every reset; None for none.
        neighbor_radius: ``neighbors`` observation: radius of the adjacency, m.
        max_neighbors: ``neighbors`` observation: None (every drone) or K ≥ 1: the min(K, D - 1) nearest drones
            only, 12 + 4·min(K, D - 1) entries whatever the team's size (`jaxdrones.envs.observations`).
        downwash_radius: the downwash's cut-off with a neighbour list for large teams, m (`SimConfig`; None: every
            pair of drones, the original).
        backend: ``"jax"`` (differentiable) or ``"pybullet"`` (collisions, obstacles, cameras; not differentiable;
            call ``close``).
        obstacles: None, True or ``"paper"``, or a sequence of `Obstacle` / URDF paths. On the PyBullet backend
            drones collide with them; on the JAX backend (with ``vision`` only) the cameras see them but the physics
            does not collide with them, and URDF meshes are refused.
        vision: camera images to add to the observation, any of ``"rgb"``, ``"depth"``, ``"seg"``; the observation
            is then a dict ``{"state": f[D, n_obs], "rgb": u8[D, H, W, 4], "depth": f32[D, H, W] m, "seg":
            i32[D, H, W]}``, the images rendered every `camera_period` steps and held. On the JAX backend they come
            from `jaxdrones.cameras` (pure JAX, batched, depth differentiable; RGBA with alpha 255), on the PyBullet
            backend from Bullet's renderer; both use the same camera and segmentation ids.
        camera_freq: camera rate asked for, Hz (the paper: 24).
        image_size: (width, height) of the camera images, pixels.
        renderer: ``"pybullet"`` only: ``"tiny"`` (CPU) or ``"egl"``.

    Raises:
        ValueError: on any invalid value, naming the field and the valid range.
    """

    n_drones: int = 1
    model: str | tuple[str, ...] = "cf2x"
    action_type: str = "rpm"
    obs_type: str = "kin_rotmat"
    action_buffer: bool = False
    pid_target: str = "absolute"
    pid_scale: float = 0.1
    sim_freq: int = 240
    ctrl_freq: int = 30
    episode_len_s: float = 5.0
    drag: bool = False
    ground_effect: bool = False
    downwash: bool = False
    kinks: Any = "exact"
    adjoint: bool = True
    reward: str = "shaped"
    init_pos: Any = None
    init_rpy: Any = None
    start_pos_range: Any = None
    start_tilt: float | None = None
    start_yaw: float | None = None
    start_vel: float | None = None
    start_ang_vel: float | None = None
    arena_xy: float = 1.5
    arena_z: float = 2.5
    max_tilt: float = math.pi / 2
    terminate_on_ground: bool = False
    randomize: Any = None
    neighbor_radius: float = math.inf
    max_neighbors: int | None = None
    downwash_radius: float | None = None
    backend: str = "jax"
    obstacles: Any = None
    vision: tuple[str, ...] = ()
    camera_freq: float = 24.0
    image_size: tuple[int, int] = (64, 48)
    renderer: str = "tiny"

    def __post_init__(self):
        _check_choice("action_type", self.action_type, ACTION_TYPES)
        _check_choice("obs_type", self.obs_type, OBS_TYPES)
        _check_choice("reward", self.reward, REWARDS)
        _check_choice("pid_target", self.pid_target, PID_TARGETS)
        if not (_is_number(self.pid_scale) and 0.0 < self.pid_scale <= PID_MAX_STEP):
            raise ValueError(f"pid_scale must be a distance in m in (0, {PID_MAX_STEP}], got {self.pid_scale!r}")
        n = self.n_drones
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f"n_drones must be a positive integer, got {n!r}")
        self._check_model()
        self._set("kinks", SimConfig(kinks=self.kinks, adjoint=self.adjoint).kinks)
        for name in ("init_pos", "init_rpy"):
            self._set(name, _fixed_array(name, getattr(self, name), n))
        if self.start_pos_range is not None:
            self._set("start_pos_range", _finite_tuple("start_pos_range", self.start_pos_range, 3, nonneg=True))
        for name in ("start_tilt", "start_yaw", "start_vel", "start_ang_vel"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite half-width >= 0, got {value!r}")
        k = self.max_neighbors
        if k is not None and (not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1):
            raise ValueError(f"max_neighbors must be None (every drone) or a positive integer, got {k!r}")
        for name in ("arena_xy", "arena_z", "max_tilt", "neighbor_radius"):
            value = getattr(self, name)
            if not (_is_number(value) and value > 0):
                raise ValueError(f"{name} must be a number > 0, got {value!r}")
        if not (_is_number(self.episode_len_s) and math.isfinite(self.episode_len_s)
                and self.episode_len_s * self.ctrl_freq >= 1):
            raise ValueError(f"episode_len_s·ctrl_freq must give at least one control step, got "
                             f"{self.episode_len_s!r} s at {self.ctrl_freq!r} Hz")
        if isinstance(self.randomize, dict):
            self._set("randomize", DomainRandomization(**self.randomize))
        elif self.randomize is not None and not isinstance(self.randomize, DomainRandomization):
            raise ValueError(f"randomize must be None, a DomainRandomization or a dict of its fields "
                             f"{[f.name for f in dataclasses.fields(DomainRandomization)]}, got {self.randomize!r}")
        self.sim_config()  # validates the rates
        self._check_backend()

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)

    def _check_model(self) -> None:
        model = self.model
        if isinstance(model, list):
            model = tuple(model)
            self._set("model", model)
        if isinstance(model, tuple) and len(model) != self.n_drones:
            raise ValueError(f"model: give one model for all drones or one per drone ({self.n_drones}), "
                             f"got {len(model)}: {model}")
        for m in (model if isinstance(model, tuple) else (model,)):
            if not isinstance(m, str) or (m not in MODELS and not m.endswith(".urdf")):
                raise ValueError(f"unknown drone model {m!r}: expected one of {MODELS} or a path to a .urdf file")

    def _check_backend(self) -> None:
        _check_choice("backend", self.backend, BACKENDS)
        _check_choice("renderer", self.renderer, RENDERERS)
        vision = self.vision
        if isinstance(vision, str) or not isinstance(vision, (tuple, list)):
            raise ValueError(f"vision must be a tuple of image names from {VISION}, got {vision!r}")
        if any(v not in VISION for v in vision) or len(set(vision)) != len(vision):
            raise ValueError(f"vision must hold distinct names from {VISION}, got {tuple(vision)!r}")
        self._set("vision", tuple(vision))
        if isinstance(self.obstacles, list):
            self._set("obstacles", tuple(self.obstacles))
        from jaxdrones.backends.scene import resolve_obstacles

        obstacles = resolve_obstacles(self.obstacles)
        if self.backend == "jax":
            if self.renderer != "tiny":
                raise ValueError("renderer needs backend='pybullet' (the jax backend renders with "
                                 "jaxdrones.cameras)")
            if obstacles and not self.vision:
                raise ValueError("obstacles on backend='jax' are only seen by its cameras (its physics models the "
                                 "ground only): pass vision=(...), or use backend='pybullet' for collisions")
            from jaxdrones.cameras import check_obstacles

            check_obstacles(obstacles)  # a mesh: a clear error now rather than at the first render
        if not (_is_number(self.camera_freq) and math.isfinite(self.camera_freq) and self.camera_freq > 0):
            raise ValueError(f"camera_freq must be a finite rate > 0 Hz, got {self.camera_freq!r}")
        size = self.image_size
        if (not isinstance(size, (tuple, list)) or len(size) != 2
                or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0 for v in size)):
            raise ValueError(f"image_size must be two positive integers (width, height) in pixels, got {size!r}")
        self._set("image_size", (int(size[0]), int(size[1])))

    def sim_config(self) -> SimConfig:
        """The `SimConfig` of the physics."""
        return SimConfig(n_drones=self.n_drones, sim_freq=self.sim_freq, ctrl_freq=self.ctrl_freq, drag=self.drag,
                         ground_effect=self.ground_effect, downwash=self.downwash, kinks=self.kinks,
                         downwash_radius=self.downwash_radius, adjoint=self.adjoint)

    @property
    def camera_period(self) -> int:
        """Control steps between two camera renders, k = max(1, round(ctrl_freq / camera_freq))."""
        return max(1, int(round(self.ctrl_freq / self.camera_freq)))

    @property
    def camera_rate(self) -> float:
        """Effective camera rate, Hz: ctrl_freq / `camera_period`."""
        return self.ctrl_freq / self.camera_period


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def _check_choice(name: str, value, choices) -> None:
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r}: expected one of {tuple(choices)}")


def _finite_tuple(name: str, value, n: int, nonneg: bool = False) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)) or (nonneg and np.any(arr < 0)):
        raise ValueError(f"{name} must be {n} finite numbers{' >= 0' if nonneg else ''}, got {value!r}")
    return tuple(float(v) for v in arr)


def _fixed_array(name: str, value, n: int):
    """A fixed start as a hashable tuple of D triples, or None."""
    if value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be f[{n}, 3] (one (x, y, z) per drone), got {value!r}") from None
    if arr.shape == (3,) and n == 1:
        arr = arr[None]
    if arr.shape != (n, 3) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be f[{n}, 3] finite numbers (one triple per drone, n_drones={n}), "
                         f"got shape {arr.shape}")
    if name == "init_pos" and np.any(arr[:, 2] < 0):
        raise ValueError(f"init_pos must be above the ground (z >= 0 m), got {arr.tolist()}")
    return tuple(tuple(float(v) for v in row) for row in arr)


class Task(abc.ABC):
    """A task: its start sampling, reward terms and termination rule; `TaskEnv` does the rest.

    Subclasses set the class attributes and override what differs from the defaults.

    Attributes:
        name: the registered name.
        config_cls: its `TaskConfig` subclass.
        min_drones, max_drones: the drone counts it allows (``None``: no upper limit).
        nonnegative_reward: clip the shaped reward at 0 (the ``"paper"`` reward is never clipped).
        success_metric, success_at, success_threshold: how an evaluation is judged (see the class attributes;
            ``success_at`` is ``"final"``, ``"mean"`` or ``"max"``).
    """

    name: str = ""
    config_cls: type[TaskConfig] = TaskConfig
    #: The metric (a key of ``metrics``) that says how well the task is solved, lower is better; whether it is read
    #: at the episode's last step (``"final"``), averaged over the episode (``"mean"``) or taken at its largest over
    #: the episode's steps (``"max"``, e.g. the worst altitude error of a flight); and the threshold below which an
    #: evaluation counts as solved.
    success_metric: str = "distance"
    success_at: str = "final"
    success_threshold: float = 0.05
    #: The unit of `success_metric` (and its threshold), for progress displays and plots.
    success_unit: str = "m"
    #: The values `success_at` may take.
    SUCCESS_AT = ("final", "mean", "max")
    min_drones: int = 1
    max_drones: int | None = 1
    nonnegative_reward: bool = False
    #: The task reads `TaskParams.scene` itself (e.g. for collisions), so it is built even without cameras.
    uses_scene: bool = False
    #: The success metric already counts the episodes that terminate (``avoid``'s collisions are failures): a run
    #: can succeed with some terminated; otherwise success also needs no terminated episode.
    success_counts_terminations: bool = False

    def __init_subclass__(cls, **kwargs):
        """Check the class attributes when a task class is defined.

        Raises:
            ValueError: a `success_at` other than ``"final"``, ``"mean"`` or ``"max"``.
        """
        super().__init_subclass__(**kwargs)
        if cls.success_at not in Task.SUCCESS_AT:
            raise ValueError(f"{cls.__name__}: success_at must be one of {Task.SUCCESS_AT}, got {cls.success_at!r}")

    def variant(self, config: TaskConfig) -> Task:
        """The task that runs ``config`` (default: this one; a setting that changes what a task observes, rewards
        and is judged by gives another, e.g. ``fly_thru_gate`` with ``gate_pose="random"``)."""
        return self

    def check(self, config: TaskConfig) -> None:
        """Validate the config against what the task allows.

        Raises:
            ValueError: a drone count the task does not allow.
        """
        n, lo, hi = config.n_drones, self.min_drones, self.max_drones
        if n < lo or (hi is not None and n > hi):
            allowed = f"exactly {lo}" if lo == hi else (f"{lo} or more" if hi is None else f"{lo} to {hi}")
            raise ValueError(f"{self.name}: n_drones must be {allowed}, got {n}")

    def start_defaults(self, config: TaskConfig) -> dict:
        """Default random start: centre ``pos`` f[D, 3] m and the half-widths (see `TaskConfig`)."""
        from jaxdrones.state import default_start_pos

        return dict(pos=default_start_pos(config.n_drones), pos_range=(0.0, 0.0, 0.0), tilt=0.0, yaw=0.0,
                    vel=0.0, ang_vel=0.0)

    def target(self, config: TaskConfig) -> np.ndarray:
        """f[D, 3] m, the position targets (default: 1 m above each start centre)."""
        return self.start_defaults(config)["pos"] + np.array([0.0, 0.0, 1.0])

    @abc.abstractmethod
    def weights(self, config: TaskConfig) -> dict[str, float]:
        """Reward weights by term name, for ``config.reward``."""

    def data(self, config: TaskConfig) -> dict[str, np.ndarray]:
        """Task-specific arrays of the task params (default: none)."""
        return {}

    def sample(self, config: TaskConfig, task: TaskParams, key: jax.Array) -> TaskParams:
        """Per-episode randomness of the task params (default: none)."""
        return task

    def scene(self, config: TaskConfig):
        """What the JAX backend's cameras see (`TaskParams.scene`), built once per env: by default the config's
        ``obstacles`` (`jaxdrones.cameras.make_scene`)."""
        from jaxdrones.backends.scene import resolve_obstacles
        from jaxdrones.cameras import make_scene

        return make_scene(resolve_obstacles(config.obstacles))

    #: Entries per drone of the task's own observation, appended after the observation type's (e.g. a commanded
    #: velocity, the offset to a waypoint); 0 for none.
    obs_size: int = 0

    def obs_bound(self, config: TaskConfig) -> np.ndarray:
        """f[obs_size], the symmetric bound of the task observation (it is clipped to it)."""
        return np.zeros(0, np.float32)

    def observe(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        """The task observation f[D, obs_size] (what the policy must know of the task: targets, commands)."""
        return jnp.zeros(sim.pos.shape[:-1] + (0,), sim.pos.dtype)

    def reference(self, config: TaskConfig, task: TaskParams, steps: jax.Array) -> Reference:
        """Where the drones should be at control step ``steps`` (default: at the target, at rest)."""
        return Reference(task.target, jnp.zeros_like(task.target))

    @abc.abstractmethod
    def reward_terms(self, config: TaskConfig, task: TaskParams, sim: DroneState, action: jax.Array,
                     steps: jax.Array) -> dict[str, jax.Array]:
        """Reward terms by name, each f[D], from the post-step state."""

    def terminated(self, config: TaskConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        """bool[]: the world's episode ends (default: any drone crashed, see `terminations.crashed`)."""
        return jnp.any(terminations.crashed(sim, task.bounds, config.terminate_on_ground))

    def reached(self, config: TaskConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        """bool[]: the world's episode ends at its goal (terminated, but not a crash; default: never, the episode
        runs to its time limit)."""
        return jnp.zeros((), bool)

    def loss_weights(self, config: TaskConfig) -> dict[str, float]:
        """Weights of `loss_terms` in the differentiable training loss (default: distance² 1, velocity error² 0.1,
        body rate² 0.01), kept apart from the RL reward's weights."""
        return {"distance_sq": 1.0, "velocity_error_sq": 0.1, "ang_speed_sq": 0.01}

    def loss_terms(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict:
        """Terms of the differentiable training loss, each f[D], from the post-step state: the squared distance
        to the reference position (m²), the squared velocity error to the reference velocity ((m/s)²) and the
        squared body rate ((rad/s)²). Smooth everywhere, unlike shaped RL rewards such as max(0, ...), which have
        no gradient far from the target."""
        ref = self.reference(config, task, steps)
        return {"distance_sq": rewards.distance_sq(sim.pos, ref.pos),
                "velocity_error_sq": rewards.velocity_error_sq(sim.vel, ref.vel),
                "ang_speed_sq": rewards.ang_speed_sq(sim.ang_vel)}

    def metrics(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict:
        """Success metrics, f[] per world (default: ``distance``, the mean distance to the reference, m)."""
        ref = self.reference(config, task, steps)
        return {"distance": jnp.mean(rewards.distance(sim.pos, ref.pos))}


class TaskEnv(Env):
    """Any `Task` on the jaxdrones physics, as a brax-protocol env (``reset``/``step``, jit and vmap).

    Observation ``f[D, n_obs]`` (`observation_spec`; a dict with camera images under ``config.vision``), action
    ``f[D, n_act]`` in the action type's box, clipped to it; a non-finite action is replaced by 0 for the physics,
    terminates the episode and sets ``metrics["invalid_action"]``. Reward ``f[D]``; ``terminated``/``truncated``
    per world. `reset` draws the start, the task params (from ``task`` or the config's defaults) and, with
    ``config.randomize``, the drones' params.

    Pickling keeps the task and its config only (no JAX arrays, compiled functions or PyBullet connections): the
    copy is built anew when unpickled, e.g. in a worker process started with ``spawn``.

    Raises:
        ValueError: a config of another task's class, or a drone count the task does not allow.
        RuntimeError: in a process forked after JAX started (it would hang; `jaxdrones._fork`).
    """

    def __init__(self, task: Task, config: TaskConfig):
        check_not_forked()
        if not isinstance(config, task.config_cls):
            raise ValueError(f"{task.name}: expected a {task.config_cls.__name__}, got {type(config).__name__}")
        task = task.variant(config)
        task.check(config)
        self.task, self.config = task, config
        self.sim_config = config.sim_config()
        model = config.model
        params = stack_params(model) if isinstance(model, tuple) else load_params(model)
        self.params = broadcast_params(params, (config.n_drones,))
        self.action_type = make_action(config.action_type, config.pid_target, config.pid_scale)
        self.obs_type = ObsType(config.obs_type, config.n_drones, config.neighbor_radius,
                                config.ctrl_freq // 2 if config.action_buffer else 0, self.action_type.size,
                                config.max_neighbors)
        options = ({"obstacles": config.obstacles, "renderer": config.renderer} if config.backend == "pybullet"
                   else {})
        self._step = make_step(self.sim_config, backend=config.backend, **options)
        self._default_task = None

    def __reduce__(self):
        return type(self), (self.task, self.config)

    # -- sizes and spaces ------------------------------------------------------------------------------------------

    @property
    def n_drones(self) -> int:
        return self.config.n_drones

    @property
    def observation_size(self) -> int:
        return self.obs_type.size + self.task.obs_size

    @property
    def action_size(self) -> int:
        return self.action_type.size

    @property
    def episode_length(self) -> int:
        return int(round(self.config.episode_len_s * self.config.ctrl_freq))

    @property
    def dtype(self):
        return self.params.mass.dtype

    @property
    def shared_params(self) -> DroneParams | None:
        """``params`` (batch shape [D]) when ``config.randomize`` is None (every episode uses them), else None."""
        return self.params if self.config.randomize is None else None

    @property
    def observation_spec(self):
        """Shape and dtype of the observation: a `jax.ShapeDtypeStruct`, or with vision a dict of them."""
        state = jax.ShapeDtypeStruct((self.n_drones, self.observation_size), self.dtype)
        if not self.config.vision:
            return state
        return {"state": state, **self._image_spec()}

    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) f32[D, n_obs] of the state observation: the observation type's, then the task's."""
        low, high = self.obs_type.bounds()
        bound = np.tile(np.asarray(self.task.obs_bound(self.config), np.float32), (self.n_drones, 1))
        return np.concatenate([low, -bound], axis=-1), np.concatenate([high, bound], axis=-1)

    def _observe(self, task: TaskParams, sim: DroneState, history: jax.Array, steps: jax.Array) -> jax.Array:
        obs = self.obs_type.observe(sim, history)
        if not self.task.obs_size:
            return obs
        bound = jnp.asarray(self.task.obs_bound(self.config), obs.dtype)
        extra = jnp.clip(self.task.observe(self.config, task, sim, steps), -bound, bound)
        return jnp.concatenate([obs, extra.astype(obs.dtype)], axis=-1)

    def action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) f32[D, n_act]."""
        a = self.action_type
        return np.tile(a.low, (self.n_drones, 1)), np.tile(a.high, (self.n_drones, 1))

    def close(self) -> None:
        """Release the backend's resources (the PyBullet worlds); the env is unusable after."""
        self._step.close()

    # -- task params -----------------------------------------------------------------------------------------------

    def default_task_params(self) -> TaskParams:
        """The task params the config describes (before per-episode sampling), in the env's dtype."""
        if self._default_task is None:  # kept as NumPy arrays, so that it can be built inside a trace
            with jax.ensure_compile_time_eval():  # what the task computes with JAX is concrete there too
                self._default_task = self._build_task_params()
        return jax.tree.map(jnp.asarray, self._default_task)

    def _build_task_params(self) -> TaskParams:
        cfg, task = self.config, self.task
        start = task.start_defaults(cfg)
        overrides = dict(pos_range=cfg.start_pos_range, tilt=cfg.start_tilt, yaw=cfg.start_yaw, vel=cfg.start_vel,
                         ang_vel=cfg.start_ang_vel)
        start.update({k: v for k, v in overrides.items() if v is not None})
        rpy = np.zeros((cfg.n_drones, 3))
        if cfg.init_pos is not None:  # a fixed start, at rest and (unless init_rpy says otherwise) level
            start.update(pos=np.asarray(cfg.init_pos), pos_range=(0.0, 0.0, 0.0), vel=0.0, ang_vel=0.0, tilt=0.0,
                         yaw=0.0)
        if cfg.init_rpy is not None:
            rpy = np.asarray(cfg.init_rpy)
            start.update(tilt=0.0, yaw=0.0)
        dt = self.dtype

        def arr(x, shape=None):
            x = np.asarray(x, np.float64)
            return np.asarray(x if shape is None else np.broadcast_to(x, shape), dt)

        ranges = StartRanges(pos=arr(start["pos"], (cfg.n_drones, 3)), pos_range=arr(start["pos_range"], (3,)),
                             rpy=arr(rpy), tilt=arr(start["tilt"]), yaw=arr(start["yaw"]),
                             vel=arr(start["vel"], (3,)), ang_vel=arr(start["ang_vel"], (3,)))
        bounds = Bounds(pos_low=arr([-cfg.arena_xy, -cfg.arena_xy, -1.0]),
                        pos_high=arr([cfg.arena_xy, cfg.arena_xy, cfg.arena_z]), max_tilt=arr(cfg.max_tilt))
        scene = None
        if (cfg.vision and cfg.backend == "jax") or task.uses_scene:
            scene = jax.tree.map(lambda x: np.asarray(x, dt) if jnp.issubdtype(x.dtype, jnp.floating)
                                 else np.asarray(x), task.scene(cfg))
        return TaskParams(target=arr(task.target(cfg), (cfg.n_drones, 3)), start=ranges, bounds=bounds,
                          weights={k: arr(v) for k, v in task.weights(cfg).items()},
                          data={k: arr(v) for k, v in task.data(cfg).items()}, scene=scene)

    # -- reset and step --------------------------------------------------------------------------------------------

    def reset(self, key: jax.Array, task: TaskParams | None = None) -> EnvState:
        """Start an episode.

        Args:
            key: PRNG key, typed (``jax.random.key``) or raw uint32.
            task: task params to sample the episode from (e.g. per-world targets or weights); default
                `default_task_params`. Its per-episode quantities (a commanded velocity, a waypoint sequence, ...)
                are drawn anew from ``key``.

        Returns:
            EnvState with reward 0 and the first observation.
        """
        cfg = self.config
        k_task, k_start, k_params, key = jax.random.split(key, 4)
        task = self.task.sample(cfg, self.default_task_params() if task is None else task, k_task)
        params = cfg.randomize.sample(k_params, self.params) if cfg.randomize is not None else self.params
        sim = sample_start(k_start, task.start, self.dtype)
        history = jnp.zeros((cfg.n_drones, self.obs_type.buffer_len, self.action_size), self.dtype)
        steps = jnp.zeros((), jnp.int32)
        obs = self._observe(task, sim, history, steps)
        if cfg.vision:
            blank = {k: jnp.zeros(v.shape, v.dtype) for k, v in self._image_spec().items()}
            obs = {"state": obs, **self._render(task.scene, params, sim, jnp.ones((), bool), blank)}
        zeros = jnp.zeros((cfg.n_drones,), self.dtype)
        terms = self.task.reward_terms(cfg, task, sim, jnp.zeros((cfg.n_drones, self.action_size), self.dtype),
                                       steps)
        metrics = self._metrics(task, sim, steps, {k: zeros for k in terms}, jnp.zeros((), bool),
                                jnp.zeros((), bool))
        return EnvState(sim=sim, params=params, task=task, ctrl=self.action_type.init(params, sim), history=history,
                        key=key, obs=obs, reward=zeros, terminated=jnp.zeros((), bool),
                        truncated=jnp.zeros((), bool), steps=steps, metrics=metrics)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Advance one control step.

        Args:
            state: from `reset` or `step`.
            action: f[D, n_act] in the action type's box (clipped to it).

        Raises:
            ValueError: an action of the wrong shape or a non-float dtype.
        """
        cfg, task = self.config, state.task
        action = self._check_action(action)
        finite = jnp.all(jnp.isfinite(action))
        low, high = (jnp.asarray(b, self.dtype) for b in self.action_bounds())
        action = jnp.where(finite, jnp.clip(action.astype(self.dtype), low, high), 0.0)
        ref = self.task.reference(cfg, task, state.steps)
        rpm, ctrl = self.action_type.to_rpm(state.params, state.sim, state.ctrl, action, ref, self.sim_config.ctrl_dt)
        sim = self._step(state.params, state.sim, rpm)
        steps = state.steps + 1
        history = state.history
        if self.obs_type.buffer_len:
            history = jnp.concatenate([history[:, 1:], action[:, None]], axis=1)
        obs = self._observe(task, sim, history, steps)
        if cfg.vision:
            held = {k: v for k, v in state.obs.items() if k != "state"}
            due = steps % cfg.camera_period == 0
            images = jax.lax.cond(due, lambda: self._render(task.scene, state.params, sim, due, held), lambda: held)
            obs = {"state": obs, **images}
        terms = self.task.reward_terms(cfg, task, sim, action, steps)
        nonneg = self.task.nonnegative_reward and cfg.reward == "shaped"
        reward, weighted = rewards.combine(terms, task.weights, nonneg)
        crashed = self.task.terminated(cfg, task, sim)
        terminated = crashed | self.task.reached(cfg, task, sim) | ~finite
        truncated = (steps >= self.episode_length) & ~terminated
        metrics = self._metrics(task, sim, steps, weighted, crashed, ~finite)
        return state.replace(sim=sim, ctrl=ctrl, history=history, obs=obs, reward=reward, terminated=terminated,
                             truncated=truncated, steps=steps, metrics=metrics)

    def loss(self, state: EnvState) -> jax.Array:
        """The task's differentiable training loss of a (post-step) state, f[D]: `Task.loss_terms` weighted by
        `Task.loss_weights` (for gradient-based training; the RL reward is ``state.reward``)."""
        terms = self.task.loss_terms(self.config, state.task, state.sim, state.steps)
        weights = self.task.loss_weights(self.config)
        return sum(weights[k] * v for k, v in terms.items() if weights.get(k, 0.0))

    def _metrics(self, task, sim, steps, weighted, crashed, invalid) -> dict:
        dtype = self.dtype
        metrics = {k: jnp.asarray(v, dtype) for k, v in self.task.metrics(self.config, task, sim, steps).items()}
        metrics.update({f"reward/{k}": jnp.mean(v) for k, v in weighted.items()})
        metrics.update(crash=crashed.astype(dtype), invalid_action=invalid.astype(dtype))
        return metrics

    def _check_action(self, action) -> jax.Array:
        action = jnp.asarray(action)
        expected = (self.n_drones, self.action_size)
        if action.shape != expected:
            raise ValueError(f"{self.task.name}: action must have shape {expected} ([n_drones, size] for "
                             f"action_type={self.config.action_type!r}, entries in [-1, 1]), got {action.shape}")
        if not jnp.issubdtype(action.dtype, jnp.floating):
            raise ValueError(f"{self.task.name}: action must be a float array, got dtype {action.dtype}")
        return action

    # -- cameras -------------------------------------------------------------------------------------------------------

    def _image_spec(self) -> dict:
        return image_shapes((self.n_drones,), *self.config.image_size, self.config.vision)

    def _render(self, scene, params: DroneParams, sim: DroneState, due: jax.Array, held: dict) -> dict:
        """The camera images of ``sim`` where ``due`` (bool[...]), ``held`` elsewhere.

        On the JAX backend, `jaxdrones.cameras.render` of every world in ``scene`` (the task params'); on the
        PyBullet backend, `jaxdrones.backends.camera.held_images` (``scene`` unused).
        """
        width, height = self.config.image_size
        if self.config.backend == "pybullet":
            from jaxdrones.backends.camera import held_images

            return held_images(self._step, params, sim, due, held, width, height)
        from jaxdrones.cameras import CameraSpec, render

        images = render(CameraSpec(width=width, height=height), scene, params, sim.pos, sim.quat,
                        kinds=self.config.vision)
        if "rgb" in images:  # RGBA, as Bullet's
            rgb = images["rgb"]
            images["rgb"] = jnp.concatenate([rgb, jnp.full(rgb.shape[:-1] + (1,), 255, rgb.dtype)], -1)
        return {k: jnp.where(jnp.reshape(due, due.shape + (1,) * (v.ndim - due.ndim)), v, held[k])
                for k, v in images.items()}


def sample_start(key: jax.Array, start: StartRanges, dtype) -> DroneState:
    """A random start state of D drones, uniform in ``start`` (see `StartRanges`), at rest in the motors.

    Positions are kept at or above the resting height of the collision cylinder's base (z ≥ 0.0125 m is the
    rest height of the Crazyflie; any z ≥ 0 is accepted and the contact model lifts a drone out of the ground).
    All the numbers are drawn from ``key`` in one call (12 per drone): on CPU, random-number generation is most
    of a reset's cost, and one draw of 12 costs about a third of six draws.
    """
    n = start.pos.shape[-2]
    u = jax.random.uniform(key, (n, 12), dtype, -1.0, 1.0)
    pos = start.pos + start.pos_range * u[:, 0:3]
    pos = jnp.concatenate([pos[:, :2], jnp.maximum(pos[:, 2:], 0.0)], axis=-1)
    tilt = start.tilt * 0.5 * (u[:, 3] + 1.0)
    phi = jnp.pi * (u[:, 4] + 1.0)
    yaw = start.yaw * u[:, 5]
    rpy = start.rpy + jnp.stack([tilt * jnp.cos(phi), tilt * jnp.sin(phi), yaw], axis=-1)
    return DroneState(pos=pos, quat=quat_from_euler(rpy), vel=start.vel * u[:, 6:9],
                      ang_vel=start.ang_vel * u[:, 9:12], rpm=jnp.zeros((n, 4), dtype),
                      contact=jnp.zeros((n,), jnp.int32))
