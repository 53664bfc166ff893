"""``jaxdrones train hover``: PPO on the take-off-and-hover task, with evaluation and saved outputs."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

#: Mean final distance to the target (m) over the evaluation episodes below which a run counts as solved.
SUCCESS_THRESHOLD_M = 0.05


def train_hover(out: str = "runs/hover", *, overwrite: bool = False, ppo_config=None, env_overrides=None,
                n_eval_episodes: int = 256, progress: bool = True, t_start: float | None = None) -> dict:
    """Train a hover policy with PPO and save the policy, a learning curve, an evaluation flight and a summary.

    Outputs in a new run folder (see `jaxdrones.runs.new_run_dir`; an existing run is never overwritten unless
    ``overwrite``): ``policy.pkl`` (load with `jaxdrones.training.load_policy`), ``learning_curve.png``,
    ``progress.json``, ``flight.png`` (z, vz and RPMs of one episode from the paper's start pose
    (0, 0, 0.1125) m) and ``summary.json``.

    Args:
        out: output folder.
        overwrite: replace an existing ``out``.
        ppo_config: `PPOConfig` (default: the tuned hover settings).
        env_overrides: `HoverConfig` fields for ``jd.make("hover", ...)``.
        n_eval_episodes: evaluation episodes from random starts (≥ 64).
        progress: show the progress bar.
        t_start: ``time.perf_counter()`` at which the wall-clock measurement starts (default: now).

    Returns:
        The summary dict (also written to ``summary.json``): ``wall_time_s`` (everything from ``t_start``:
        imports, compilation, training, evaluation, plots), ``train_time_s``, ``env_steps``,
        ``eval_final_pos_error_m`` (mean over ``n_eval_episodes`` random starts), ``success``
        (that mean < 5 cm with no episode terminated early), the output folder and the settings.

    Raises:
        ValueError: bad settings (e.g. fewer than 64 evaluation episodes, unknown env option).
    """
    t_start = time.perf_counter() if t_start is None else t_start
    import jax
    import numpy as np

    from jaxdrones.envs import make
    from jaxdrones.plotting import plot_hover_flight, plot_learning_curve
    from jaxdrones.runs import new_run_dir
    from jaxdrones.training.ppo import PPOConfig, ProgressLog, evaluate, rollout_policy, save_policy, train

    if n_eval_episodes < 64:
        raise ValueError(f"n_eval_episodes must be >= 64, got {n_eval_episodes}")
    config = ppo_config or PPOConfig()
    env_overrides = dict(env_overrides or {})
    env = make("hover", **env_overrides)
    out = new_run_dir(out, overwrite=overwrite)

    log = ProgressLog(config.num_timesteps, env.episode_length, enabled=progress)
    t_train = time.perf_counter()
    try:
        make_policy, params = train(env, config, progress=log)
    finally:
        log.close()
    train_time = time.perf_counter() - t_train
    policy = make_policy(params, deterministic=True)

    key_eval, key_flight = jax.random.split(jax.random.key(config.seed + 1))
    stats = evaluate(env, policy, key_eval, n_eval_episodes)

    start = env.reset(key_flight)
    start = start.replace(sim=start.sim.replace(pos=start.sim.pos.at[0].set(np.array([0.0, 0.0, 0.1125])),
                                                vel=start.sim.vel * 0))
    flight = jax.jit(lambda k, s: rollout_policy(env, policy, k, s))(key_flight, start)
    times = np.arange(env.episode_length + 1) / env.config.ctrl_freq

    save_policy(os.path.join(out, "policy.pkl"), params, "hover", env_overrides, config)
    log.save(os.path.join(out, "progress.json"))
    plot_learning_curve(log.history, os.path.join(out, "learning_curve.png"),
                        title=f"PPO on hover ({env.config.model}, {env.config.action_type})")
    plot_hover_flight(times, flight.sim.pos[:, 0], flight.sim.vel[:, 0], flight.sim.rpm[:, 0],
                      env.config.target[2], os.path.join(out, "flight.png"),
                      title="Evaluation flight from (0, 0, 0.1125) m")
    summary = {
        "wall_time_s": time.perf_counter() - t_start,
        "train_time_s": train_time,
        "env_steps": int(log.history[-1]["env_steps"]) if log.history else config.num_timesteps,
        "eval_final_pos_error_m": stats["final_pos_error_m"],
        "success": bool(stats["final_pos_error_m"] < SUCCESS_THRESHOLD_M and stats["terminated_rate"] == 0.0),
        "eval": stats,
        "flight_final_pos_error_m": float(flight.metrics["distance"][-1]),
        "out_dir": out,
        "env": dataclasses.asdict(env.config),
        "ppo": dataclasses.asdict(config),
        "devices": [str(d) for d in jax.devices()],
    }
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    return summary


def register(subparsers) -> None:
    """Add the ``train`` subcommand to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "train", help="train a policy with batched PPO (brax)",
        description="Train a policy with brax's PPO on a jaxdrones task, then evaluate it and save the policy, "
                    "a learning curve, an evaluation flight plot and summary.json in a new run folder.")
    parser.add_argument("task", choices=["hover"], help="task to train")
    parser.add_argument("--steps", type=int, default=None, help="env steps to train (default: the tuned budget)")
    parser.add_argument("--num-envs", type=int, default=None, help="parallel environments")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--action-type", choices=["one_d_rpm", "rpm"], default="one_d_rpm",
                        help="one_d_rpm (the paper's hover default) or rpm (one action per motor)")
    parser.add_argument("--model", default="cf2x", help="drone model name or URDF path (default cf2x)")
    parser.add_argument("--eval-episodes", type=int, default=256, help="evaluation episodes, >= 64 (default 256)")
    parser.add_argument("--out", default="runs/hover", help="output folder (default runs/hover; a numbered "
                                                              "sibling is used if it exists, unless --overwrite)")
    parser.add_argument("--overwrite", action="store_true", help="replace the contents of an existing --out")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    """Run ``jaxdrones train``; returns the exit status (0 also when the run did not reach the threshold)."""
    from jaxdrones.training.ppo import PPOConfig

    overrides = {"seed": args.seed}
    if args.steps is not None:
        overrides["num_timesteps"] = args.steps
    if args.num_envs is not None:
        overrides["num_envs"] = overrides["batch_size"] = args.num_envs
    try:
        config = dataclasses.replace(PPOConfig(), **overrides)
        summary = train_hover(args.out, overwrite=args.overwrite, ppo_config=config,
                              env_overrides={"action_type": args.action_type, "model": args.model},
                              n_eval_episodes=args.eval_episodes, progress=not args.no_progress,
                              t_start=getattr(args, "t_start", None))
    except ValueError as err:
        print(f"jaxdrones train: error: {err}")
        return 2
    verdict = "solved" if summary["success"] else "not solved"
    print(f"{verdict}: mean final position error {100 * summary['eval_final_pos_error_m']:.2f} cm over "
          f"{summary['eval']['n_episodes']} random starts ({summary['eval']['terminated_rate']:.0%} terminated), "
          f"{summary['env_steps']:,} env steps, {summary['wall_time_s']:.1f} s wall time")
    print(f"saved policy.pkl, learning_curve.png, flight.png, summary.json in {summary['out_dir']}")
    return 0
