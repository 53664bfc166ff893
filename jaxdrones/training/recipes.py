"""How ``jaxdrones train TASK`` trains each task: one recipe per task (`RECIPES`), read in one place.

A task's recipe (`TaskRecipe`) holds, per profile of default settings (``cpu``: few worlds, many small updates;
``gpu``: many worlds, few large updates; `jaxdrones.training.common.DEFAULTS`) and kind of run (plain, under
sim-to-real options, with camera images), a `Setting`: the env's fields, the trainer, and for each trainer tuned on
the task its config's fields and its training env's fields. `recipe` resolves a task and a run's options into a
`Recipe`, the one value that `jaxdrones.training.run.train_task` trains from; the command line applies its flags to
it once (`Recipe.with_options`).

Every setting cites the row of docs/experiments.md (or docs/training.md) whose runs chose it; ``python
benchmarks/training/suite.py`` trains every task at its recipe and writes the suite's table (docs/benchmarks.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from jaxdrones.training.common import check_defaults
from jaxdrones.training.trainers import APG, BRAX_PPO, MAPPO, PPO
from jaxdrones.training.trainers import get as get_trainer


@dataclasses.dataclass(frozen=True)
class Tuned:
    """A trainer's settings on a task.

    Attributes:
        config: fields of the trainer's config over its own (`jaxdrones.training.trainers.Trainer.config`).
        train_env: task config fields of the training env only, for the fields the run's env does not set (wider
            starts than the evaluation's); the evaluation and the saved policy keep the env's.
    """

    config: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    train_env: Mapping[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Setting:
    """How a task trains in one kind of run and profile.

    Attributes:
        algo: the trainer a run takes unless told (`jaxdrones.training.trainers.ALGOS`).
        tuned: per trainer tuned on the task, its `Tuned` settings (``algo``'s among them); a trainer not listed
            runs at its own config.
        env: task config fields of the env the policy is trained in, evaluated in and saved with (under the run's
            own).
    """

    algo: str
    tuned: Mapping[str, Tuned] = dataclasses.field(default_factory=dict)
    env: Mapping[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class TaskRecipe:
    """A task's recipe: its `Setting` per profile, and where they differ, under sim-to-real options and with camera
    images.

    Attributes:
        cpu, gpu: the plain run's settings per profile.
        realism: per profile, the settings of a run under sim-to-real options (``--realism``; absent: the plain
            ones).
        vision: the settings of a run with camera images, either profile (absent: the plain ones where their
            trainer takes images, `Trainer.images`, else `VISION`).
        teams: per team size, the settings per profile of teams of that many drones or more (absent: the plain
            ones).
    """

    cpu: Setting
    gpu: Setting
    realism: Mapping[str, Setting] = dataclasses.field(default_factory=dict)
    vision: Setting | None = None
    teams: Mapping[int, Mapping[str, Setting]] = dataclasses.field(default_factory=dict)

    def setting(self, defaults: str, realism: bool = False, vision: bool = False, n_drones: int = 1) -> Setting:
        """The `Setting` of a run: with camera images `vision`'s, under sim-to-real options `realism`'s for the
        profile, for a team of ``n_drones`` the largest of `teams` it reaches, else the profile's."""
        if vision and self.vision is not None:
            return self.vision
        if realism and defaults in self.realism:
            return self.realism[defaults]
        sizes = [size for size in self.teams if n_drones >= size and defaults in self.teams[size]]
        if sizes:
            return self.teams[max(sizes)][defaults]
        return self.gpu if defaults == "gpu" else self.cpu


# ---------------------------------------------------------------------------------------------------------------
# The trainers' settings that recipes share
# ---------------------------------------------------------------------------------------------------------------

#: APG on a smooth task (a target or a reference to reach, a loss without contacts), ``cpu``: 0.6 M env steps of 16
#: worlds, a step size of 3e-3 decayed to 0 along a half cosine (docs/training.md, "Which trainer for hover", the
#: ``apg`` row; docs/experiments.md, "The suite at its defaults").
APG_CPU = Tuned({"num_timesteps": 600_000, "learning_rate": 3e-3, "cosine_decay": True})
#: APG, ``gpu``: 200 updates of 4096 worlds (26.2 M env steps) at a step size of 1e-2 with the same decay
#: (docs/training.md, "Defaults per device", the ``apg``, 4096 × 200 row).
APG_GPU = Tuned(
    {"num_timesteps": 4096 * 32 * 200, "num_envs": 4096, "learning_rate": 1e-2, "cosine_decay": True, "num_evals": 5}
)
#: APG, ``gpu``, in 64-step windows (100 updates), for the tasks that 32-step windows left short (docs/experiments.md,
#: "The suite at its defaults": the gpu profile).
APG_GPU_LONG = Tuned({**APG_GPU.config, "horizon": 64})
#: APG on the smooth tasks that 0.6 M steps left close to their thresholds: 1.2 M env steps in 64-step windows
#: (docs/experiments.md, "The suite at its defaults").
APG_LONG = Tuned({**APG_CPU.config, "num_timesteps": 1_200_000, "horizon": 64})
#: Our PPO trains hover from wider starts than the task's (docs/training.md, "Defaults per device", the ``ppo`` rows
#: from wider starts).
PPO_HOVER_STARTS = {"start_tilt": 0.8, "start_ang_vel": 2.0}
#: Our PPO on hover, ``cpu``: 512 worlds, 1.2 M env steps (docs/training.md, "Which trainer for hover", the ``ppo``
#: rows); ``gpu``: 8192 worlds, 80 updates (docs/training.md, "Defaults per device", the ``ppo``, 8192 × 100 rows).
PPO_HOVER_CPU = Tuned({"num_timesteps": 1_200_000, "num_envs": 512}, PPO_HOVER_STARTS)
PPO_HOVER_GPU = Tuned({"num_timesteps": 8192 * 32 * 80, "num_envs": 8192, "num_evals": 5}, PPO_HOVER_STARTS)
#: brax's PPO on the tasks without images: 1024 worlds of 10-step unrolls (docs/training.md, "Which trainer for
#: hover", the ``brax_ppo`` row).
BRAX_CPU = {"num_envs": 1024, "batch_size": 1024, "num_minibatches": 8, "unroll_length": 10, "discounting": 0.97}
BRAX_HOVER = Tuned({**BRAX_CPU, "num_timesteps": 2_500_000, "learning_rate": 2e-3})
#: brax's PPO, ``gpu``: one 32-step unroll of 8192 worlds per update, in 4 minibatches, as our PPO's (docs/training.md,
#: "Defaults per device").
BRAX_GPU = Tuned(
    {
        **BRAX_CPU,
        "num_timesteps": 8192 * 32 * 60,
        "num_envs": 8192,
        "batch_size": 2048,
        "num_minibatches": 4,
        "unroll_length": 32,
        "learning_rate": 3e-3,
        "discounting": 0.99,
        "num_evals": 6,
    }
)
#: brax's vision PPO: 256 worlds of 16-step unrolls, the adaptive KL step size, the asymmetric critic
#: (docs/experiments.md, "Vision: the avoid task").
BRAX_VISION = Tuned(
    {
        "num_timesteps": 2_000_000,
        "num_envs": 256,
        "batch_size": 256,
        "num_minibatches": 4,
        "unroll_length": 16,
        "learning_rate": 1e-3,
        "entropy_cost": 1e-3,
        "discounting": 0.98,
        "num_updates_per_batch": 2,
        "policy_hidden_layer_sizes": (64, 64),
        "value_hidden_layer_sizes": (64, 64),
        "num_evals": 9,
        "learning_rate_schedule": "ADAPTIVE_KL",
        "privileged_critic": True,
    }
)
#: ``avoid``: twice the worlds, 4.5 M env steps, the rewards scaled by 0.1, the first convolution at stride 4
#: (docs/experiments.md, "Vision: the avoid task").
BRAX_AVOID = Tuned(
    {
        **BRAX_VISION.config,
        "num_envs": 512,
        "batch_size": 512,
        "num_timesteps": 4_500_000,
        "reward_scaling": 0.1,
        "cnn_stride": (4, 2, 2),
    }
)
#: MAPPO trains multi_hover from body rates up to 1 rad/s (docs/multi-agent.md, after the table).
MULTI_HOVER_STARTS = {"start_ang_vel": 1.0}
#: Under sim-to-real options (hover, velocity): collective thrust and body rates, the integral of the tracking
#: error in the observation, a touch of the ground ends the episode as a crash (docs/experiments.md, "Training
#: under the crazyflie preset").
REALISM_ENV = {"action_type": "ctbr", "error_integral": True, "terminate_on_ground": True}
#: With camera images: brax's vision PPO, every profile.
VISION = Setting(BRAX_PPO, {BRAX_PPO: BRAX_VISION})


def _smooth(env: Mapping[str, Any] | None = None, cpu: Tuned = APG_CPU, gpu: Tuned = APG_GPU, **others: Tuned):
    """``cpu`` and ``gpu`` keywords of the `TaskRecipe` of a smooth task that APG trains, in the env ``env``, at
    ``cpu`` and ``gpu`` (default `APG_CPU`, `APG_GPU`), with ``others``, other trainers' settings for the task."""
    env = dict(env or {})
    return {"cpu": Setting(APG, {APG: cpu, **others}, env), "gpu": Setting(APG, {APG: gpu, **others}, env)}


def _both(setting: Setting) -> dict[str, Setting]:
    """``setting`` for both profiles."""
    return {"cpu": setting, "gpu": setting}


def _with(tuned: Tuned, **config: Any) -> Tuned:
    """``tuned`` with ``config``'s fields over its config's."""
    return Tuned({**tuned.config, **config}, tuned.train_env)


# ---------------------------------------------------------------------------------------------------------------
# One recipe per task
# ---------------------------------------------------------------------------------------------------------------

#: Every built-in task's recipe (the settings' runs: docs/experiments.md, "The suite at its defaults").
RECIPES: dict[str, TaskRecipe] = {
    "hover": TaskRecipe(
        cpu=Setting(APG, {APG: APG_CPU, BRAX_PPO: BRAX_HOVER, PPO: PPO_HOVER_CPU}),
        gpu=Setting(PPO, {PPO: PPO_HOVER_GPU, BRAX_PPO: BRAX_GPU, APG: APG_GPU}),
        # docs/experiments.md, "Training under the crazyflie preset": our PPO, 8 M env steps (cpu) or 160 updates
        # (gpu), its step size decayed to 0; on the cpu 1024 worlds and γ = 0.995 ("Crash-free seeds under the
        # preset": a third of the crashed starts of 512 worlds and γ = 0.99).
        realism={
            "cpu": Setting(
                PPO,
                {
                    PPO: _with(
                        PPO_HOVER_CPU, num_timesteps=8_000_000, anneal_lr=True, num_envs=1024, discounting=0.995
                    ),
                    APG: APG_CPU,
                },
                REALISM_ENV,
            ),
            "gpu": Setting(
                PPO, {PPO: _with(PPO_HOVER_GPU, num_timesteps=8192 * 32 * 160, anneal_lr=True)}, REALISM_ENV
            ),
        },
    ),
    # The firmware's controller is not differentiable (its int16 outputs): our PPO at its own settings, whose
    # policies `jaxdrones export` writes as C (docs/experiments.md, "The suite at its defaults": firmware_hover).
    "firmware_hover": TaskRecipe(**_both(Setting(PPO))),
    "takeoff": TaskRecipe(**_smooth()),
    "velocity": TaskRecipe(
        **_smooth(cpu=APG_LONG),
        # docs/experiments.md, "Training under the crazyflie preset": velocity, APG at its own settings.
        realism={"cpu": Setting(APG, {APG: Tuned()}, REALISM_ENV), "gpu": Setting(APG, {APG: Tuned()}, REALISM_ENV)},
    ),
    "waypoints": TaskRecipe(**_smooth()),
    # The gate's climb from the ground and its reference need more thrust than the rpm action's ±5 %: ctbr
    # (docs/experiments.md, "The suite at its defaults": fly_thru_gate).
    "fly_thru_gate": TaskRecipe(
        **_smooth({"action_type": "ctbr"}, APG_LONG, APG_GPU_LONG),
        # docs/experiments.md, "Vision: the gate drawn per episode".
        vision=Setting(
            BRAX_PPO,
            {BRAX_PPO: BRAX_VISION},
            {
                "gate_pose": "random",
                "action_type": "pid",
                "pid_target": "relative",
                "pid_scale": 0.3,
                "camera_freq": 15.0,
                "episode_len_s": 6.0,
            },
        ),
    ),
    # APG through the tun action's PID lost episodes (docs/experiments.md, "The suite at its defaults").
    "tune": TaskRecipe(cpu=Setting(BRAX_PPO, {BRAX_PPO: BRAX_HOVER}), gpu=Setting(BRAX_PPO, {BRAX_PPO: BRAX_GPU})),
    "avoid": TaskRecipe(**_both(Setting(BRAX_PPO, {BRAX_PPO: BRAX_AVOID}))),
    # APG's shared policy falls short from 7 drones on: MAPPO there, 6 M env steps from body rates up to 1 rad/s
    # (docs/experiments.md, "The suite at its defaults": team sizes; docs/multi-agent.md, the multi_hover rows).
    "multi_hover": TaskRecipe(
        **_smooth(**{MAPPO: Tuned({}, MULTI_HOVER_STARTS)}),
        teams={7: _both(Setting(MAPPO, {MAPPO: Tuned({"num_timesteps": 6_000_000}, MULTI_HOVER_STARTS)}))},
    ),
    # The paper's multi-agent example trains leader_follower with one_d_rpm actions (reference facts §11.4).
    "leader_follower": TaskRecipe(**_both(Setting(MAPPO, {}, {"action_type": "one_d_rpm"}))),
    "flock": TaskRecipe(**_smooth(cpu=APG_LONG)),
    "meetup": TaskRecipe(**_smooth(gpu=APG_GPU_LONG)),
    # The upper drone's downwash exceeds what the rpm action's ±5 % can hold: ctbr (docs/experiments.md, "The
    # suite at its defaults": crossing). APG over 4096 worlds crashed in every evaluation episode (the gpu profile's
    # rows there): the gpu profile keeps the cpu setting.
    "crossing": TaskRecipe(**_smooth({"action_type": "ctbr"}, gpu=APG_CPU)),
}
#: The recipe of a task of your own (`jaxdrones.envs.register`): brax's PPO at hover's settings for one drone,
#: MAPPO for a team.
SINGLE_AGENT_RECIPE = TaskRecipe(
    cpu=Setting(BRAX_PPO, {BRAX_PPO: BRAX_HOVER}), gpu=Setting(BRAX_PPO, {BRAX_PPO: BRAX_GPU})
)
MULTI_AGENT_RECIPE = TaskRecipe(**_both(Setting(MAPPO)))


# ---------------------------------------------------------------------------------------------------------------
# A run's recipe
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Recipe:
    """What a run trains (`jaxdrones.training.run.train_task`'s first argument).

    Attributes:
        task: the task's name.
        algo: the trainer (`jaxdrones.training.trainers.ALGOS`).
        config: the trainer's config.
        env: task config fields of the env the policy is trained in, evaluated in and saved with
            (``jd.make(task, **env)``).
        train_env: task config fields of the training env only (over ``env``).
        defaults: the profile the settings come from (`jaxdrones.training.common.DEFAULTS`).
    """

    task: str
    algo: str
    config: Any
    env: Mapping[str, Any]
    train_env: Mapping[str, Any]
    defaults: str

    def with_options(
        self,
        *,
        seed: int | None = None,
        steps: int | None = None,
        num_envs: int | None = None,
        num_evals: int | None = None,
    ) -> Recipe:
        """The recipe with the command line's options (None: the recipe's): the random seed, the env steps to
        train (``num_timesteps``), the parallel envs (every field of `Trainer.num_envs_fields`) and the
        evaluations over the run (`Trainer.evals_before_training` more, where the trainer counts one before
        training).

        Raises:
            ValueError: a value the trainer's config rejects.
        """
        trainer = get_trainer(self.algo)
        fields: dict[str, Any] = {}
        if seed is not None:
            fields["seed"] = seed
        if steps is not None:
            fields["num_timesteps"] = steps
        if num_envs is not None:
            fields.update(dict.fromkeys(trainer.num_envs_fields, num_envs))
        if num_evals is not None:
            fields["num_evals"] = num_evals + trainer.evals_before_training
        return dataclasses.replace(self, config=dataclasses.replace(self.config, **fields))


def _any_backend(task: str, setting: Setting, defaults: str) -> Setting:
    """``setting`` with a trainer that does not differentiate the simulator: the first such of its tuned trainers,
    else the trainer of `task_recipe`'s default for a task of the kind (`SINGLE_AGENT_RECIPE`, `MULTI_AGENT_RECIPE`)."""
    from jaxdrones.envs import is_multi_agent

    for name in setting.tuned:
        if not get_trainer(name).differentiable:
            return dataclasses.replace(setting, algo=name)
    default = (MULTI_AGENT_RECIPE if is_multi_agent(task) else SINGLE_AGENT_RECIPE).setting(defaults, False, False)
    return dataclasses.replace(default, env=setting.env)


def task_recipe(task: str) -> TaskRecipe:
    """The `TaskRecipe` of ``task``: `RECIPES`' for a built-in task, else `SINGLE_AGENT_RECIPE` or
    `MULTI_AGENT_RECIPE`."""
    from jaxdrones.envs import is_multi_agent

    if task in RECIPES:
        return RECIPES[task]
    return MULTI_AGENT_RECIPE if is_multi_agent(task) else SINGLE_AGENT_RECIPE


def recipe(
    task: str, defaults: str | None = None, env: Mapping[str, Any] | None = None, algo: str | None = None
) -> Recipe:
    """The `Recipe` of a run of ``task``: its `TaskRecipe`'s `Setting` for the profile and the kind of run (the
    env's camera images and sim-to-real options, from ``env`` and the task's own), ``env`` over the setting's env,
    and the trainer (``algo``, or the setting's; on a backend a differentiable trainer cannot differentiate, the
    first of the setting's other trainers that can train there, else the task's kind's default), at the setting's
    config for it (`Trainer.config` with `Tuned.config`) and training env (`Tuned.train_env` for the fields ``env``
    does not set, for actions of more than one entry: a 1-D action cannot level a drone).

    Args:
        task: a registered task's name (`jaxdrones.envs.registered`).
        defaults: ``"cpu"`` or ``"gpu"`` (default: the device's, `jaxdrones.training.trainers.default_profile`).
        env: task config fields of the run (``jd.make`` options, e.g. ``n_drones``, ``vision``, ``realism``).
        algo: one of `jaxdrones.training.trainers.ALGOS` (default: the setting's).

    Raises:
        ValueError: an unknown task, profile, algorithm or env option, or an invalid value.
    """
    from jaxdrones.envs import make_config, registered
    from jaxdrones.envs.actions import ACTION_SIZES
    from jaxdrones.training.trainers import default_profile

    if task not in registered():
        raise ValueError(
            f"train: task must be one of {registered()} (a task of your own: register it with "
            f"jaxdrones.envs.register), got {task!r}"
        )
    defaults = default_profile() if defaults is None else defaults
    check_defaults(defaults)
    requested = dict(env or {})
    kind = make_config(task, **requested)
    entry = task_recipe(task)
    vision = bool(kind.vision)
    setting = entry.setting(defaults, kind.realism is not None, vision, kind.n_drones)
    if vision and not get_trainer(setting.algo).images:
        setting = VISION
    env = {**setting.env, **requested}
    config = make_config(task, **env)
    if algo is None and get_trainer(setting.algo).differentiable and config.backend != "jax":
        setting = _any_backend(task, setting, defaults)
    name = setting.algo if algo is None else algo
    trainer = get_trainer(name)
    tuned = setting.tuned.get(name, Tuned())
    train_env = tuned.train_env if ACTION_SIZES[config.action_type] > 1 else {}
    return Recipe(
        task=task,
        algo=name,
        config=trainer.config(defaults, **tuned.config),
        env=env,
        train_env={k: v for k, v in train_env.items() if k not in env},
        defaults=defaults,
    )


def resolve_recipe(
    task: str | Recipe,
    algo: str | None = None,
    config: Any = None,
    env_overrides: Mapping[str, Any] | None = None,
    train_env_overrides: Mapping[str, Any] | None = None,
    defaults: str | None = None,
) -> Recipe:
    """`jaxdrones.training.run.train_task`'s recipe: ``task`` if it is one (and nothing else is given), else the
    task's (`recipe`) with ``config`` and ``train_env_overrides`` in its place where given.

    Raises:
        ValueError: a `Recipe` with other settings beside it, a ``task`` that is neither a name nor a `Recipe`,
            overrides that are not dicts, or what `recipe` raises.
    """
    given = {
        "algo": algo,
        "config": config,
        "env_overrides": env_overrides,
        "train_env_overrides": train_env_overrides,
        "defaults": defaults,
    }
    for name in ("env_overrides", "train_env_overrides"):
        if given[name] is not None and not isinstance(given[name], Mapping):
            raise ValueError(f"train: {name} must be a dict of task config fields, got {given[name]!r}")
    if isinstance(task, Recipe):
        if any(value is not None for value in given.values()):
            named = ", ".join(name for name, value in given.items() if value is not None)
            raise ValueError(f"train: a Recipe holds the run's settings; set them in it, not as {named}")
        return task
    if not isinstance(task, str):
        raise ValueError(f"train: task must be a task's name (str) or a Recipe, got {task!r}")
    run = recipe(task, defaults, env_overrides, algo)
    if config is not None:
        run = dataclasses.replace(run, config=config)
    if train_env_overrides is not None:
        run = dataclasses.replace(run, train_env={k: v for k, v in train_env_overrides.items() if k not in run.env})
    return run
