"""The paper's multi-agent workflow on RLlib's current API: two drones, leader and follower, trained with PPO and a
centralised critic, each drone's action one RPM value (``one_d_rpm``).

The paper (§IV; gym-pybullet-drones' ``multiagent.py``, RLlib's old API) trains ``LeaderFollowerAviary`` with
``act=one_d_rpm``: an action model per drone on its own observation, and a critic on its own observation, the other
drone's and the other drone's action (its ``central_critic_observer`` and ``FillInActions``: 25 inputs), 256-256
tanh layers for both. Here the same on RLlib's RLModule/Learner stack (ray 2.60):

- `CentralCriticEnv`: the PettingZoo adapter (`jaxdrones.adapters.pettingzoo.parallel_env`) in RLlib's
  ``ParallelPettingZooEnv``, each agent's observation extended with the other agents' observations and their last
  actions, as the paper's observer builds it;
- `CentralCriticModule`: an RLModule whose action model reads the agent's own observation only and whose value
  function reads all of it (RLlib's PPO learner and its GAE take it as they take their default module);
- `train`: PPO (one module per drone) until ``timesteps`` env steps, then the policies evaluated as ``jaxdrones
  train`` evaluates its own (`evaluate`: 256 random starts, the task's metric and threshold).

The paper's kinematic observation is ``obs_type="kin"`` and its rewards ``reward="paper"``; the defaults are the
task's (``neighbors``, ``shaped``). Run it in the environment of the ``rllib`` extra (docs/adapters.md, "RLlib")::

    python -m jaxdrones.examples.rllib_leader_follower --timesteps 400000 --out runs/rllib_leader_follower

Ray starts its processes before JAX runs anything in this one (`main`): a process that has started JAX warns at
``fork``, and Ray's start forks.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from jaxdrones.io.runs import output_folder, write_json

#: The paper's team: two drones, one RPM value per drone.
TASK, N_DRONES, ACTION_TYPE = "leader_follower", 2, "one_d_rpm"
#: Name under which `train` registers the env with Ray.
ENV_NAME = "jaxdrones_leader_follower"
#: The paper's layers, for the action model and the critic.
HIDDEN = (256, 256)
#: How to install what this example needs (ray's RLlib and torch, at the versions it was run with).
INSTALL = (
    'pip install -c constraints-rllib.txt ".[rllib]" in a virtual environment of its own (docs/adapters.md, RLlib)'
)


def _options(obs_type: str | None, reward: str | None) -> dict:
    """The task's settings: 2 drones, ``one_d_rpm``, and the paper's ``obs_type="kin"`` or ``reward="paper"`` where
    given."""
    given = {k: v for k, v in {"obs_type": obs_type, "reward": reward}.items() if v is not None}
    return dict(n_drones=N_DRONES, action_type=ACTION_TYPE, **given)


def make_parallel_env(obs_type: str | None = None, reward: str | None = None) -> Any:
    """The task's PettingZoo env (`_options`), which RLlib's env runners step."""
    from jaxdrones.adapters.pettingzoo import parallel_env

    return parallel_env(TASK, **_options(obs_type, reward))


def make_env(obs_type: str | None = None, reward: str | None = None) -> Any:
    """The task's jaxdrones env (`jaxdrones.make`, `_options`), on which the policies are evaluated."""
    import jaxdrones as jd

    return jd.make(TASK, **_options(obs_type, reward))


def _env_classes():
    """`CentralCriticEnv` and `CentralCriticModule`, defined where ray and torch are imported."""
    import gymnasium as gym
    import torch
    from ray.rllib.core.columns import Columns
    from ray.rllib.core.rl_module.apis.value_function_api import ValueFunctionAPI
    from ray.rllib.core.rl_module.torch import TorchRLModule
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    class CentralCriticEnv(ParallelPettingZooEnv):
        """RLlib's wrapper of a PettingZoo env, each agent's observation followed by the other agents' observations
        and last actions (in agent order; zeros at a reset): f[n_obs + (D - 1)(n_obs + n_act)]."""

        def __init__(self, env):
            super().__init__(env)
            self.order = list(env.possible_agents)
            self.own = {a: env.observation_space(a).shape[0] for a in self.order}
            self.acts = {a: env.action_space(a).shape[0] for a in self.order}
            size = sum(self.own.values()) + sum(self.acts.values())
            self.observation_space = gym.spaces.Dict(
                {a: gym.spaces.Box(-np.inf, np.inf, (size - self.acts[a],), np.float32) for a in self.order}
            )
            self._last = {a: np.zeros(self.acts[a], np.float32) for a in self.order}

        def _central(self, obs: dict) -> dict:
            out = {}
            for a in obs:
                others = [b for b in self.order if b != a]
                parts = [obs[a], *(obs.get(b, np.zeros(self.own[b], np.float32)) for b in others)]
                out[a] = np.concatenate([*parts, *(self._last[b] for b in others)]).astype(np.float32)
            return out

        def reset(self, *, seed=None, options=None):
            obs, info = super().reset(seed=seed, options=options)
            self._last = {a: np.zeros(self.acts[a], np.float32) for a in self.order}
            return self._central(obs), info

        def step(self, action_dict):
            self._last.update({a: np.asarray(v, np.float32).reshape(-1) for a, v in action_dict.items()})
            obs, rewards, terminated, truncated, infos = super().step(action_dict)
            return self._central(obs), rewards, terminated, truncated, infos

    class CentralCriticModule(TorchRLModule, ValueFunctionAPI):
        """PPO's module with a centralised critic: the action model (a Gaussian's mean and log-std) on the first
        ``model_config["own_obs_size"]`` entries of the observation, the agent's own; the value function on all of
        it. Both 256-256 tanh (``model_config["hidden"]``)."""

        def setup(self):
            own, full = self.model_config["own_obs_size"], self.observation_space.shape[0]
            hidden = list(self.model_config.get("hidden", HIDDEN))
            n_act = self.action_space.shape[0]

            def mlp(sizes):
                layers = []
                for a, b in zip(sizes[:-1], sizes[1:], strict=True):
                    layers += [torch.nn.Linear(a, b), torch.nn.Tanh()]
                return torch.nn.Sequential(*layers[:-1])

            self.own_obs_size = own
            self.pi = mlp([own, *hidden, 2 * n_act])
            self.vf = mlp([full, *hidden, 1])

        def _forward(self, batch, **kwargs):
            return {Columns.ACTION_DIST_INPUTS: self.pi(batch[Columns.OBS][..., : self.own_obs_size])}

        def compute_values(self, batch, embeddings=None):
            return self.vf(batch[Columns.OBS]).squeeze(-1)

    return CentralCriticEnv, CentralCriticModule


def algorithm_config(
    obs_type: str | None = None,
    reward: str | None = None,
    seed: int = 0,
    num_env_runners: int = 1,
    train_batch_size: int = 4000,
) -> Any:
    """RLlib's `PPOConfig` of the workflow: one `CentralCriticModule` per drone, the env registered as `ENV_NAME`."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.tune.registry import register_env

    from jaxdrones.adapters.agents import agent_names

    central_env, central_module = _env_classes()
    register_env(ENV_NAME, lambda cfg: central_env(make_parallel_env(cfg.get("obs_type"), cfg.get("reward"))))
    agents = agent_names(N_DRONES)
    own = make_env(obs_type, reward).observation_size  # a drone's own observation: an agent's of the adapter
    specs = {
        a: RLModuleSpec(module_class=central_module, model_config={"own_obs_size": own, "hidden": list(HIDDEN)})
        for a in agents
    }
    return (
        PPOConfig()
        .environment(ENV_NAME, env_config={"obs_type": obs_type, "reward": reward})
        .env_runners(num_env_runners=num_env_runners)
        .multi_agent(policies=set(agents), policy_mapping_fn=lambda agent_id, *args, **kwargs: agent_id)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs=specs))
        .training(
            lr=3e-4,
            gamma=0.99,
            lambda_=0.95,
            train_batch_size_per_learner=train_batch_size,
            minibatch_size=256,
            num_epochs=10,
            entropy_coeff=0.0,
            use_kl_loss=False,
            vf_clip_param=100.0,
        )
        .debugging(seed=seed)
    )


def policy_of(algo: Any, env: Any) -> Callable:
    """The trained drones' actions as a jaxdrones policy on ``env`` (the task's env, `jaxdrones.make`),
    ``policy(obs, key) -> (action, {})`` on a world's flat observation f[D·n_obs] (`jaxdrones.training.evaluation`):
    each drone's action model (RLlib module ``drone_<i>``, the PettingZoo adapter's agent) on its own observation,
    its Gaussian's mean clipped to the action box, called from JAX through ``jax.pure_callback``."""
    import jax
    import jax.numpy as jnp
    import torch
    from ray.rllib.core.columns import Columns

    from jaxdrones.adapters.agents import agent_names

    agents = agent_names(env.n_drones)
    modules = [algo.get_module(a) for a in agents]
    n_obs, n_act = env.observation_size, env.action_size

    def actions(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32).reshape(-1, len(agents), n_obs)
        out = []
        with torch.no_grad():
            for i, module in enumerate(modules):
                inputs = module.forward_inference({Columns.OBS: torch.from_numpy(np.ascontiguousarray(obs[:, i]))})
                out.append(inputs[Columns.ACTION_DIST_INPUTS][:, :n_act].numpy())
        return np.clip(np.concatenate(out, axis=-1), -1.0, 1.0).astype(np.float32)

    def policy(obs, key):
        del key
        shape = jax.ShapeDtypeStruct(obs.shape[:-1] + (len(agents) * n_act,), jnp.float32)
        return jax.pure_callback(actions, shape, obs, vmap_method="broadcast_all").reshape(shape.shape), {}

    return policy


def evaluate(algo: Any, obs_type: str | None = None, reward: str | None = None, n_episodes: int = 256) -> dict:
    """The trained policies judged as ``jaxdrones train`` judges its own: ``n_episodes`` random starts of the task
    (`jaxdrones.training.evaluation.evaluate`), the task's success metric against its threshold, with none
    terminated early. Returns `jaxdrones.training.evaluation.judged`'s dict (the statistics under ``"eval"``)."""
    import jax

    from jaxdrones.training.evaluation import evaluate as evaluate_policy
    from jaxdrones.training.evaluation import judged

    env = make_env(obs_type, reward)
    return judged(env.task, evaluate_policy(env, policy_of(algo, env), jax.random.key(1), n_episodes))


def train(
    timesteps: int = 400_000,
    seed: int = 0,
    obs_type: str | None = None,
    reward: str | None = None,
    num_env_runners: int = 1,
    train_batch_size: int = 4000,
    eval_every: int = 10,
    checkpoint: str | None = None,
    log: Callable[[str], None] = print,
) -> dict:
    """Train the two drones with RLlib's PPO and the centralised critic until ``timesteps`` env steps (rounded up to
    whole iterations of ``train_batch_size``), evaluating every ``eval_every`` iterations (0: at the end only) and
    at the end. Ray must be started (`main` starts it).

    Args:
        checkpoint: a new folder to save the trained algorithm in (RLlib's ``Algorithm.save_to_path``: restore it
            with ``ray.rllib.algorithms.algorithm.Algorithm.from_checkpoint``), or None.

    Returns:
        The summary: the settings, ``env_steps``, ``iterations``, ``train_time_s``, ``progress`` (a row per
        evaluation: ``env_steps``, ``time_s``, ``success_value``, ``terminated_rate``, ``episode_reward``) and the
        last evaluation's verdict (`jaxdrones.training.evaluation.judged`: ``success``, ``success_value``, ...).
    """
    from jaxdrones.training.progress import ProgressLog

    config = algorithm_config(obs_type, reward, seed, num_env_runners, train_batch_size)
    start = time.perf_counter()
    log_rows = ProgressLog(timesteps, make_env(obs_type, reward).task, enabled=False)  # progress.json's rows
    algo = config.build_algo()
    steps, iteration = 0, 0
    try:
        while steps < timesteps:
            result = algo.train()
            iteration += 1
            steps = int(result["env_runners"]["num_env_steps_sampled_lifetime"])
            returns = result["env_runners"].get("agent_episode_returns_mean", {})
            returns = ", ".join(f"{agent} {float(value):.2f}" for agent, value in sorted(returns.items()))
            log(f"iteration {iteration}: {steps:,} env steps, {time.perf_counter() - start:.0f} s, returns: {returns}")
            if eval_every and iteration % eval_every == 0 and steps < timesteps:
                verdict = evaluate(algo, obs_type, reward)
                log_rows(steps, verdict["eval"])
                value, unit = verdict["success_value"], verdict["success_unit"]
                log(f"  evaluation: {verdict['success_metric']} {value:.4g} {unit}")
        train_s = time.perf_counter() - start
        final = evaluate(algo, obs_type, reward)
        log_rows(steps, final["eval"])
        if checkpoint is not None:
            algo.save_to_path(os.path.abspath(checkpoint))
    finally:
        algo.stop()
    return {
        "task": TASK,
        "n_drones": N_DRONES,
        "action_type": ACTION_TYPE,
        "obs_type": obs_type,
        "reward": reward,
        "seed": seed,
        "env_steps": steps,
        "iterations": iteration,
        "train_batch_size": train_batch_size,
        "num_env_runners": num_env_runners,
        "train_time_s": train_s,
        "progress": log_rows.history,
        **final,
    }


def write_run(folder: str, summary: dict) -> None:
    """What ``jaxdrones train`` writes beside the policy: ``summary.json`` (strict JSON, plain numbers),
    ``progress.json`` (the evaluations) and ``learning_curve.png`` (the task's metric against its threshold)."""
    from jaxdrones.io.plotting import plot_learning_curve

    write_json(os.path.join(folder, "summary.json"), summary)
    write_json(os.path.join(folder, "progress.json"), summary["progress"], indent=1)
    plot_learning_curve(
        summary["progress"],
        os.path.join(folder, "learning_curve.png"),
        metric_label=f"evaluation {summary['success_metric']} ({summary['success_unit']})",
        threshold=summary["success_threshold"],
        title=f"RLlib PPO, centralised critic, on {TASK} ({N_DRONES} drones, {ACTION_TYPE})",
    )


def main(argv: list[str] | None = None) -> int:
    """The command line (module doc); returns 0 when both drones end within the task's threshold."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--timesteps", type=int, default=400_000, help="env steps to train (default 400k)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--obs-type", default=None, help="kin: the paper's kinematic observation (default: the task's)")
    parser.add_argument("--reward", default=None, help="paper: the paper's rewards (default: the task's shaped ones)")
    parser.add_argument("--num-env-runners", type=int, default=1, help="Ray's sampling processes (default 1)")
    parser.add_argument("--train-batch-size", type=int, default=4000, help="env steps per PPO iteration")
    parser.add_argument(
        "--eval-every",
        type=int,
        default=10,
        help="evaluate every N iterations, and at the end (default 10; 0: at the end)",
    )
    parser.add_argument(
        "--out",
        default=None,
        help="write the run (summary.json, progress.json, learning_curve.png, checkpoint/) to this new folder (a "
        "numbered sibling where it exists)",
    )
    args = parser.parse_args(argv)
    try:
        import ray
    except ModuleNotFoundError:
        parser.error(f"needs ray[rllib], the rllib extra: {INSTALL}")

    from jaxdrones.training.evaluation import result_line

    start = time.perf_counter()
    ray.init(include_dashboard=False, log_to_driver=False)  # before JAX runs anything in this process
    try:
        with contextlib.ExitStack() as stack:
            folder = stack.enter_context(output_folder(args.out)) if args.out else None
            summary = train(
                args.timesteps,
                args.seed,
                args.obs_type,
                args.reward,
                args.num_env_runners,
                args.train_batch_size,
                args.eval_every,
                checkpoint=os.path.join(folder.path, "checkpoint") if folder else None,
            )
            summary["wall_time_s"] = time.perf_counter() - start
            if folder:
                write_run(folder.path, summary)
    finally:
        ray.shutdown()
    print(result_line(summary))
    if folder:
        print(f"saved summary.json, progress.json, learning_curve.png, checkpoint/ in {folder.final}")
    return 0 if summary["success"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
