"""Stable-Baselines3 (or sbx) PPO on the hover env: env steps, wall time and final distance to the target.

``--vec make_vec_env`` (default): SB3's PPO with its default hyperparameters trains ``jaxdrones/Hover-v0`` through
SB3's own ``make_vec_env(id, n_envs=4, env_kwargs=...)`` (a ``DummyVecEnv`` of four gymnasium envs, each a
`GymnasiumEnv` stepping one world). ``--vec jaxdrones``: PPO trains on `jaxdrones.adapters.sb3.VecEnv` (all
``--n-envs`` worlds, default 256, in one jitted call per step, wrapped in SB3's ``VecMonitor``), with rollouts of
``--n-steps`` (default 32) and minibatches of ``--batch-size`` (default 256), SB3's other defaults.
``--algo sbx`` takes sbx's PPO (JAX) instead of SB3's (torch). ``--baseline-steps N`` first times SB3's PPO
(default hyperparameters) on ``make_vec_env`` with 8 envs for N env steps in the same process, for the env-steps/s
of both routes side by side. Training stops at checkpoints (every ``--eval-every`` env steps) to evaluate the
deterministic policy on ``--eval-episodes`` episodes of a separate env, the final distance to the target being
``info["distance"]`` at the last step of each episode. Every checkpoint is printed and the JSON file is rewritten,
so a run that is stopped early keeps what it reached.

PPO collects whole rollouts of ``n_steps · n_envs`` = 2048 · 4 = 8192 env steps, so the step counts are rounded
down to multiples of that: ``--steps 200000`` trains 24 rollouts (196,608 steps). Wall times are of training
only (the first rollout includes the JIT compilation of the four envs), with the process's CPU time beside them
(less sensitive to other work on the machine) and the load average; evaluation time is reported apart.

torch runs with one intra-op thread (``--torch-threads 1``). In a process where JAX has started its CPU backend,
torch's default (one thread per core) made SB3's PPO several times slower on a shared 2-core CPU: 4096 steps of
PPO on gymnasium's Pendulum-v1 (n_steps=512, 4 envs) took 62 s with 2 torch threads and JAX initialised, 7.7 s
with 2 threads and no JAX, 5.1 s with 1 thread and JAX, 3.2 s with 1 thread and no JAX.

    python benchmarks/training/sb3_hover.py --action-type one_d_rpm --steps 200000      # the paper's 1-D hover
    python benchmarks/training/sb3_hover.py --action-type rpm --steps 1000000 --eval-every 250000  # the 3-D task
    python benchmarks/training/sb3_hover.py --vec jaxdrones --steps 300000 --baseline-steps 16384  # batched
    python benchmarks/training/sb3_hover.py --vec jaxdrones --algo sbx --steps 300000 --baseline-steps 16384

Needs the ``sb3`` extra: ``pip install torch==2.13.0 && pip install -e ".[sb3]"``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import gymnasium as gym
import numpy as np

import jaxdrones  # registers the gymnasium ids, e.g. jaxdrones/Hover-v0

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS  # noqa: E402

ENV_ID = "jaxdrones/Hover-v0"


def evaluate(model, env_kwargs: dict, n_episodes: int, seed: int) -> dict:
    """Run ``n_episodes`` deterministic episodes; statistics of ``info["distance"]`` at their last step (m)."""
    env = gym.make(ENV_ID, **env_kwargs)
    final, returns, lengths, terminated_early = [], [], [], 0
    obs, info = env.reset(seed=seed)
    for _ in range(n_episodes):
        ret, length = 0.0, 0
        while True:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += reward
            length += 1
            if terminated or truncated:
                break
        final.append(info["distance"])
        returns.append(ret)
        lengths.append(length)
        terminated_early += bool(terminated)
        obs, info = env.reset()
    env.close()
    final = np.asarray(final)
    return {
        "final_distance_mean_m": float(final.mean()),
        "final_distance_median_m": float(np.median(final)),
        "final_distance_max_m": float(final.max()),
        "final_distance_m": final.tolist(),
        "episode_return_mean": float(np.mean(returns)),
        "episode_length_mean": float(np.mean(lengths)),
        "terminated_early": terminated_early,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n")[0])
    parser.add_argument("--action-type", default="one_d_rpm", help="one_d_rpm (1-D, level starts) or rpm (3-D)")
    parser.add_argument("--obs-type", default=None, help="observation type (default: the env's, kin_rotmat)")
    parser.add_argument("--steps", type=int, default=200_000, help="at most this many env steps (default 200000)")
    parser.add_argument(
        "--eval-every", type=int, default=None, help="env steps between evaluations (default: only at the end)"
    )
    parser.add_argument("--eval-episodes", type=int, default=10, help="evaluation episodes (default 10)")
    parser.add_argument(
        "--vec", choices=("make_vec_env", "jaxdrones"), default="make_vec_env", help="the vectorised env (see above)"
    )
    parser.add_argument("--algo", choices=("sb3", "sbx"), default="sb3", help="SB3's PPO (torch) or sbx's (JAX)")
    parser.add_argument(
        "--n-envs", type=int, default=None, help="envs of make_vec_env (default 4) or worlds of VecEnv (default 256)"
    )
    parser.add_argument("--n-steps", type=int, default=None, help="PPO's rollout per env (default: 2048 / 32)")
    parser.add_argument("--batch-size", type=int, default=None, help="PPO's minibatch (default: 64 / 256)")
    parser.add_argument(
        "--baseline-steps", type=int, default=0, help="first time make_vec_env(8) with SB3's PPO for this many steps"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of PPO and of the envs (default 0)")
    parser.add_argument(
        "--torch-threads", type=int, default=1, help="torch intra-op threads (default 1; 0: torch's default)"
    )
    parser.add_argument("--out", default=None, help="JSON file (default benchmarks/results/sb3_hover_<action>.json)")
    args = parser.parse_args(argv)

    import stable_baselines3
    import torch
    from stable_baselines3 import PPO as SB3PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecMonitor

    from jaxdrones.adapters.sb3 import VecEnv

    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    env_kwargs = {"action_type": args.action_type}
    if args.obs_type:
        env_kwargs["obs_type"] = args.obs_type
    batched = args.vec == "jaxdrones"
    suffix = f"_{args.vec}_{args.algo}" if batched or args.algo != "sb3" else ""
    out = args.out or os.path.join(RESULTS, f"sb3_hover_{args.action_type}{suffix}.json")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)

    baseline = None
    if args.baseline_steps:
        venv = make_vec_env(ENV_ID, n_envs=8, seed=args.seed, env_kwargs=env_kwargs)
        model = SB3PPO("MlpPolicy", venv, seed=args.seed, device="cpu")
        t = time.perf_counter()
        model.learn(args.baseline_steps)
        seconds = time.perf_counter() - t
        baseline = {"vec": "make_vec_env(8)", "algo": "sb3 PPO defaults", "env_steps": int(model.num_timesteps)}
        baseline |= {"train_wall_s": seconds, "env_steps_per_s": model.num_timesteps / seconds}
        venv.close()
        print(
            f"baseline: SB3 PPO on make_vec_env(8): {model.num_timesteps:,} steps in {seconds:.1f} s "
            f"({model.num_timesteps / seconds:,.0f} steps/s, first rollout's compilation included)",
            flush=True,
        )

    if args.algo == "sbx":
        from sbx import PPO

        algo_kwargs = {}
    else:
        PPO, algo_kwargs = SB3PPO, {"device": "cpu"}
    t0 = time.perf_counter()
    if batched:
        venv = VecMonitor(VecEnv("hover", num_envs=args.n_envs or 256, **env_kwargs))
        venv.seed(args.seed)
        algo_kwargs |= {"n_steps": args.n_steps or 32, "batch_size": args.batch_size or 256}
    else:
        venv = make_vec_env(ENV_ID, n_envs=args.n_envs or 4, seed=args.seed, env_kwargs=env_kwargs)
        algo_kwargs |= {"n_steps": args.n_steps or 2048, "batch_size": args.batch_size or 64}  # SB3's defaults
    model = PPO("MlpPolicy", venv, seed=args.seed, **algo_kwargs)
    rollout = model.n_steps * venv.num_envs
    total = args.steps // rollout * rollout
    every = total if args.eval_every is None else max(args.eval_every // rollout, 1) * rollout
    checkpoints = sorted({min(k, total) for k in range(every, total + every, every)})
    if total < rollout:
        parser.error(f"--steps must be at least one rollout ({rollout} env steps)")

    result = {
        "command": "python benchmarks/training/sb3_hover.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "env_id": ENV_ID,
        "env_kwargs": env_kwargs,
        "vec": "jaxdrones.adapters.sb3.VecEnv" if batched else "make_vec_env",
        "n_envs": venv.num_envs,
        "seed": args.seed,
        "algorithm": f"PPO ({'sbx' if args.algo == 'sbx' else 'stable-baselines3'}, MlpPolicy, the settings below)",
        "baseline": baseline,
        "ppo": {
            "n_steps": model.n_steps,
            "batch_size": model.batch_size,
            "n_epochs": model.n_epochs,
            "learning_rate": model.learning_rate,
            "gamma": model.gamma,
            "gae_lambda": model.gae_lambda,
        },
        "eval_episodes": args.eval_episodes,
        "versions": {
            "python": platform.python_version(),
            "stable_baselines3": stable_baselines3.__version__,
            "sbx": __import__("sbx").__version__ if args.algo == "sbx" else None,
            "torch": torch.__version__,
            "gymnasium": gym.__version__,
            "jaxdrones": jaxdrones.__version__,
            "jax": __import__("jax").__version__,
        },
        "machine": {
            "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "load_average_at_start": list(os.getloadavg()),
        },
        "setup_s": time.perf_counter() - t0,
        "checkpoints": [],
    }
    print(
        f"{args.algo} PPO on {result['vec']} {env_kwargs}, {venv.num_envs} envs, {total:,} env steps "
        f"(rollouts of {rollout}), evaluations at {[f'{c:,}' for c in checkpoints]}",
        flush=True,
    )

    train_s = eval_s = train_cpu_s = 0.0
    for target in checkpoints:
        t, c = time.perf_counter(), time.process_time()
        model.learn(total_timesteps=target - model.num_timesteps, reset_num_timesteps=False)
        train_s += time.perf_counter() - t
        train_cpu_s += time.process_time() - c
        t = time.perf_counter()
        stats = evaluate(model, env_kwargs, args.eval_episodes, seed=10_000 + args.seed)
        eval_s += time.perf_counter() - t
        row = {
            "env_steps": int(model.num_timesteps),
            "train_wall_s": train_s,
            "train_cpu_s": train_cpu_s,
            "eval_wall_s": eval_s,
            "load_average": list(os.getloadavg()),
            **stats,
        }
        result["checkpoints"].append(row)
        result["final"] = row
        with open(out, "w") as f:
            json.dump(result, f, indent=2)
        print(
            f"{row['env_steps']:>9,} steps  train {train_s:7.1f} s (CPU {train_cpu_s:7.1f} s)  "
            f"({row['env_steps'] / train_s:,.0f} steps/s)  mean final distance "
            f"{100 * stats['final_distance_mean_m']:.2f} cm (median {100 * stats['final_distance_median_m']:.2f}, "
            f"max {100 * stats['final_distance_max_m']:.2f})  return {stats['episode_return_mean']:.1f}  "
            f"terminated early {stats['terminated_early']}/{args.eval_episodes}",
            flush=True,
        )
    venv.close()
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
