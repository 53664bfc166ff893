"""``jaxdrones train TASK``: PPO (brax), analytic policy gradients or short-horizon actor-critic on a single-agent
task, multi-agent PPO on a team, with evaluation and saved outputs."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time

#: Single-agent tasks ``jaxdrones train`` trains (default algorithm: PPO).
SINGLE_AGENT = ("hover", "takeoff", "velocity", "waypoints", "fly_thru_gate", "tune")
#: Multi-agent tasks ``jaxdrones train`` trains (default algorithm: MAPPO).
MULTI_AGENT = ("leader_follower", "multi_hover", "flock", "meetup", "crossing")
TRAINABLE = SINGLE_AGENT + MULTI_AGENT
#: Task settings ``jaxdrones train`` uses unless told otherwise: the paper's multi-agent example trains
#: leader-follower with one_d_rpm actions (docs: reference facts §11.4).
DEFAULT_ENV = {"leader_follower": {"action_type": "one_d_rpm"}}
#: Random starts ``jaxdrones train`` trains from in place of the task's own, for the fields a run does not set and
#: actions of more than one entry (a 1-D action cannot level a drone); the evaluation and the saved policy's env keep
#: the task's starts. In ``multi_hover`` the drone that climbs 1 m does so with its four RPM actions near their +5 %
#: bound, where little authority is left for the attitude, and its policy's own corrections can spin it up in yaw:
#: trained from the task's starts (body rates up to 0.1 rad/s), 8-drone teams lost a drone in 0.4-1.2 % of
#: evaluation episodes (5 runs of 3-6 M env steps, with γ 0.97 or 0.99, learning rate 1e-3 or 3e-4, 64 or 128
#: units); trained from body rates up to 1 rad/s, a policy has met such spins and learned to stop them. (Tilts and
#: speeds up to 0.3 rad and 0.3 m/s as well slowed the 1 m climb's learning: 31 and 15 cm short after 3 and 6 M
#: steps with seed 1.)
TRAIN_STARTS = {"multi_hover": {"start_ang_vel": 1.0}}


def default_ppo(task: str):
    """The tuned `PPOConfig` of a task (the hover settings for tasks without their own)."""
    from jaxdrones.training.ppo import PPOConfig

    tuned = {
        "hover": dict(num_timesteps=2_500_000, num_envs=1024, batch_size=1024, num_minibatches=8, unroll_length=10,
                      learning_rate=2e-3, entropy_cost=1e-3, discounting=0.97),
        "velocity": dict(num_timesteps=4_000_000, num_envs=1024, batch_size=1024, num_minibatches=8,
                         unroll_length=10, discounting=0.97),
        "waypoints": dict(num_timesteps=6_000_000, num_envs=1024, batch_size=1024, num_minibatches=8,
                          unroll_length=10, discounting=0.97),
    }
    return PPOConfig(**tuned.get(task, tuned["hover"]))


#: How the summary names a task's `success_at`.
AGGREGATES = {"final": "final", "mean": "mean over episode", "max": "max over episode"}
#: Training algorithms of ``jaxdrones train --algo``.
ALGOS = ("ppo", "apg", "shac", "mappo", "ippo")


def default_algo(task: str) -> str:
    """``"mappo"`` for a multi-agent task, ``"ppo"`` otherwise."""
    return "mappo" if task in MULTI_AGENT else "ppo"


def _trainer(algo: str):
    """``(config class, default config, train, make_policy, save)`` of a trainer other than PPO."""
    from jaxdrones.training import apg, mappo, shac

    if algo in ("apg", "shac"):
        module = {"apg": apg, "shac": shac}[algo]
        cls = apg.APGConfig if algo == "apg" else shac.SHACConfig
        return cls, cls(), module.train, apg.make_policy, apg.save
    critic = "central" if algo == "mappo" else "local"
    return mappo.MAPPOConfig, mappo.MAPPOConfig(critic=critic), mappo.train, mappo.make_policy, mappo.save


def train_task(task: str = "hover", out: str | None = None, *, overwrite: bool = False, ppo_config=None,
               env_overrides=None, n_eval_episodes: int = 256, progress: bool = True,
               t_start: float | None = None, algo: str | None = None, algo_config=None,
               train_env_overrides: dict | None = None) -> dict:
    """Train a policy on a task and save it with a learning curve, a flight plot and a summary. Algorithms:
    brax's PPO (``algo="ppo"``, on the drones' joint observation and action); through the differentiable simulator,
    analytic policy gradients (``"apg"``, `jaxdrones.training.apg`) or short-horizon actor-critic (``"shac"``,
    `jaxdrones.training.shac`); for teams, multi-agent PPO with a centralised critic (``"mappo"``) or independent
    PPO (``"ippo"``), `jaxdrones.training.mappo`.

    Outputs in a new run folder (see `jaxdrones.runs.new_run_dir`; an existing run is never overwritten unless
    ``overwrite``): ``policy.pkl`` (load with `jaxdrones.training.load_policy`), ``learning_curve.png``,
    ``progress.json``, ``flight.png`` (position against the task's reference, speed and RPMs of one evaluation
    episode) and ``summary.json``.

    Args:
        task: a task name (`TRAINABLE`).
        out: output folder (default ``runs/<task>``).
        overwrite: replace an existing ``out``.
        ppo_config: `PPOConfig` (default `default_ppo`), for PPO.
        env_overrides: task config fields for ``jd.make(task, ...)``, over `DEFAULT_ENV`'s: the env the policy is
            trained in, evaluated in and saved with.
        train_env_overrides: task config fields of the training env only, for the fields ``env_overrides`` does not
            set (default: `TRAIN_STARTS`' for the task unless its action has one entry; ``{}`` trains in the
            evaluation env).
        n_eval_episodes: evaluation episodes from random starts (≥ 64).
        progress: show the progress bar.
        t_start: ``time.perf_counter()`` at which the wall-clock measurement starts (default: now).
        algo: one of `ALGOS` (default `default_algo`).
        algo_config: for ``"apg"`` an `jaxdrones.training.apg.APGConfig`, for ``"shac"`` a
            `jaxdrones.training.shac.SHACConfig`, for ``"mappo"`` and ``"ippo"`` a
            `jaxdrones.training.mappo.MAPPOConfig` with ``critic="central"`` or ``"local"`` (default: the
            class's defaults).

    Returns:
        The summary dict (also written to ``summary.json``): ``wall_time_s`` (everything from ``t_start``:
        imports, compilation, training, evaluation, plots), ``train_time_s``, ``env_steps``, ``success_metric``,
        ``success_value`` (the task's success metric over ``n_eval_episodes`` random starts), ``success`` (that
        value below the task's threshold with no episode terminated early), ``eval`` (all evaluation statistics),
        for distance tasks ``eval_final_pos_error_m``, the output folder and the settings.

    Raises:
        ValueError: bad settings (unknown task, algorithm or env option, fewer than 64 evaluation episodes, ...).
    """
    t_start = time.perf_counter() if t_start is None else t_start
    import jax
    import numpy as np

    from jaxdrones.envs import make
    from jaxdrones.plotting import plot_learning_curve, plot_task_flight
    from jaxdrones.runs import new_run_dir
    from jaxdrones.training.ppo import ProgressLog, evaluate, rollout_policy, save_policy, total_steps, train

    if task not in TRAINABLE:
        raise ValueError(f"train: task must be one of {TRAINABLE}, got {task!r}")
    algo = default_algo(task) if algo is None else algo
    if algo not in ALGOS:
        raise ValueError(f"train: algo must be one of {ALGOS}, got {algo!r}")
    if n_eval_episodes < 64:
        raise ValueError(f"n_eval_episodes must be >= 64, got {n_eval_episodes}")
    if algo == "ppo":
        config = ppo_config or default_ppo(task)
    else:
        config_cls, config, train_fn, make_policy_fn, save_fn = _trainer(algo)
        config = algo_config or config
        if type(config) is not config_cls or getattr(config, "algo", algo) != algo:
            raise ValueError(f"train: algo {algo!r} takes a {config_cls.__name__} for {algo}, got {config!r}")
    env_overrides = {**DEFAULT_ENV.get(task, {}), **(env_overrides or {})}
    env = make(task, **env_overrides)
    if train_env_overrides is None:
        train_env_overrides = TRAIN_STARTS.get(task, {}) if env.action_size > 1 else {}
    train_env_overrides = {k: v for k, v in train_env_overrides.items() if k not in env_overrides}
    train_env = make(task, **env_overrides, **train_env_overrides) if train_env_overrides else env
    if env.config.vision:
        raise ValueError("train: vision observations are not supported by the trainers")
    if algo in ("apg", "shac") and env.config.backend != "jax":
        raise ValueError(f"train: --algo {algo} differentiates the simulator and needs backend='jax'")
    out = new_run_dir(out or os.path.join("runs", task), overwrite=overwrite)

    metric = env.task.success_metric
    log = ProgressLog(total_steps(config) if algo == "ppo" else config.total_steps, metric, enabled=progress)
    t_train = time.perf_counter()
    try:
        if algo == "ppo":
            make_policy, params = train(train_env, config, progress=log, eval_env=env)
            policy = make_policy(params, deterministic=True)
        else:
            network, params = train_fn(train_env, config, progress=log,
                                       evaluate=_policy_evaluation(env, config.seed, make_policy_fn))
            policy = make_policy_fn(network, params)
    finally:
        log.close()
    train_time = time.perf_counter() - t_train

    key_eval, key_flight = jax.random.split(jax.random.key(config.seed + 1))
    stats = evaluate(env, policy, key_eval, n_eval_episodes)
    flight = jax.jit(lambda k: rollout_policy(env, policy, k))(key_flight)
    steps = np.arange(env.episode_length + 1)
    ref = jax.vmap(lambda s: env.task.reference(jax.tree.map(lambda x: x[0], flight.task), s, env.config))(steps)
    times = steps / env.config.ctrl_freq

    if algo == "ppo":
        save_policy(os.path.join(out, "policy.pkl"), params, task, env_overrides, config)
    else:
        save_fn(os.path.join(out, "policy.pkl"), params, task, env_overrides, config)
    log.save(os.path.join(out, "progress.json"))
    label = f"{metric} ({AGGREGATES[env.task.success_at]})"
    curve = _curve_aggregate(env, brax_ppo=algo == "ppo")
    plot_learning_curve(log.history, os.path.join(out, "learning_curve.png"), metric="metric",
                        metric_label=f"evaluation {metric} ({curve} over episode)",
                        title=f"{algo.upper()} on {task} ({env.config.model}, {env.config.action_type})")
    plot_task_flight(times, flight.sim.pos, ref.pos, flight.sim.vel, flight.sim.rpm, os.path.join(out, "flight.png"),
                     title=f"{task}: evaluation flight")
    value = stats.get("success_value", math.nan)
    summary = {
        "task": task,
        "wall_time_s": time.perf_counter() - t_start,
        "train_time_s": train_time,
        "algo": algo,
        "env_steps": int(log.history[-1]["env_steps"]) if log.history else config.num_timesteps,
        "success_metric": label,
        "success_value": value,
        "success_threshold": env.task.success_threshold,
        "success": bool(value < env.task.success_threshold and stats["terminated_rate"] == 0.0),
        "eval": stats,
        "out_dir": out,
        "env": json.loads(json.dumps(dataclasses.asdict(env.config), default=str)),
        "train_env_overrides": train_env_overrides,
        algo: dataclasses.asdict(config),
        "devices": [str(d) for d in jax.devices()],
    }
    if "final_pos_error_m" in stats:
        summary["eval_final_pos_error_m"] = stats["final_pos_error_m"]
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    return summary


def _policy_evaluation(env, seed: int, make_policy):
    """Evaluation of the policy ``make_policy(network, params)`` at each learning-curve point of a trainer other
    than brax's PPO, as the brax-style metrics `ProgressLog` reads: 64 episodes from random starts, the task's
    metric averaged over each episode (its maximum for a task judged at the maximum); compiled once for the run."""
    import jax

    from jaxdrones.training.ppo import episode_outcomes, episode_statistics

    keys = jax.random.split(jax.random.split(jax.random.key(seed + 2))[0], 64)
    metric = env.task.success_metric
    compiled = {}

    def run(network, params) -> dict:
        if "outcomes" not in compiled:
            compiled["outcomes"] = jax.jit(lambda p: episode_outcomes(env, make_policy(network, p), keys))
        stats = episode_statistics(env, compiled["outcomes"](params))
        return {"eval/episode_reward": stats["episode_reward"],
                f"eval/episode_{metric}": stats[f"{_curve_aggregate(env, brax_ppo=False)}_{metric}"],
                "eval/avg_episode_length": 1.0}

    return run


def _curve_aggregate(env, brax_ppo: bool) -> str:
    """How the learning curve aggregates the metric over an episode: ``"max"`` for a task judged at the maximum
    trained by our own trainers, else ``"mean"`` (brax's PPO reports episode means)."""
    return "max" if env.task.success_at == "max" and not brax_ppo else "mean"


def register(subparsers) -> None:
    """Add the ``train`` subcommand to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "train", help="train a policy with batched PPO (brax), APG, SHAC or multi-agent PPO",
        description="Train a policy on a jaxdrones task with brax's PPO, through the differentiable simulator with "
                    "APG or SHAC, or a team with multi-agent PPO; then evaluate it and save the policy, "
                    "a learning curve, an evaluation flight plot and summary.json in a new run folder.")
    parser.add_argument("task", choices=TRAINABLE, help="task to train")
    ppo = parser.add_argument_group("training")
    ppo.add_argument("--algo", choices=ALGOS, default=None,
                     help="ppo (brax's batched PPO, the default for single-agent tasks), apg (analytic policy "
                          "gradients through the simulator), shac (short-horizon actor-critic through the simulator), "
                          "mappo (multi-agent PPO with a centralised critic, the default for multi-agent tasks) or "
                          "ippo (independent PPO)")
    ppo.add_argument("--steps", type=int, default=None, help="env steps to train (default: the task's tuned budget)")
    ppo.add_argument("--num-envs", type=int, default=None, help="parallel environments")
    ppo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ppo.add_argument("--eval-episodes", type=int, default=256, help="evaluation episodes, >= 64 (default 256)")
    env = parser.add_argument_group("task")
    env.add_argument("--action-type", default=None, help="action type (default: the task's): rpm, one_d_rpm (the "
                     "paper's 1-D hover setting), pid, one_d_pid, vel, thrust_torque, one_d_thrust, tun, ctbr")
    env.add_argument("--obs-type", default=None, help="observation type (default: the task's): kin, kin_norm, "
                     "kin_rotmat, neighbors")
    env.add_argument("--model", default=None, help="drone model name (cf2x, cf2p, racer) or URDF path")
    env.add_argument("--num-drones", type=int, default=None,
                     help="drones per world (single-agent tasks: 1; multi-agent tasks: 2 by default)")
    env.add_argument("--ctrl-freq", type=int, default=None, help="control rate, Hz (default 30)")
    env.add_argument("--episode-len", type=float, default=None, help="episode length, s")
    env.add_argument("--reward", choices=("shaped", "paper"), default=None,
                     help="shaped (default, for fast learning) or the paper's reward")
    for effect in ("drag", "ground-effect", "downwash"):
        env.add_argument(f"--{effect}", action=argparse.BooleanOptionalAction, default=None,
                         help=f"aerodynamic effect {effect.replace('-', ' ')} on, or off with --no-{effect} "
                              f"(default: the task's; downwash is on in crossing)")
    env.add_argument("--max-neighbors", type=int, default=None, metavar="K",
                     help="neighbors observation of the K nearest drones only (default: every drone)")
    env.add_argument("--downwash-radius", type=float, default=None, metavar="R",
                     help="downwash cut-off in m, with a neighbour list: a cost linear in the team size (default: "
                          "every pair of drones within 10 m, the original)")
    env.add_argument("--backend", choices=("jax", "pybullet"), default=None, help="physics backend (default jax)")
    env.add_argument("--target", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                     help="hover/takeoff target, m")
    env.add_argument("--start-pos-range", type=float, nargs=3, default=None, metavar=("DX", "DY", "DZ"),
                     help="half-widths of random start positions, m")
    env.add_argument("--start-tilt", type=float, default=None, help="largest random start tilt, rad")
    env.add_argument("--start-yaw", type=float, default=None, help="half-width of the random start yaw, rad")
    env.add_argument("--start-vel", type=float, default=None, help="half-width of random start velocities, m/s")
    env.add_argument("--start-ang-vel", type=float, default=None,
                     help="half-width of random start body rates, rad/s (default: the task's; multi_hover trains from "
                          "1 rad/s and is evaluated from its own 0.1)")
    out = parser.add_argument_group("output")
    out.add_argument("--out", default=None, help="output folder (default runs/TASK; a numbered sibling is used if "
                                                 "it exists, unless --overwrite)")
    out.add_argument("--overwrite", action="store_true", help="replace the contents of an existing --out")
    out.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.set_defaults(func=run_cli)


_ENV_OPTIONS = {"action_type": "action_type", "obs_type": "obs_type", "model": "model", "num_drones": "n_drones",
                "ctrl_freq": "ctrl_freq", "episode_len": "episode_len_s", "reward": "reward", "backend": "backend",
                "target": "target", "start_pos_range": "start_pos_range", "start_tilt": "start_tilt",
                "start_yaw": "start_yaw", "start_vel": "start_vel", "start_ang_vel": "start_ang_vel",
                "max_neighbors": "max_neighbors", "downwash_radius": "downwash_radius", "drag": "drag",
                "ground_effect": "ground_effect", "downwash": "downwash"}


def _positive(name: str, value) -> None:
    if value is not None and value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value}")


def run_cli(args: argparse.Namespace) -> int:
    """Run ``jaxdrones train``; returns the exit status (0 also when the run did not reach the threshold)."""
    try:
        _positive("--steps", args.steps)
        _positive("--num-envs", args.num_envs)
        _positive("--eval-episodes", args.eval_episodes)
        algo = default_algo(args.task) if args.algo is None else args.algo
        overrides = {"seed": args.seed}
        if args.steps is not None:
            overrides["num_timesteps"] = args.steps
        if args.num_envs is not None:
            overrides["num_envs"] = args.num_envs
            if algo == "ppo":
                overrides["batch_size"] = args.num_envs
        env = {field: getattr(args, arg) for arg, field in _ENV_OPTIONS.items() if getattr(args, arg) is not None}
        if "target" in env and args.task not in ("hover", "takeoff"):
            raise ValueError(f"--target applies to hover and takeoff, not {args.task}")
        if algo == "ppo":
            configs = {"ppo_config": dataclasses.replace(default_ppo(args.task), **overrides)}
        else:
            configs = {"algo_config": dataclasses.replace(_trainer(algo)[1], **overrides)}
        summary = train_task(args.task, args.out, overwrite=args.overwrite, env_overrides=env,
                             n_eval_episodes=args.eval_episodes, progress=not args.no_progress,
                             t_start=getattr(args, "t_start", None), algo=algo, **configs)
    except (ValueError, OSError) as err:
        print(f"jaxdrones train: error: {err}", file=sys.stderr)
        return 2
    verdict = "solved" if summary["success"] else "not solved"
    stats = summary["eval"]
    print(f"{verdict}: {summary['success_metric']} {summary['success_value']:.4g} (threshold "
          f"{summary['success_threshold']:g}) over {stats['n_episodes']} random starts "
          f"({stats['terminated_rate']:.1%} terminated), {summary['env_steps']:,} env steps, "
          f"{summary['wall_time_s']:.1f} s wall time")
    print(f"saved policy.pkl, learning_curve.png, flight.png, summary.json in {summary['out_dir']}")
    return 0
