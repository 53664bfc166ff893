"""The table of trainers: every algorithm ``jaxdrones train --algo`` runs, with its config class and the settings it
takes on any task, how it trains, what it can train on, and how its saved parameters become a policy (the settings
per task are the tasks' recipes, `jaxdrones.training.recipes`).

A trainer's ``train(env, config, progress, evaluate) -> (network, params)`` calls ``progress(env_steps, metrics)``
after each of its ``config.num_evals`` chunks of updates, with its training metrics (floats) and, under
``"eval"``, the arrays that ``evaluate(network, params, seed)`` returned (compiled and called after each chunk, with
the run's seed as an int array; e.g. `jaxdrones.training.evaluation.episode_outcomes` of ``make_policy(network,
params)``); on Ctrl-C it raises `jaxdrones.training.common.Interrupted` with the result of the last completed
chunk. A trainer that maps runs (`Trainer.maps_runs`) also takes ``runs``, configs of its class that differ in their
seed and float fields (step sizes, discounts, weights): one run per config as one program mapped over them
(`jaxdrones.training.common.run_updates`), a list of ``(network, params)`` returned, each metric an array over the
runs.
``make_network(config, env)`` rebuilds the network of a saved policy, ``make_policy(network, params)`` gives
``policy(obs, key) -> (action, extras)`` on a world's flat observation (the signature of brax's policies).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from jaxdrones.envs import MULTI_AGENT, SINGLE_AGENT
from jaxdrones.training.common import BUILD_SETTINGS, check_defaults
from jaxdrones.training.common import DEFAULTS as DEFAULTS  # the profiles, beside the table that uses them

#: The built-in tasks ``jaxdrones train`` trains, each at its recipe (`jaxdrones.training.recipes.RECIPES`): the
#: single-agent ones and the multi-agent ones; it trains a task of your own too (`jaxdrones.envs.register`).
TRAINABLE = SINGLE_AGENT + MULTI_AGENT


@dataclasses.dataclass(frozen=True)
class Trainer:
    """One algorithm of the table (see the module doc).

    Attributes:
        name, description: as ``jaxdrones train --algo`` lists it.
        config_cls: the trainer's config (a frozen dataclass).
        base: fields of ``config_cls`` that make this trainer of the class (e.g. MAPPO's central critic) and its
            settings on any task; a task's recipe sets more (`jaxdrones.training.recipes`).
        train, make_network, make_policy: see the module doc.
        evals_before_training: evaluations the trainer counts in ``num_evals`` before it trains (brax's PPO
            evaluates its initial policy: ``--num-evals N`` asks it for N + 1).
        num_envs_fields: the config fields that ``--num-envs`` sets (brax's PPO ties its batch size to the number
            of envs).
        images: trains on camera images.
        differentiable: differentiates the simulator (needs the JAX backend).
        stochastic: ``make_policy`` takes ``deterministic`` (the distribution's mode, or samples).
        maps_runs: ``train`` takes ``runs`` (module doc); the others' runs go one after another (brax's PPO runs
            its own training loop, which cannot be mapped).
    """

    name: str
    description: str
    config_cls: type
    train: Callable
    make_network: Callable
    make_policy: Callable
    base: dict[str, Any] = dataclasses.field(default_factory=dict)
    evals_before_training: int = 0
    num_envs_fields: tuple[str, ...] = ("num_envs",)
    images: bool = False
    differentiable: bool = False
    stochastic: bool = False
    maps_runs: bool = True

    def config(self, defaults: str = "cpu", **fields: Any) -> Any:
        """The trainer's config: `base` and ``fields`` over ``config_cls``'s defaults, with the build settings of
        the ``gpu`` profile (`gpu_build`) under ``defaults="gpu"``.

        Raises:
            ValueError: ``defaults`` not one of `DEFAULTS`, or a field the config rejects.
        """
        check_defaults(defaults)
        build = gpu_build(self.config_cls) if defaults == "gpu" else {}
        return self.config_cls(**{**self.base, **build, **fields})


def gpu_build(config_cls: type) -> dict[str, bool]:
    """The build settings of a trainer's config class with ``defaults="gpu"``: every one of `BUILD_SETTINGS` it
    has, on."""
    fields = {field.name for field in dataclasses.fields(config_cls)}
    return {name: True for name in BUILD_SETTINGS if name in fields}


def default_profile() -> str:
    """The `DEFAULTS` profile of JAX's default device: ``"gpu"`` on a GPU or TPU, else ``"cpu"``."""
    import jax

    return "cpu" if jax.default_backend() == "cpu" else "gpu"


def _module_trainer(module: str, function: str):
    """A function of a training module, imported when first called (so that the table imports nothing heavy)."""

    def call(*args, **kwargs):
        import importlib

        return getattr(importlib.import_module(f"jaxdrones.training.{module}"), function)(*args, **kwargs)

    return call


def _config_cls(module: str, name: str):
    import importlib

    return getattr(importlib.import_module(f"jaxdrones.training.{module}"), name)


def _functions(module: str, train: str | None = None) -> dict[str, Callable]:
    """A training module's ``train``, ``make_network`` and ``make_policy`` (``train`` from module ``train``)."""
    return dict(
        train=_module_trainer(train or module, "train"),
        make_network=_module_trainer(module, "make_network"),
        make_policy=_module_trainer(module, "make_policy"),
    )


#: Algorithm names of ``jaxdrones train --algo``.
ALGOS = ("ppo", "brax_ppo", "apg", "shac", "mappo", "ippo")
PPO, BRAX_PPO, APG, SHAC, MAPPO, IPPO = ALGOS

#: Our PPO's settings on any task: a local critic (PPO is MAPPO's independent-critic form at one drone), γ = 0.99
#: over 32-step unrolls, 4 epochs of 4 minibatches, learning rate 3e-3 (docs/training.md, "PPO on hover").
PPO_BASE = dict(critic="local", unroll_length=32, minibatches=4, epochs=4, learning_rate=3e-3, discounting=0.99)


def _table() -> dict[str, Trainer]:
    mappo = _config_cls("mappo", "MAPPOConfig")
    return {
        PPO: Trainer(
            PPO, "PPO (ours: one compiled program per chunk of updates)", mappo, **_functions("mappo"), base=PPO_BASE
        ),
        BRAX_PPO: Trainer(
            BRAX_PPO,
            "brax's PPO (brax.training.agents.ppo) through the brax adapter",
            _config_cls("brax_ppo", "BraxPPOConfig"),
            **_functions("brax_ppo"),
            evals_before_training=1,
            num_envs_fields=("num_envs", "batch_size"),
            images=True,
            stochastic=True,
            maps_runs=False,
        ),
        APG: Trainer(
            APG,
            "analytic policy gradients through the simulator (the default for the smooth tasks)",
            _config_cls("apg", "APGConfig"),
            **_functions("apg"),
            differentiable=True,
        ),
        SHAC: Trainer(
            SHAC,
            "short-horizon actor-critic through the simulator",
            _config_cls("shac", "SHACConfig"),
            **_functions("apg", train="shac"),
            differentiable=True,
        ),
        MAPPO: Trainer(
            MAPPO,
            "multi-agent PPO with a centralised critic",
            mappo,
            **_functions("mappo"),
            base={"critic": "central"},
        ),
        IPPO: Trainer(
            IPPO,
            "independent PPO (each agent's critic sees its own observation)",
            mappo,
            **_functions("mappo"),
            base={"critic": "local"},
        ),
    }


def get(algo: str) -> Trainer:
    """The trainer named ``algo``.

    Raises:
        ValueError: an unknown name, listing `ALGOS`.
    """
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    return _table()[algo]


#: What a policy file written before FORMAT 1 holds instead of its algorithm's name: brax's PPO wrote its config
#: under ``"ppo_config"`` (`jaxdrones.training.checkpoint.read_payload`).
LEGACY_CONFIG_KEYS = {"ppo_config": BRAX_PPO}
