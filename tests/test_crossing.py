"""The crossing task (the paper's downwash example as a multi-agent task): its moving reference, starts,
observation, rewards and metrics, downwash on by default and what it does to the lower drone, the config's
validation, and evaluation judged at the episode's maximum (``success_at = "max"``)."""

from __future__ import annotations

import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.envs.task import Task
from jaxdrones.envs.tasks.multi import Crossing, CrossingConfig
from jaxdrones.training.evaluation import episode_outcomes, episode_statistics, rollout_policy


def _reference(env, steps):
    ref = env.task.reference(env.config, env.default_task_params(), jnp.asarray(steps))
    return np.asarray(ref.pos), np.asarray(ref.vel)


def test_registered_with_downwash_on_by_default():
    env = jd.make("crossing")
    assert isinstance(env.task, Crossing) and env.config.sim.downwash and env.config.sim.downwash
    assert env.n_drones == 2 and env.episode_length == 150
    off = jd.make("crossing", downwash=False)
    assert not off.config.sim.downwash and not off.config.sim.downwash
    assert "crossing" in jd.envs.MULTI_AGENT
    task = env.task
    assert (task.success_metric, task.success_at, task.success_threshold) == ("max_altitude_error", "max", 0.05)


@pytest.mark.parametrize("n_drones", [2, 3])
def test_reference_crosses_at_quarter_periods(n_drones):
    """Period 4 s at 30 Hz: the reference points coincide in x at t = 0, T/4 = 1 s and 3T/4 = 3 s (x = 0 at the
    quarter periods), each at its own height, adjacent drones `spacing` apart; D = 2 is the original's layout."""
    env = jd.make("crossing", n_drones=n_drones, period_s=4.0, spacing=0.4)
    heights = 0.5 + 0.4 * (n_drones - 1 - np.arange(n_drones))
    pos0, vel0 = _reference(env, 0)
    np.testing.assert_allclose(pos0[:, 0], 0.5 * np.cos(np.pi * np.arange(n_drones)), atol=1e-6)
    np.testing.assert_allclose(vel0, 0.0, atol=1e-6)
    for steps in (0, 30, 90):
        pos, _ = _reference(env, steps)
        np.testing.assert_allclose(pos[:, 1], 0.0)
        np.testing.assert_allclose(pos[:, 2], heights, atol=1e-6)
        np.testing.assert_allclose(np.diff(pos[:, 2]), -0.4, atol=1e-6)
        if steps:
            np.testing.assert_allclose(pos[:, 0], 0.0, atol=1e-6)
        else:  # the drones start at opposite ends of the path: the same x every other drone
            np.testing.assert_allclose(pos[1:, 0], -pos[:-1, 0], atol=1e-6)
    # at T/2 the drones have swapped ends
    np.testing.assert_allclose(_reference(env, 60)[0][:, 0], -pos0[:, 0], atol=1e-5)
    pos_default, _ = _reference(jd.make("crossing"), 0)
    np.testing.assert_allclose(pos_default, [[0.5, 0.0, 1.0], [-0.5, 0.0, 0.5]], atol=1e-6)


def test_reference_velocity_is_the_derivative_of_the_position():
    env = jd.make("crossing", n_drones=3, amplitude=0.7, period_s=3.0)
    dt = 1 / env.config.sim.ctrl_freq
    for k in (1, 17, 40, 101):
        before, _ = _reference(env, k - 1)
        after, _ = _reference(env, k + 1)
        _, vel = _reference(env, k)
        np.testing.assert_allclose(vel, (after - before) / (2 * dt), atol=2e-3)
    assert np.max(np.abs(_reference(env, 22)[1][:, 0])) > 1.0  # near the peak speed A·2π/T = 1.47 m/s


def test_reference_of_a_flight_under_vmap():
    """As the training flight plot computes it: vmapped over the steps, f[T, D, 3]."""
    env = jd.make("crossing")
    task = env.reset(jax.random.key(0)).task
    ref = jax.vmap(lambda s: env.task.reference(env.config, task, s))(np.arange(env.episode_length + 1))
    assert ref.pos.shape == ref.vel.shape == (env.episode_length + 1, 2, 3)
    np.testing.assert_allclose(ref.pos[-1], ref.pos[0], atol=1e-5)  # one full 5 s period


def test_starts_observation_rewards_and_metrics():
    env = jd.make("crossing")
    states = jax.vmap(env.reset)(jax.random.split(jax.random.key(1), 64))
    pos0, _ = _reference(env, 0)
    pos = np.asarray(states.sim.pos)
    assert np.all(np.abs(pos[..., :2] - pos0[:, :2]) <= 0.02 + 1e-6)
    np.testing.assert_allclose(pos[..., 2], np.broadcast_to(pos0[:, 2], pos.shape[:2]), atol=1e-6)
    assert np.ptp(pos[:, 0, 0]) > 0.01  # the starts differ
    one_d = jax.vmap(jd.make("crossing", action_type="one_d_rpm").reset)(jax.random.split(jax.random.key(1), 8))
    np.testing.assert_array_equal(one_d.sim.vel, 0.0)
    np.testing.assert_array_equal(one_d.sim.ang_vel, 0.0)
    np.testing.assert_allclose(np.abs(one_d.sim.quat[..., 3]), 1.0, atol=1e-6)  # (x, y, z, w): level, facing +x

    step = jax.jit(env.step)
    s = env.reset(jax.random.key(2))
    for _ in range(20):
        s = step(s, jnp.zeros((2, 4)))
    ref_pos, ref_vel = _reference(env, 20)
    p, v = np.asarray(s.sim.pos), np.asarray(s.sim.vel)
    assert env.observation_size == s.obs.shape[-1] and env.task.obs_size == 6
    np.testing.assert_allclose(s.obs[:, -6:-3], ref_pos - p, atol=1e-5)
    np.testing.assert_allclose(s.obs[:, -3:], ref_vel, atol=1e-5)
    dist = np.linalg.norm(ref_pos - p, axis=-1)
    alt = np.abs(p[:, 2] - ref_pos[:, 2])
    np.testing.assert_allclose(s.metrics["tracking_error"], dist.mean(), rtol=1e-5)
    np.testing.assert_allclose(s.metrics["altitude_error"], alt.mean(), rtol=1e-5)
    np.testing.assert_allclose(s.metrics["max_altitude_error"], alt.max(), rtol=1e-5)
    closeness = np.exp(-dist / 0.3) + 2 * np.exp(-((dist / 0.03) ** 2))
    shaped = closeness - 0.1 * np.sum((v - ref_vel) ** 2, -1) - 0.01 * np.sum(np.asarray(s.sim.ang_vel) ** 2, -1)
    np.testing.assert_allclose(s.reward, np.maximum(shaped, 0.0), rtol=1e-5, atol=1e-6)

    paper = jd.make("crossing", reward="paper")
    sp = paper.reset(jax.random.key(2))
    for _ in range(20):
        sp = jax.jit(paper.step)(sp, jnp.zeros((2, 4)))
    d = np.linalg.norm(ref_pos - np.asarray(sp.sim.pos), axis=-1)
    np.testing.assert_allclose(sp.reward, np.maximum(0.0, 2.0 - d**4), rtol=1e-5)


def test_downwash_pushes_the_lower_drone_down():
    """Two drones exactly one above the other, 0.5 m apart, at hover RPM: with downwash the lower one gains the
    downward speed α/m·dt over one control step, α = c1 (R / (4·0.5 m))² ≈ 0.30 N (docs/physics.md §6.3); the
    upper drone feels nothing."""
    init = [[0.0, 0.0, 1.0], [0.0, 0.0, 0.5]]
    runs = {}
    for downwash in (True, False):
        env = jd.make("crossing", downwash=downwash, init_pos=init)
        s = env.reset(jax.random.key(0))
        s = jax.jit(env.step)(s, jnp.zeros((2, 4)))
        runs[downwash] = s.sim
    params = env.params
    c1 = float(params.dw_coeff[1, 0])
    alpha = c1 * (float(params.prop_radius[1]) / (4 * 0.5)) ** 2
    assert 0.25 < alpha < 0.35
    dvz = float(runs[True].vel[1, 2] - runs[False].vel[1, 2])
    np.testing.assert_allclose(dvz, -alpha / float(params.mass[1]) / env.config.sim.ctrl_freq, rtol=0.05)
    assert runs[True].pos[1, 2] < runs[False].pos[1, 2] - 3e-3
    np.testing.assert_allclose(runs[True].pos[0], runs[False].pos[0], atol=1e-7)
    np.testing.assert_allclose(runs[True].vel[0], runs[False].vel[0], atol=1e-7)


@pytest.mark.parametrize("field", ["period_s", "amplitude", "spacing"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf, "1", True, None])
def test_bad_config_values_raise(field, value):
    with pytest.raises(ValueError, match=f"crossing: {field} must be a finite number > 0"):
        jd.make("crossing", **{field: value})


def test_paths_outside_the_arena_raise():
    with pytest.raises(ValueError, match=r"top drone's altitude .* = 4 m must be below arena_z"):
        jd.make("crossing", n_drones=8)
    jd.make("crossing", n_drones=8, arena_z=5.0)
    with pytest.raises(ValueError, match="amplitude must be below arena_xy"):
        jd.make("crossing", amplitude=1.5)
    with pytest.raises(ValueError, match="n_drones must be 2 or more"):
        jd.make("crossing", n_drones=1)
    assert CrossingConfig(spacing=0.25, period_s=2).period_s == 2


def test_success_at_must_be_known():
    with pytest.raises(ValueError, match=r"success_at must be one of \('final', 'mean', 'max'\)"):
        type("Median", (Crossing,), {"success_at": "median"})


def _fake_outcomes():
    final = {"max_altitude_error": np.array([0.01, 0.03]), "distance": np.array([0.1, 0.2])}
    mean = {"max_altitude_error": np.array([0.02, 0.04]), "distance": np.array([0.2, 0.3])}
    maximum = {"max_altitude_error": np.array([0.1, 0.3]), "distance": np.array([0.5, 0.6])}
    return final, mean, np.array([False, False]), np.array([1.0, 3.0]), maximum


@pytest.mark.parametrize("success_at, expected", [("final", 0.02), ("mean", 0.03), ("max", 0.2)])
def test_episode_statistics_reads_the_success_metric_as_the_task_says(success_at, expected):
    task = types.SimpleNamespace(name="t", success_metric="max_altitude_error", success_at=success_at)
    stats = episode_statistics(types.SimpleNamespace(task=task), _fake_outcomes())
    assert stats["success_value"] == pytest.approx(expected)
    assert stats["final_max_altitude_error"] == pytest.approx(0.02)
    assert stats["mean_max_altitude_error"] == pytest.approx(0.03)
    assert stats["final_pos_error_m"] == pytest.approx(0.15) and stats["episode_reward"] == pytest.approx(2.0)
    if success_at == "max":
        assert stats["max_max_altitude_error"] == pytest.approx(0.2) and stats["max_distance"] == pytest.approx(0.55)
    else:  # the final and mean tasks report no maxima
        assert not any(k.startswith("max_") for k in stats)


def test_evaluation_takes_the_episode_maximum():
    """A proportional altitude policy (all four motors a = 20·Δz, with Δz the task observation's offset to the
    reference in z), which overshoots: the evaluation's max of the success metric is the largest value over the live
    steps of a manual rollout, and differs from the final and mean values."""
    env = jd.make("crossing", episode_len_s=1.0)

    def policy(obs, key):
        dz = jnp.reshape(obs, (env.n_drones, env.observation_size))[:, -4]
        return jnp.reshape(jnp.broadcast_to(jnp.clip(20 * dz, -1, 1)[:, None], (env.n_drones, 4)), (-1,)), {}

    keys = jax.random.split(jax.random.key(3), 4)
    outcomes = jax.jit(lambda k: episode_outcomes(env, policy, k))(keys)
    stats = episode_statistics(env, outcomes)
    values = []
    for k in keys:
        states = rollout_policy(env, policy, k)
        live = np.asarray(states.steps[1:] > states.steps[:-1])
        values.append(np.asarray(states.metrics["max_altitude_error"][1:])[live].max())
    # Equal up to float32 rounding: the evaluation's program and the rollout's are compiled apart.
    np.testing.assert_allclose(outcomes[4]["max_altitude_error"], values, rtol=1e-5)
    assert stats["success_value"] == pytest.approx(np.mean(values), rel=1e-5)
    assert stats["max_max_altitude_error"] == stats["success_value"]
    assert stats["success_value"] > stats["mean_max_altitude_error"]
    assert stats["success_value"] != pytest.approx(stats["final_max_altitude_error"])
    assert {"max_tracking_error", "max_altitude_error"} <= set(stats)


def test_jit_vmap_episode_with_downwash_stays_finite():
    env = jd.make("crossing", n_drones=3)

    def run(key):
        s = env.reset(key)
        return jax.lax.scan(lambda s, _: (env.step(s, jnp.zeros((3, 4))), None), s, None, length=30)[0]

    states = jax.jit(jax.vmap(run))(jax.random.split(jax.random.key(4), 8))
    assert np.all(np.isfinite(states.obs)) and np.all(np.isfinite(states.reward))
    assert Task.SUCCESS_AT == ("final", "mean", "max")


def test_bounded_downwash_keeps_every_drone_in_the_arena_under_random_actions():
    """`downwash="bounded"` (fitted to real flights, finite as Δz → 0): 1024 crossing episodes of uniformly random
    actions, each until it ends: no drone gets farther than 0.5 m beyond the arena (an episode ends at the step that
    leaves it), nor moves more than 0.5 m in one control step (with the paper's model, the same episodes move a drone
    1.26 m in one step; a trained policy once had one thrown 145 km)."""
    env = jd.make("crossing", downwash="bounded")
    assert env.config.sim.downwash == "bounded"
    policy = lambda obs, key: (jax.random.uniform(key, (env.n_drones, env.action_size), minval=-1, maxval=1), {})  # noqa: E731

    def run(key):
        return rollout_policy(env, policy, key).sim.pos

    pos = np.asarray(jax.jit(jax.vmap(run))(jax.random.split(jax.random.key(0), 1024)))  # [W, T, D, 3]
    assert np.all(np.isfinite(pos))
    assert np.max(np.abs(pos[..., :2])) < env.config.arena_xy + 0.5 and np.max(pos[..., 2]) < env.config.arena_z + 0.5
    assert np.max(np.linalg.norm(np.diff(pos, axis=1), axis=-1)) < 0.5


def test_bounded_downwash_is_finite_where_the_papers_is_not():
    """Two hovering cf2x 5 mm apart in height: the paper's downwash pushes the lower one at hundreds of g, the
    bounded form at under a fifth of its weight (α ≤ c1 (R/4)² / δ² at hover thrust, `BOUNDED_DOWNWASH`)."""
    from jaxdrones.physics.aerodynamics import BOUNDED_DOWNWASH, DOWNWASH_THRUST_REF, downwash_force

    params = jd.load_params("cf2x")
    pos = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.005]])
    thrust = jnp.full(2, DOWNWASH_THRUST_REF)
    weight = float(params.mass * params.gravity)
    paper = float(downwash_force(params, pos)[0])
    bounded = float(downwash_force(params, pos, bounded=BOUNDED_DOWNWASH, thrust=thrust)[0])
    c1, _, _, soft = BOUNDED_DOWNWASH
    assert paper < -100 * weight
    assert bounded == pytest.approx(-c1 * (float(params.prop_radius) / 4) ** 2 / (0.005**2 + soft**2), rel=1e-4)
    assert -0.2 * weight < bounded < 0
    with pytest.raises(ValueError, match="needs each drone's thrust"):
        downwash_force(params, pos, bounded=BOUNDED_DOWNWASH)
