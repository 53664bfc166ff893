"""Batched PPO on jaxdrones envs with ``brax.training``, plus policy evaluation, saving and loading."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pickle
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs.base import Env, EnvState
from jaxdrones.wrappers.brax import BraxEnv, wrap_for_brax_training


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Hyperparameters of brax's PPO (``brax.training.agents.ppo.train``) and of the networks.

    Field names and meanings are brax's; see its documentation. ``num_timesteps`` counts env (control) steps.
    """

    num_timesteps: int = 2_500_000
    num_envs: int = 512
    batch_size: int = 512
    num_minibatches: int = 8
    unroll_length: int = 10
    num_updates_per_batch: int = 4
    learning_rate: float = 1e-3
    entropy_cost: float = 1e-3
    discounting: float = 0.98
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    max_grad_norm: float = 1.0
    reward_scaling: float = 1.0
    normalize_observations: bool = True
    num_evals: int = 10
    num_eval_envs: int = 128
    policy_hidden_layer_sizes: tuple[int, ...] = (32, 32)
    value_hidden_layer_sizes: tuple[int, ...] = (64, 64)
    seed: int = 0

    def __post_init__(self):
        if self.num_timesteps < 1 or self.num_envs < 1 or self.num_evals < 1:
            raise ValueError("PPOConfig: num_timesteps, num_envs and num_evals must be >= 1")
        if (self.batch_size * self.num_minibatches) % self.num_envs:
            raise ValueError(f"PPOConfig: batch_size·num_minibatches ({self.batch_size}·{self.num_minibatches}) "
                             f"must be a multiple of num_envs ({self.num_envs}), as brax's PPO requires")


def _network_factory(config: PPOConfig):
    from brax.training.agents.ppo import networks as ppo_networks

    return functools.partial(ppo_networks.make_ppo_networks,
                             policy_hidden_layer_sizes=tuple(config.policy_hidden_layer_sizes),
                             value_hidden_layer_sizes=tuple(config.value_hidden_layer_sizes))


def train(env: Env, config: PPOConfig = PPOConfig(),
          progress: Callable[[int, dict], None] | None = None):
    """Train a policy on ``env`` with brax's PPO.

    Args:
        env: a jaxdrones `Env` (single agent, flat observation and action).
        config: PPO hyperparameters.
        progress: called as ``progress(env_steps, metrics)`` after each of brax's evaluations, with brax's metric
            dict (``eval/episode_reward``, ``eval/episode_<metric>`` summed over the episode, ...).

    Returns:
        ``(make_policy, params)``: brax's policy factory and the trained (normaliser, policy, value) parameters.
        ``make_policy(params, deterministic=True)`` gives ``policy(obs, key) -> (action, extras)``.
    """
    from brax.training.agents.ppo import train as ppo

    kwargs = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    for key in ("policy_hidden_layer_sizes", "value_hidden_layer_sizes"):
        kwargs.pop(key)
    make_policy, params, _ = ppo.train(
        BraxEnv(env), episode_length=env.episode_length, wrap_env_fn=wrap_for_brax_training,
        network_factory=_network_factory(config), deterministic_eval=True,
        progress_fn=progress or (lambda *_: None), **kwargs)
    return make_policy, params


def rollout_policy(env: Env, policy, key: jax.Array, state: EnvState | None = None) -> EnvState:
    """Run one episode of ``policy`` under ``lax.scan``; the env freezes once the episode is done.

    Args:
        env: the env.
        policy: ``policy(obs, key) -> (action, extras)``.
        key: PRNG key (for reset and the policy).
        state: optional start state; by default ``env.reset(key)``.

    Returns:
        EnvState with a leading time axis [episode_length + 1] (the reset state first).
    """
    key_reset, key_act = jax.random.split(key)
    state = env.reset(key_reset) if state is None else state

    def body(s, k):
        action, _ = policy(s.obs, k)
        nxt = env.step(s, action)
        nxt = jax.tree.map(lambda old, new: jnp.where(s.done, old, new), s, nxt)
        return nxt, nxt

    _, states = jax.lax.scan(body, state, jax.random.split(key_act, env.episode_length))
    return jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, states)


def evaluate(env: Env, policy, key: jax.Array, n_episodes: int = 256) -> dict:
    """Final-state statistics of ``n_episodes`` episodes from random starts (one jitted, vmapped call).

    Returns:
        dict of floats: ``final_pos_error_m`` (mean ‖target − pos‖ at the episode's last state),
        ``final_pos_error_max_m``, ``final_pos_error_p90_m``, ``terminated_rate`` (crashed or left the arena),
        ``episode_reward`` (mean return).
    """

    @jax.jit
    def run(keys):
        states = jax.vmap(lambda k: rollout_policy(env, policy, k))(keys)
        final = jax.tree.map(lambda x: x[:, -1], states)
        returns = jnp.sum(jnp.where(states.steps[:, 1:] > states.steps[:, :-1], states.reward[:, 1:], 0.0), axis=1)
        return final.metrics["distance"], final.terminated, returns

    dist, terminated, returns = (np.asarray(x, dtype=np.float64) for x in run(jax.random.split(key, n_episodes)))
    return {
        "final_pos_error_m": float(dist.mean()), "final_pos_error_max_m": float(dist.max()),
        "final_pos_error_p90_m": float(np.percentile(dist, 90)), "terminated_rate": float(terminated.mean()),
        "episode_reward": float(returns.mean()), "n_episodes": int(n_episodes),
    }


def save_policy(path: str, params, env_name: str, env_overrides: dict, config: PPOConfig) -> None:
    """Save trained parameters with what is needed to rebuild the policy (`load_policy`)."""
    payload = {"params": jax.tree.map(np.asarray, params), "env_name": env_name, "env_overrides": env_overrides,
               "ppo_config": dataclasses.asdict(config)}
    with open(path, "wb") as f:
        pickle.dump(payload, f)


def load_policy(path: str | os.PathLike, deterministic: bool = True):
    """Load a policy saved by ``jaxdrones train``.

    Args:
        path: ``policy.pkl`` of a run folder, or the run folder.
        deterministic: use the distribution's mode (True) or sample.

    Returns:
        ``(env, policy)``: the env it was trained on (``jd.make(name, **overrides)``) and
        ``policy(obs, key) -> (action, extras)``.

    Raises:
        ValueError: if the file is missing or is not a saved jaxdrones policy.
    """
    from brax.training.agents.ppo import networks as ppo_networks

    from jaxdrones.envs import make

    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, "policy.pkl")
    if not os.path.isfile(path):
        raise ValueError(f"no saved policy at {path!r}")
    with open(path, "rb") as f:
        payload = pickle.load(f)
    if not isinstance(payload, dict) or not {"params", "env_name", "ppo_config"} <= set(payload):
        raise ValueError(f"{path!r} is not a jaxdrones policy file")
    config = PPOConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in payload["ppo_config"].items()})
    env = make(payload["env_name"], **payload["env_overrides"])
    from brax.training.acme import running_statistics

    preprocess = running_statistics.normalize if config.normalize_observations else (lambda x, _: x)
    networks = _network_factory(config)(env.observation_size, env.action_size,
                                        preprocess_observations_fn=preprocess)
    make_policy = ppo_networks.make_inference_fn(networks)
    return env, make_policy(payload["params"], deterministic=deterministic)


class ProgressLog:
    """Collects brax's evaluation metrics and shows a progress bar with steps/s and reward (tqdm)."""

    def __init__(self, total_steps: int, episode_length: int, enabled: bool = True):
        from tqdm.auto import tqdm

        self.t0 = time.perf_counter()
        self.episode_length = episode_length
        self.history: list[dict] = []
        self.bar = tqdm(total=total_steps, unit="step", unit_scale=True, disable=not enabled,
                        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}] {postfix}")

    def __call__(self, step: int, metrics: dict) -> None:
        elapsed = time.perf_counter() - self.t0
        row = {"env_steps": int(step), "time_s": elapsed,
               "episode_reward": float(metrics.get("eval/episode_reward", np.nan)),
               "mean_distance_m": float(metrics.get("eval/episode_distance", np.nan)) / self.episode_length}
        self.history.append(row)
        rate = step / elapsed if elapsed > 0 else 0.0
        self.bar.set_postfix_str(f"{rate:,.0f} steps/s  reward {row['episode_reward']:.1f}  "
                                 f"mean dist {row['mean_distance_m']:.3f} m")
        if step > self.bar.total:  # brax rounds the budget up to whole training epochs
            self.bar.total = step
        self.bar.update(step - self.bar.n)

    def close(self) -> None:
        self.bar.close()

    def save(self, path: str) -> None:
        with open(path, "w") as f:
            json.dump(self.history, f, indent=1)
