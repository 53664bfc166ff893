"""Stable-Baselines3 (and sbx) on the batched env: `VecEnv`, N worlds stepped in one jitted call.

SB3's vectorised envs (``DummyVecEnv``, ``SubprocVecEnv``, what ``make_vec_env`` builds) step one Python env per
world; `VecEnv` is a ``stable_baselines3.common.vec_env.VecEnv`` whose N worlds are one jaxdrones env stepped by one
jitted, vmapped call (`jaxdrones.adapters.gymnasium.GymnasiumVectorEnv` with same-step autoreset), so that PPO, SAC,
sbx's JAX algorithms and SB3's wrappers (``VecMonitor``, ``VecNormalize``, ``VecVideoRecorder``) take it as they take
their own::

    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor
    from jaxdrones.adapters.sb3 import VecEnv

    env = VecMonitor(VecEnv("hover", num_envs=256, action_type="one_d_rpm"))
    PPO("MlpPolicy", env).learn(1_000_000)

Stable-Baselines3 is optional (``pip install ".[sb3]"`` from a clone): this module imports it when `VecEnv` is
first used, and says how to install it where it is missing.
"""

from __future__ import annotations

import functools
from typing import Any

#: What installs Stable-Baselines3 (and the CPU torch CI ran) from a clone of the project.
INSTALL_HINT = 'pip install -c constraints.txt ".[sb3]" (from a clone of jaxdrones), or pip install stable-baselines3'


def __getattr__(name: str) -> Any:
    if name == "VecEnv":
        return _vec_env_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@functools.cache
def _vec_env_class() -> type:
    try:
        from stable_baselines3.common.vec_env import VecEnv as SB3VecEnv
    except ImportError as err:
        raise ImportError(f"jaxdrones.adapters.sb3.VecEnv needs Stable-Baselines3: {INSTALL_HINT}") from err
    import numpy as np

    from jaxdrones._hints import did_you_mean
    from jaxdrones.adapters.gymnasium import GYM_IDS, GymnasiumVectorEnv
    from jaxdrones.envs.base import Env
    from jaxdrones.envs.registry import check_options, make

    class VecEnv(SB3VecEnv):
        """N worlds of a jaxdrones task as a Stable-Baselines3 ``VecEnv`` (also sbx's): one jitted call per step.

        Built like ``jd.make``: ``VecEnv("hover", num_envs=1024, action_type="one_d_rpm")``, or from a gymnasium id
        (``VecEnv("jaxdrones/Hover-v0", num_envs=1024)``) or an `Env` (``VecEnv(jd.make("hover"), num_envs=...)``).

        NumPy in and out, as SB3 expects: ``reset() -> obs`` f32[N, ...], ``step(actions)`` with actions f32[N, ...]
        (the single world's action space batched; outside it they are clipped and counted in
        ``info["clipped_actions"]``, or refused with ``strict_actions=True``) returns ``(obs, rewards f32[N],
        dones bool[N], infos)``, ``infos`` a list of N dicts. A world whose episode ended is reset in the same step:
        its ``obs`` row is the next episode's first observation, ``infos[i]["terminal_observation"]`` the last one of
        the ended episode, and ``infos[i]["TimeLimit.truncated"]`` says that it hit the time limit without
        terminating (so that SB3 bootstraps its value). With a single drone the observation is f32[N, n_obs]; with D
        drones f32[N, D, n_obs] and actions f32[N, D, n_act] (one policy flying the team).

        ``seed(s)`` seeds the next ``reset``; ``render()`` tiles the worlds' frames (``render_mode="rgb_array"``:
        every world is drawn, so record videos with a few worlds). ``get_attr``, ``set_attr`` and ``env_method``
        act on the env that the worlds share (`GymnasiumVectorEnv.call`); ``env_is_wrapped`` is False (no gymnasium
        wrapper is involved).

        Args:
            task: a registered task's name, its gymnasium id, or an `Env` (then ``options`` must be empty).
            num_envs: the worlds, ≥ 1.
            render_mode: None, ``"rgb_array"`` or ``"human"``.
            strict_actions: refuse actions outside the action space instead of clipping them.
            options: the task's config fields (``jd.make(task, **options)``).

        Raises:
            ValueError: an unknown task or option, ``num_envs`` below 1, options given with an `Env`.
        """

        def __init__(
            self,
            task: str | Env = "hover",
            num_envs: int = 1,
            render_mode: str | None = None,
            strict_actions: bool = False,
            **options: Any,
        ):
            if isinstance(task, Env):
                if options:
                    raise ValueError(f"VecEnv: options {sorted(options)} apply to a task's name, not to an Env")
                env = task
            else:
                ids = {gym_id: name for name, gym_id in GYM_IDS.items()}
                if isinstance(task, str) and task.startswith("jaxdrones/") and task not in ids:
                    raise ValueError(
                        f"VecEnv: unknown gymnasium id {task!r}{did_you_mean(task, ids)}: expected a task's name or "
                        f"one of {sorted(ids)}"
                    )
                task = ids.get(task, task)
                check_options(task, options, also=("num_envs", "render_mode", "strict_actions"))
                env = make(task, **options)
            self.venv = GymnasiumVectorEnv(
                env, num_envs, render_mode=render_mode, strict_actions=strict_actions, autoreset_mode="same_step"
            )
            self.env = env
            self._init_args = (task, num_envs, render_mode, strict_actions, options)
            super().__init__(num_envs, self.venv.single_observation_space, self.venv.single_action_space)
            self._actions = None

        def reset(self):
            seed = self._seeds[0]
            obs, infos = self.venv.reset(seed=seed)
            self._reset_seeds()
            self._reset_options()
            self.reset_infos = self._world_infos(infos, np.zeros((self.num_envs,), bool))
            return obs

        def step_async(self, actions: np.ndarray) -> None:
            self._actions = actions

        def step_wait(self):
            if self._actions is None:
                raise RuntimeError("VecEnv: call step_async(actions) before step_wait()")
            actions, self._actions = self._actions, None
            obs, rewards, terminated, truncated, infos = self.venv.step(actions)
            dones = terminated | truncated
            world_infos = self._world_infos(infos, dones)
            for i in np.flatnonzero(dones):
                world_infos[i]["terminal_observation"] = _row(infos["final_obs"], i)
                world_infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            return obs, rewards, dones, world_infos

        def _world_infos(self, infos: dict, dones: np.ndarray) -> list[dict]:
            """Per-world dicts of the metrics (those of the ended episode's last step where ``dones``)."""
            metrics = {k: v for k, v in infos.items() if not k.startswith("_") and k not in ("final_obs", "final_info")}
            final = infos.get("final_info", {})
            rows = [{} for _ in range(self.num_envs)]
            for name, values in metrics.items():
                values = np.where(dones, final[name], values) if name in final else values
                for row, value in zip(rows, values.tolist(), strict=True):
                    row[name] = value
            return rows

        def close(self) -> None:
            self.venv.close()

        def get_attr(self, attr_name: str, indices=None) -> list[Any]:
            value = self.venv.get_attr(attr_name)[0]
            return [value for _ in self._get_indices(indices)]

        def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
            if len(list(self._get_indices(indices))) != self.num_envs:
                raise ValueError(f"VecEnv.set_attr: the {self.num_envs} worlds share one env; set {attr_name!r} on all")
            self.venv.set_attr(attr_name, value)

        def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
            results = self.venv.call(method_name, *method_args, **method_kwargs)
            return [results[i] for i in self._get_indices(indices)]

        def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
            return [False for _ in self._get_indices(indices)]

        def get_images(self) -> list[np.ndarray | None]:
            return list(self.venv.call("render"))

        def __reduce__(self):
            task, num_envs, render_mode, strict_actions, options = self._init_args
            return _rebuild, (task, num_envs, render_mode, strict_actions, options)

    VecEnv.__module__, VecEnv.__qualname__ = __name__, "VecEnv"
    return VecEnv


def _rebuild(task, num_envs, render_mode, strict_actions, options):
    """An unpickled `VecEnv`: built anew from its arguments, with no episode running."""
    return _vec_env_class()(task, num_envs, render_mode, strict_actions, **options)


def _row(obs, i: int):
    """World ``i`` of a (possibly dict) batched observation."""
    if isinstance(obs, dict):
        return {k: v[i] for k, v in obs.items()}
    return obs[i]
