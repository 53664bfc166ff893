"""`TaskEnv`: any `jaxdrones.envs.task.Task` as a functional env (``reset``/``step``, jit and vmap).

Every env holds ``D ≥ 1`` drones with stacked arrays: obs ``f[D, n_obs]``, action ``f[D, n_act]``, reward ``f[D]``;
``terminated``/``truncated`` are per world.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from jaxdrones._fork import check_not_forked
from jaxdrones.envs import rewards
from jaxdrones.envs.actions import make_action
from jaxdrones.envs.base import Env, EnvState
from jaxdrones.envs.config import TaskConfig
from jaxdrones.envs.observations import ObsType
from jaxdrones.envs.realism import RealismModel
from jaxdrones.envs.task import Bounds, StartRanges, Task, TaskParams
from jaxdrones.physics.params import DroneParams, broadcast_params, load_params, stack_params
from jaxdrones.physics.rotations import quat_from_euler
from jaxdrones.physics.state import DroneState
from jaxdrones.sensors.camera import image_shapes
from jaxdrones.sim import make_step

#: How far (in action units) an entry may lie outside its box before ``metrics["clipped_actions"]`` counts it:
#: float32 round-off of actions computed at the bounds (e.g. ``tanh`` saturating to 1 + 1 ulp) is not a clip.
CLIP_TOLERANCE = 1e-6
#: The error integral's clip, per entry (`jaxdrones.envs.config.TaskConfig.error_integral`): m·s for a position
#: error, m for a velocity error. A PID's anti-windup: a drone 5 cm off for 20 s reaches it.
ERROR_INTEGRAL_BOUND = 1.0
#: The PRNG stream of the sim-to-real options' draws at reset (`jax.random.fold_in` of the reset's key).
_REALISM_STREAM = 0x5EA1


def outside_box(action: ArrayLike, low: ArrayLike, high: ArrayLike) -> jax.Array | np.ndarray:
    """bool[...]: the entries of ``action`` below ``low`` or above ``high`` by more than `CLIP_TOLERANCE` (NumPy or
    JAX arrays): those the env clips and counts, and ``strict_actions`` refuses."""
    return (action < low - CLIP_TOLERANCE) | (action > high + CLIP_TOLERANCE)


def clipped_per_drone(action: ArrayLike, low: ArrayLike, high: ArrayLike) -> jax.Array | np.ndarray:
    """i[..., D]: each drone's action entries (``action`` f[..., D, n_act]) that the env clips (`outside_box`):
    ``metrics["clipped_actions"]`` is their sum over the drones, and the multi-agent adapters report each agent's."""
    return outside_box(action, low, high).sum(axis=-1)


class TaskEnv(Env):
    """Any `Task` on the jaxdrones physics, as a brax-protocol env (``reset``/``step``, jit and vmap).

    Observation ``f[D, n_obs]`` (`observation_spec`; a dict with camera images under ``config.vision``), action
    ``f[D, n_act]`` in the action type's box, clipped to it (``metrics["clipped_actions"]`` counts the entries that
    were outside it, by more than `CLIP_TOLERANCE`); a non-finite action is replaced by 0 for the physics,
    terminates the episode and sets ``metrics["invalid_action"]``. Reward ``f[D]``; ``terminated``/``truncated``
    per world. `reset` draws the start, the task params (from ``task`` or the config's defaults) and, with
    ``config.param_draws``, the drones' params.

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
        model = config.model
        params = stack_params(model) if isinstance(model, tuple) else load_params(model)
        # Broadcast on the host and copied once: no device program compiled (each costs a compilation on a GPU).
        self.params = jax.device_put(broadcast_params(jax.tree.map(np.asarray, params), (config.n_drones,), xp=np))
        self.action_type = make_action(config.action_type, config.pid_target, config.pid_scale)
        self.obs_type = ObsType(
            config.obs_type,
            config.n_drones,
            config.neighbor_radius,
            config.buffer_len,
            self.action_type.size,
            config.max_neighbors,
        )
        options = {"obstacles": config.obstacles, "renderer": config.renderer} if config.backend == "pybullet" else {}
        self._step = make_step(self.config.sim, backend=config.backend, **options)
        if self.action_type.firmware:  # the firmware's controller drives the physics at every 1 ms tick
            self._tick_step = make_step(dataclasses.replace(config.sim, ctrl_freq=config.sim.sim_freq), **options)
        self._default_task = None
        self.realism = None
        if config.realism is not None:
            self.realism = RealismModel(config.realism, config.n_drones, self.action_type.size, self.config.sim.ctrl_dt)
        if config.param_draws is not None:  # what every episode shares (a time constant without a range)
            self.params = config.param_draws.fixed(self.params)

    def __reduce__(self):
        return type(self), (self.task, self.config)

    # -- sizes and spaces ------------------------------------------------------------------------------------------

    @property
    def n_drones(self) -> int:
        return self.config.n_drones

    @property
    def observation_size(self) -> int:
        return self.obs_type.size + self.task.obs_size + self.integral_size

    @property
    def integral_size(self) -> int:
        """Entries per drone of the error integral at the observation's end (``config.error_integral``): 3 or 0."""
        return 3 if self.config.error_integral else 0

    @property
    def action_size(self) -> int:
        return self.action_type.size

    @property
    def episode_length(self) -> int:
        return int(round(self.config.episode_len_s * self.config.sim.ctrl_freq))

    @property
    def dtype(self) -> np.dtype:
        return self.params.mass.dtype

    @property
    def shared_params(self) -> DroneParams | None:
        """``params`` (batch shape [D]) when every episode uses them, else None: ``config.param_draws`` draws them
        per episode."""
        draws = self.config.param_draws
        return None if draws is not None and draws.draws else self.params

    @property
    def observation_spec(self) -> jax.ShapeDtypeStruct | dict[str, jax.ShapeDtypeStruct]:
        """Shape and dtype of the observation: a `jax.ShapeDtypeStruct`, or with vision a dict of them."""
        state = jax.ShapeDtypeStruct((self.n_drones, self.observation_size), self.dtype)
        if not self.config.vision:
            return state
        return {"state": state, **self._image_spec()}

    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) f32[D, n_obs] of the state observation: the observation type's, then the task's."""
        low, high = self.obs_type.bounds()
        task = np.asarray(self.task.obs_bound(self.config), np.float32)
        bound = np.tile(
            np.concatenate([task, np.full(self.integral_size, ERROR_INTEGRAL_BOUND, np.float32)]), (self.n_drones, 1)
        )
        return np.concatenate([low, -bound], axis=-1), np.concatenate([high, bound], axis=-1)

    def _integrate(self, task: TaskParams, seen: DroneState, steps: jax.Array, integral: jax.Array) -> jax.Array:
        """The error integral after a step (``config.error_integral``): ``integral`` + e / ctrl_freq, clipped to
        ±`ERROR_INTEGRAL_BOUND`, with e = `Task.tracking_error` of the state the sensors report; f[D, 0] without."""
        if not self.integral_size:
            return integral
        error = self.task.tracking_error(self.config, task, seen, steps).astype(integral.dtype)
        return jnp.clip(integral + error / self.config.sim.ctrl_freq, -ERROR_INTEGRAL_BOUND, ERROR_INTEGRAL_BOUND)

    def _observe(
        self, task: TaskParams, sim: DroneState, history: jax.Array, integral: jax.Array, steps: jax.Array
    ) -> jax.Array:
        """The state observation, f[D, n_obs], recomputed from its inputs in the backward pass (``jax.checkpoint``)
        rather than its intermediates stored: differentiated under a scan (APG, SHAC), the attitude's
        trigonometry stored 35 arrays per control step of the default hover env, a third of all it stored
        (`benchmarks/gradients/gradients.py`, caller ``default_env``)."""
        return jax.checkpoint(self._observation)(task, sim, history, integral, steps)

    def _observation(
        self, task: TaskParams, sim: DroneState, history: jax.Array, integral: jax.Array, steps: jax.Array
    ) -> jax.Array:
        """The observation type's entries (with the action buffer), the task's (clipped to `Task.obs_bound`), then
        the error integral."""
        obs = self.obs_type.observe(sim, history)
        parts = [obs]
        if self.task.obs_size:
            extra = self.task.observe(self.config, task, sim, steps)
            bound = jnp.broadcast_to(jnp.asarray(self.task.obs_bound(self.config), obs.dtype), extra.shape)
            parts.append(jnp.clip(extra, -bound, bound).astype(obs.dtype))
        if self.integral_size:
            parts.append(integral.astype(obs.dtype))
        return parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis=-1)

    def privileged(self, state: EnvState) -> jax.Array | None:
        """f[D, k] of the env's dtype: the task's privileged observation of ``state`` (`Task.privileged`, e.g. the
        obstacles around each drone for ``avoid``), or None for a task without one."""
        out = self.task.privileged(self.config, state.task, state.sim)
        return None if out is None else out.astype(self.dtype)

    def action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) f32[D, n_act]."""
        a = self.action_type
        return np.tile(a.low, (self.n_drones, 1)), np.tile(a.high, (self.n_drones, 1))

    def close(self) -> None:
        """Release the backend's resources (the PyBullet worlds); the env is unusable after."""
        self._step.close()

    def render_world(
        self, params: DroneParams, sim: DroneState, width: int = 480, height: int = 360
    ) -> np.ndarray | None:
        """`Env.render_world`: PyBullet's third-person view of the drones on that backend, None on the JAX backend."""
        return self._step.render(params, sim, width=width, height=height) if self._step.has_cameras else None

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
        given = cfg.starts
        ranges = {k: getattr(given, k) for k in ("pos_range", "tilt", "yaw", "vel", "ang_vel")}
        start.update({k: v for k, v in ranges.items() if v is not None})
        rpy = np.zeros((cfg.n_drones, 3))
        if given.init_pos is not None:  # a fixed start, at rest and (unless init_rpy says otherwise) level
            start.update(
                pos=np.asarray(given.init_pos), pos_range=(0.0, 0.0, 0.0), vel=0.0, ang_vel=0.0, tilt=0.0, yaw=0.0
            )
        if given.init_rpy is not None:
            rpy = np.asarray(given.init_rpy)
            start.update(tilt=0.0, yaw=0.0)
        dt = self.dtype

        def arr(x, shape=None):
            x = np.asarray(x, np.float64)
            return np.asarray(x if shape is None else np.broadcast_to(x, shape), dt)

        ranges = StartRanges(
            pos=arr(start["pos"], (cfg.n_drones, 3)),
            pos_range=arr(start["pos_range"], (3,)),
            rpy=arr(rpy),
            tilt=arr(start["tilt"]),
            yaw=arr(start["yaw"]),
            vel=arr(start["vel"], (3,)),
            ang_vel=arr(start["ang_vel"], (3,)),
        )
        bounds = Bounds(
            pos_low=arr([-cfg.arena_xy, -cfg.arena_xy, -1.0]),
            pos_high=arr([cfg.arena_xy, cfg.arena_xy, cfg.arena_z]),
            max_tilt=arr(cfg.max_tilt),
        )
        scene = None
        if (cfg.vision and cfg.backend == "jax") or task.uses_scene:
            scene = jax.tree.map(
                lambda x: np.asarray(x, dt) if jnp.issubdtype(x.dtype, jnp.floating) else np.asarray(x), task.scene(cfg)
            )
        return TaskParams(
            target=arr(task.target(cfg), (cfg.n_drones, 3)),
            start=ranges,
            bounds=bounds,
            weights={k: arr(v) for k, v in task.weights(cfg).items()},
            data={k: arr(v) for k, v in task.data(cfg).items()},
            scene=scene,
        )

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
        k_realism = jax.random.fold_in(key, _REALISM_STREAM)  # apart from the other draws, which stay as they were
        k_task, k_start, k_params, key = jax.random.split(key, 4)
        task = self.task.sample(cfg, self.default_task_params() if task is None else task, k_task)
        draws = cfg.param_draws
        params = draws.sample(k_params, self.params) if draws is not None and draws.draws else self.params
        sim = sample_start(k_start, task.start, self.dtype)
        if self.config.sim.motor_dynamics and cfg.starts.rpm == "hover":  # the motors already turning
            sim = sim.replace(rpm=jnp.broadcast_to(params.hover_rpm[..., None], sim.rpm.shape).astype(self.dtype))
        history = jnp.zeros((cfg.n_drones, self.obs_type.buffer_len, self.action_size), self.dtype)
        integral = jnp.zeros((cfg.n_drones, self.integral_size), self.dtype)
        steps = jnp.zeros((), jnp.int32)
        realism, seen = None, sim
        if self.realism is not None:
            realism = self.realism.reset(k_realism, sim, self.dtype)
            seen = self.realism.initial(realism, sim)
        integral = self._integrate(task, seen, steps, integral)
        obs = self._observe(task, seen, history, integral, steps)
        if cfg.vision:
            blank = {k: jnp.zeros(v.shape, v.dtype) for k, v in self._image_spec(frames=False).items()}
            first = self._render(task.scene, params, sim, jnp.ones((), bool), blank)
            obs = {"state": obs, **self._stack(first)}
        zeros = jnp.zeros((cfg.n_drones,), self.dtype)
        terms = self.task.reward_terms(cfg, task, sim, jnp.zeros((cfg.n_drones, self.action_size), self.dtype), steps)
        false = jnp.zeros((), bool)
        metrics = self._metrics(task, sim, steps, {k: zeros for k in terms}, false, false, jnp.zeros((), jnp.int32))
        return EnvState(
            sim=sim,
            params=params,
            task=task,
            ctrl=self.action_type.init(params, sim),
            history=history,
            integral=integral,
            key=key,
            obs=obs,
            reward=zeros,
            terminated=jnp.zeros((), bool),
            truncated=jnp.zeros((), bool),
            steps=steps,
            metrics=metrics,
            realism=realism,
        )

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
        action = action.astype(self.dtype)
        clipped = jnp.where(finite, jnp.sum(clipped_per_drone(action, low, high)), 0)
        action = jnp.where(finite, jnp.clip(action, low, high), 0.0)
        ref = self.task.reference(cfg, task, state.steps)
        realism, applied, disturbance = state.realism, action, None
        if self.realism is not None:  # the delayed action, and the wind and disturbance of this step
            applied, realism = self.realism.delay_action(realism, action)
            disturbance, realism = self.realism.disturbance(realism, state.sim)
        if self.action_type.firmware:
            ticks = cfg.sim.sim_freq // cfg.sim.ctrl_freq
            sim, ctrl = self.action_type.fly(
                self._tick_step, state.params, state.sim, state.ctrl, applied, ticks, disturbance
            )
        else:
            rpm, ctrl = self.action_type.to_rpm(state.params, state.sim, state.ctrl, applied, ref, cfg.sim.ctrl_dt)
            sim = self._step(state.params, state.sim, rpm, disturbance)
        steps = state.steps + 1
        history = state.history
        if self.obs_type.buffer_len:
            history = jnp.concatenate([history[:, 1:], action[:, None]], axis=1)
        seen = sim
        if self.realism is not None:  # what the sensors report: delayed, biased, noisy
            seen, realism = self.realism.observe(realism, sim)
        integral = self._integrate(task, seen, steps, state.integral)
        obs = self._observe(task, seen, history, integral, steps)
        if cfg.vision:
            held = {k: v for k, v in state.obs.items() if k != "state"}
            due = steps % cfg.camera_period == 0
            images = jax.lax.cond(due, lambda: self._capture(task.scene, state.params, sim, due, held), lambda: held)
            obs = {"state": obs, **images}
        terms = self.task.reward_terms(cfg, task, sim, action, steps)
        nonneg = self.task.nonnegative_reward and cfg.reward == "shaped"
        reward, weighted = rewards.combine(terms, task.weights, nonneg)
        crashed = self.task.terminated(cfg, task, sim)
        terminated = crashed | self.task.reached(cfg, task, sim) | ~finite
        truncated = (steps >= self.episode_length) & ~terminated
        metrics = self._metrics(task, sim, steps, weighted, crashed, ~finite, clipped)
        return state.replace(
            sim=sim,
            ctrl=ctrl,
            history=history,
            integral=integral,
            obs=obs,
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            steps=steps,
            metrics=metrics,
            realism=realism,
        )

    def loss(self, state: EnvState) -> jax.Array:
        """The task's differentiable training loss of a (post-step) state, f[D]: `Task.loss_terms` weighted by
        `Task.loss_weights` (for gradient-based training; the RL reward is ``state.reward``)."""
        terms = self.task.loss_terms(self.config, state.task, state.sim, state.steps)
        weights = self.task.loss_weights(self.config)
        return sum(weights[k] * v for k, v in terms.items() if weights.get(k, 0.0))

    def _metrics(self, task, sim, steps, weighted, crashed, invalid, clipped) -> dict:
        dtype = self.dtype
        metrics = {k: jnp.asarray(v, dtype) for k, v in self.task.metrics(self.config, task, sim, steps).items()}
        metrics.update({f"reward/{k}": jnp.mean(v) for k, v in weighted.items()})
        metrics.update(
            crash=crashed.astype(dtype), invalid_action=invalid.astype(dtype), clipped_actions=clipped.astype(dtype)
        )
        return metrics

    def _check_action(self, action) -> jax.Array:
        action = jnp.asarray(action)
        expected = (self.n_drones, self.action_size)
        if action.shape != expected:
            raise ValueError(
                f"{self.task.name}: action must have shape {expected} ([n_drones, size] for "
                f"action_type={self.config.action_type!r}, entries in [-1, 1]), got {action.shape}"
            )
        if not jnp.issubdtype(action.dtype, jnp.floating):
            raise ValueError(f"{self.task.name}: action must be a float array, got dtype {action.dtype}")
        return action

    # -- cameras -------------------------------------------------------------------------------------------------------

    def _image_spec(self, frames: bool = True) -> dict:
        """Shapes of the observation's images: [D, (K,) H, W(, C)], with the frame axis when ``config.frame_stack``
        > 1 and ``frames``."""
        k = self.config.frame_stack
        lead = (self.n_drones, k) if frames and k > 1 else (self.n_drones,)
        return image_shapes(lead, *self.config.image_size, self.config.vision)

    def _stack(self, images: dict) -> dict:
        """The observation's images from one capture (``images`` [D, H, W(, C)]): repeated along the frame axis
        when ``config.frame_stack`` > 1 (the reset's padding)."""
        k = self.config.frame_stack
        return images if k == 1 else {name: jnp.repeat(v[:, None], k, axis=1) for name, v in images.items()}

    def _capture(self, scene, params: DroneParams, sim: DroneState, due: jax.Array, held: dict) -> dict:
        """The observation's images after a capture of ``sim`` where ``due``: the new frame, or with a frame
        stack the held frames shifted by one and the new frame last; ``held`` elsewhere."""
        if self.config.frame_stack == 1:
            return self._render(scene, params, sim, due, held)
        last = {name: v[:, -1] for name, v in held.items()}
        new = self._render(scene, params, sim, due, last)
        shifted = {name: jnp.concatenate([v[:, 1:], new[name][:, None]], axis=1) for name, v in held.items()}
        return {
            name: jnp.where(jnp.reshape(due, due.shape + (1,) * (v.ndim - due.ndim)), v, held[name])
            for name, v in shifted.items()
        }

    def _render(self, scene, params: DroneParams, sim: DroneState, due: jax.Array, held: dict) -> dict:
        """The camera images of ``sim`` where ``due`` (bool[...]), ``held`` elsewhere.

        On the JAX backend, `jaxdrones.cameras.render` of every world in ``scene`` (the task params'); on the
        PyBullet backend, `jaxdrones.backends.camera.held_images` (``scene`` unused).
        """
        width, height = self.config.image_size
        if self.config.backend == "pybullet":
            from jaxdrones.backends.camera import held_images

            return held_images(self._step, params, sim, due, held, width, height, self.config.camera_fov)
        from jaxdrones.sensors.camera import CameraSpec, render

        spec = CameraSpec(width=width, height=height, fov=self.config.camera_fov)
        images = render(spec, scene, params, sim.pos, sim.quat, kinds=self.config.vision)
        if "rgb" in images:  # RGBA, as Bullet's
            rgb = images["rgb"]
            images["rgb"] = jnp.concatenate([rgb, jnp.full(rgb.shape[:-1] + (1,), 255, rgb.dtype)], -1)
        return {
            k: jnp.where(jnp.reshape(due, due.shape + (1,) * (v.ndim - due.ndim)), v, held[k])
            for k, v in images.items()
        }


def sample_start(key: jax.Array, start: StartRanges, dtype: DTypeLike) -> DroneState:
    """A random start state of D drones, uniform in ``start`` (see `StartRanges`), at rest in the motors.

    Positions are kept at or above the resting height of the collision cylinder's base (z ≥ 0.0125 m is the
    rest height of the Crazyflie; any z ≥ 0 is accepted and the contact model lifts a drone out of the ground).
    All the numbers are drawn from ``key`` in one call (12 per drone): on CPU, random-number generation is most
    of a reset's cost, and one draw of 12 costs about a third of six draws.
    """
    n = start.pos.shape[-2]
    u = jax.random.uniform(key, (n, 12), dtype, -1.0, 1.0)
    pos = start.pos + start.pos_range[None] * u[:, 0:3]
    pos = jnp.concatenate([pos[:, :2], jnp.maximum(pos[:, 2:], 0.0)], axis=-1)
    tilt = start.tilt * 0.5 * (u[:, 3] + 1.0)
    phi = jnp.pi * (u[:, 4] + 1.0)
    yaw = start.yaw * u[:, 5]
    rpy = start.rpy + jnp.stack([tilt * jnp.cos(phi), tilt * jnp.sin(phi), yaw], axis=-1)
    return DroneState(
        pos=pos,
        quat=quat_from_euler(rpy),
        vel=start.vel[None] * u[:, 6:9],
        ang_vel=start.ang_vel[None] * u[:, 9:12],
        rpm=jnp.zeros((n, 4), dtype),
        contact=jnp.zeros((n,), jnp.int32),
    )
