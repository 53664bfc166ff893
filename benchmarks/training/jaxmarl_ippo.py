"""JaxMARL's IPPO baseline on the JaxMARL view, as a JaxMARL user runs it: ``baselines/IPPO/ippo_ff_mabrax.py`` with
its own hyperparameters (``config/ippo_ff_mabrax.yaml``), the env built by `jaxdrones.adapters.jaxmarl.make` where
the script calls ``jaxmarl.make`` (the one line a user changes; done here by replacing ``jaxmarl.make`` before the
script builds its env, so the script's file is used unchanged). The trained policy (the Gaussian's mean) is then
evaluated as ``jaxdrones train`` evaluates its own: 256 episodes, the task's success metric at the end.

Needs JaxMARL's baselines, which its pip package does not ship: a checkout of https://github.com/FLAIROx/JaxMARL
(``--baselines PATH/baselines/IPPO``) and what the script imports (``pip install jaxmarl distrax hydra-core wandb``;
wandb stays disabled). Measured with JaxMARL 0.2.0 and distrax 0.1.9; the README's table (Multi-agent tasks) came
from these runs, 10 M env steps each (the yaml's budget):

    python benchmarks/training/jaxmarl_ippo.py --baselines ~/JaxMARL/baselines/IPPO --task leader_follower \\
        --action-type one_d_rpm --seed 30
    python benchmarks/training/jaxmarl_ippo.py --baselines ~/JaxMARL/baselines/IPPO --task multi_hover --seed 30

It prints one JSON line (env steps, wall time, the success metric in m, the terminated share, each drone's final
height) and writes it to ``benchmarks/results/jaxmarl_ippo_<task>_<action type>_s<seed>.json``.
"""

from __future__ import annotations

import time

T0 = time.perf_counter()
import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxdrones  # noqa: E402,F401  (first, so that the wall time counts its import, as a user's run does)
from jaxdrones.adapters import jaxmarl as jd_marl  # noqa: E402
from jaxdrones.training.evaluation import episode_outcomes, episode_statistics, rollout_policy  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--baselines", required=True, help="JaxMARL's baselines/IPPO folder (a checkout)")
    parser.add_argument("--task", default="leader_follower")
    parser.add_argument("--n-drones", type=int, default=2)
    parser.add_argument("--action-type", default=None, help="default: the task's own (rpm)")
    parser.add_argument("--seed", type=int, default=30, help="the yaml's SEED")
    parser.add_argument("--steps", type=float, default=None, help="TOTAL_TIMESTEPS (default: the yaml's, 1e7)")
    parser.add_argument("--episodes", type=int, default=256)
    args = parser.parse_args()

    import jaxmarl
    import wandb
    from omegaconf import OmegaConf

    options = {"n_drones": args.n_drones, **({"action_type": args.action_type} if args.action_type else {})}
    jaxmarl.make = lambda name, **kwargs: jd_marl.make(name, **kwargs)  # the line a user changes
    sys.path.insert(0, os.path.abspath(args.baselines))
    import ippo_ff_mabrax as script

    config = OmegaConf.to_container(OmegaConf.load(os.path.join(args.baselines, "config", "ippo_ff_mabrax.yaml")))
    config.update(ENV_NAME=args.task, ENV_KWARGS=options, SEED=args.seed)
    if args.steps:
        config["TOTAL_TIMESTEPS"] = int(args.steps)
    wandb.init(mode="disabled")  # the script logs through wandb in an io_callback
    rng, init = jax.random.split(jax.random.PRNGKey(config["SEED"]))  # as the script's main()
    out = jax.block_until_ready(jax.jit(script.make_train(config, init))(rng))
    trained_s = time.perf_counter() - T0

    view = jd_marl.make(args.task, **options)
    env, n_obs = view.env, view.env.observation_size
    network = script.ActorCritic(view.action_space(view.agents[0]).shape[0], activation=config["ACTIVATION"])
    params = out["runner_state"][0].params

    def policy(obs, key):  # a world's flat observation f[D·n_obs] -> flat action, as jaxdrones' policies
        pi, _ = network.apply(params, obs.reshape(env.n_drones, n_obs))
        return pi.mean().reshape(-1), {}

    keys = jax.random.split(jax.random.key(0), args.episodes)
    stats = episode_statistics(env, jax.jit(lambda k: episode_outcomes(env, policy, k))(keys))
    final = jax.jit(jax.vmap(lambda k: rollout_policy(env, policy, k)))(keys).sim.pos[:, -1]
    steps = int(np.asarray(out["metrics"]["env_step"])[-1])
    result = {
        "task": args.task,
        **options,
        "seed": args.seed,
        "env_steps": steps,
        "train_s": round(trained_s, 1),
        "wall_time_s": round(time.perf_counter() - T0, 1),
        "success_metric": env.task.success_metric,
        "success_value_m": stats.get("success_value"),
        "terminated_rate": stats["terminated_rate"],
        "final_z_m": np.asarray(final[..., 2]).mean(0).round(4).tolist(),
        "jax": jax.__version__,
        "jaxmarl": getattr(jaxmarl, "__version__", "?"),
    }
    print(json.dumps(result))
    os.makedirs(RESULTS, exist_ok=True)
    name = f"jaxmarl_ippo_{args.task}_{options.get('action_type', 'rpm')}_s{args.seed}.json"
    with open(os.path.join(RESULTS, name), "w") as f:
        json.dump(result, f, indent=2)


if __name__ == "__main__":
    main()
