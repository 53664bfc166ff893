"""Take-off and hover, the paper's single-agent task (IROS 2021 §V, gym-pybullet-drones HoverAviary)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs.base import Env, EnvState, kinematic_obs
from jaxdrones.params import DroneParams, load_params
from jaxdrones.rotations import quat_from_euler
from jaxdrones.sim import SimConfig, make_step
from jaxdrones.state import DroneState

#: Normalised actions a in [-1, 1] map to rpm = hover_rpm · (1 + RPM_ACTION_SCALE · a) (facts §10.1).
RPM_ACTION_SCALE = 0.05
ACTION_TYPES = {"rpm": 4, "one_d_rpm": 1}
REWARDS = ("shaped", "paper")
BACKENDS = ("jax", "pybullet")
#: Camera images a vision observation can hold, with their dtypes and per-pixel shapes (see `HoverConfig.vision`).
VISION = {"rgb": (np.uint8, (4,)), "depth": (np.float32, ()), "seg": (np.int32, ())}


@dataclasses.dataclass(frozen=True)
class HoverConfig:
    """Settings of the hover task (static; a field changes the compiled program).

    Attributes:
        model: drone model name or URDF path for `load_params`.
        sim_freq: physics rate, Hz.
        ctrl_freq: control (env step) rate, Hz; the paper's code uses 30 Hz for HoverAviary.
        episode_len_s: episode length, s (the paper's single-agent tasks: 5 s).
        target: (x, y, z) hover target, m, world frame (the paper: (0, 0, 1)).
        action_type: ``"one_d_rpm"`` (one value for all four motors, the paper's hover default) or ``"rpm"``
            (one per motor). Both map a in [-1, 1] to hover_rpm·(1 + 0.05 a) (facts §10.1); actions are clipped to
            [-1, 1] (the original does not clip).
        reward: ``"shaped"`` (default): r = max(0, exp(-d / 0.3) + 2 exp(-(d / 0.03)²) - 0.1 ‖v‖²) with
            d = ‖target - pos‖ in m and v in m/s: non-negative, so that ending an episode early never pays, and
            sharp near the target, so that PPO settles on it rather than near it; ``"paper"``: the paper's eq.
            (single), r = -d².
        drag, ground_effect, downwash: aerodynamic effects of the simulator.
        init_z: (low, high) start height range, m.
        init_vz: start vertical speed drawn from [-init_vz, init_vz], m/s.
        init_xy: start x, y drawn from [-init_xy, init_xy], m (keep 0 for ``one_d_rpm``, which cannot move sideways).
        init_rpy: start roll, pitch and yaw drawn from [-init_rpy, init_rpy], rad (keep 0 for ``one_d_rpm``).
        arena_xy: the episode terminates when |x| or |y| exceeds this, m.
        arena_z: the episode terminates when z exceeds this, m.
        max_tilt: the episode terminates when |roll| or |pitch| exceeds this, rad (the paper's code: 0.4).
        terminate_on_ground: a touch of the ground terminates the episode as a crash. Off by default: the ground
            holds the drone (see `dynamics.ground_contact_c`) and it may take off again, as in the paper's task.
        backend: ``"jax"`` (the differentiable JAX core) or ``"pybullet"`` (Bullet: collisions with the ground and
            obstacles, cameras; see `jaxdrones.backends.pybullet`). Both take the same actions and give the same
            kinematic observation; on ``"pybullet"`` ``reset``/``step`` still run under ``jit`` and ``vmap`` (the
            physics runs on the host through `jax.pure_callback`) but are not differentiable. Release the Bullet
            worlds with `HoverEnv.close`.
        obstacles: ``"pybullet"`` only: the obstacles of every world: None, True or ``"paper"``
            (`jaxdrones.backends.scene.PAPER_OBSTACLES`), or a sequence of `jaxdrones.backends.scene.Obstacle` /
            URDF paths. They do not end the episode; ``state.sim.contact`` reports touching them.
        vision: ``"pybullet"`` only: camera images to add to the observation, any of ``"rgb"``, ``"depth"``,
            ``"seg"`` (the paper's VisionAviary "rgb", "dep", "seg"; facts §8). With vision the observation is a
            dict ``{"state": f[12], "rgb": u8[H, W, 4], "depth": f32[H, W] m, "seg": i32[H, W]}`` (only the
            requested images) from the drone's camera (`PyBulletStep.camera_images`).
        camera_freq: camera rate asked for, Hz (the paper: 24). Images are rendered at reset and then every
            k = max(1, round(ctrl_freq / camera_freq)) control steps and held in between, so the effective rate is
            ctrl_freq / k Hz: 30 Hz for the default 30 Hz control (k = 1), 24 Hz at 48 Hz control (k = 2). Unlike
            the original, which rejects a capture period that does not divide evenly into control steps (no RGB at
            30 Hz control, facts §8), any control rate works.
        image_size: (width, height) of the camera images in pixels (the paper: 64 × 48).
        renderer: ``"pybullet"`` only: ``"tiny"`` (TinyRenderer, CPU) or ``"egl"`` (OpenGL through EGL, headless
            GPU), see `jaxdrones.backends.pybullet.PyBulletStep`.
    """

    model: str = "cf2x"
    sim_freq: int = 240
    ctrl_freq: int = 30
    episode_len_s: float = 5.0
    target: tuple[float, float, float] = (0.0, 0.0, 1.0)
    action_type: str = "one_d_rpm"
    reward: str = "shaped"
    drag: bool = False
    ground_effect: bool = False
    downwash: bool = False
    init_z: tuple[float, float] = (0.1125, 1.8)
    init_vz: float = 0.2
    init_xy: float = 0.0
    init_rpy: float = 0.0
    arena_xy: float = 1.5
    arena_z: float = 2.5
    max_tilt: float = 0.4
    terminate_on_ground: bool = False
    backend: str = "jax"
    obstacles: object = None
    vision: tuple[str, ...] = ()
    camera_freq: float = 24.0
    image_size: tuple[int, int] = (64, 48)
    renderer: str = "tiny"

    def __post_init__(self):
        if self.action_type not in ACTION_TYPES:
            raise ValueError(f"hover: action_type must be one of {tuple(ACTION_TYPES)}, got {self.action_type!r}")
        if self.reward not in REWARDS:
            raise ValueError(f"hover: reward must be one of {REWARDS}, got {self.reward!r}")
        if len(self.target) != 3 or not all(math.isfinite(v) for v in self.target):
            raise ValueError(f"hover: target must be three finite numbers (x, y, z) in m, got {self.target}")
        if (len(self.init_z) != 2 or not all(math.isfinite(v) for v in self.init_z)
                or not 0 <= self.init_z[0] <= self.init_z[1]):
            raise ValueError(f"hover: init_z must be a finite (low, high) range with 0 <= low <= high, m, "
                             f"got {self.init_z}")
        for name in ("init_vz", "init_xy", "init_rpy"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"hover: {name} must be a finite half-width >= 0, got {value}")
        for name in ("arena_xy", "arena_z", "max_tilt"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"hover: {name} must be > 0, got {value}")
        if not (math.isfinite(self.episode_len_s) and self.episode_len_s * self.ctrl_freq >= 1):
            raise ValueError(f"hover: episode_len_s·ctrl_freq must give at least one step, got {self.episode_len_s} s "
                             f"at {self.ctrl_freq} Hz")
        self._check_backend()

    def _check_backend(self) -> None:
        """Validate (and normalise to hashable tuples) the backend, obstacle and camera fields."""
        if self.backend not in BACKENDS:
            raise ValueError(f"hover: backend must be one of {BACKENDS}, got {self.backend!r}")
        vision = self.vision
        if isinstance(vision, str) or not isinstance(vision, (tuple, list)):
            raise ValueError(f"hover: vision must be a tuple of image names from {tuple(VISION)}, got {vision!r}")
        unknown = [v for v in vision if v not in VISION]
        if unknown or len(set(vision)) != len(vision):
            raise ValueError(f"hover: vision must hold distinct names from {tuple(VISION)}, got {tuple(vision)!r}")
        object.__setattr__(self, "vision", tuple(vision))
        if self.backend == "jax" and self.vision:
            raise ValueError("hover: vision needs backend='pybullet' (the jax backend does not render)")
        if self.backend == "jax" and self.obstacles not in (None, False):
            raise ValueError("hover: obstacles need backend='pybullet' (the jax backend models the ground only)")
        if isinstance(self.obstacles, list):
            object.__setattr__(self, "obstacles", tuple(self.obstacles))
        if self.renderer not in ("tiny", "egl"):
            raise ValueError(f"hover: renderer must be 'tiny' or 'egl', got {self.renderer!r}")
        if self.backend == "jax" and self.renderer != "tiny":
            raise ValueError("hover: renderer needs backend='pybullet' (the jax backend does not render)")
        if self.backend == "pybullet":
            from jaxdrones.backends.scene import resolve_obstacles

            resolve_obstacles(self.obstacles)
        if not (isinstance(self.camera_freq, (int, float)) and math.isfinite(self.camera_freq)
                and self.camera_freq > 0):
            raise ValueError(f"hover: camera_freq must be a finite rate > 0 Hz, got {self.camera_freq!r}")
        size = self.image_size
        if (not isinstance(size, (tuple, list)) or len(size) != 2
                or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0 for v in size)):
            raise ValueError(f"hover: image_size must be two positive integers (width, height) in pixels, "
                             f"got {size!r}")
        object.__setattr__(self, "image_size", (int(size[0]), int(size[1])))

    @property
    def camera_period(self) -> int:
        """Control steps between two camera renders, k = max(1, round(ctrl_freq / camera_freq))."""
        return max(1, int(round(self.ctrl_freq / self.camera_freq)))

    @property
    def camera_rate(self) -> float:
        """Effective camera rate, Hz: ctrl_freq / `camera_period`."""
        return self.ctrl_freq / self.camera_period


class HoverEnv(Env):
    """One drone takes off and hovers at a target (brax protocol; jit and vmap over ``reset``/``step``).

    Observation: f[12] kinematic state (eq. obs): pos m, rpy rad, vel m/s (world), ang_vel rad/s (body); with
    ``config.vision`` a dict of it (``"state"``) and the camera images (see `HoverConfig.vision` and
    `observation_spec`), the images held between renders.
    Action: f[1] (``one_d_rpm``) or f[4] (``rpm``) in [-1, 1], see `HoverConfig`.
    A non-finite action is replaced by 0 (hover RPM) for the physics, terminates the episode and sets
    ``metrics["invalid_action"]`` to 1.
    The physics runs on ``config.backend``; call `close` (or use a ``with`` block) to release a PyBullet backend.
    """

    def __init__(self, config: HoverConfig = HoverConfig()):
        self.config = config
        self.sim_config = SimConfig(n_drones=1, sim_freq=config.sim_freq, ctrl_freq=config.ctrl_freq,
                                    drag=config.drag, ground_effect=config.ground_effect,
                                    downwash=config.downwash)
        self.params = load_params(config.model)
        options = ({"obstacles": config.obstacles, "renderer": config.renderer} if config.backend == "pybullet"
                   else {})
        self._step = make_step(self.sim_config, backend=config.backend, **options)
        self._target = np.asarray(config.target, dtype=np.float64)

    def close(self) -> None:
        """Release the PyBullet backend's worlds (nothing to do on the jax backend); the env is unusable after."""
        close = getattr(self._step, "close", None)
        if close is not None:
            close()

    @property
    def observation_size(self) -> int:
        """Length of the kinematic observation (the ``"state"`` entry of a vision observation)."""
        return 12

    @property
    def observation_spec(self):
        """Shape and dtype of the observation: a `jax.ShapeDtypeStruct`, or with vision a dict of them."""
        state = jax.ShapeDtypeStruct((12,), self.params.mass.dtype)
        if not self.config.vision:
            return state
        return {"state": state, **self._image_spec()}

    @property
    def action_size(self) -> int:
        return ACTION_TYPES[self.config.action_type]

    @property
    def episode_length(self) -> int:
        return int(round(self.config.episode_len_s * self.config.ctrl_freq))

    @property
    def target(self) -> jax.Array:
        """f[3] hover target, m, world frame."""
        return jnp.asarray(self._target, dtype=self.params.mass.dtype)

    def reset(self, key: jax.Array) -> EnvState:
        cfg = self.config
        key, k_z, k_vz, k_xy, k_rpy = jax.random.split(key, 5)
        dtype = self.params.mass.dtype
        z = jax.random.uniform(k_z, (), dtype, cfg.init_z[0], cfg.init_z[1])
        xy = jax.random.uniform(k_xy, (2,), dtype, -cfg.init_xy, cfg.init_xy)
        vz = jax.random.uniform(k_vz, (), dtype, -cfg.init_vz, cfg.init_vz)
        rpy = jax.random.uniform(k_rpy, (3,), dtype, -cfg.init_rpy, cfg.init_rpy)
        zeros3 = jnp.zeros((1, 3), dtype)
        sim = DroneState(
            pos=jnp.concatenate([xy, z[None]])[None], quat=quat_from_euler(rpy)[None],
            vel=zeros3.at[0, 2].set(vz), ang_vel=zeros3, rpm=jnp.zeros((1, 4), dtype),
            contact=jnp.zeros((1,), jnp.int32),
        )
        zero = jnp.zeros((), dtype)
        obs = self._obs(sim)
        if self.config.vision:
            blank = {k: jnp.zeros(v.shape, v.dtype) for k, v in self._image_spec().items()}
            obs = {"state": obs, **self._render(self.params, sim, jnp.ones((), bool), blank)}
        return EnvState(
            sim=sim, params=self.params, key=key, obs=obs, reward=zero,
            terminated=jnp.zeros((), bool), truncated=jnp.zeros((), bool), steps=jnp.zeros((), jnp.int32),
            metrics={"distance": self._distance(sim), "crash": zero, "invalid_action": zero},
        )

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        cfg = self.config
        action = jnp.asarray(action)
        if action.shape != (self.action_size,):
            raise ValueError(f"hover: action must have shape ({self.action_size},) for action_type="
                             f"{cfg.action_type!r} (normalised RPM in [-1, 1]), got {action.shape}")
        if not jnp.issubdtype(action.dtype, jnp.floating):
            raise ValueError(f"hover: action must be a float array in [-1, 1], got dtype {action.dtype}")
        finite = jnp.all(jnp.isfinite(action))
        action = jnp.where(finite, jnp.clip(action, -1.0, 1.0), 0.0).astype(state.sim.pos.dtype)
        rpm = state.params.hover_rpm * (1.0 + RPM_ACTION_SCALE * jnp.broadcast_to(action, (4,)))
        sim = self._step(state.params, state.sim, rpm[None])
        steps = state.steps + 1
        obs = self._obs(sim)
        crashed = self._crashed(sim, rpy=obs[3:6])
        if cfg.vision:
            held = {k: v for k, v in state.obs.items() if k != "state"}
            due = steps % cfg.camera_period == 0
            images = jax.lax.cond(due, lambda: self._render(state.params, sim, due, held), lambda: held)
            obs = {"state": obs, **images}
        terminated = crashed | ~finite
        truncated = (steps >= self.episode_length) & ~terminated
        dtype = sim.pos.dtype
        metrics = {"distance": self._distance(sim), "crash": crashed.astype(dtype),
                   "invalid_action": (~finite).astype(dtype)}
        return state.replace(sim=sim, obs=obs, reward=self._reward(sim), terminated=terminated,
                             truncated=truncated, steps=steps, metrics=metrics)

    def _obs(self, sim: DroneState) -> jax.Array:
        return kinematic_obs(sim)[0]

    def _image_spec(self) -> dict:
        width, height = self.config.image_size
        return {name: jax.ShapeDtypeStruct((height, width) + VISION[name][1], VISION[name][0])
                for name in self.config.vision}

    def _render(self, params: DroneParams, sim: DroneState, due: jax.Array, held: dict) -> dict:
        """The camera images of ``sim`` where ``due`` (bool[...]), ``held`` elsewhere.

        One host callback: under ``vmap`` (where `jax.lax.cond` runs both branches) only the worlds whose render is
        due are rendered. A world whose pose is not finite reads rgb 0, depth NaN and seg -1, as in
        `PyBulletStep.camera_images`.
        """
        spec = self._image_spec()
        width, height = self.config.image_size
        blank = {"rgb": 0, "depth": np.nan, "seg": -1}

        def render(params, sim, due, held):
            lead = np.shape(due)

            def flat(x):
                x = np.asarray(x)
                return x.reshape((-1,) + x.shape[len(lead):])

            out = {k: flat(v).copy() for k, v in held.items()}
            pos, quat = flat(sim.pos), flat(sim.quat)
            finite = (np.all(np.isfinite(pos), axis=(-2, -1)) & np.all(np.isfinite(quat), axis=(-2, -1))
                      & np.all(np.sum(quat * quat, -1) > 0, axis=-1))
            due = flat(due)
            for k in out:
                out[k][due & ~finite] = blank[k]
            index = np.flatnonzero(due & finite)
            if index.size:  # params [n, 1, ...] per world (one drone); the state [n, 1, ...]
                images = self._step.camera_images(jax.tree.map(lambda x: flat(x)[index][:, None], params),
                                                  jax.tree.map(lambda x: flat(x)[index], sim),
                                                  width=width, height=height)
                for k in out:
                    out[k][index] = images[k][:, 0]
            return {k: v.reshape(lead + spec[k].shape) for k, v in out.items()}

        return jax.pure_callback(render, spec, params, sim, due, held, vmap_method="broadcast_all")

    def _distance(self, sim: DroneState) -> jax.Array:
        return jnp.linalg.norm(sim.pos[0] - self.target)

    def _reward(self, sim: DroneState) -> jax.Array:
        d2 = jnp.sum((sim.pos[0] - self.target) ** 2)
        if self.config.reward == "paper":
            return -d2
        speed2 = jnp.sum(sim.vel[0] ** 2)
        shaped = jnp.exp(-jnp.sqrt(d2 + 1e-12) / 0.3) + 2.0 * jnp.exp(-d2 / 0.03**2) - 0.1 * speed2
        return jnp.maximum(0.0, shaped)

    def _crashed(self, sim: DroneState, rpy: jax.Array) -> jax.Array:
        """Left the arena or tilted too far (``rpy`` f[3] rad, from the observation), or touched the ground."""
        cfg = self.config
        pos = sim.pos[0]
        out = (jnp.any(jnp.abs(pos[:2]) > cfg.arena_xy) | (pos[2] > cfg.arena_z)
               | jnp.any(jnp.abs(rpy[:2]) > cfg.max_tilt))
        if cfg.terminate_on_ground:
            out = out | sim.ground_contact[0]
        return out
