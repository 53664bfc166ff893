"""gymnasium adapters: `GymnasiumEnv` (one world, NumPy in and out) and `GymnasiumVectorEnv` (N worlds stepped
in one jitted call), registered for every task.

Ids (registered when ``jaxdrones`` is imported; ``gymnasium.make("jaxdrones:jaxdrones/Hover-v0")`` imports it
for you): `GYM_IDS`, e.g. ``jaxdrones/Hover-v0``, ``jaxdrones/Velocity-v0``, ``jaxdrones/LeaderFollower-v0``. Task
config fields are keyword arguments of ``gymnasium.make`` (``action_type``, ``obs_type``, ``model``,
``ctrl_freq``, ``init_pos``, ...). ``render_mode="rgb_array"`` renders a frame (PyBullet's renderer on that
backend, a matplotlib view of the drones on the JAX backend) and ``render_mode="human"`` shows it in a window at
every ``reset`` and ``step`` (`HumanView`).

Actions outside the action space are clipped to it and counted in ``info["clipped_actions"]`` (what many
training libraries expect: they sample unclipped Gaussian actions and leave the clipping to the env);
``gymnasium.make(id, strict_actions=True)`` refuses them with a ``ValueError`` instead. NaN or inf actions are always
refused.

``gymnasium.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point")`` gives a `GymnasiumVectorEnv`:
all N worlds in one jitted, vmapped call, with gymnasium's default next-step autoreset. The ``"sync"`` mode works
but compiles every sub-env separately; the ``"async"`` mode needs ``vector_kwargs={"context": "spawn"}``: JAX
hangs in a process forked after it started, so with ``fork`` the sub-envs raise a `RuntimeError` saying so
(`jaxdrones._fork`).

The envs pickle as the arguments they were built with (the task env as its task and config): an unpickled copy
is built anew, with no episode running and no seed (its first ``reset`` takes one), so that worker processes
started with ``spawn`` receive small, JAX-free payloads.
"""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import VectorEnv
from gymnasium.vector.utils import batch_space
from numpy.typing import ArrayLike

try:
    from gymnasium.vector import AutoresetMode

    _NEXT_STEP, _SAME_STEP = AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP
except ImportError:  # gymnasium < 1.1, where `GymnasiumVectorEnv` refuses to run
    _NEXT_STEP, _SAME_STEP = "next_step", "same_step"

from jaxdrones._fork import check_not_forked
from jaxdrones._validate import check_int
from jaxdrones.adapters._host import (
    RENDER_MODES,
    HumanView,
    OneWorldRendering,
    check_torch_threads,
    host_metrics,
    render_frame,
)
from jaxdrones.envs.base import Env, world_axes
from jaxdrones.envs.env import outside_box
from jaxdrones.envs.registry import check_options, make, option_names, registered, subscribe
from jaxdrones.sensors.camera import ENV_IMAGES
from jaxdrones.wrappers.autoreset import reset_where

#: `GymnasiumVectorEnv`'s autoreset modes, by their names (gymnasium's ``AutoresetMode`` values).
AUTORESET_MODES = {"next_step": _NEXT_STEP, "same_step": _SAME_STEP}

#: The gymnasium releases the adapters need: `GymnasiumEnv` the reset/step API of 0.26 (tested with 0.29.1, the
#: release CleanRL's main branch pins), `GymnasiumVectorEnv` the ``VectorEnv`` of 1.x with ``AutoresetMode`` (1.1).
MIN_GYMNASIUM, MIN_GYMNASIUM_VECTOR = (0, 26), (1, 1)
#: The installed gymnasium's (major, minor).
GYMNASIUM_VERSION = tuple(int(part) for part in gym.__version__.split(".")[:2])


#: ``jax.jit`` of ``reset`` and ``step`` by (env class, task class, config): see `compiled`.
_COMPILED: dict = {}


def compiled(env: Env) -> tuple:
    """``(jax.jit(env.reset), jax.jit(env.step))``, shared by every env of the same task class and config on the JAX
    backend, so that copies compile once: SuperSuit's ``concat_vec_envs_v1`` makes one (by pickling) per slot.
    The functions are pure, so the copies share nothing else. On the PyBullet backend each env steps its own Bullet
    worlds and compiles its own."""
    config = getattr(env, "config", None)
    if getattr(config, "backend", None) != "jax":
        return jax.jit(env.reset), jax.jit(env.step)
    key = (type(env), type(env.task), config)
    if key not in _COMPILED:
        _COMPILED[key] = (jax.jit(env.reset), jax.jit(env.step))
    return _COMPILED[key]


def _check_render_mode(render_mode) -> None:
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")


def spaces(env: Env) -> tuple[gym.Space, gym.Space]:
    """(observation space, action space) of one world: Boxes of shape (n,) for D = 1, (D, n) for D ≥ 2, float32,
    bounded by the observation and action types (a ``Dict`` with the camera images under ``vision``)."""
    low, high = env.observation_bounds()
    a_low, a_high = env.action_bounds()
    if env.n_drones == 1:
        low, high, a_low, a_high = low[0], high[0], a_low[0], a_high[0]
    obs = gym.spaces.Box(low, high, dtype=np.float32)
    spec = env.observation_spec
    if isinstance(spec, dict):
        images = {
            k: _image_box(k, v.shape[1:] if env.n_drones == 1 else v.shape) for k, v in spec.items() if k != "state"
        }
        obs = gym.spaces.Dict({"state": obs, **images})
    return obs, gym.spaces.Box(a_low, a_high, dtype=np.float32)


def _image_box(name: str, shape) -> gym.spaces.Box:
    kind = ENV_IMAGES[name]  # rgb 0-255, depth in m along the optical axis, seg body ids (-1: nothing seen)
    return gym.spaces.Box(kind.low, kind.high, shape, kind.dtype)


def _to_numpy(obs, space: gym.Space, squeeze: bool):
    """``obs`` as NumPy in ``space``'s dtypes (``space`` of one world); ``squeeze`` drops the drone axis (D = 1)."""
    if isinstance(space, gym.spaces.Dict):
        return {k: _to_numpy(v, space[k], squeeze) for k, v in obs.items()}
    obs = np.asarray(obs, space.dtype)
    return np.take(obs, 0, axis=obs.ndim - len(space.shape) - 1) if squeeze else obs


def check_action(
    action: ArrayLike, space: gym.spaces.Box, batch: tuple[int, ...] = (), strict: bool = False, name: str = "action"
) -> np.ndarray:
    """``action`` as f32 of shape ``batch + space.shape``, checked at the adapters' boundary.

    Entries outside the box are passed on (the env clips them and counts them in ``clipped_actions``), unless
    ``strict``; non-finite entries are always refused.

    Raises:
        ValueError: not a float array of the expected shape; NaN or inf entries, or entries beyond float32's range;
            with ``strict``, entries outside the box by more than `jaxdrones.envs.env.CLIP_TOLERANCE`. The message
            names ``name``.
    """
    expected = batch + space.shape
    try:
        given = np.asarray(action, dtype=np.float64)  # checked before the cast, which would overflow to inf
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a float array of shape {expected}, got {action!r}") from e
    if given.shape != expected:
        raise ValueError(f"{name} must have shape {expected}, got {given.shape}")
    if not np.all(np.isfinite(given)):
        raise ValueError(
            f"{name} must be finite, got {np.sum(~np.isfinite(given))} NaN or inf entries: "
            f"{given.tolist() if given.size <= 16 else given}"
        )
    beyond = np.abs(given) > np.finfo(np.float32).max
    if np.any(beyond):
        raise ValueError(
            f"{name} must lie within float32's range (±{np.finfo(np.float32).max:.4g}), the env's action dtype; "
            f"got {np.sum(beyond)} entries beyond it, the largest {given[beyond].flat[0]:.4g}"
        )
    action = given.astype(np.float32)
    if strict and np.any(outside_box(action, space.low, space.high)):
        raise ValueError(
            f"{name} must lie in the action space [{space.low.min():g}, {space.high.max():g}] "
            f"(strict_actions=True), got values in [{action.min():g}, {action.max():g}]; without "
            f"strict_actions the env clips them and counts them in info['clipped_actions']"
        )
    return action


class GymnasiumEnv(OneWorldRendering, gym.Env):
    """A functional jaxdrones env as a stateful gymnasium env (one world, NumPy in and out).

    The wrapper owns the env state and the PRNG key: ``reset(seed=...)`` makes the episode sequence reproducible,
    ``reset()`` without a seed continues it. ``reset`` and ``step`` are jitted once. Observations are float32 in
    the env's bounded Box.

    Actions outside the action space are clipped to it, as gymnasium's ``ClipAction`` would (policies that sample
    unclipped Gaussians, as skrl's and many others do, run unchanged), and ``info["clipped_actions"]`` counts the
    entries that were clipped at this step; ``strict_actions=True`` raises a ``ValueError`` instead. A NaN or inf
    action always raises a ``ValueError``.

    ``step`` returns ``(obs, reward, terminated, truncated, info)``; ``info`` holds the env's metrics (floats;
    ``clipped_actions`` an int) and, for D ≥ 2, the per-drone rewards (``"rewards"``); the reward is the sum over
    drones. ``render()`` returns an
    RGB frame when ``render_mode="rgb_array"``; ``render_mode="human"`` shows every step in a window (`HumanView`).
    `close` releases the backend. Pickled as its task env and render mode (see the module docstring).
    """

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 30}

    def __init__(self, env: Env, render_mode: str | None = None, strict_actions: bool = False):
        _check_render_mode(render_mode)
        check_not_forked()
        self._init_args = (env, render_mode, strict_actions)
        self.env = env
        self.render_mode = render_mode
        self.strict_actions = bool(strict_actions)
        self.metadata = {**self.metadata, "render_fps": env.config.sim.ctrl_freq}
        self.observation_space, self.action_space = spaces(env)
        self._reset, self._step = compiled(env)
        self._state = None
        self._view = HumanView.for_mode(env, render_mode)

    def __reduce__(self):
        return type(self), self._init_args

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray | dict[str, np.ndarray], dict[str, Any]]:
        check_not_forked()
        check_torch_threads()
        super().reset(seed=seed)
        key = jax.random.key(int(self.np_random.integers(2**31)))
        self._state = self._reset(key)
        self._show()
        return self._obs(), self._info()

    def step(self, action: ArrayLike) -> tuple[np.ndarray | dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        check_not_forked()
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = check_action(action, self.action_space, strict=self.strict_actions)
        self._state = self._step(self._state, action.reshape(self.env.n_drones, self.env.action_size))
        self._show()
        s = self._state
        return self._obs(), float(np.sum(s.reward)), bool(s.terminated), bool(s.truncated), self._info()

    def _obs(self):
        return _to_numpy(self._state.obs, self.observation_space, self.env.n_drones == 1)

    def _info(self) -> dict:
        info = host_metrics(self._state.metrics)
        if self.env.n_drones > 1:
            info["rewards"] = np.asarray(self._state.reward, np.float32)
        return info


class ImageObservation(gym.ObservationWrapper):
    """A `GymnasiumEnv` with cameras, its observation as image policies take it (SB3's ``MultiInputPolicy``, whose
    ``CombinedExtractor`` runs a CNN on every image space): `jaxdrones.envs.observations.policy_input`, the one
    transform our trainers use, with its ``pixels/`` prefix dropped.

    Observation: ``{"state": f32[D·n], "depth": f32[H, W, D] in [0, 1] (depth / `DEPTH_SCALE` m, clipped),
    "rgb": f32[H, W, 3D] in [0, 1]}`` (the images the env renders; segmentation ids are left out), channels last,
    or with ``channels_first`` f32[D, H, W] and f32[3D, H, W]. For SB3 pass ``channels_first=True`` (SB3 moves
    only ``uint8`` images' channels first itself) and ``policy_kwargs=dict(normalize_images=False)`` (the images
    are already in [0, 1]).

    Raises:
        ValueError: the env has no depth or RGB camera.
    """

    def __init__(self, env: gym.Env, channels_first: bool = False):
        super().__init__(env)
        from jaxdrones.envs.observations import policy_input

        inner = env.unwrapped.env
        spec = inner.observation_spec
        if not isinstance(spec, dict) or not {"depth", "rgb"} & set(spec):
            raise ValueError(
                f"ImageObservation needs an env with a depth or RGB camera (vision=('depth',) or "
                f"('rgb',)), got observations {sorted(spec) if isinstance(spec, dict) else 'f[D, n]'}"
            )
        self._n_drones = inner.n_drones

        def transform(obs):
            out = policy_input(obs)
            return {
                k.removeprefix("pixels/"): jnp.moveaxis(v, -1, 0) if channels_first and k != "state" else v
                for k, v in out.items()
            }

        self._transform = jax.jit(transform)
        shapes = jax.eval_shape(
            transform, {k: jax.ShapeDtypeStruct(v.shape, v.dtype) for k, v in spec.items() if k != "seg"}
        )
        state = env.observation_space["state"]
        self.observation_space = gym.spaces.Dict(
            {
                "state": gym.spaces.Box(state.low.reshape(-1), state.high.reshape(-1), dtype=np.float32),
                **{k: gym.spaces.Box(0.0, 1.0, v.shape, np.float32) for k, v in shapes.items() if k != "state"},
            }
        )

    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self._n_drones == 1:  # the gymnasium env drops the drone axis of one drone
            observation = {k: np.expand_dims(v, 0) for k, v in observation.items()}
        out = self._transform({k: v for k, v in observation.items() if k != "seg"})
        return {k: np.asarray(v, np.float32) for k, v in out.items()}


def _options(env: Env) -> set[str]:
    """The options `jaxdrones.make` takes for ``env``'s task (none for an env of an unregistered task)."""
    try:
        return option_names(env.task.name)
    except (AttributeError, ValueError):
        return set()


class GymnasiumVectorEnv(VectorEnv):
    """N worlds of a jaxdrones env as a gymnasium ``VectorEnv``: one jitted, vmapped call per ``step``.

    NumPy in and out: observations f32[N, ...] (the single space batched), actions f32[N, ...]; actions outside
    the action space are clipped as in `GymnasiumEnv` (``infos["clipped_actions"]`` i64[N] counts them per world;
    ``strict_actions=True`` raises instead), NaN or inf ones raise a ``ValueError``. Each reset draws a fresh start,
    task params and (with ``randomize``) drone params from the world's key. ``infos`` holds the metrics, arrays f[N].

    Autoreset (``autoreset_mode``, gymnasium's ``AutoresetMode``): ``"next_step"`` (gymnasium's default): the step
    after a world's episode ended resets it and returns its first observation with reward 0. ``"same_step"``: the
    step that ends an episode returns the next episode's first observation, and the last one of the ended episode in
    ``infos["final_obs"]`` (f32[N, ...], valid where ``infos["_final_obs"]`` bool[N] holds), with its metrics in
    ``infos["final_info"]``; what Stable-Baselines3 expects (`jaxdrones.adapters.sb3.VecEnv` builds on it).

    The worlds share one env (`Env`): `call`, `get_attr` and `set_attr` act on it as gymnasium's ``SyncVectorEnv``
    acts on each sub-env, with a tuple of one entry per world (``call("render")``: each world's frame).

    Raises:
        ValueError: a ``num_envs`` below 1, an unknown ``render_mode`` or ``autoreset_mode``.
        RuntimeError: gymnasium older than 1.1, or a process forked after JAX started.
    """

    metadata = {"autoreset_mode": _NEXT_STEP, "render_modes": list(RENDER_MODES)}

    def __init__(
        self,
        env: Env,
        num_envs: int,
        render_mode: str | None = None,
        strict_actions: bool = False,
        autoreset_mode: str = "next_step",
    ):
        if GYMNASIUM_VERSION < MIN_GYMNASIUM_VECTOR:
            raise RuntimeError(
                f"jaxdrones' vector env needs gymnasium >= {'.'.join(map(str, MIN_GYMNASIUM_VECTOR))} "
                f"(its VectorEnv API); gymnasium {gym.__version__} is installed. With this gymnasium, "
                f"batch the single-world env: gymnasium.vector.SyncVectorEnv([lambda: "
                f"gymnasium.make(id) for _ in range(n)]), or upgrade: pip install 'gymnasium>=1.1'"
            )
        _check_render_mode(render_mode)
        check_int("num_envs", num_envs)
        # Our names, or gymnasium's AutoresetMode members (whose values are "NextStep" and "SameStep").
        names = {str(getattr(member, "value", name)): name for name, member in AUTORESET_MODES.items()}
        mode = names.get(str(getattr(autoreset_mode, "value", autoreset_mode)), autoreset_mode)
        if mode not in AUTORESET_MODES:
            raise ValueError(
                f"autoreset_mode must be one of {list(AUTORESET_MODES)} or gymnasium's AutoresetMode.NEXT_STEP or "
                f"SAME_STEP, got {autoreset_mode!r}"
            )
        check_not_forked()
        self._init_args = (env, num_envs, render_mode, strict_actions, autoreset_mode)
        self._user_attrs: set[str] = set()  # the attributes set_attr set
        self.autoreset_mode = AUTORESET_MODES[mode]
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}
        self.env = env
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.strict_actions = bool(strict_actions)
        self.single_observation_space, self.single_action_space = spaces(env)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        # Params that every world shares are held once (see `Env.shared_params`); the old state is not kept, so
        # each step may reuse its buffers.
        self._shared_params = env.shared_params is not None
        self._axes = world_axes(self._shared_params)
        self._reset = jax.jit(jax.vmap(env.reset, out_axes=self._axes))
        same = self.autoreset_mode == _SAME_STEP
        self._step = jax.jit(self._step_same if same else self._step_worlds, donate_argnums=0)
        self._final = None  # same_step: (obs, metrics, done) of the last step, before the ended worlds' reset
        self._state = None
        self._needs_reset = None
        self._key = None
        self._view = HumanView.for_mode(env, render_mode)

    def _step_all(self, state, action):
        """Every world's env step, before any reset."""
        shape = (action.shape[0], self.env.n_drones, self.env.action_size)
        step = jax.vmap(self.env.step, in_axes=(self._axes, 0), out_axes=self._axes)
        return step(state, action.reshape(shape).astype(state.sim.pos.dtype))

    def _step_worlds(self, state, action, needs_reset):
        stepped = self._step_all(state, action)
        # Only the worlds whose episode ended at the last step are reset.
        out = reset_where(self.env, stepped, needs_reset, shared_params=self._shared_params)
        return out, out.done

    def _step_same(self, state, action, needs_reset):
        del needs_reset  # the ended worlds were reset in their last step
        stepped = self._step_all(state, action)
        keep = ("reward", "terminated", "truncated", "metrics")
        out = reset_where(self.env, stepped, stepped.done, keep=keep, shared_params=self._shared_params)
        return out, (stepped.obs, stepped.metrics, stepped.done)

    def __reduce__(self):
        return type(self), self._init_args

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray | dict[str, np.ndarray], dict[str, np.ndarray]]:
        check_not_forked()
        check_torch_threads()
        super().reset(seed=seed)
        self._key = jax.random.key(int(self.np_random.integers(2**31)))
        self._key, sub = jax.random.split(self._key)
        self._state = self._reset(jax.random.split(sub, self.num_envs))
        self._needs_reset = jnp.zeros((self.num_envs,), bool)
        self._show()
        return self._obs(), self._infos()

    def step(
        self, actions: ArrayLike
    ) -> tuple[np.ndarray | dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        check_not_forked()
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = check_action(actions, self.single_action_space, (self.num_envs,), strict=self.strict_actions)
        was_reset = self._needs_reset
        if self.autoreset_mode == _SAME_STEP:
            self._state, self._final = self._step(self._state, actions, self._needs_reset)
            self._show()
            return self._step_results(np.zeros((self.num_envs,), bool))
        self._state, self._needs_reset = self._step(self._state, actions, self._needs_reset)
        self._show()
        return self._step_results(np.asarray(was_reset))

    def _step_results(self, reset: np.ndarray) -> tuple:
        s = self._state
        reward = np.where(reset, 0.0, np.asarray(s.reward).reshape(self.num_envs, -1).sum(-1))
        terminated = np.asarray(s.terminated) & ~reset
        truncated = np.asarray(s.truncated) & ~reset
        infos = self._infos()
        if self.autoreset_mode == _SAME_STEP:
            obs, metrics, ended = self._final
            infos["final_obs"] = _to_numpy(obs, self.single_observation_space, self.env.n_drones == 1)
            infos["_final_obs"] = np.asarray(ended)
            infos["final_info"] = {k: np.asarray(v) for k, v in metrics.items()}
            infos["_final_info"] = infos["_final_obs"]
        return self._obs(), reward.astype(np.float32), terminated, truncated, infos

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """What each world's env gives for ``name``, as ``SyncVectorEnv.call`` (one entry per world): the world's
        spaces (``observation_space``, ``action_space``), ``render_mode``, ``metadata``, ``spec``, its frame for
        ``render`` (None unless ``render_mode="rgb_array"``), else the shared `Env`'s attribute, called with
        ``args`` and ``kwargs`` if it is a method.

        Raises:
            AttributeError: the env has no attribute ``name``.
        """
        if name == "render":
            if self.render_mode != "rgb_array" or self._state is None:
                return (None,) * self.num_envs
            return tuple(
                render_frame(self.env, self._state, world=w, shared_params=self._shared_params)
                for w in range(self.num_envs)
            )
        value = self._world_attr(name)
        return (value(*args, **kwargs) if callable(value) else value,) * self.num_envs

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """``name`` of each world's env (`call` without arguments)."""
        return self.call(name)

    def set_attr(self, name: str, values: Any) -> None:
        """Set ``name`` on the env that the worlds share: one value, or a list or tuple of one per world, all equal;
        an attribute of your own (the env's own attributes and options were compiled into its step, which a new
        value would not change).

        Raises:
            ValueError: a list or tuple of another length than ``num_envs``, or of different values; an option of
                the env (``ctrl_freq``, ``episode_len_s``, ...: make a new env with it) or another of its own
                attributes.
        """
        if name in _options(self.env) or (hasattr(self.env, name) and name not in self._user_attrs):
            raise ValueError(
                f"set_attr: {name!r} is the env's own and was compiled into its step, which a new value would not "
                f"change; make a new env with it instead, e.g. gym.make_vec(id, num_envs, {name}=...) or "
                f"jaxdrones.make(task, {name}=...)"
            )
        if isinstance(values, (list, tuple)):
            if len(values) != self.num_envs:
                raise ValueError(f"set_attr: expected one value or {self.num_envs} values, got {len(values)}")
            if any(v is not values[0] and v != values[0] for v in values[1:]):
                raise ValueError(f"set_attr: the {self.num_envs} worlds share one env; give {name!r} one value")
            values = values[0]
        setattr(self.env, name, values)
        self._user_attrs.add(name)

    def _world_attr(self, name: str) -> Any:
        own = {
            "observation_space": self.single_observation_space,
            "action_space": self.single_action_space,
            "render_mode": self.render_mode,
            "metadata": self.metadata,
            "spec": self.spec,
        }
        return own[name] if name in own else getattr(self.env, name)

    def render(self) -> np.ndarray | None:
        """An RGB frame of world 0 with ``render_mode="rgb_array"``; None otherwise (with ``"human"``, `reset`
        and `step` show world 0)."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return self._frame()

    def close_extras(self, **kwargs: Any) -> None:
        if self._view is not None:
            self._view.close()
        self.env.close()

    def _frame(self) -> np.ndarray:
        return render_frame(self.env, self._state, world=0, shared_params=self._shared_params)

    def _show(self) -> None:
        if self._view is not None:
            self._view.show(self._frame())

    def _obs(self):
        return _to_numpy(self._state.obs, self.single_observation_space, self.env.n_drones == 1)

    def _infos(self) -> dict:
        return host_metrics(self._state.metrics)


def make_env(task: str, render_mode: str | None = None, strict_actions: bool = False, **overrides: Any) -> GymnasiumEnv:
    """Entry point of ``gymnasium.make(GYM_IDS[task], **overrides)``; overrides are the task's config fields,
    ``strict_actions`` that of `GymnasiumEnv`."""
    check_options(task, overrides, also=("render_mode", "strict_actions"))
    _check_render_mode(render_mode)
    return GymnasiumEnv(make(task, **overrides), render_mode=render_mode, strict_actions=strict_actions)


def make_vector_env(
    task: str,
    num_envs: int = 1,
    render_mode: str | None = None,
    strict_actions: bool = False,
    autoreset_mode: str = "next_step",
    **overrides: Any,
) -> GymnasiumVectorEnv:
    """Vector entry point of ``gymnasium.make_vec(GYM_IDS[task], num_envs, vectorization_mode="vector_entry_point",
    **overrides)``; ``autoreset_mode`` (``"next_step"`` or ``"same_step"``) as in `GymnasiumVectorEnv`."""
    check_options(task, overrides, also=("num_envs", "render_mode", "strict_actions", "autoreset_mode"))
    _check_render_mode(render_mode)
    return GymnasiumVectorEnv(
        make(task, **overrides), num_envs, render_mode, strict_actions=strict_actions, autoreset_mode=autoreset_mode
    )


def gym_id(task: str) -> str:
    """A task's gymnasium id: ``jaxdrones/`` and its name in CamelCase, version 0 (``"my_hover"`` →
    ``"jaxdrones/MyHover-v0"``, ``"fly_thru_gate"`` → ``"jaxdrones/FlyThruGate-v0"``)."""
    return "jaxdrones/" + "".join(part.capitalize() for part in task.split("_")) + "-v0"


#: gymnasium id of every registered task (`gym_id`; a task of your own gets one from `jaxdrones.envs.register`).
GYM_IDS = {task: gym_id(task) for task in registered()}


def register() -> None:
    """Register every task's id (`GYM_IDS`) with gymnasium (done on ``import jaxdrones``).

    With gymnasium older than `MIN_GYMNASIUM` nothing is registered and a `UserWarning` names the installed and the
    required versions.
    """
    subscribe(register_task)  # and each task registered later (`jaxdrones.envs.register`)
    if GYMNASIUM_VERSION < MIN_GYMNASIUM:
        warnings.warn(
            f"jaxdrones registers its gymnasium ids with gymnasium >= {'.'.join(map(str, MIN_GYMNASIUM))} "
            f"(the reset/step API of 0.26); gymnasium {gym.__version__} is installed, so none were "
            f"registered: pip install 'gymnasium>=0.29.1'",
            UserWarning,
            stacklevel=2,
        )
        return
    for task in GYM_IDS:
        register_task(task)


def register_task(task: str) -> str:
    """Register the gymnasium id (`gym_id`) of the task ``task`` of `jaxdrones.envs.registered` (what
    `jaxdrones.envs.register` does for a task of your own); returns the id. Nothing is registered with gymnasium
    older than `MIN_GYMNASIUM`."""
    env_id = GYM_IDS.setdefault(task, gym_id(task))
    if GYMNASIUM_VERSION >= MIN_GYMNASIUM and env_id not in gym.registry:
        gym.register(
            id=env_id,
            entry_point="jaxdrones.adapters.gymnasium:make_env",
            vector_entry_point="jaxdrones.adapters.gymnasium:make_vector_env",
            kwargs={"task": task},
            disable_env_checker=True,
        )
    return env_id
