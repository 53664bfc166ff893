"""The table of trainers: every algorithm ``jaxdrones train --algo`` runs, with its config class, its default settings
per task and device, how it trains, and how its saved parameters become a policy.

A trainer's ``train(env, config, progress, evaluate) -> (network, params)`` calls ``progress(env_steps, metrics)``
after each of its ``config.num_evals`` chunks of updates, with its training metrics (floats) and, under
``"eval"``, the arrays that ``evaluate(network, params)`` returned (compiled and called after each chunk; e.g.
`jaxdrones.training.evaluation.episode_outcomes` of ``make_policy(network, params)``); on Ctrl-C it raises
`jaxdrones.training.common.Interrupted` with the result of the last completed chunk.
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

#: The built-in tasks ``jaxdrones train`` trains: the single-agent ones (default algorithm: `default_algo`) and the
#: multi-agent ones (default algorithm: MAPPO); it trains a task of your own too (`jaxdrones.envs.register`).
TRAINABLE = SINGLE_AGENT + MULTI_AGENT


@dataclasses.dataclass(frozen=True)
class Trainer:
    """One algorithm of the table (see the module doc)."""

    name: str
    description: str
    config_cls: type
    #: (task, vision=False, defaults="cpu") → the trainer's config for the task (with camera images if vision), from
    #: the `DEFAULTS` profile ``defaults``.
    default_config: Callable[..., Any]
    train: Callable
    make_network: Callable
    make_policy: Callable


def gpu_build(config_cls: type) -> dict[str, bool]:
    """The build settings of a trainer's config class with ``defaults="gpu"``: every one of `BUILD_SETTINGS` it
    has, on."""
    fields = {field.name for field in dataclasses.fields(config_cls)}
    return {name: True for name in BUILD_SETTINGS if name in fields}


def default_profile() -> str:
    """The `DEFAULTS` profile of JAX's default device: ``"gpu"`` on a GPU or TPU, else ``"cpu"``."""
    import jax

    return "cpu" if jax.default_backend() == "cpu" else "gpu"


def _ppo_config(task: str, vision: bool = False, defaults: str = "cpu"):
    """Our PPO's settings: a local critic (PPO is MAPPO's independent-critic form at one drone), γ = 0.99 over
    32-step unrolls, 4 epochs of 4 minibatches, learning rate 3e-3. ``cpu``: tuned for the fewest seconds to a solved
    3-D hover on 2 CPU cores (512 worlds, 1.3 M env steps; see the table in docs/training.md); ``gpu``: 8192 worlds,
    80 updates (21.0 M env steps, 5 evaluations): after 60 updates runs on an H200 ended 0.3-6.8 cm from the target
    (the same settings, rounded differently), after 70-100 on 2 CPU cores 0.2-0.7 cm (docs/training.md)."""
    from jaxdrones.training.mappo import MAPPOConfig

    check_defaults(defaults)
    common = dict(critic="local", unroll_length=32, minibatches=4, epochs=4, learning_rate=3e-3, discounting=0.99)
    if defaults == "gpu":
        return MAPPOConfig(num_timesteps=8192 * 32 * 80, num_envs=8192, num_evals=5, **common, **gpu_build(MAPPOConfig))
    return MAPPOConfig(num_timesteps=1_200_000, num_envs=512, **common)


def _brax_ppo_config(task: str, vision: bool = False, defaults: str = "cpu"):
    from jaxdrones.training.brax_ppo import default_config

    return default_config(task, vision, defaults)


def _mappo_config(critic: str):
    def config(task: str, vision: bool = False, defaults: str = "cpu"):
        from jaxdrones.training.mappo import MAPPOConfig

        check_defaults(defaults)
        return MAPPOConfig(critic=critic)

    return config


def _apg_config(task: str, vision: bool = False, defaults: str = "cpu"):
    """APG's defaults; for hover, the settings that solved it fastest: ``cpu``, on 2 CPU cores: 0.6 M env steps of
    16 worlds, a step size of 3e-3 decayed to 0 along a half cosine (seeds 0-2 all solved, 1.4-2.5 cm; without the
    decay 0.8 M steps at 2e-3 ended 2.2-4.2 cm, and 0.5 M steps with it lost a drone in 0.8 % of the episodes of seed
    1); ``gpu``, in the fewest updates: 200 updates of 4096 worlds (26.2 M env steps) at a step size of 1e-2 with
    the same decay (8192 worlds in 120 updates, or 16-step windows, ended 11-12 cm short: docs/training.md)."""
    from jaxdrones.training.apg import APGConfig

    check_defaults(defaults)
    if task == "hover" and defaults == "gpu":
        return APGConfig(
            num_timesteps=4096 * 32 * 200,
            num_envs=4096,
            learning_rate=1e-2,
            cosine_decay=True,
            num_evals=5,
            **gpu_build(APGConfig),
        )
    if task == "hover":
        return APGConfig(num_timesteps=600_000, learning_rate=3e-3, cosine_decay=True)
    return APGConfig()


def _shac_config(task: str, vision: bool = False, defaults: str = "cpu"):
    from jaxdrones.training.shac import SHACConfig

    check_defaults(defaults)
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
    mappo_kw = dict(
        train=_module_trainer("mappo", "train"),
        make_network=_module_trainer("mappo", "make_network"),
        make_policy=_module_trainer("mappo", "make_policy"),
    )
    apg_kw = dict(
        make_network=_module_trainer("apg", "make_network"), make_policy=_module_trainer("apg", "make_policy")
    )
    return {
        "ppo": Trainer(
            "ppo",
            "PPO (ours: one compiled program per chunk of updates)",
            _config_cls("mappo", "MAPPOConfig"),
            _ppo_config,
            **mappo_kw,
        ),
        "brax_ppo": Trainer(
            "brax_ppo",
            "brax's PPO (brax.training.agents.ppo) through the brax adapter",
            _config_cls("brax_ppo", "BraxPPOConfig"),
            _brax_ppo_config,
            _module_trainer("brax_ppo", "train"),
            _module_trainer("brax_ppo", "make_network"),
            _module_trainer("brax_ppo", "make_policy"),
        ),
        "apg": Trainer(
            "apg",
            "analytic policy gradients through the simulator (the default for hover)",
            _config_cls("apg", "APGConfig"),
            _apg_config,
            _module_trainer("apg", "train"),
            **apg_kw,
        ),
        "shac": Trainer(
            "shac",
            "short-horizon actor-critic through the simulator",
            _config_cls("shac", "SHACConfig"),
            _shac_config,
            _module_trainer("shac", "train"),
            **apg_kw,
        ),
        "mappo": Trainer(
            "mappo",
            "multi-agent PPO with a centralised critic (the default for multi-agent tasks)",
            _config_cls("mappo", "MAPPOConfig"),
            _mappo_config("central"),
            **mappo_kw,
        ),
        "ippo": Trainer(
            "ippo",
            "independent PPO (each agent's critic sees its own observation)",
            _config_cls("mappo", "MAPPOConfig"),
            _mappo_config("local"),
            **mappo_kw,
        ),
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


#: The default algorithm of a single-agent task per `DEFAULTS` profile: on a few CPU cores the fastest to a solved
#: hover is APG (see the table in docs/training.md); on a GPU, where the sequential operations of the updates are the
#: cost, our PPO, which solves hover in the fewest of them (80 updates; `benchmarks/train_cost.py`). The other
#: single-agent tasks keep brax's PPO, with the settings it was tuned with for them
#: (`jaxdrones.training.brax_ppo.default_config`).
DEFAULT_ALGO = {"cpu": {"hover": "apg"}, "gpu": {"hover": "ppo"}}


#: How ``jaxdrones train`` trains a task under sim-to-real options (``--realism``; the task's side, the action and
#: the memory, is `jaxdrones.training.run.REALISM_ENV`): the algorithm, and the fields of its config per `DEFAULTS`
#: profile over `Trainer.default_config`'s. Hover under the ``crazyflie`` preset (2 CPU cores, ctbr actions with the
#: error integral, docs/experiments.md): APG plateaued 5.9-6.1 cm from the target after 2 M env steps (its
#: squared-distance loss barely pulls at a few cm); our PPO at its hover settings reached 3.3 and 7.3 cm (seeds 0, 1;
#: 1.2 % crashed) in 8 M env steps, and with its step size decayed to 0 over the run (``anneal_lr``) 2.2 cm for seed 1
#: with none crashed, within 5 cm from 4.8 M steps on. Velocity: APG at its defaults (1 M env steps) tracked the
#: command within 0.081 m/s with the integral and 0.124 m/s without it; our PPO at its hover settings (0.73 m/s after
#: 8 M) and brax's PPO at its velocity settings (1.13 m/s, 31 % crashed) learned to hover, not to track.
#: Hover's ``gpu`` profile trains 160 updates of 8192 worlds, twice the default hover's: on an H200 at 80 updates
#: 3.6 cm, at 160 2.1-3.9 cm (two runs of seeds 0-2; docs/experiments.md).
REALISM_TRAINING = {
    "hover": (
        "ppo",
        {
            "cpu": {"num_timesteps": 8_000_000, "anneal_lr": True},
            "gpu": {"num_timesteps": 8192 * 32 * 160, "anneal_lr": True},
        },
    ),
    "velocity": ("apg", {"cpu": {}, "gpu": {}}),
}


def default_algo(
    task: str, backend: str = "jax", vision: bool = False, defaults: str = "cpu", realism: bool = False
) -> str:
    """``"mappo"`` for a multi-agent task; for a single-agent one `DEFAULT_ALGO`'s for the ``defaults`` profile
    (``"brax_ppo"`` if none, on the PyBullet backend, which APG cannot differentiate, and with camera images, which
    brax's vision PPO takes); with sim-to-real options (``realism``) on the JAX backend, `REALISM_TRAINING`'s."""
    from jaxdrones.envs import is_multi_agent

    check_defaults(defaults)
    if is_multi_agent(task):
        return "mappo"
    if realism and task in REALISM_TRAINING and backend == "jax" and not vision:
        return REALISM_TRAINING[task][0]
    algo = DEFAULT_ALGO[defaults].get(task, "brax_ppo")
    return "brax_ppo" if (backend != "jax" or vision) and algo in ("apg", "shac") else algo


def run_config(trainer: Trainer, task: str, vision: bool = False, defaults: str = "cpu", realism: bool = False) -> Any:
    """The config a ``jaxdrones train`` run of ``task`` starts from: `Trainer.default_config`'s, with
    `REALISM_TRAINING`'s fields for the profile under sim-to-real options (``realism``) when ``trainer`` is the
    task's algorithm there."""
    config = trainer.default_config(task, vision, defaults)
    algo, fields = REALISM_TRAINING.get(task, (None, {}))
    if realism and trainer.name == algo:
        config = dataclasses.replace(config, **fields[defaults])
    return config
