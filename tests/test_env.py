"""Contract of the hover task (`jd.make("hover")`): shapes under jit and vmap, rewards, the action mapping, the
time limit, termination, bad input, the brax adapter and the random initial states."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.envs.base import kinematic_obs
from jaxdrones.rotations import quat_from_euler, quat_to_euler
from jaxdrones.wrappers.brax import BraxEnv, wrap_for_brax_training

N_WORLDS = 8
TARGET = np.array([0.0, 0.0, 1.0])


class Jitted:
    """An env with its jitted, vmapped reset and step (built once per module, so each compiles once)."""

    def __init__(self, **overrides):
        self.env = jd.make("hover", **overrides)
        self.reset = jax.jit(jax.vmap(self.env.reset))
        self.step = jax.jit(jax.vmap(self.env.step))
        self.step1 = jax.jit(self.env.step)
        self.episode = jax.jit(self._episode)

    def _episode(self, start, action):
        """Hold one action for a whole episode from ``start`` (no freezing after termination)."""

        def body(s, _):
            s = self.env.step(s, action)
            return s, s

        return jax.lax.scan(body, start, None, length=self.env.episode_length)[1]

    def start(self, key, pos, vel=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0)):
        """A reset state moved to ``pos`` m with ``vel`` m/s (world) and ``rpy`` rad."""
        s = self.env.reset(key)
        dtype = s.sim.pos.dtype
        return s.replace(sim=s.sim.replace(pos=jnp.asarray([pos], dtype), vel=jnp.asarray([vel], dtype),
                                           quat=quat_from_euler(jnp.asarray([rpy], dtype))))


@pytest.fixture(scope="module")
def hover():
    return Jitted()


@pytest.fixture(scope="module")
def hover_rpm():
    return Jitted(action_type="rpm")


def keys(n=N_WORLDS, seed=0):
    return jax.random.split(jax.random.key(seed), n)


def random_actions(n, size, seed=1, scale=1.0):
    return scale * jax.random.uniform(jax.random.key(seed), (n, size), minval=-1.0, maxval=1.0)


def pd_hold(obs):
    """A PD altitude hold at z = 1 m on the one_d_rpm action: keeps every default start inside the arena."""
    return jnp.clip(-2.0 * (obs[2] - 1.0) - 2.0 * obs[8], -1.0, 1.0)[None]


# ------------------------------------------------------------------------------------------------------------------
# Shapes, jit and vmap, rewards
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("action_type, size", [("one_d_rpm", 1), ("rpm", 4)])
def test_reset_step_batched(hover, hover_rpm, action_type, size):
    h = hover if action_type == "one_d_rpm" else hover_rpm
    assert h.env.action_size == size
    assert h.env.observation_size == 12
    s0 = h.reset(keys())
    assert s0.obs.shape == (N_WORLDS, 12)
    assert np.all(np.isfinite(s0.obs))
    assert not np.any(s0.terminated | s0.truncated)
    np.testing.assert_array_equal(s0.steps, 0)
    np.testing.assert_array_equal(s0.reward, 0.0)

    actions = random_actions(N_WORLDS, size)
    s1 = h.step(s0, actions)
    assert s1.obs.shape == (N_WORLDS, 12) and s1.reward.shape == (N_WORLDS,)
    assert np.all(np.isfinite(s1.obs)) and np.all(np.isfinite(s1.reward))
    assert np.all(s1.reward >= 0.0)
    np.testing.assert_array_equal(s1.steps, 1)
    # The observation is the kinematic state: pos, rpy, vel (world), ang_vel (body).
    np.testing.assert_allclose(s1.obs, kinematic_obs(s1.sim)[:, 0], rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(s1.obs[:, :3], s1.sim.pos[:, 0])
    np.testing.assert_array_equal(s1.obs[:, 6:9], s1.sim.vel[:, 0])

    if action_type == "one_d_rpm":  # vmap(step)(states)[i] == step(states[i])
        i = 3
        single = h.step1(jax.tree.map(lambda x: x[i], s0), actions[i])
        np.testing.assert_allclose(single.obs, s1.obs[i], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(single.reward, s1.reward[i], rtol=1e-6)


def test_shaped_reward_matches_documented_formula(hover):
    s = hover.step(hover.reset(keys()), random_actions(N_WORLDS, 1))
    d = np.linalg.norm(TARGET - np.asarray(s.sim.pos[:, 0]), axis=-1)
    v2 = np.sum(np.asarray(s.sim.vel[:, 0]) ** 2, axis=-1)
    expected = np.maximum(0.0, np.exp(-d / 0.3) + 2.0 * np.exp(-((d / 0.03) ** 2)) - 0.1 * v2)
    np.testing.assert_allclose(s.reward, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(s.metrics["distance"], d, rtol=1e-6)


def test_paper_reward_is_negative_squared_distance():
    h = Jitted(reward="paper")
    s = h.step(h.reset(keys()), random_actions(N_WORLDS, 1))
    expected = -np.sum((TARGET - np.asarray(s.sim.pos[:, 0])) ** 2, axis=-1)
    assert np.all(expected < 0)
    np.testing.assert_allclose(s.reward, expected, rtol=1e-6)


# ------------------------------------------------------------------------------------------------------------------
# Action mapping: rpm = hover_rpm · (1 + 0.05 · clip(a, -1, 1))
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("action, factor", [(0.0, 1.0), (1.0, 1.05), (-1.0, 0.95), (0.5, 1.025), (3.0, 1.05),
                                            (-7.0, 0.95)])
def test_one_d_rpm_action_mapping(hover, key, action, factor):
    s = hover.env.reset(key)
    nxt = hover.step1(s, jnp.array([action]))
    np.testing.assert_allclose(nxt.sim.rpm, np.full((1, 4), factor * float(s.params.hover_rpm)), rtol=1e-6)


def test_rpm_action_mapping_per_motor_and_clipped(hover_rpm, key):
    s = hover_rpm.env.reset(key)
    nxt = hover_rpm.step1(s, jnp.array([1.0, -1.0, 0.5, 7.0]))
    np.testing.assert_allclose(nxt.sim.rpm[0], float(s.params.hover_rpm) * np.array([1.05, 0.95, 1.025, 1.05]),
                               rtol=1e-6)


def test_out_of_range_action_acts_like_the_bound(hover, key):
    s = hover.env.reset(key)
    for big, bound in ((5.0, 1.0), (-5.0, -1.0)):
        a, b = hover.step1(s, jnp.array([big])), hover.step1(s, jnp.array([bound]))
        for x, y in zip(jax.tree.leaves(a.sim), jax.tree.leaves(b.sim)):
            np.testing.assert_array_equal(x, y)


# ------------------------------------------------------------------------------------------------------------------
# Time limit and termination
# ------------------------------------------------------------------------------------------------------------------


def test_truncation_exactly_at_episode_length(hover):
    env = hover.env
    assert env.episode_length == 150  # 5 s at 30 Hz

    @jax.jit
    def run(ks):
        def episode(k):
            def body(s, _):
                s = env.step(s, pd_hold(s.obs))
                return s, (s.terminated, s.truncated, s.steps, s.sim.pos[0, 2])

            return jax.lax.scan(body, env.reset(k), None, length=env.episode_length)[1]

        return jax.vmap(episode)(ks)

    terminated, truncated, steps, z = (np.asarray(x) for x in run(keys()))
    assert not terminated.any()
    assert not truncated[:, :-1].any()
    assert truncated[:, -1].all()
    np.testing.assert_array_equal(steps, np.broadcast_to(np.arange(1, 151), steps.shape))
    assert np.all((z > 0) & (z < env.config.arena_z))


@pytest.mark.parametrize("exit_via", ["top", "side", "tilt"])
def test_leaving_the_arena_terminates(hover, key, exit_via):
    cfg = hover.env.config
    if exit_via == "top":  # start near the ceiling, full thrust: a = g·(1.05² − 1) upwards
        start, action = hover.start(key, (0.0, 0.0, 2.3)), jnp.ones(1)
    elif exit_via == "side":
        start, action = hover.start(key, (1.41, 0.0, 1.0), vel=(1.0, 0.0, 0.0)), jnp.zeros(1)
    else:
        start, action = hover.start(key, (0.0, 0.0, 1.0), rpy=(cfg.max_tilt + 0.05, 0.0, 0.0)), jnp.zeros(1)
    states = hover.episode(start, action)
    pos = np.asarray(states.sim.pos[:, 0])
    rpy = np.asarray(quat_to_euler(states.sim.quat[:, 0]))
    outside = ((np.abs(pos[:, :2]) > cfg.arena_xy).any(-1) | (pos[:, 2] > cfg.arena_z)
               | (np.abs(rpy[:, :2]) > cfg.max_tilt).any(-1))
    assert outside.any()
    np.testing.assert_array_equal(states.terminated, outside)
    np.testing.assert_array_equal(states.metrics["crash"], outside.astype(float))
    assert not np.asarray(states.truncated).any()
    first = int(np.argmax(outside))
    if exit_via == "top":
        a = 9.8 * (1.05**2 - 1.0)
        t_exit = np.sqrt(2 * (cfg.arena_z - 2.3) / a)
        assert abs(first + 1 - t_exit * cfg.ctrl_freq) <= 1.0
    elif exit_via == "side":
        assert first + 1 == 3  # x = 1.41 + k/30 m exceeds 1.5 m at step k = 3
    else:
        assert first == 0


def test_ground_contact_terminates_only_when_asked(hover, key):
    on_ground = Jitted(terminate_on_ground=True)
    action = -jnp.ones(1)  # 0.95 hover RPM: sinks at g·(1 − 0.95²) ≈ 0.96 m/s²
    holding = hover.episode(hover.start(key, (0.0, 0.0, 0.3)), action)
    assert np.asarray(holding.sim.ground_contact[-1, 0])
    np.testing.assert_allclose(holding.sim.pos[-1, 0, 2], 0.0125, atol=1e-6)  # rests on the ground
    assert not np.asarray(holding.terminated).any()
    assert np.asarray(holding.truncated[-1])

    crashing = on_ground.episode(on_ground.start(key, (0.0, 0.0, 0.3)), action)
    contact = np.asarray(crashing.sim.ground_contact[:, 0])
    first = int(np.argmax(contact))
    assert contact.any() and 15 < first < 30
    assert not np.asarray(crashing.terminated[:first]).any()
    assert np.asarray(crashing.terminated[first])
    assert crashing.metrics["crash"][first] == 1.0
    assert not np.asarray(crashing.truncated).any()


# ------------------------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(), (4,), (1, 1), (2,)])
def test_wrong_action_shape(hover, key, shape):
    s = hover.env.reset(key)
    with pytest.raises(ValueError, match=re.escape("action must have shape (1,)") + ".*" + re.escape(str(shape))):
        hover.env.step(s, jnp.zeros(shape))


def test_wrong_action_shape_rpm(hover_rpm, key):
    s = hover_rpm.env.reset(key)
    with pytest.raises(ValueError, match=re.escape("action must have shape (4,)") + ".*'rpm'.*" + re.escape("(1,)")):
        hover_rpm.env.step(s, jnp.zeros(1))
    with pytest.raises(ValueError, match=re.escape("action must have shape (4,)")):  # also inside jit
        hover_rpm.step1(s, jnp.zeros(1))


@pytest.mark.parametrize("dtype", [np.int32, bool])
def test_non_float_action_rejected(hover, key, dtype):
    s = hover.env.reset(key)
    with pytest.raises(ValueError, match="action must be a float array.*" + np.dtype(dtype).name):
        hover.env.step(s, np.zeros(1, dtype=dtype))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_action_terminates_and_is_reported(hover, hover_rpm, key, bad):
    for h, action in ((hover, jnp.array([bad])), (hover_rpm, jnp.array([0.5, bad, 0.0, -0.5]))):
        s = h.env.reset(key)
        nxt = h.step1(s, action)
        assert bool(nxt.terminated) and not bool(nxt.truncated)
        assert nxt.metrics["invalid_action"] == 1.0
        assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(nxt.sim) if x.dtype != bool)
        assert np.all(np.isfinite(nxt.obs)) and np.isfinite(nxt.reward)
        # Documented: the physics sees action 0, i.e. hover RPM on every motor.
        np.testing.assert_allclose(nxt.sim.rpm, np.full((1, 4), float(s.params.hover_rpm)), rtol=1e-6)
    ok = hover.step1(hover.env.reset(key), jnp.zeros(1))
    assert ok.metrics["invalid_action"] == 0.0 and not bool(ok.terminated)


def test_make_unknown_name():
    with pytest.raises(ValueError, match=r"unknown environment 'nope'.*'hover'"):
        jd.make("nope")


def test_make_unknown_option():
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['bogus'\].*valid options.*action_type"):
        jd.make("hover", bogus=1)


@pytest.mark.parametrize("overrides, message", [
    (dict(action_type="x"), r"action_type must be one of \('rpm', 'one_d_rpm'\), got 'x'"),
    (dict(reward="dense"), r"reward must be one of \('shaped', 'paper'\), got 'dense'"),
    (dict(target=(0.0, 1.0)), r"target must be three finite numbers \(x, y, z\)"),
    (dict(init_z=(1.0, 0.5)), r"init_z must be a finite \(low, high\) range"),
    (dict(episode_len_s=0.0), r"at least one step"),
    (dict(ctrl_freq=7), r"sim_freq \(240 Hz\) must be a multiple of ctrl_freq \(7 Hz\)"),
    (dict(model="nope"), r"unknown drone model 'nope'"),
])
def test_make_invalid_option_value(overrides, message):
    with pytest.raises(ValueError, match=message):
        jd.make("hover", **overrides)


@pytest.mark.parametrize("overrides", [
    dict(init_vz=-0.2),
    dict(init_xy=-0.5),
    dict(init_rpy=float("inf")),
    dict(episode_len_s=float("nan")),
    dict(target=(0.0, 0.0, float("nan"))),
    dict(init_z=(-0.1, 1.0)),
    dict(arena_z=0.0),
])
def test_make_rejects_negative_ranges_and_non_finite_values(overrides):
    with pytest.raises(ValueError, match="hover"):
        jd.make("hover", **overrides)


# ------------------------------------------------------------------------------------------------------------------
# brax adapter
# ------------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def brax_env(hover):
    env = wrap_for_brax_training(BraxEnv(hover.env), episode_length=hover.env.episode_length)
    return env, jax.jit(env.reset), jax.jit(env.step)


def test_brax_adapter_batch_and_time_limit(hover, brax_env):
    _, reset, step = brax_env
    assert BraxEnv(hover.env).observation_size == 12 and BraxEnv(hover.env).action_size == 1
    rng = jax.random.split(jax.random.PRNGKey(0), N_WORLDS)  # brax passes raw uint32 keys
    state = reset(rng)
    assert state.obs.shape == (N_WORLDS, 12) and state.reward.shape == (N_WORLDS,)
    # Each world starts as the jaxdrones env does from the same key.
    np.testing.assert_allclose(state.obs, hover.reset(jax.random.wrap_key_data(rng)).obs, rtol=1e-6)

    first_obs = np.asarray(state.obs)
    dones, truncs = [], []
    for _ in range(hover.env.episode_length):
        state = step(state, jax.vmap(pd_hold)(state.obs))
        dones.append(np.asarray(state.done))
        truncs.append(np.asarray(state.info["truncation"]))
    dones, truncs = np.array(dones), np.array(truncs)
    assert not dones[:-1].any() and not truncs[:-1].any()
    assert dones[-1].all() and truncs[-1].all()  # brax's time limit, marked as truncation
    assert not np.asarray(state.pipeline_state.terminated).any()
    # Auto-reset: the next state is the first one again.
    np.testing.assert_array_equal(state.obs, first_obs)
    assert np.all(np.isfinite(state.reward))


def test_brax_adapter_done_from_termination(hover, brax_env):
    _, reset, step = brax_env
    state = reset(jax.random.split(jax.random.PRNGKey(1), N_WORLDS))
    # Put world 0 just under the ceiling, climbing fast: it terminates on the next step.
    ps = state.pipeline_state
    sim = ps.sim.replace(pos=ps.sim.pos.at[0, 0].set(jnp.array([0.0, 0.0, 2.45])),
                         vel=ps.sim.vel.at[0, 0].set(jnp.array([0.0, 0.0, 3.0])))
    state = state.replace(pipeline_state=ps.replace(sim=sim))
    state = step(state, jnp.zeros((N_WORLDS, 1)).at[0].set(1.0))
    expected = np.zeros(N_WORLDS)
    expected[0] = 1.0
    np.testing.assert_array_equal(state.done, expected)
    np.testing.assert_array_equal(state.info["truncation"], 0.0)
    np.testing.assert_array_equal(state.metrics["crash"], expected)
    # World 0 was auto-reset; the others went on.
    np.testing.assert_array_equal(state.pipeline_state.steps, 1 - expected)

    # The bare adapter: done is the task's termination only, not its time limit.
    bare = BraxEnv(hover.env)
    bare_step = jax.jit(bare.step)
    s = bare.reset(jax.random.PRNGKey(2))
    assert float(bare_step(s, jnp.array([np.nan])).done) == 1.0
    late = s.replace(pipeline_state=s.pipeline_state.replace(steps=jnp.array(hover.env.episode_length - 1)))
    late = bare_step(late, jnp.zeros(1))
    assert bool(late.pipeline_state.truncated) and float(late.done) == 0.0


def test_brax_rejects_randomization_fn(hover):
    with pytest.raises(ValueError, match="randomization_fn"):
        wrap_for_brax_training(BraxEnv(hover.env), 150, randomization_fn=lambda sys: (sys, None))


# ------------------------------------------------------------------------------------------------------------------
# Random initial states
# ------------------------------------------------------------------------------------------------------------------


def test_initial_states_random_and_within_documented_ranges():
    h = Jitted(action_type="rpm", init_xy=0.3, init_rpy=0.1)
    cfg = h.env.config
    s = h.reset(keys(256))
    pos, vel = np.asarray(s.sim.pos[:, 0]), np.asarray(s.sim.vel[:, 0])
    rpy = np.asarray(quat_to_euler(s.sim.quat[:, 0]))
    # Different keys give different starts, and the same key the same start.
    assert len(np.unique(pos[:, 2])) > 250 and len(np.unique(vel[:, 2])) > 250  # float32 ties are possible
    np.testing.assert_array_equal(h.reset(keys(256)).obs, s.obs)
    assert np.all((pos[:, 2] >= cfg.init_z[0]) & (pos[:, 2] <= cfg.init_z[1]))
    assert np.all(np.abs(pos[:, :2]) <= cfg.init_xy)
    assert np.all(np.abs(vel[:, 2]) <= cfg.init_vz)
    assert np.all(np.abs(rpy) <= cfg.init_rpy + 1e-6)
    np.testing.assert_array_equal(vel[:, :2], 0.0)
    np.testing.assert_array_equal(s.sim.ang_vel, 0.0)
    np.testing.assert_array_equal(s.sim.rpm, 0.0)
    # The samples cover their ranges (256 uniform draws: each end within 5 % of the width).
    for x, lo, hi in ((pos[:, 2], *cfg.init_z), (vel[:, 2], -cfg.init_vz, cfg.init_vz),
                      (pos[:, 0], -cfg.init_xy, cfg.init_xy), (rpy[:, 0], -cfg.init_rpy, cfg.init_rpy)):
        assert x.min() < lo + 0.05 * (hi - lo) and x.max() > hi - 0.05 * (hi - lo)


def test_default_starts_are_vertical_and_centred(hover):
    s = hover.reset(keys())
    np.testing.assert_array_equal(s.sim.pos[:, 0, :2], 0.0)
    np.testing.assert_allclose(quat_to_euler(s.sim.quat[:, 0]), 0.0, atol=1e-7)
