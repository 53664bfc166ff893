"""Tasks of the paper as functional environments, and the registry behind `jaxdrones.make`.

Single-agent: ``hover``, ``takeoff``, ``velocity``, ``waypoints``, ``fly_thru_gate``, ``tune``, and ``avoid`` (a
vision task: obstacles drawn per episode, seen only through the depth camera).
Multi-agent: ``multi_hover``, ``leader_follower``, ``flock``, ``meetup``, ``crossing``.
"""

from __future__ import annotations

import dataclasses

from jaxdrones.envs.actions import ACTION_TYPES
from jaxdrones.envs.base import Env, EnvState
from jaxdrones.envs.core import DomainRandomization, Task, TaskConfig, TaskEnv, TaskParams
from jaxdrones.envs.observations import OBS_TYPES, kinematic_obs
from jaxdrones.envs.tasks.avoid import AVOID
from jaxdrones.envs.tasks.multi import MULTI_AGENT_TASKS
from jaxdrones.envs.tasks.single import SINGLE_AGENT_TASKS, HoverConfig

_REGISTRY: dict[str, Task] = {task.name: task for task in SINGLE_AGENT_TASKS + (AVOID,) + MULTI_AGENT_TASKS}
#: Names of the single-agent tasks (D = 1) and of the multi-agent tasks (D ≥ 2).
SINGLE_AGENT = tuple(t.name for t in SINGLE_AGENT_TASKS + (AVOID,))
MULTI_AGENT = tuple(t.name for t in MULTI_AGENT_TASKS)


def get_task(name: str) -> Task:
    """The registered `Task` called ``name``.

    Raises:
        ValueError: unknown name.
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}: expected one of {registered()}")
    return _REGISTRY[name]


def make_config(name: str, **overrides) -> TaskConfig:
    """The task's config with ``overrides`` (fields of its `TaskConfig` subclass).

    Raises:
        ValueError: unknown task or option, or an invalid value.
    """
    task = get_task(name)
    fields = {f.name for f in dataclasses.fields(task.config_cls)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {unknown}; valid options are {sorted(fields)}")
    return task.config_cls(**overrides)


def make(name: str, **overrides) -> TaskEnv:
    """Build a registered environment, e.g. ``jd.make("hover", action_type="one_d_rpm")`` or
    ``jd.make("leader_follower", n_drones=3)``.

    Args:
        name: registered task name (see `registered`).
        **overrides: fields of the task's config (`TaskConfig` and the task's subclass, e.g. `HoverConfig`).

    Raises:
        ValueError: unknown task name or option, an invalid value, or a drone count the task does not allow.
    """
    task = get_task(name)
    return TaskEnv(task, make_config(name, **overrides))


def registered() -> tuple[str, ...]:
    """Names accepted by `make`."""
    return tuple(_REGISTRY)


__all__ = ["ACTION_TYPES", "MULTI_AGENT", "OBS_TYPES", "SINGLE_AGENT", "DomainRandomization", "Env", "EnvState",
           "HoverConfig", "Task", "TaskConfig", "TaskEnv", "TaskParams", "get_task", "kinematic_obs", "make",
           "make_config", "registered"]
