"""Evaluating a policy on a task: episodes from random starts under one jitted, vmapped call, and their statistics
(the task's success metric as it is judged: at the episode's end, its mean or its maximum).

Every trainer is evaluated here, with the same episodes: `episode_outcomes` is compiled with the trainers' programs
(`jaxdrones.training.common.run_updates`), `episode_statistics` turns its arrays into the numbers that progress
displays, learning curves and ``summary.json`` report.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs.base import Env, EnvState
from jaxdrones.envs.observations import policy_input

if TYPE_CHECKING:
    from jaxdrones.envs.task import Task
    from jaxdrones.training.trainers import Trainer

#: What `episode_outcomes` returns: (final metrics, episode-mean metrics, terminated, return, episode-max metrics),
#: each with a leading episode axis.
Outcomes = tuple[dict[str, jax.Array], dict[str, jax.Array], jax.Array, jax.Array, dict[str, jax.Array]]


def act(env: Env, policy: Callable, obs: jax.Array | dict[str, jax.Array], key: jax.Array) -> jax.Array:
    """The policy's action f[D, n_act] for an observation f[D, n_obs] or a dict with camera images (policies see
    `jaxdrones.envs.observations.policy_input`: flat vectors, or brax's vision dict)."""
    action, _ = policy(policy_input(obs), key)
    return jnp.reshape(action, (env.n_drones, env.action_size))


def rollout_policy(env: Env, policy: Callable, key: jax.Array, state: EnvState | None = None) -> EnvState:
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


def evaluate(env: Env, policy: Callable, key: jax.Array, n_episodes: int = 256) -> dict:
    """Statistics of ``n_episodes`` episodes from random starts (one jitted, vmapped call).

    Returns:
        dict of floats: ``final_<metric>`` (mean over episodes of the metric at the episode's last state) and
        ``mean_<metric>`` (mean over episodes of its average over the episode) for every metric of the task, and for
        a task judged at the maximum (`Task.success_at` ``"max"``) ``max_<metric>`` (mean over episodes of its
        largest value over the episode's steps); ``success_value`` (the task's success metric,
        `Task.success_metric`, read as `Task.success_at`: final, mean or max, averaged over the episodes),
        ``terminated_rate`` (crashed, left the arena or an invalid action; not an episode that ends at its goal,
        `Task.reached`), ``episode_reward`` (mean return, summed over drones),
        ``n_episodes``; and for tasks measured by a distance, ``final_pos_error_m`` with its max and 90th percentile.
    """
    return episode_statistics(
        env, jax.jit(lambda keys: episode_outcomes(env, policy, keys))(jax.random.split(key, n_episodes))
    )


def episode_outcomes(env: Env, policy: Callable, keys: jax.Array) -> Outcomes:
    """Traced part of `evaluate`: one episode per key; returns (final metrics, episode-mean metrics, terminated,
    return, episode-max metrics), each with a leading episode axis.

    The mean and the max run over the episode's live steps (after each step until it ends; the reset state is not
    counted)."""
    return outcomes_of(jax.vmap(lambda k: rollout_policy(env, policy, k))(keys))


def outcomes_of(states: EnvState) -> Outcomes:
    """`episode_outcomes` of episodes already flown: ``states`` with leading axes [episode, time] (`rollout_policy`
    vmapped)."""
    live = (states.steps[:, 1:] > states.steps[:, :-1]).astype(states.reward.dtype)
    returns = jnp.sum(live * jnp.sum(states.reward[:, 1:], axis=-1), axis=1)
    final = {k: v[:, -1] for k, v in states.metrics.items()}
    mean = {
        k: jnp.sum(live * v[:, 1:], axis=1) / jnp.maximum(jnp.sum(live, axis=1), 1) for k, v in states.metrics.items()
    }
    # Every episode has a live first step; the frozen steps after its end repeat its last state.
    maximum = {k: jnp.max(jnp.where(live > 0, v[:, 1:], -jnp.inf), axis=1) for k, v in states.metrics.items()}
    return final, mean, states.terminated[:, -1], returns, maximum


def episode_statistics(env: Env, outcomes: Outcomes) -> dict:
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
    if "failure" in final:  # tasks judged per episode (``avoid``): the share of episodes that succeeded
        stats["success_rate"] = 1.0 - float(final["failure"].mean())
    if "distance" in final:
        dist = final["distance"]
        stats.update(
            final_pos_error_m=float(dist.mean()),
            final_pos_error_max_m=float(dist.max()),
            final_pos_error_p90_m=float(np.percentile(dist, 90)),
        )
    if "crash" in final and "invalid_action" in final:  # a `TaskEnv`: not the episodes that end at their goal
        terminated = np.maximum(final["crash"], final["invalid_action"])
    stats.update(
        terminated_rate=float(terminated.mean()),
        episode_reward=float(returns.mean()),
        n_episodes=int(terminated.shape[0]),
    )
    return stats


def eval_program(env: Env, trainer: Trainer, n_episodes: int) -> Callable:
    """The evaluation compiled beside the trainer's chunks: ``n_episodes`` episodes from random starts (for a run of
    seed ``s``, the same keys at every evaluation: ``jax.random.split(key(s + 1))[0]`` split ``n_episodes`` ways;
    `outcomes_of`) and the flight of the first one for the plot (positions, the task's reference, velocities, RPMs),
    as ``evaluate(networks, params, seed) -> pytree of arrays`` for a trainer's ``evaluate`` argument
    (`jaxdrones.training.trainers`)."""
    from jaxdrones.viz import VIEW_EPISODES, flight_data

    def evaluate(network, params, seed):
        keys = jax.random.split(jax.random.split(jax.random.key(seed + 1))[0], n_episodes)
        policy = trainer.make_policy(network, params)
        # The episodes' starts, as rollout_policy draws them; the task of the first episode from its start, not from
        # the flown states, so that the compiled evaluation keeps no per-step copy of every episode's task data.
        starts = jax.vmap(lambda k: env.reset(jax.random.split(k)[0]))(keys)
        states = jax.vmap(lambda k, start: rollout_policy(env, policy, k, start))(keys, starts)
        flight = jax.tree.map(lambda x: x[0], states)  # the first episode, for the flight plot
        steps = jnp.arange(env.episode_length + 1)
        task = jax.tree.map(lambda x: x[0], starts.task)
        ref = jax.vmap(lambda s: env.task.reference(env.config, task, s))(steps)
        return {
            "outcomes": outcomes_of(states),
            "flight": {"pos": flight.sim.pos, "ref": ref.pos, "vel": flight.sim.vel, "rpm": flight.sim.rpm},
            "viewer": jax.tree.map(lambda x: x[:VIEW_EPISODES], flight_data(states)),
        }  # for flight.html

    evaluate.description = f"evaluation {n_episodes} {trainer.name} {env.task.name} {env.config!r}"
    return evaluate


def failed_criteria(task: Task, stats: dict) -> list[str]:
    """The criteria of a solved run that the evaluation ``stats`` (`episode_statistics`) miss, as sentences (empty:
    solved): an evaluation ran, the task's success metric is below its threshold, and, unless the task's metric
    counts them itself (``success_counts_terminations``), no episode ended early (a crash, or leaving the arena)."""
    from jaxdrones.training.progress import AGGREGATES

    if not stats:
        return ["no evaluation ran (the run stopped before its first)"]
    failed = []
    value = stats.get("success_value", math.nan)
    if not value < task.success_threshold:
        failed.append(
            f"{task.success_metric} ({AGGREGATES[task.success_at]}) {value:.4g} {task.success_unit} is not below "
            f"the threshold {task.success_threshold:g}"
        )
    rate, n = stats.get("terminated_rate", math.nan), stats.get("n_episodes", 0)
    if not task.success_counts_terminations and not rate == 0.0:
        ended = f"{round(rate * n)} of {n}" if math.isfinite(rate) else "some"
        failed.append(f"{ended} episodes ended early (crashed or left the arena; a solved run has none)")
    return failed


def judged(task: Task, stats: dict) -> dict:
    """The verdict on an evaluation, as ``summary.json`` records it: ``success_metric`` (with how it is read, e.g.
    ``"distance (final)"``), ``success_unit``, ``success_value``, ``success_threshold``, ``success`` (bool),
    ``failed_criteria`` (`failed_criteria`'s sentences) and ``eval`` (``stats``).

    Args:
        task: the `jaxdrones.envs.task.Task` judged (``env.task``).
        stats: `episode_statistics`' dict (or any with ``success_value``, ``terminated_rate`` and ``n_episodes``,
            e.g. from episodes run outside jaxdrones' trainers).
    """
    from jaxdrones.training.progress import AGGREGATES

    failed = failed_criteria(task, stats)
    return {
        "success_metric": f"{task.success_metric} ({AGGREGATES[task.success_at]})",
        "success_unit": task.success_unit,
        "success_value": stats.get("success_value", math.nan),
        "success_threshold": task.success_threshold,
        "success": not failed,
        "failed_criteria": failed,
        "eval": dict(stats),
    }


def result_line(summary: dict) -> str:
    """One line on a run: ``"solved: distance (final) 0.02218 m (threshold 0.05 m) over 256 random starts (0.0 %
    terminated), 604,160 env steps, 17.6 s wall time"``, or ``"not solved: <the failed criteria>. ..."``: what
    ``jaxdrones train`` prints, and the notebooks.

    Args:
        summary: `judged`'s keys (``train_task``'s summary has them), with ``env_steps`` and ``wall_time_s`` where
            known.
    """
    stats, unit = summary["eval"], summary["success_unit"]
    threshold, n = summary["success_threshold"], stats.get("n_episodes", "?")
    result = (
        f"{summary['success_metric']} {summary['success_value']:.4g} {unit} (threshold {threshold:g} {unit}) over "
        f"{n} random starts ({stats.get('terminated_rate', math.nan):.1%} terminated)"
    )
    if summary.get("env_steps") is not None:
        result += f", {summary['env_steps']:,} env steps"
    if summary.get("wall_time_s") is not None:
        result += f", {summary['wall_time_s']:.1f} s wall time"
    if summary["success"]:
        return f"solved: {result}"
    return f"not solved: {'; '.join(summary['failed_criteria'])}. {result}"
