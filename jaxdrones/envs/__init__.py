"""Tasks of the paper as functional environments, and the registry behind `jaxdrones.make`.

Single-agent: ``hover``, ``takeoff``, ``velocity``, ``waypoints``, ``fly_thru_gate``, ``tune``, and ``avoid`` (a
vision task: obstacles drawn per episode, seen only through the depth camera).
Multi-agent: ``multi_hover``, ``leader_follower``, ``flock``, ``meetup``, ``crossing``.
Your own: a `Task` subclass, added with `register`.
"""

from __future__ import annotations

from jaxdrones.envs.actions import ACTION_TYPES
from jaxdrones.envs.base import Env, EnvState
from jaxdrones.envs.config import START_OPTIONS, DomainRandomization, Starts, TaskConfig
from jaxdrones.envs.env import TaskEnv
from jaxdrones.envs.observations import OBS_TYPES, kinematic_obs
from jaxdrones.envs.registry import (
    MULTI_AGENT,
    REALISM_OPTIONS,
    SINGLE_AGENT,
    get_task,
    is_multi_agent,
    make,
    make_config,
    register,
    registered,
    subscribe,
)
from jaxdrones.envs.task import Task, TaskParams
from jaxdrones.envs.tasks.single import HoverConfig

__all__ = [
    "ACTION_TYPES",
    "MULTI_AGENT",
    "OBS_TYPES",
    "REALISM_OPTIONS",
    "SINGLE_AGENT",
    "START_OPTIONS",
    "DomainRandomization",
    "Env",
    "EnvState",
    "HoverConfig",
    "Starts",
    "Task",
    "TaskConfig",
    "TaskEnv",
    "TaskParams",
    "get_task",
    "is_multi_agent",
    "kinematic_obs",
    "make",
    "make_config",
    "register",
    "registered",
    "subscribe",
]
