"""The task registry behind `jaxdrones.make`: the built-in tasks, `register` for your own, and `subscribe` for
what follows each new task (the gymnasium adapter registers its id)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from typing import Any

from jaxdrones._hints import did_you_mean, unknown_option
from jaxdrones.envs.config import START_OPTIONS, TaskConfig
from jaxdrones.envs.env import TaskEnv
from jaxdrones.envs.realism import Realism
from jaxdrones.envs.realism import resolve as resolve_realism
from jaxdrones.envs.task import Task
from jaxdrones.envs.tasks.avoid import AVOID
from jaxdrones.envs.tasks.gate import FLY_THRU_GATE
from jaxdrones.envs.tasks.multi import MULTI_AGENT_TASKS
from jaxdrones.envs.tasks.single import FirmwareHover, Hover, Takeoff, Tune, Velocity, Waypoints
from jaxdrones.sim import SimConfig

#: The `Realism` fields that `make` and `make_config` take as keywords.
REALISM_OPTIONS = frozenset(f.name for f in dataclasses.fields(Realism))
#: The physics' options `make` takes by their own names into the config's ``sim``: `SimConfig`'s fields but the team's
#: size (the config's ``n_drones``) and the motors' dynamics (on with the realism's motor time constants).
SIM_OPTIONS = frozenset(f.name for f in dataclasses.fields(SimConfig)) - {"n_drones", "motor_dynamics"}
#: The config's fields that group options `make` takes by flat names: field → {flat name: the group's field}.
GROUPED_OPTIONS = {"sim": {name: name for name in sorted(SIM_OPTIONS)}, "starts": START_OPTIONS}

#: The built-in single-agent tasks but ``avoid`` (`jaxdrones.envs.tasks.single`, `jaxdrones.envs.tasks.gate`).
SINGLE_AGENT_TASKS = (Hover(), Takeoff(), Velocity(), Waypoints(), FLY_THRU_GATE, Tune(), FirmwareHover())
_REGISTRY: dict[str, Task] = {task.name: task for task in SINGLE_AGENT_TASKS + (AVOID,) + MULTI_AGENT_TASKS}
#: What `register` calls with each new task's name (`subscribe`).
_SUBSCRIBERS: list[Callable[[str], object]] = []
#: Names of the single-agent tasks (D = 1) and of the multi-agent tasks (D ≥ 2).
SINGLE_AGENT = tuple(t.name for t in SINGLE_AGENT_TASKS + (AVOID,))
MULTI_AGENT = tuple(t.name for t in MULTI_AGENT_TASKS)
_BUILT_IN = frozenset(_REGISTRY)


def get_task(name: str) -> Task:
    """The registered `Task` called ``name``.

    Raises:
        ValueError: unknown name.
    """
    if name not in _REGISTRY:
        hint = did_you_mean(name, registered()) if isinstance(name, str) else ""
        raise ValueError(f"unknown task {name!r}{hint}: expected one of {registered()}")
    return _REGISTRY[name]


def make_config(name: str, **overrides: Any) -> TaskConfig:
    """The task's config with ``overrides`` (fields of its `TaskConfig` subclass, and `Realism` fields: see `make`).

    Raises:
        ValueError: unknown task or option, or an invalid value.
    """
    task = get_task(name)
    check_options(name, overrides)
    fields = {f.name for f in dataclasses.fields(task.config_cls)}
    options = {k: overrides.pop(k) for k in list(overrides) if k in REALISM_OPTIONS and k not in fields}
    if options:  # a realism option given alone: on top of the preset (or of none)
        realism = resolve_realism(overrides.get("realism"))
        overrides["realism"] = dataclasses.replace(realism or Realism(), **options)
    for group, names in GROUPED_OPTIONS.items():
        given = {names[k]: overrides.pop(k) for k in list(overrides) if k in names and k not in fields}
        if given:  # by their flat names: on top of the given group (the config puts a dict's on the task's own)
            base = overrides.get(group) or {}
            overrides[group] = dataclasses.replace(base, **given) if not isinstance(base, dict) else {**base, **given}
    return task.config_cls(**overrides)


def option_names(name: str) -> set[str]:
    """The options `make` takes for the task ``name``: its config's fields, the physics' (`SIM_OPTIONS`), the
    starts' and the `Realism` fields.

    Raises:
        ValueError: an unknown task.
    """
    fields = {f.name for f in dataclasses.fields(get_task(name).config_cls)} | REALISM_OPTIONS | SIM_OPTIONS
    return fields | set(START_OPTIONS)


def check_options(name: str, options: Iterable[str], also: Iterable[str] = ()) -> None:
    """Raise for an option of ``options`` that is not one of `option_names` of the task ``name`` nor one of ``also``
    (a caller's own keywords, e.g. an adapter's ``strict_actions``), naming the closest valid one
    (`jaxdrones._hints.unknown_option`).

    Raises:
        ValueError: an unknown task or option.
    """
    fields = option_names(name) | set(also)
    unknown = sorted(set(options) - fields)
    if unknown:
        raise ValueError(unknown_option(name, unknown[0], fields))


def make(name: str, **overrides: Any) -> TaskEnv:
    """Build a registered environment, e.g. ``jd.make("hover", action_type="one_d_rpm")`` or
    ``jd.make("leader_follower", n_drones=3)``.

    Args:
        name: registered task name (see `registered`).
        **overrides: fields of the task's config (`TaskConfig` and the task's subclass, e.g. `HoverConfig`), the
            physics' (`SIM_OPTIONS`: ``ctrl_freq=48``, ``drag=True``, ..., into the config's ``sim``), the
            starts' (`jaxdrones.envs.config.START_OPTIONS`: ``init_pos``, ``start_tilt``, ..., into its ``starts``),
            and the fields of `jaxdrones.envs.realism.Realism` (e.g. ``action_delay=1``, ``motor_tau_up=(0.05, 0.2)``),
            which set the config's ``realism`` on top of its preset: ``jd.make("hover", realism="crazyflie",
            turbulence=0.5)``.

    Raises:
        ValueError: unknown task name or option, an invalid value, or a drone count the task does not allow.
    """
    task = get_task(name)
    return TaskEnv(task, make_config(name, **overrides))


def registered() -> tuple[str, ...]:
    """Names accepted by `make`: the built-in tasks and those added by `register`."""
    return tuple(_REGISTRY)


def is_multi_agent(name: str) -> bool:
    """Whether the registered task ``name`` is multi-agent (it allows more than one drone; `Task.max_drones`)."""
    task = get_task(name)
    return task.max_drones is None or task.max_drones > 1


def register(task: Task, *, overwrite: bool = False) -> Task:
    """Add a task of your own to the registry, by its ``name``: then ``jd.make(name, ...)`` builds it, its gymnasium
    id (`jaxdrones.adapters.gymnasium.gym_id`, e.g. ``"my_hover"`` → ``jaxdrones/MyHover-v0``) is registered when
    gymnasium is installed, and ``jaxdrones.training.train_task(name)`` or ``jaxdrones train name --import MODULE``
    (MODULE registers it) trains it.

    A task is an instance of a `Task` subclass (see `Task` for the hooks and class attributes, and
    ``jaxdrones/envs/tasks`` for the built-in ones); its settings are a `TaskConfig` subclass (``config_cls``).

    Returns:
        ``task``, so that ``MY_TASK = register(MyTask())`` defines and registers it.

    Raises:
        ValueError: ``task`` not a `Task` instance, a ``name`` that is not a Python identifier, a ``config_cls`` that
            is not a `TaskConfig` subclass, or a name already registered (a built-in task's, or another task's
            unless ``overwrite``; re-registering the same task is allowed).
    """
    if not isinstance(task, Task):
        raise ValueError(f"register takes an instance of a jaxdrones.envs.Task subclass, got {task!r}")
    name = task.name
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"a task's name must be a Python identifier (e.g. 'my_hover'), got {name!r}")
    if not (isinstance(task.config_cls, type) and issubclass(task.config_cls, TaskConfig)):
        raise ValueError(f"{name}: config_cls must be a subclass of jaxdrones.envs.TaskConfig, got {task.config_cls!r}")
    known = _REGISTRY.get(name)
    if known is not None and known is not task and (name in _BUILT_IN or not overwrite):
        raise ValueError(
            f"a task named {name!r} is already registered ({type(known).__name__})"
            + ("" if name in _BUILT_IN else ": pass overwrite=True to replace it")
        )
    _REGISTRY[name] = task
    for callback in _SUBSCRIBERS:
        callback(name)
    return task


def subscribe(callback: Callable[[str], object]) -> None:
    """Call ``callback(name)`` for every task `register` adds from now on (the gymnasium adapter registers the
    task's id this way, `jaxdrones.adapters.gymnasium.register`). A callback subscribed twice is called once."""
    if callback not in _SUBSCRIBERS:
        _SUBSCRIBERS.append(callback)
