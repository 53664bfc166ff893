"""Batched PPO on jaxdrones envs with ``brax.training``, plus policy evaluation, saving and loading."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import pickle
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs.base import Env, EnvState


def _import_brax():
    """Import brax's PPO with the lines that brax's MuJoCo dependency prints (missing GPU plugins) swallowed."""
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from brax.training.agents.ppo import networks, train  # noqa: F401
    from jaxdrones.adapters import brax as adapter

    return adapter


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
        for name in ("num_timesteps", "num_envs", "batch_size", "num_minibatches", "unroll_length", "num_evals"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise ValueError(f"PPOConfig: {name} must be an integer >= 1, got {value!r}")
        if (self.batch_size * self.num_minibatches) % self.num_envs:
            raise ValueError(f"PPOConfig: batch_size·num_minibatches ({self.batch_size}·{self.num_minibatches}) "
                             f"must be a multiple of num_envs ({self.num_envs}), as brax's PPO requires")


def _network_factory(config: PPOConfig):
    from brax.training.agents.ppo import networks as ppo_networks

    return functools.partial(ppo_networks.make_ppo_networks,
                             policy_hidden_layer_sizes=tuple(config.policy_hidden_layer_sizes),
                             value_hidden_layer_sizes=tuple(config.value_hidden_layer_sizes))


def train(env: Env, config: PPOConfig = PPOConfig(),
          progress: Callable[[int, dict], None] | None = None, eval_env: Env | None = None):
    """Train a policy on ``env`` with brax's PPO.

    Args:
        env: a jaxdrones `Env` without camera images (the brax adapter flattens its f[D, n] observation and action).
        config: PPO hyperparameters.
        progress: called as ``progress(env_steps, metrics)`` after each of brax's evaluations, with brax's metric
            dict (``eval/episode_reward``, ``eval/episode_<metric>`` summed over the episode, ...).
        eval_env: the env of those evaluations (default ``env``), e.g. the task's starts where ``env`` trains from
            wider ones.

    Returns:
        ``(make_policy, params)``: brax's policy factory and the trained (normaliser, policy, value) parameters.
        ``make_policy(params, deterministic=True)`` gives ``policy(obs, key) -> (action, extras)``.
    """
    adapter = _import_brax()
    from brax.training.agents.ppo import train as ppo

    kwargs = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    for key in ("policy_hidden_layer_sizes", "value_hidden_layer_sizes"):
        kwargs.pop(key)
    make_policy, params, _ = ppo.train(
        adapter.BraxEnv(env), episode_length=env.episode_length, wrap_env_fn=adapter.wrap_for_brax_training,
        network_factory=_network_factory(config), deterministic_eval=True,
        progress_fn=progress or (lambda *_: None), eval_env=None if eval_env is None else adapter.BraxEnv(eval_env),
        **kwargs)
    return make_policy, params


def total_steps(config: PPOConfig) -> int:
    """The env steps brax's PPO runs for ``config``: ``num_timesteps`` rounded up to whole training epochs."""
    per_step = config.batch_size * config.unroll_length * config.num_minibatches
    epochs = max(config.num_evals - 1, 1)
    return int(epochs * math.ceil(config.num_timesteps / (epochs * per_step)) * per_step)


def act(env: Env, policy, obs: jax.Array, key: jax.Array) -> jax.Array:
    """The policy's action f[D, n_act] for an observation f[D, n_obs] (policies see flat vectors)."""
    action, _ = policy(jnp.reshape(obs, (-1,)), key)
    return jnp.reshape(action, (env.n_drones, env.action_size))


def rollout_policy(env: Env, policy, key: jax.Array, state: EnvState | None = None) -> EnvState:
    """Run one episode of ``policy`` under ``lax.scan``; the env freezes once the episode is done.

    Args:
        env: the env.
        policy: ``policy(obs, key) -> (action, extras)`` on flat vectors (as brax's policies).
        key: PRNG key (for reset and the policy).
        state: optional start state; by default ``env.reset(key)``.

    Returns:
        EnvState with a leading time axis [episode_length + 1] (the reset state first).
    """
    key_reset, key_act = jax.random.split(key)
    state = env.reset(key_reset) if state is None else state

    def body(s, k):
        nxt = env.step(s, act(env, policy, s.obs, k))
        nxt = jax.tree.map(lambda old, new: jnp.where(s.done, old, new), s, nxt)
        return nxt, nxt

    _, states = jax.lax.scan(body, state, jax.random.split(key_act, env.episode_length))
    return jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, states)


def evaluate(env: Env, policy, key: jax.Array, n_episodes: int = 256) -> dict:
    """Statistics of ``n_episodes`` episodes from random starts (one jitted, vmapped call).

    Returns:
        dict of floats: ``final_<metric>`` (mean over episodes of the metric at the episode's last state) and
        ``mean_<metric>`` (mean over episodes of its average over the episode) for every metric of the task, and for
        a task judged at the maximum (`Task.success_at` ``"max"``) ``max_<metric>`` (mean over episodes of its
        largest value over the episode's steps); ``success_value`` (the task's success metric,
        `Task.success_metric`, read as `Task.success_at`: final, mean or max, averaged over the episodes),
        ``terminated_rate`` (crashed or left the arena), ``episode_reward`` (mean return, summed over drones),
        ``n_episodes``; and for tasks measured by a distance, ``final_pos_error_m`` with its max and 90th percentile.
    """
    return episode_statistics(env, jax.jit(lambda keys: episode_outcomes(env, policy, keys))(
        jax.random.split(key, n_episodes)))


def episode_outcomes(env: Env, policy, keys: jax.Array):
    """Traced part of `evaluate`: one episode per key; returns (final metrics, episode-mean metrics, terminated,
    return, episode-max metrics), each with a leading episode axis.

    The mean and the max run over the episode's live steps (after each step until it ends; the reset state is not
    counted)."""
    states = jax.vmap(lambda k: rollout_policy(env, policy, k))(keys)
    live = (states.steps[:, 1:] > states.steps[:, :-1]).astype(states.reward.dtype)
    returns = jnp.sum(live * jnp.sum(states.reward[:, 1:], axis=-1), axis=1)
    final = {k: v[:, -1] for k, v in states.metrics.items()}
    mean = {k: jnp.sum(live * v[:, 1:], axis=1) / jnp.maximum(jnp.sum(live, axis=1), 1) for k, v in
            states.metrics.items()}
    # Every episode has a live first step; the frozen steps after its end repeat its last state.
    maximum = {k: jnp.max(jnp.where(live > 0, v[:, 1:], -jnp.inf), axis=1) for k, v in states.metrics.items()}
    return final, mean, states.terminated[:, -1], returns, maximum


def episode_statistics(env: Env, outcomes) -> dict:
    """Host part of `evaluate`: the statistics of `episode_outcomes` (see `evaluate`)."""
    final, mean, terminated, returns, maximum = jax.tree.map(lambda x: np.asarray(x, np.float64), outcomes)
    stats = {f"final_{k}": float(v.mean()) for k, v in final.items()}
    stats.update({f"mean_{k}": float(v.mean()) for k, v in mean.items()})
    task = getattr(env, "task", None)
    success_at = getattr(task, "success_at", "final")
    if success_at == "max":
        stats.update({f"max_{k}": float(v.mean()) for k, v in maximum.items()})
    if task is not None and task.success_metric in final:
        source = {"final": final, "mean": mean, "max": maximum}[success_at]
        stats["success_value"] = float(source[task.success_metric].mean())
    if "distance" in final:
        dist = final["distance"]
        stats.update(final_pos_error_m=float(dist.mean()), final_pos_error_max_m=float(dist.max()),
                     final_pos_error_p90_m=float(np.percentile(dist, 90)))
    stats.update(terminated_rate=float(terminated.mean()), episode_reward=float(returns.mean()),
                 n_episodes=int(terminated.shape[0]))
    return stats


def save_policy(path: str, params, env_name: str, env_overrides: dict, config: PPOConfig) -> None:
    """Save trained parameters with what is needed to rebuild the policy (`load_policy`)."""
    payload = {"params": jax.tree.map(np.asarray, params), "env_name": env_name, "env_overrides": env_overrides,
               "ppo_config": dataclasses.asdict(config)}
    with open(path, "wb") as f:
        pickle.dump(payload, f)


def load_policy(path: str | os.PathLike, deterministic: bool = True, env: Env | None = None):
    """Load a policy saved by ``jaxdrones train`` (PPO, APG, SHAC, MAPPO or IPPO).

    Args:
        path: ``policy.pkl`` of a run folder, or the run folder.
        deterministic: use the distribution's mode (True) or sample (PPO; the other trainers' policies are
            deterministic).
        env: the env to fly the policy in (default: the one it was trained on, ``jd.make(name, **overrides)``);
            it may differ in its physics or starts (e.g. with downwash on), not in its task, team size,
            observation or action.

    Returns:
        ``(env, policy)``: the env and ``policy(obs, key) -> (action, extras)``.

    Raises:
        ValueError: if the file is missing or is not a saved jaxdrones policy, or ``env`` is not of the policy's
            task, team size, observation size or action size.
    """
    from jaxdrones.envs import make

    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, "policy.pkl")
    if not os.path.isfile(path):
        raise ValueError(f"no saved policy at {path!r}")
    with open(path, "rb") as f:
        payload = pickle.load(f)
    if not isinstance(payload, dict) or not ({"params", "env_name"} <= set(payload)
                                             and ({"ppo_config", "apg_config", "shac_config", "mappo_config"}
                                                  & set(payload))):
        raise ValueError(f"{path!r} is not a jaxdrones policy file")
    trained_on = make(payload["env_name"], **payload["env_overrides"])
    if env is None:
        env = trained_on
    else:
        _check_same_agents(path, payload["env_name"], trained_on, env)
    if payload.get("algo") in ("apg", "shac"):  # trained by `jaxdrones train --algo apg|shac` (deterministic)
        from jaxdrones.training import apg

        return env, apg.load(payload, env)
    if payload.get("algo") in ("mappo", "ippo"):  # trained by `jaxdrones train --algo mappo|ippo`
        from jaxdrones.training import mappo

        return env, mappo.load(payload, env)
    _import_brax()
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import networks as ppo_networks

    config = PPOConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in payload["ppo_config"].items()})
    preprocess = running_statistics.normalize if config.normalize_observations else (lambda x, _: x)
    networks = _network_factory(config)(env.n_drones * env.observation_size, env.n_drones * env.action_size,
                                        preprocess_observations_fn=preprocess)
    make_policy = ppo_networks.make_inference_fn(networks)
    return env, make_policy(payload["params"], deterministic=deterministic)


def _check_same_agents(path: str, name: str, trained_on: Env, env: Env) -> None:
    """Raise ValueError unless ``env`` has the task, team size, observation and action sizes of ``trained_on``."""
    have = (getattr(getattr(env, "task", None), "name", None), env.n_drones, env.observation_size, env.action_size)
    want = (name, trained_on.n_drones, trained_on.observation_size, trained_on.action_size)
    if have != want:
        raise ValueError(f"the policy in {path!r} was trained on {want[0]!r} with {want[1]} drones, observation "
                         f"size {want[2]} and action size {want[3]}; the env given is {have[0]!r} with {have[1]} "
                         f"drones, observation size {have[2]} and action size {have[3]}")


class ProgressLog:
    """Collects brax's evaluation metrics and shows a progress bar (tqdm) with the training speed, the evaluation
    return and the task's success metric.

    The bar's total is the number of steps brax will run (`total_steps`); its steps/s counts from the first
    evaluation (after compilation), so it is the training speed.

    Args:
        total_steps: env steps of the run.
        metric: the task's success metric (a key of the env's metrics).
        enabled: show the bar.
    """

    def __init__(self, total_steps: int, metric: str = "distance", enabled: bool = True):
        from tqdm.auto import tqdm

        self.t0 = time.perf_counter()
        self.metric = metric
        self.history: list[dict] = []
        self._first: tuple[float, int] | None = None
        self.bar = tqdm(total=total_steps, unit="step", unit_scale=True, disable=not enabled,
                        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}] {postfix}")

    def __call__(self, step: int, metrics: dict) -> None:
        now = time.perf_counter()
        length = float(metrics.get("eval/avg_episode_length", np.nan))
        row = {"env_steps": int(step), "time_s": now - self.t0,
               "episode_reward": float(metrics.get("eval/episode_reward", np.nan)),
               "metric": float(metrics.get(f"eval/episode_{self.metric}", np.nan)) / length}
        self.history.append(row)
        if self._first is None:
            self._first = (now, step)
        elapsed, done = now - self._first[0], step - self._first[1]
        rate = f"{done / elapsed:,.0f} steps/s  " if elapsed > 0 and done > 0 else ""
        self.bar.set_postfix_str(f"{rate}reward {row['episode_reward']:.1f}  {self.metric} {row['metric']:.3g}")
        if step > self.bar.total:
            self.bar.total = step
        self.bar.update(step - self.bar.n)

    def close(self) -> None:
        self.bar.close()

    def save(self, path: str) -> None:
        with open(path, "w") as f:
            json.dump(self.history, f, indent=1)
