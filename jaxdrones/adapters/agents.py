"""What the multi-agent adapters share: agent names and host-side checks.

Used by `jaxdrones.adapters.pettingzoo` and `jaxdrones.adapters.jaxmarl`; imports nothing of jaxdrones above
`jaxdrones.envs`.
"""

from __future__ import annotations

from typing import Any

from jaxdrones.envs import MULTI_AGENT, SINGLE_AGENT, TaskEnv, make


def agent_names(n_drones: int) -> list[str]:
    """``["drone_0", ..., "drone_{D-1}"]``: agent ``drone_i`` is row ``i`` of the env's stacked arrays."""
    return [f"drone_{i}" for i in range(n_drones)]


def make_multi_agent(task: str, **options: Any) -> TaskEnv:
    """``jaxdrones.make(task, **options)`` for a multi-agent task.

    Raises:
        ValueError: a single-agent or unknown task name (naming the multi-agent tasks), or what `jaxdrones.make`
            raises (an unknown option, an invalid value, an ``n_drones`` the task does not allow).
    """
    if task not in MULTI_AGENT:
        kind = (
            "is a single-agent task (use jaxdrones.adapters.gymnasium)"
            if task in SINGLE_AGENT
            else "is not a registered task"
        )
        raise ValueError(f"{task!r} {kind}; the multi-agent tasks are {MULTI_AGENT}")
    return make(task, **options)


def check_agent_keys(actions: object, agents: list[str]) -> None:
    """Check that ``actions`` is a dict with exactly one entry per agent of ``agents``.

    Raises:
        ValueError: not a dict, or missing, unknown or extra agent names (naming the expected agents).
    """
    if not isinstance(actions, dict):
        raise ValueError(
            f"actions must be a dict {{agent: action}} over the agents {agents}, got {type(actions).__name__}"
        )
    missing = [a for a in agents if a not in actions]
    extra = [a for a in actions if a not in agents]
    if missing or extra:
        parts = ([f"missing {missing}"] if missing else []) + ([f"unexpected {extra}"] if extra else [])
        raise ValueError(f"actions must have exactly one entry per agent {agents}: {', '.join(parts)}")
