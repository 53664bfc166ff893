"""The table of trainers: every algorithm ``jaxdrones train --algo`` runs, with its config class, its default settings
per task and device, how it trains, and how its saved parameters become a policy.

A trainer's ``train(env, config, progress, evaluate) -> (network, params)`` takes ``progress(env_steps, metrics)``
(training metrics and, under ``"eval"``, the arrays ``evaluate`` returned) and ``evaluate(network, params)``
(traced; e.g. `jaxdrones.training.evaluation.episode_outcomes` of ``make_policy(network, params)``).
``make_network(config, env)`` rebuilds the network of a saved policy, ``make_policy(network, params)`` gives
``policy(obs, key) -> (action, extras)`` on a world's flat observation (the signature of brax's policies).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

#: Single-agent tasks ``jaxdrones train`` trains (default algorithm: PPO).
SINGLE_AGENT = ("hover", "takeoff", "velocity", "waypoints", "fly_thru_gate", "tune")
#: Multi-agent tasks ``jaxdrones train`` trains (default algorithm: MAPPO).
MULTI_AGENT = ("leader_follower", "multi_hover", "flock", "meetup", "crossing")
TRAINABLE = SINGLE_AGENT + MULTI_AGENT


@dataclasses.dataclass(frozen=True)
class Trainer:
    """One algorithm of the table (see the module doc)."""

    name: str
    description: str
    config_cls: type
    default_config: Callable[[str], Any]
    train: Callable
    make_network: Callable
    make_policy: Callable


def _ppo_config(task: str):
    """Our PPO's settings: a local critic (PPO is MAPPO's independent-critic form at one drone), tuned for the
    fewest seconds to a solved hover on CPU (`benchmarks/train_algos.py`); the other single-agent tasks take them
    with the budget of their own."""
    from jaxdrones.training.mappo import MAPPOConfig

    budgets = {"hover": 2_000_000, "velocity": 4_000_000, "waypoints": 6_000_000}
    return MAPPOConfig(critic="local", num_timesteps=budgets.get(task, 2_000_000))


def _brax_ppo_config(task: str):
    from jaxdrones.training.brax_ppo import default_config

    return default_config(task)


def _mappo_config(critic: str):
    def config(task: str):
        from jaxdrones.training.mappo import MAPPOConfig

        return MAPPOConfig(critic=critic)

    return config


def _apg_config(task: str):
    from jaxdrones.training.apg import APGConfig

    return APGConfig()


def _shac_config(task: str):
    from jaxdrones.training.shac import SHACConfig

    return SHACConfig()


def _module_trainer(module: str, function: str):
    """A function of a training module, imported when first called (so that the table imports nothing heavy)."""

    def call(*args, **kwargs):
        import importlib

        return getattr(importlib.import_module(f"jaxdrones.training.{module}"), function)(*args, **kwargs)

    return call


def _config_cls(module: str, name: str):
    import importlib

    return getattr(importlib.import_module(f"jaxdrones.training.{module}"), name)


def _table() -> dict[str, Trainer]:
    mappo_kw = dict(train=_module_trainer("mappo", "train"), make_network=_module_trainer("mappo", "make_network"),
                    make_policy=_module_trainer("mappo", "make_policy"))
    apg_kw = dict(make_network=_module_trainer("apg", "network_of"), make_policy=_module_trainer("apg", "make_policy"))
    return {
        "ppo": Trainer("ppo", "PPO (ours: one compiled program per chunk of updates; the default for single-agent "
                       "tasks)", _config_cls("mappo", "MAPPOConfig"), _ppo_config, **mappo_kw),
        "brax_ppo": Trainer("brax_ppo", "brax's PPO (brax.training.agents.ppo) through the brax adapter",
                            _config_cls("brax_ppo", "BraxPPOConfig"), _brax_ppo_config,
                            _module_trainer("brax_ppo", "train"), _module_trainer("brax_ppo", "make_network"),
                            _module_trainer("brax_ppo", "make_policy")),
        "apg": Trainer("apg", "analytic policy gradients through the simulator", _config_cls("apg", "APGConfig"),
                       _apg_config, _module_trainer("apg", "train"), **apg_kw),
        "shac": Trainer("shac", "short-horizon actor-critic through the simulator", _config_cls("shac", "SHACConfig"),
                        _shac_config, _module_trainer("shac", "train"), **apg_kw),
        "mappo": Trainer("mappo", "multi-agent PPO with a centralised critic (the default for multi-agent tasks)",
                         _config_cls("mappo", "MAPPOConfig"), _mappo_config("central"), **mappo_kw),
        "ippo": Trainer("ippo", "independent PPO (each agent's critic sees its own observation)",
                        _config_cls("mappo", "MAPPOConfig"), _mappo_config("local"), **mappo_kw),
    }


#: Algorithm names of ``jaxdrones train --algo``.
ALGOS = ("ppo", "brax_ppo", "apg", "shac", "mappo", "ippo")


def get(algo: str) -> Trainer:
    """The trainer named ``algo``.

    Raises:
        ValueError: an unknown name, listing `ALGOS`.
    """
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    return _table()[algo]


def default_algo(task: str) -> str:
    """``"mappo"`` for a multi-agent task, ``"ppo"`` otherwise."""
    return "mappo" if task in MULTI_AGENT else "ppo"
