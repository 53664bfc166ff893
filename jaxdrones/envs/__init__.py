"""Tasks of the paper as functional environments, and the registry behind `jaxdrones.make`."""

from __future__ import annotations

import dataclasses

from jaxdrones.envs.base import Env, EnvState, kinematic_obs
from jaxdrones.envs.hover import HoverConfig, HoverEnv

_REGISTRY = {"hover": (HoverEnv, HoverConfig)}


def make(name: str, **overrides) -> Env:
    """Build a registered environment, e.g. ``jd.make("hover", action_type="rpm")``.

    Args:
        name: registered task name (see `registered`).
        **overrides: fields of the task's config dataclass (e.g. `HoverConfig`).

    Raises:
        ValueError: unknown task name or config field, or an invalid config value.
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown environment {name!r}: expected one of {registered()}")
    env_cls, config_cls = _REGISTRY[name]
    fields = {f.name for f in dataclasses.fields(config_cls)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {unknown}; valid options are {sorted(fields)}")
    return env_cls(config_cls(**overrides))


def registered() -> tuple[str, ...]:
    """Names accepted by `make`."""
    return tuple(_REGISTRY)


__all__ = ["Env", "EnvState", "HoverConfig", "HoverEnv", "kinematic_obs", "make", "registered"]
