"""The static side of a task: `TaskConfig` (frozen, hashable; a change recompiles) with its validation, and
`DomainRandomization` (the ranges of the drones' params drawn per episode).

The env layer has three tiers (docs/physics.md §11): the config here; the traced task params
(`jaxdrones.envs.task.TaskParams`, sampled at ``reset``); the drones' params (`DroneParams`, in `EnvState.params`).
A `jaxdrones.envs.task.Task` supplies what differs between tasks; `jaxdrones.envs.env.TaskEnv` runs any of them.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from jaxdrones._validate import check_bool, check_choice, check_int, check_real, check_reals, is_integer, is_real
from jaxdrones.backends import BACKENDS, RENDERERS, require_pybullet
from jaxdrones.control.firmware.loop import POSITION_PERIOD
from jaxdrones.envs.actions import ACTION_TYPES, FIRMWARE_ACTIONS, FIRMWARE_SIM_FREQ, PID_MAX_STEP, PID_TARGETS
from jaxdrones.envs.observations import OBS_TYPES
from jaxdrones.envs.realism import resolve as resolve_realism
from jaxdrones.physics.params import MODELS, DroneParams, with_derived
from jaxdrones.scene import resolve_obstacles
from jaxdrones.sensors.camera import ENV_IMAGES
from jaxdrones.sim import SimConfig

#: Camera images a vision observation can hold (see `TaskConfig.vision`; their dtypes and per-pixel shapes in
#: `jaxdrones.cameras.ENV_IMAGES`).
VISION = tuple(ENV_IMAGES)
#: Reward variants: ``"shaped"`` (ours, for fast RL) and ``"paper"`` (the original's).
REWARDS = ("shaped", "paper")
#: The motors' speeds at an episode's start where they have dynamics (`Starts.rpm`).
START_RPMS = ("hover", "zero")


@dataclasses.dataclass(frozen=True)
class DomainRandomization:
    """The drones' params drawn anew at every reset (per world, episode and drone): relative half-widths, each
    field's value multiplied by a factor uniform in [1 − r, 1 + r], and the motors' time constants, drawn uniform in
    a range of seconds.

    The derived quantities (hover and max RPM, max thrust and torques, J⁻¹) are recomputed from the sampled values
    by `jaxdrones.physics.params.with_derived`. A task's config gives the one it draws from as
    `TaskConfig.param_draws` (its ``randomize`` with its realism's motor time constants).

    Attributes:
        mass: of ``mass``.
        inertia: of the inertia matrix (one factor for the whole matrix, which stays positive definite).
        kf: of the thrust coefficient.
        km: of the torque coefficient.
        drag: of the drag coefficients.
        motor_tau_up, motor_tau_down: (low, high) s, the motors' time constants (`DroneParams.motor_tau_up`,
            `jaxdrones.physics.dynamics.motor_response_c`), or None to keep the params' (the URDF's); low = high sets
            every episode's. The realism's (`jaxdrones.envs.realism.Realism.motor_tau_up`) come here.

    Raises:
        ValueError: a relative range that is not finite or not in [0, 1) (1 or more would allow a non-positive
            value); a time-constant range that is not 0 <= low <= high, finite.
    """

    mass: float = 0.0
    inertia: float = 0.0
    kf: float = 0.0
    km: float = 0.0
    drag: float = 0.0
    motor_tau_up: tuple[float, float] | None = None
    motor_tau_down: tuple[float, float] | None = None

    def __post_init__(self):
        for name in RELATIVE_DRAWS:
            what = f"a relative half-width (a factor in [1 - r, 1 + r]; r >= 1 allows a non-positive {name})"
            check_real(f"randomize.{name}", getattr(self, name), 0, 1, high_open=True, what=what)
        for name in TAU_DRAWS:
            value = getattr(self, name)
            if value is None:
                continue
            low, high = check_reals(f"randomize.{name}", value, 2, nonneg=True)
            if low > high:
                raise ValueError(f"randomize.{name} must be (low, high) s with low <= high, got {value!r}")
            object.__setattr__(self, name, (low, high))

    @property
    def taus(self) -> dict[str, tuple[float, float]]:
        """The time-constant ranges given (not None), by `TAU_DRAWS` name."""
        return {name: getattr(self, name) for name in TAU_DRAWS if getattr(self, name) is not None}

    @property
    def motor_dynamics(self) -> bool:
        """Some time constant can be above 0: the motors have first-order dynamics (`SimConfig.motor_dynamics`)."""
        return any(high > 0 for _, high in self.taus.values())

    @property
    def draws(self) -> bool:
        """Whether a reset draws params of its own (a relative half-width above 0 or a time-constant range wider than
        a point); False: every episode has the same params (`fixed`)."""
        relative = any(getattr(self, name) != 0 for name in RELATIVE_DRAWS)
        return relative or any(low != high for low, high in self.taus.values())

    def fixed(self, params: DroneParams) -> DroneParams:
        """``params`` with the time constants that every episode shares (low = high) set."""
        lead, dtype = params.mass.shape, params.mass.dtype
        new = {name: jnp.full(lead, low, dtype) for name, (low, high) in self.taus.items() if low == high}
        return params.replace(**new) if new else params

    def sample(self, key: jax.Array, params: DroneParams) -> DroneParams:
        """Randomised ``params`` (batch shape [..., D]), with the derived fields recomputed."""
        lead, dtype = params.mass.shape, params.mass.dtype
        new = {}
        for k, (name, attr) in zip(jax.random.split(key, len(RELATIVE_DRAWS)), RELATIVE_DRAWS.items(), strict=True):
            r = getattr(self, name)
            if r == 0:
                continue
            factor = jax.random.uniform(k, lead, dtype, 1.0 - r, 1.0 + r)
            value = getattr(params, attr)
            new[attr] = value * factor.reshape(lead + (1,) * (value.ndim - len(lead)))
        for name, (low, high) in self.taus.items():
            k = jax.random.fold_in(key, len(RELATIVE_DRAWS) + TAU_DRAWS.index(name))
            new[name] = jax.random.uniform(k, lead, dtype, low, high)
        return with_derived(params.replace(**new)) if new else params


#: `DomainRandomization`'s relative draws: its field → the `DroneParams` field it scales.
RELATIVE_DRAWS = {"mass": "mass", "inertia": "inertia", "kf": "kf", "km": "km", "drag": "drag_coeff"}
#: `DomainRandomization`'s ranges of the motors' time constants (s), named as the `DroneParams` fields.
TAU_DRAWS = ("motor_tau_up", "motor_tau_down")


@dataclasses.dataclass(frozen=True)
class Starts:
    """How an episode starts (`TaskConfig.starts`): fixed poses, or random ranges around the task's start centre
    (each None: the task's own, `jaxdrones.envs.task.Task.start_defaults`), and the motors' speeds.

    Attributes:
        init_pos: f[D, 3] m, fixed start positions (the original's ``initial_xyzs``): they override the random
            ranges; the drones start at rest and level (unless ``init_rpy`` is given). Flat name ``init_pos``.
        init_rpy: f[D, 3] rad, fixed start attitudes (``initial_rpys``), overriding the random attitude.
        pos_range: (x, y, z) half-widths of random start positions, m (``start_pos_range``).
        tilt: largest random start tilt, rad (``start_tilt``).
        yaw: half-width of the random start yaw, rad (``start_yaw``).
        vel: half-width of each random start velocity component, m/s (``start_vel``).
        ang_vel: half-width of each random start body-rate component, rad/s (``start_ang_vel``).
        rpm: the motors' speeds at the start where they have dynamics (`SimConfig.motor_dynamics`, from motor time
            constants): ``"hover"`` (default), each drone's hover RPM with its episode's params
            (``DroneParams.hover_rpm``), as a flying Crazyflie's motors spin when a controller takes over; ``"zero"``,
            stopped motors (a take-off from rest: at the hover action the drone first sinks while they spin up).
            Without motor dynamics each command is reached within a substep and the state's ``rpm`` starts at 0
            either way (the paper's physics). Flat name ``start_rpm``.

    Raises:
        ValueError: a range that is not finite and >= 0, an unknown ``rpm``; `TaskConfig` checks the fixed poses
            against its drones (and stores them as tuples).
    """

    init_pos: Any = None
    init_rpy: Any = None
    pos_range: Any = None
    tilt: float | None = None
    yaw: float | None = None
    vel: float | None = None
    ang_vel: float | None = None
    rpm: str = "hover"

    def __post_init__(self):
        check_choice("start_rpm", self.rpm, START_RPMS)
        if self.pos_range is not None:
            object.__setattr__(self, "pos_range", check_reals("start_pos_range", self.pos_range, 3, nonneg=True))
        for name in ("tilt", "yaw", "vel", "ang_vel"):
            if getattr(self, name) is not None:
                check_real(f"start_{name}", getattr(self, name), 0, what="a finite half-width")


#: The fixed poses of `Starts`, checked against the team by `TaskConfig`.
POSES = ("init_pos", "init_rpy")
#: `TaskConfig`'s flat names of the `Starts` fields (`jaxdrones.make` takes them): flat name → field.
START_OPTIONS = {
    "init_pos": "init_pos",
    "init_rpy": "init_rpy",
    "start_pos_range": "pos_range",
    "start_tilt": "tilt",
    "start_yaw": "yaw",
    "start_vel": "vel",
    "start_ang_vel": "ang_vel",
    "start_rpm": "rpm",
}


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
        action_buffer: append the last actions to the observation, oldest first: True for ``ctrl_freq // 2`` (0.5 s,
            the original's KIN), an integer k >= 1 for the last k, False (or 0) for none. A memory of what the
            policy commanded, against the motors' lag and the actions' delay (Learning to Fly in Seconds feeds the
            last 32 actions at 100 Hz, 0.32 s).
        error_integral: append the integral of the task's tracking error (`jaxdrones.envs.task.Task.tracking_error`:
            hover and the position tasks, reference position − position, m; ``velocity``, commanded − measured
            velocity, m/s) over the episode, f[3] per drone, world frame: I_t = clip(I_{t-1} + e_t / ctrl_freq, ±1)
            (`jaxdrones.envs.env.ERROR_INTEGRAL_BOUND`), I_0 = e_0 / ctrl_freq, computed from what the sensors
            report (the realism's noise and delay included). A PID's integral term: it lets a policy cancel a
            constant unknown force (the ``crazyflie`` preset's per-episode disturbance) that a memoryless policy
            leaves as a steady offset.
        pid_target: ``pid`` action: ``"absolute"`` (main) or ``"relative"`` (the paper).
        pid_scale: ``pid`` with relative targets: target = pos + pid_scale · a, m, in (0, 1]; the paper's 0.1 m,
            which the DSL PID flies at up to about 0.5 m/s (0.3 m: about 1 m/s).
        episode_len_s: episode length, s.
        sim: the physics (`jaxdrones.physics.config.SimConfig`, or a dict of its fields): its rates ``sim_freq`` and
            ``ctrl_freq`` (the env steps at ``ctrl_freq``), the aerodynamic effects ``drag``, ``ground_effect``,
            ``downwash`` (docs/physics.md §6), ``downwash_radius``, ``kinks``, ``adjoint``, ``unroll_substeps``,
            ``integrator``. `jaxdrones.make` takes each of these by its own name (``jd.make("hover", ctrl_freq=48,
            drag=True)``), on top of the task's own. Stored with the config's ``n_drones``, ``drag`` on where the
            ``realism`` has wind and ``motor_dynamics`` where it has motor time constants: what the env steps.
        reward: ``"shaped"`` (the task's shaped reward) or ``"paper"`` (the original's reward).
        starts: how episodes start (`Starts`, or a dict of its fields over the task's own): fixed poses or random
            ranges around the task's start, and the motors' speeds. `jaxdrones.make` takes each by its flat name
            (`START_OPTIONS`: ``init_pos``, ``start_tilt``, ...).
        arena_xy: an episode terminates when a drone's |x| or |y| exceeds this, m.
        arena_z: ... or its z exceeds this, m.
        max_tilt: ... or its tilt exceeds this, rad.
        terminate_on_ground: a touch of the ground terminates the episode as a crash.
        randomize: `DomainRandomization` (or a dict of its fields) drawn at every reset; None for none. The realism's
            motor time constants join it (`param_draws`).
        neighbor_radius: ``neighbors`` observation: radius of the adjacency, m.
        max_neighbors: ``neighbors`` observation: None (every drone) or K ≥ 1: the min(K, D - 1) nearest drones
            only, 12 + 4·min(K, D - 1) entries whatever the team's size (`jaxdrones.envs.observations`).
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
        camera_fov: the cameras' vertical field of view, degrees, in (0, 180) (the paper's 60; the horizontal one
            follows from the image's aspect: 75° at 4:3).
        renderer: ``"pybullet"`` only: ``"tiny"`` (CPU) or ``"egl"``.
        frame_stack: camera frames per image in the observation, K ≥ 1 (needs ``vision`` when K > 1). With K > 1
            each image gains a frame axis after the drone axis (``depth`` f32[D, K, H, W], ``rgb`` u8[D, K, H, W, 4],
            ``seg`` i32[D, K, H, W]): the last K captures, oldest first, the reset's capture repeated until K have
            been taken (gymnasium's ``FrameStackObservation`` with ``padding_type="reset"``; the frame stack of
            Mnih et al. 2015, "Human-level control through deep reinforcement learning"). A memory for a policy
            without one: what it passed and no longer sees, and its motion relative to the scene.
        realism: sim-to-real options (`jaxdrones.envs.realism`): None (the paper's physics, default), a preset name
            (``"crazyflie"``: Learning to Fly in Seconds' Crazyflie values; ``"crazyflie_harsh"``), a
            `jaxdrones.envs.realism.Realism`, or a dict of its fields (with an optional ``"preset"`` they override).
            `jaxdrones.make` also takes each `Realism` field as a keyword (``jd.make("hover", realism="crazyflie",
            action_delay=1)``). Motor time constants turn on `SimConfig.motor_dynamics`; wind turns on ``drag``
            (through which it acts). Stored as a `Realism` (or None).

    Raises:
        ValueError: on any invalid value, naming the field and the valid range; a firmware setpoint action
            (``firmware_pos``, ``firmware_vel``) without the physics at 1 kHz, a control step of a multiple of 10 ms
            or motor time constants, or on ``backend="pybullet"``.
        ModuleNotFoundError: ``backend="pybullet"`` without pybullet installed, naming the extra that installs it.
    """

    n_drones: int = 1
    model: str | tuple[str, ...] = "cf2x"
    action_type: str = "rpm"
    obs_type: str = "kin_rotmat"
    action_buffer: bool | int = False
    error_integral: bool = False
    pid_target: str = "absolute"
    pid_scale: float = 0.1
    episode_len_s: float = 5.0
    sim: Any = SimConfig(ctrl_freq=30)
    reward: str = "shaped"
    starts: Any = Starts()
    arena_xy: float = 1.5
    arena_z: float = 2.5
    max_tilt: float = math.pi / 2
    terminate_on_ground: bool = False
    randomize: Any = None
    neighbor_radius: float = math.inf
    max_neighbors: int | None = None
    backend: str = "jax"
    obstacles: Any = None
    vision: tuple[str, ...] = ()
    camera_freq: float = 24.0
    image_size: tuple[int, int] = (64, 48)
    camera_fov: float = 60.0
    renderer: str = "tiny"
    frame_stack: int = 1
    realism: Any = None

    def __post_init__(self):
        check_choice("action_type", self.action_type, ACTION_TYPES)
        check_choice("obs_type", self.obs_type, OBS_TYPES)
        check_choice("reward", self.reward, REWARDS)
        check_choice("pid_target", self.pid_target, PID_TARGETS)
        for name in ("error_integral", "terminate_on_ground"):
            check_bool(name, getattr(self, name))
        buffer = self.action_buffer
        if not isinstance(buffer, (bool, np.bool_)) and not (is_integer(buffer) and buffer >= 0):
            raise ValueError(
                f"action_buffer must be True (the last ctrl_freq // 2 actions), False, or the number of actions to "
                f"keep (an integer >= 0), got {buffer!r}"
            )
        check_real("pid_scale", self.pid_scale, 0, PID_MAX_STEP, low_open=True, what="a distance in m")
        check_int("n_drones", self.n_drones)
        self._check_model()
        self._set("realism", resolve_realism(self.realism))
        self._check_randomize()
        self._set("sim", self._physics())
        sim = self.sim
        self._set("starts", self._starts())
        if self.max_neighbors is not None:
            check_int("max_neighbors", self.max_neighbors, what="None for every drone")
        for name in ("arena_xy", "arena_z", "max_tilt", "neighbor_radius"):
            check_real(name, getattr(self, name), 0, low_open=True, finite=False)
        if not (
            is_real(self.episode_len_s)
            and math.isfinite(self.episode_len_s)
            and self.episode_len_s * sim.ctrl_freq >= 1
        ):
            raise ValueError(
                f"episode_len_s·ctrl_freq must give at least one control step, got "
                f"{self.episode_len_s!r} s at {sim.ctrl_freq!r} Hz"
            )
        self._check_firmware()  # before the backend's: it names what a firmware action needs, pybullet installed or not
        self._check_backend()

    def _check_firmware(self) -> None:
        """A firmware setpoint action (`jaxdrones.envs.actions.FIRMWARE_ACTIONS`) needs the physics at the firmware's
        1 kHz, a whole number of its position loop's 10 ticks per control step, first-order motors and the JAX
        backend."""
        if self.action_type not in FIRMWARE_ACTIONS:
            return
        sim, name = self.sim, self.action_type
        ticks = sim.sim_freq // sim.ctrl_freq
        if sim.sim_freq != FIRMWARE_SIM_FREQ or ticks % POSITION_PERIOD:
            raise ValueError(
                f"action_type {name!r} is flown by the firmware's controller at its {FIRMWARE_SIM_FREQ} Hz: it needs "
                f"sim={{'sim_freq': {FIRMWARE_SIM_FREQ}, 'ctrl_freq': F}} with F one of 100, 50, 25, 20, 10 Hz (a "
                f"multiple of 10 ticks per control step), got sim_freq={sim.sim_freq}, ctrl_freq={sim.ctrl_freq}"
            )
        if not sim.motor_dynamics:
            raise ValueError(
                f"action_type {name!r}: the firmware's gains need motors that lag (docs/firmware.md); give their time "
                f"constants, e.g. randomize={{'motor_tau_up': (0.061, 0.061), 'motor_tau_down': (0.061, 0.061)}} "
                f"(the fitted 61 ms, docs/validation.md §3) or a realism preset with motor lag"
            )
        if self.backend != "jax":
            raise ValueError(f"action_type {name!r} runs on backend='jax' only, got backend={self.backend!r}")

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)

    def _group(self, name: str, cls: type) -> tuple[Any, dict]:
        """The field ``name``, a ``cls`` or a dict of its fields, as (base, given): the value itself and no fields,
        or the task's own default (its config class's) and the dict's fields over it.

        Raises:
            ValueError: neither, or a dict key that is not a ``cls`` field.
        """
        value = getattr(self, name)
        if isinstance(value, dict):
            unknown = sorted(set(value) - {f.name for f in dataclasses.fields(cls)})
            if unknown:
                raise ValueError(f"{name}: {unknown[0]!r} is not a {cls.__name__} field")
            return next(f.default for f in dataclasses.fields(self) if f.name == name), value
        if isinstance(value, cls):
            return value, {}
        raise ValueError(f"{name} must be a {cls.__name__} or a dict of its fields, got {value!r}")

    def _check_model(self) -> None:
        model = self.model
        if isinstance(model, list):
            model = tuple(model)
            self._set("model", model)
        if isinstance(model, tuple) and len(model) != self.n_drones:
            raise ValueError(
                f"model: give one model for all drones or one per drone ({self.n_drones}), got {len(model)}: {model}"
            )
        for m in model if isinstance(model, tuple) else (model,):
            if not isinstance(m, str) or (m not in MODELS and not m.endswith(".urdf")):
                raise ValueError(f"unknown drone model {m!r}: expected one of {MODELS} or a path to a .urdf file")

    def _check_backend(self) -> None:
        check_choice("backend", self.backend, BACKENDS)
        check_choice("renderer", self.renderer, RENDERERS)
        if self.backend == "pybullet":
            require_pybullet()  # here, not at the first step: a missing pybullet is named before any work
        vision = self.vision
        if isinstance(vision, str) or not isinstance(vision, (tuple, list)):
            raise ValueError(f"vision must be a tuple of image names from {VISION}, got {vision!r}")
        if any(v not in VISION for v in vision) or len(set(vision)) != len(vision):
            raise ValueError(f"vision must hold distinct names from {VISION}, got {tuple(vision)!r}")
        self._set("vision", tuple(vision))
        if isinstance(self.obstacles, list):
            self._set("obstacles", tuple(self.obstacles))
        obstacles = resolve_obstacles(self.obstacles)
        if self.backend == "jax":
            if self.renderer != "tiny":
                raise ValueError("renderer needs backend='pybullet' (the jax backend renders with jaxdrones.cameras)")
            if obstacles and not self.vision:
                raise ValueError(
                    "obstacles on backend='jax' are only seen by its cameras (its physics models the "
                    "ground only): pass vision=(...), or use backend='pybullet' for collisions"
                )
            from jaxdrones.scene.primitives import check_obstacles

            check_obstacles(obstacles)  # a mesh: a clear error now rather than at the first render
        check_real("camera_freq", self.camera_freq, 0, low_open=True, what="a finite rate in Hz")
        size = self.image_size
        if not isinstance(size, (tuple, list)) or len(size) != 2 or not all(is_integer(v) and v > 0 for v in size):
            raise ValueError(f"image_size must be two positive integers (width, height) in pixels, got {size!r}")
        self._set("image_size", (int(size[0]), int(size[1])))
        what = "the vertical field of view in degrees,"
        check_real("camera_fov", self.camera_fov, 0, 180, low_open=True, high_open=True, what=what)
        k = check_int("frame_stack", self.frame_stack, what="camera frames per image")
        if k > 1 and not self.vision:
            raise ValueError(f"frame_stack={k} stacks camera frames: it needs vision=('depth',), ('rgb',) or ('seg',)")
        self._set("frame_stack", k)

    def _starts(self) -> Starts:
        """``starts`` as `Starts` (a dict: its fields over the task's default), the fixed poses checked against
        ``n_drones``."""
        base, given = self._group("starts", Starts)
        poses = {name: fixed_triples(name, given.get(name, getattr(base, name)), self.n_drones) for name in POSES}
        return dataclasses.replace(base, **{**given, **poses})

    def _check_randomize(self) -> None:
        if isinstance(self.randomize, dict):
            self._set("randomize", DomainRandomization(**self.randomize))
        elif self.randomize is not None and not isinstance(self.randomize, DomainRandomization):
            raise ValueError(
                f"randomize must be None, a DomainRandomization or a dict of its fields "
                f"{[f.name for f in dataclasses.fields(DomainRandomization)]}, got {self.randomize!r}"
            )
        realism, randomize = self.realism, self.randomize
        if realism is not None and realism.motor_dynamics and randomize is not None and randomize.taus:
            raise ValueError(
                f"randomize.{next(iter(randomize.taus))} and the realism's motor time constants both set the motors' "
                f"time constants: give them once (realism: {realism.motor_tau_up}, {realism.motor_tau_down} s)"
            )

    @property
    def param_draws(self) -> DomainRandomization | None:
        """What a reset draws the drones' params from: ``randomize`` with the realism's motor time constants (where
        its motors have dynamics), or None for the model's params in every episode."""
        realism, randomize = self.realism, self.randomize
        if realism is None or not realism.motor_dynamics:
            return randomize
        taus = {name: getattr(realism, name) for name in TAU_DRAWS}
        return dataclasses.replace(randomize or DomainRandomization(), **taus)

    def _physics(self) -> SimConfig:
        """``sim`` as a `SimConfig` (a dict: its fields over the task's default ``sim``), with the config's
        ``n_drones``, the realism's wind turning on ``drag`` and the motors' time constants (`param_draws`)
        ``motor_dynamics``."""
        base, given = self._group("sim", SimConfig)
        realism = self.realism
        wind = realism is not None and realism.wind  # the wind acts through the drag
        return dataclasses.replace(  # built once, here: it checks the rates and the physics' options
            base,
            **{
                **given,
                "n_drones": self.n_drones,
                "drag": True if wind else given.get("drag", base.drag),
                "motor_dynamics": self.param_draws is not None and self.param_draws.motor_dynamics,
            },
        )

    @property
    def buffer_len(self) -> int:
        """Actions kept in the observation's action buffer (``action_buffer``): ``ctrl_freq // 2`` for True, 0 for
        False."""
        buffer = self.action_buffer
        if isinstance(buffer, (bool, np.bool_)):
            return self.sim.ctrl_freq // 2 if buffer else 0
        return int(buffer)

    @property
    def camera_period(self) -> int:
        """Control steps between two camera renders, k = max(1, round(ctrl_freq / camera_freq))."""
        return max(1, int(round(self.sim.ctrl_freq / self.camera_freq)))

    @property
    def camera_rate(self) -> float:
        """Effective camera rate, Hz: ctrl_freq / `camera_period`."""
        return self.sim.ctrl_freq / self.camera_period


def fixed_triples(name: str, value: ArrayLike | None, n: int) -> tuple[tuple[float, float, float], ...] | None:
    """A fixed start (``init_pos``, ``init_rpy``, or the compat aviaries' ``initial_xyzs``) as a hashable tuple of
    D triples, or None; a single triple is taken for D = 1.

    Raises:
        ValueError: not f[n, 3] finite numbers, or an ``init_pos`` below the ground.
    """
    if value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be f[{n}, 3] (one (x, y, z) per drone), got {value!r}") from None
    if arr.shape == (3,) and n == 1:
        arr = arr[None]
    if arr.shape != (n, 3) or not np.all(np.isfinite(arr)):
        raise ValueError(
            f"{name} must be f[{n}, 3] finite numbers (one triple per drone, n_drones={n}), got shape {arr.shape}"
        )
    if name == "init_pos" and np.any(arr[:, 2] < 0):
        raise ValueError(f"init_pos must be above the ground (z >= 0 m), got {arr.tolist()}")
    return tuple(tuple(float(v) for v in row) for row in arr)
