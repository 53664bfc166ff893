"""The env layer: a contract test over every registered task × action type × observation type, then the hover
task's reward, action mappings, time limit, termination and starts, domain randomisation, auto-reset, the brax
adapter and bad input."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.adapters.brax import BraxEnv, wrap_for_brax_training
from jaxdrones.envs import ACTION_TYPES, MULTI_AGENT, OBS_TYPES, SINGLE_AGENT, registered
from jaxdrones.envs.actions import ACTION_SIZES, FIRMWARE_ACTIONS
from jaxdrones.envs.observations import kinematic_obs
from jaxdrones.params import with_derived
from jaxdrones.rotations import quat_from_euler, quat_to_euler, quat_to_rotmat
from jaxdrones.wrappers import AutoReset, VmapAutoReset

N_WORLDS = 64
CONTRACT_STEPS = 300  # five 2-second episodes at the least (60 steps each)


def contract_cases():
    """Every task with its default observation type, and every action type on a single-agent and a multi-agent
    task (hover, leader_follower) with the observation types and the action buffer in turn. Tasks share the action
    and observation modules (a task adds only its own observation entries, present in every case) and differ in
    their starts, rewards and terminations, so this covers every task, every action mapping and every observation
    type on both kinds of task."""
    cases = {}
    for task in registered():
        default_obs = jd.envs.get_task(task).config_cls.obs_type
        cases[(task, "tun" if task == "tune" else "rpm", default_obs)] = False
    for task in ("hover", "leader_follower"):
        for i, action in enumerate(ACTION_TYPES):
            if action in FIRMWARE_ACTIONS:  # they need the physics at 1 kHz and lagging motors: firmware_hover's
                if task == "hover":
                    cases.setdefault(("firmware_hover", action, OBS_TYPES[i % len(OBS_TYPES)]), i % 2 == 1)
                continue
            cases.setdefault((task, action, OBS_TYPES[i % len(OBS_TYPES)]), i % 2 == 1)
    return [pytest.param(*k, buf, id="-".join(k), marks=pytest.mark.slow) for k, buf in cases.items()]


@pytest.mark.parametrize("task, action_type, obs_type, buffer", contract_cases())
def test_contract(task, action_type, obs_type, buffer):
    """Reset and 300 random steps under jit and vmap over 64 worlds: observations inside their bounds, no NaN,
    episodes ending and auto-resetting with fresh starts."""
    n = 3 if task in MULTI_AGENT else 1
    cameras = {"vision": ()} if task == "avoid" else {}  # the state contract (images: tests/test_cameras.py)
    env = jd.make(
        task,
        n_drones=n,
        action_type=action_type,
        obs_type=obs_type,
        action_buffer=buffer,
        episode_len_s=2.0,
        ctrl_freq=50 if task == "firmware_hover" else 30,  # the firmware's 1 kHz: 20 ticks a step
        **cameras,
    )
    auto = AutoReset(env)
    low, high = env.observation_bounds()
    a_low, a_high = env.action_bounds()
    assert low.shape == high.shape == (n, env.observation_size)

    def run(keys, actions):
        state = jax.vmap(auto.reset)(keys)

        def body(s, a):
            s = jax.vmap(auto.step)(s, a)
            out = (s.obs, s.reward, s.done, s.steps, s.sim.pos, s.info["final_obs"], s.terminated)
            return s, out

        return state.obs, jax.lax.scan(body, state, actions)[1]

    keys = jax.random.split(jax.random.key(0), N_WORLDS)
    actions = jax.random.uniform(
        jax.random.key(1), (CONTRACT_STEPS, N_WORLDS, n, env.action_size), minval=a_low, maxval=a_high
    )
    outputs = jax.tree.map(np.asarray, jax.jit(run)(keys, actions))
    first, (obs, reward, done, steps, pos, final_obs, terminated) = outputs
    assert first.shape == (N_WORLDS, n, env.observation_size)
    assert reward.shape == (CONTRACT_STEPS, N_WORLDS, n)
    for o in (first, obs, final_obs):
        assert np.all(np.isfinite(o))
        assert np.all(o >= low - 1e-5) and np.all(o <= high + 1e-5)
    assert np.all(np.isfinite(reward))
    # Episodes end (by the time limit at the latest) and every world starts new ones.
    assert done.any(axis=0).all()
    assert np.all(steps[done] == 0) and np.all(steps[~done] > 0)
    # Two consecutive episodes of a world start differently.
    w = int(np.argmax(done.sum(axis=0) >= 2))
    ends = np.flatnonzero(done[:, w])
    assert len(ends) >= 2
    starts = [pos[ends[0], w], pos[ends[1], w]]
    assert not np.allclose(starts[0], starts[1])
    assert not np.allclose(obs[ends[0], w], obs[ends[1], w])


# ------------------------------------------------------------------------------------------------------------------
# hover: the default 3-D task and the paper's 1-D setting
# ------------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def hover():
    env = jd.make("hover")
    return env, jax.jit(jax.vmap(env.reset)), jax.jit(env.step)


def keys(n=N_WORLDS, seed=0):
    return jax.random.split(jax.random.key(seed), n)


def test_the_control_rate_has_one_home(monkeypatch):
    """``jd.make(task, ctrl_freq=48)``: the config builds its `SimConfig` once, and the env, its physics step, its
    episode length, the tasks' references and the pickled config all read the rate from it."""
    from jaxdrones.physics import config as physics_config

    built = []
    post_init = physics_config.SimConfig.__post_init__
    monkeypatch.setattr(physics_config.SimConfig, "__post_init__", lambda self: built.append(post_init(self)))
    env = jd.make("velocity", ctrl_freq=48, episode_len_s=2.0)
    assert len(built) == 1
    assert env.config.sim is env._step.config
    assert (env.config.sim.ctrl_freq, env.config.sim.n_substeps, env.episode_length) == (48, 5, 96)
    state = env.reset(jax.random.key(0))
    ref = env.task.reference(env.config, state.task, jnp.asarray(48))  # one second in: the commanded velocity
    assert np.all(np.abs(state.task.data["target_vel"]) > 0.01)
    np.testing.assert_allclose(ref.pos - state.task.start.pos, state.task.data["target_vel"], atol=1e-6)
    import pickle

    loaded = pickle.loads(pickle.dumps(env.config))
    assert loaded == env.config and loaded.sim == env.config.sim and len(built) == 1


def test_hover_default_is_3d_with_random_starts(hover):
    env, reset, _ = hover
    assert env.config.action_type == "rpm" and env.action_size == 4 and env.observation_size == 21
    s = reset(keys(512))
    pos, vel, w = (np.asarray(x[:, 0]) for x in (s.sim.pos, s.sim.vel, s.sim.ang_vel))
    tilt = np.arccos(np.clip(np.asarray(jax.vmap(lambda q: 1 - 2 * (q[0] ** 2 + q[1] ** 2))(s.sim.quat[:, 0])), -1, 1))
    yaw = np.asarray(quat_to_euler(s.sim.quat[:, 0]))[:, 2]
    assert np.all(np.abs(pos - [0, 0, 1]) <= 0.5 + 1e-6) and np.ptp(pos, axis=0).min() > 0.9
    assert np.all(tilt <= 0.5 + 1e-4) and tilt.max() > 0.45
    assert yaw.min() < -2.8 and yaw.max() > 2.8
    assert np.all(np.abs(vel) <= 0.5 + 1e-6) and np.abs(vel).max() > 0.45
    assert np.all(np.abs(w) <= 1.0 + 1e-6) and np.abs(w).max() > 0.9
    # Same keys, same starts.
    np.testing.assert_array_equal(reset(keys(512)).obs, s.obs)


def test_hover_one_d_setting_has_level_vertical_starts():
    env = jd.make("hover", action_type="one_d_rpm")
    s = jax.vmap(env.reset)(keys(256))
    np.testing.assert_array_equal(s.sim.pos[:, 0, :2], 0.0)
    np.testing.assert_allclose(quat_to_euler(s.sim.quat[:, 0]), 0.0, atol=1e-6)
    z = np.asarray(s.sim.pos[:, 0, 2])
    assert z.min() >= 0.1125 - 1e-6 and z.max() <= 1.8 + 1e-6 and np.ptp(z) > 1.5
    np.testing.assert_array_equal(s.sim.vel[:, 0, :2], 0.0)


def test_fixed_start_overrides_random_ranges():
    init_pos, init_rpy = [[0.3, -0.2, 0.7]], [[0.1, -0.1, 0.5]]
    env = jd.make("hover", init_pos=init_pos, init_rpy=init_rpy)
    s = jax.vmap(env.reset)(keys(16))
    np.testing.assert_allclose(s.sim.pos[:, 0], np.broadcast_to(init_pos[0], (16, 3)), atol=1e-6)
    np.testing.assert_allclose(quat_to_euler(s.sim.quat[:, 0]), np.broadcast_to(init_rpy[0], (16, 3)), atol=1e-5)
    np.testing.assert_array_equal(s.sim.vel, 0.0)
    np.testing.assert_array_equal(s.sim.ang_vel, 0.0)
    multi = jd.make("multi_hover", n_drones=3, init_pos=[[0, 0, 1], [1, 0, 1], [0, 1, 1]])
    np.testing.assert_allclose(multi.reset(jax.random.key(3)).sim.pos, [[0, 0, 1], [1, 0, 1], [0, 1, 1]])


def test_shaped_reward_matches_documented_formula(hover):
    env, reset, step = hover
    s = reset(keys(8))
    s1 = jax.vmap(step)(s, jnp.zeros((8, 1, 4)))
    d = np.linalg.norm(np.asarray(s1.sim.pos[:, 0]) - [0, 0, 1], axis=-1)
    v2 = np.sum(np.asarray(s1.sim.vel[:, 0]) ** 2, -1)
    w2 = np.sum(np.asarray(s1.sim.ang_vel[:, 0]) ** 2, -1)
    expected = np.maximum(0, np.exp(-d / 0.3) + 2 * np.exp(-((d / 0.03) ** 2)) - 0.1 * v2 - 0.01 * w2)
    np.testing.assert_allclose(s1.reward[:, 0], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(
        s1.metrics["reward/closeness"], np.exp(-d / 0.3) + 2 * np.exp(-((d / 0.03) ** 2)), rtol=1e-5
    )


def test_paper_rewards():
    env = jd.make("hover", reward="paper")
    s = env.step(env.reset(jax.random.key(0)), jnp.zeros((1, 4)))
    np.testing.assert_allclose(s.reward, -np.sum((np.asarray(s.sim.pos) - [0, 0, 1]) ** 2, -1), rtol=1e-6)
    env = jd.make("takeoff", reward="paper")
    s = env.step(env.reset(jax.random.key(0)), jnp.zeros((1, 4)))
    z = float(s.sim.pos[0, 2])
    assert float(s.reward[0]) == pytest.approx(-5.0 if z < 0.02 else -1 / (10 * z), rel=1e-6)
    env = jd.make("leader_follower", n_drones=3, reward="paper")
    s = env.step(env.reset(jax.random.key(0)), jnp.zeros((3, 4)))
    p = np.asarray(s.sim.pos)
    expected = [-np.sum((p[0] - [0, 0, 0.5]) ** 2), -((p[1, 2] - p[0, 2]) ** 2) / 3, -((p[2, 2] - p[0, 2]) ** 2) / 3]
    np.testing.assert_allclose(s.reward, expected, rtol=1e-5)


@pytest.mark.parametrize(
    "action_type, action, factor",
    [
        ("rpm", [[0.0, 1.0, -1.0, 0.5]], [1.0, 1.05, 0.95, 1.025]),
        ("rpm", [[3.0, -3.0, 0.0, 0.0]], [1.05, 0.95, 1.0, 1.0]),  # clipped to the box
        ("one_d_rpm", [[-0.4]], [0.98] * 4),
    ],
)
def test_rpm_action_mappings(action_type, action, factor):
    env = jd.make("hover", action_type=action_type)
    s = env.step(env.reset(jax.random.key(0)), jnp.asarray(action, jnp.float32))
    np.testing.assert_allclose(s.sim.rpm[0], env.params.hover_rpm[0] * np.asarray(factor), rtol=1e-6)


def test_truncation_exactly_at_episode_length():
    env = jd.make("hover", init_pos=[[0, 0, 1]])
    assert env.episode_length == 150
    step = jax.jit(env.step)
    s = env.reset(jax.random.key(0))
    for _k in range(env.episode_length):
        assert not bool(s.truncated)
        s = step(s, jnp.zeros((1, 4)))
    assert bool(s.truncated) and not bool(s.terminated) and int(s.steps) == 150


@pytest.mark.parametrize(
    "pos, vel", [([1.49, 0, 1], [3, 0, 0]), ([0, 0, 2.45], [0, 0, 3]), ([0, -1.49, 1], [0, -3, 0])]
)
def test_leaving_the_arena_terminates(hover, pos, vel):
    env, _, step = hover
    s = env.reset(jax.random.key(0))
    s = s.replace(
        sim=s.sim.replace(
            pos=jnp.asarray([pos], jnp.float32),
            vel=jnp.asarray([vel], jnp.float32),
            quat=quat_from_euler(jnp.zeros((1, 3))),
        )
    )
    s = step(s, jnp.zeros((1, 4)))
    assert bool(s.terminated) and not bool(s.truncated) and float(s.metrics["crash"]) == 1.0


def test_ground_contact_terminates_only_when_asked():
    for flag in (False, True):
        env = jd.make("hover", init_pos=[[0, 0, 0.0125]], terminate_on_ground=flag)
        s = env.step(env.reset(jax.random.key(0)), -jnp.ones((1, 4)))
        assert bool(s.sim.ground_contact[0]) and bool(s.terminated) == flag


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_action_terminates_and_is_reported(hover, bad):
    env, _, step = hover
    s = step(env.reset(jax.random.key(0)), jnp.full((1, 4), bad))
    assert bool(s.terminated) and float(s.metrics["invalid_action"]) == 1.0
    assert np.all(np.isfinite(s.sim.pos))


def test_action_buffer_holds_last_actions_and_is_cleared_at_reset():
    env = jd.make("hover", obs_type="kin", action_buffer=True)
    k = env.config.sim.ctrl_freq // 2
    assert env.observation_size == 12 + 4 * k
    s = env.reset(jax.random.key(0))
    np.testing.assert_array_equal(s.obs[0, 12:], 0.0)
    a1, a2 = jnp.full((1, 4), 0.25), jnp.full((1, 4), -0.5)
    s = env.step(env.step(s, a1), a2)
    buf = np.asarray(s.obs[0, 12:]).reshape(k, 4)
    np.testing.assert_allclose(buf[-1], -0.5)
    np.testing.assert_allclose(buf[-2], 0.25)
    np.testing.assert_array_equal(buf[:-2], 0.0)
    auto = AutoReset(env)
    done = s.replace(truncated=jnp.array(True))
    fresh = auto.step(done.replace(steps=jnp.array(env.episode_length - 1)), a1)
    np.testing.assert_array_equal(fresh.obs[0, 12:], 0.0)


def test_action_buffer_of_k_actions():
    env = jd.make("hover", action_buffer=3)
    assert env.observation_size == 21 + 3 * 4 and jd.make("hover", action_buffer=0).observation_size == 21
    s = env.reset(jax.random.key(0))
    actions = [jnp.full((1, 4), v) for v in (0.1, 0.2, 0.3, 0.4)]
    for a in actions:
        s = env.step(s, a)
    np.testing.assert_allclose(np.asarray(s.obs[0, 21:]).reshape(3, 4), [[0.2] * 4, [0.3] * 4, [0.4] * 4], rtol=1e-6)


@pytest.mark.parametrize("task", ["hover", "velocity"])
def test_error_integral_sums_the_tracking_error(task):
    """I_t = clip(I_{t-1} + e_t / ctrl_freq, ±1), I_0 = e_0 / ctrl_freq, at the observation's end: hover's e is the
    target minus the position, velocity's the commanded minus the measured velocity."""
    from jaxdrones.envs.env import ERROR_INTEGRAL_BOUND

    env = jd.make(task, error_integral=True)
    plain = jd.make(task)
    assert env.observation_size == plain.observation_size + 3
    low, high = env.observation_bounds()
    np.testing.assert_array_equal(high[0, -3:], ERROR_INTEGRAL_BOUND)
    np.testing.assert_array_equal(low[0, -3:], -ERROR_INTEGRAL_BOUND)

    def error(s):
        if task == "velocity":
            return np.asarray(s.task.data["target_vel"] - s.sim.vel, np.float64)
        return np.asarray(s.task.target - s.sim.pos, np.float64)

    s = env.reset(jax.random.key(2))
    expected = error(s) / env.config.sim.ctrl_freq
    np.testing.assert_allclose(s.obs[:, -3:], expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(s.obs[:, :-3], plain.reset(jax.random.key(2)).obs)
    step = jax.jit(env.step)
    for _ in range(40):
        s = step(s, jnp.full((1, env.action_size), 0.3))  # climbs away: the integral grows, then saturates
        expected = np.clip(expected + error(s) / env.config.sim.ctrl_freq, -1.0, 1.0)
        np.testing.assert_allclose(s.obs[:, -3:], expected, rtol=1e-4, atol=1e-6)
    assert np.abs(expected).max() > 0.1


def test_error_integral_is_cleared_at_reset():
    env = AutoReset(jd.make("hover", error_integral=True))
    s = env.reset(jax.random.key(0))
    for _ in range(5):
        s = env.step(s, jnp.full((1, 4), 0.5))
    first = jd.make("hover", error_integral=True).reset(s.key)  # the episode the auto-reset starts
    done = s.replace(truncated=jnp.array(True), steps=jnp.array(env.episode_length - 1))
    fresh = env.step(done, jnp.full((1, 4), 0.5))
    np.testing.assert_allclose(fresh.obs[0, -3:], first.obs[0, -3:], rtol=1e-6)
    assert np.abs(np.asarray(s.obs[0, -3:])).max() > 2 * np.abs(np.asarray(fresh.obs[0, -3:])).max()


def test_observation_types():
    env = jd.make("multi_hover", n_drones=3, obs_type="neighbors", neighbor_radius=0.2)
    s = env.reset(jax.random.key(0))
    assert env.observation_size == 12 + 3 + 6 + 3
    pos = np.asarray(s.sim.pos)
    np.testing.assert_allclose(s.obs[:, :12], kinematic_obs(s.sim), rtol=1e-6, atol=1e-7)
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    np.testing.assert_array_equal(s.obs[:, 12:15], (dist < 0.2).astype(np.float32))
    rel = np.asarray(s.obs[0, 15:21]).reshape(2, 3)
    for row, j in zip(rel, (1, 2), strict=False):
        np.testing.assert_allclose(row, (pos[j] - pos[0]) * (dist[0, j] < 0.2), atol=1e-6)
    rot = jd.make("hover")
    s = rot.reset(jax.random.key(2))
    assert rot.config.obs_type == "kin_rotmat" and rot.observation_size == 21
    np.testing.assert_allclose(
        np.asarray(s.obs[0, 12:]).reshape(3, 3), np.asarray(jax.vmap(quat_to_rotmat)(s.sim.quat))[0], atol=1e-6
    )
    norm = jd.make("hover", obs_type="kin_norm")
    s = norm.reset(jax.random.key(1))
    s = s.replace(sim=s.sim.replace(vel=jnp.asarray([[0.3, -6.0, 0.5]], jnp.float32)))
    obs = np.asarray(norm.obs_type.observe(s.sim, s.history))[0]
    np.testing.assert_allclose(obs[6:9], [0.1, -1.0, 0.5], rtol=1e-6)  # vz over its own limit, 1 m/s


def test_nearest_neighbors_observation():
    """max_neighbors=k: the k nearest drones, nearest first, flagged within the radius; the size stays 12 + 4k + 3
    whatever the team; k >= D - 1 holds everyone. downwash_radius reaches the physics."""
    env = jd.make(
        "multi_hover", n_drones=16, obs_type="neighbors", max_neighbors=3, neighbor_radius=0.5, downwash_radius=1.0
    )
    assert env.observation_size == 12 + 4 * 3 + 3 and env.config.sim.downwash_radius == 1.0
    assert (
        jd.make("multi_hover", n_drones=64, obs_type="neighbors", max_neighbors=3).observation_size
        == env.observation_size
    )
    s = env.reset(jax.random.key(0))
    pos = np.asarray(s.sim.pos, np.float64)
    np.testing.assert_allclose(s.obs[:, :12], kinematic_obs(s.sim), rtol=1e-6, atol=1e-7)
    for i in range(16):
        dist = np.linalg.norm(pos - pos[i], axis=-1)
        dist[i] = np.inf
        order = np.argsort(dist)[:3]
        np.testing.assert_array_equal(s.obs[i, 12:15], (dist[order] < 0.5).astype(np.float32))
        expected = (pos[order] - pos[i]) * (dist[order] < 0.5)[:, None]
        np.testing.assert_allclose(np.asarray(s.obs[i, 15:24]).reshape(3, 3), expected, atol=1e-6)
    assert 0.0 < float(np.mean(s.obs[:, 12:15])) < 1.0  # some neighbours inside the radius, some outside
    low, high = env.observation_bounds()
    assert low.shape == (16, env.observation_size) and np.all(s.obs >= low) and np.all(s.obs <= high)
    small = jd.make("multi_hover", n_drones=3, obs_type="neighbors", max_neighbors=8)
    assert small.observation_size == 12 + 4 * 2 + 3
    with pytest.raises(ValueError, match="max_neighbors"):
        jd.make("multi_hover", n_drones=3, max_neighbors=0)
    with pytest.raises(ValueError, match="downwash_radius"):
        jd.make("multi_hover", n_drones=3, downwash_radius=-1.0)


def test_domain_randomisation_recomputes_derived_params():
    env = jd.make("hover", randomize={"mass": 0.2, "kf": 0.1, "inertia": 0.3})
    s = jax.vmap(env.reset)(keys(256))
    mass, kf = np.asarray(s.params.mass[:, 0]), np.asarray(s.params.kf[:, 0])
    base = env.params
    assert np.all(np.abs(mass / float(base.mass[0]) - 1) <= 0.2 + 1e-6) and np.ptp(mass) > 0.3 * float(base.mass[0])
    assert np.ptp(kf) > 0.1 * float(base.kf[0])
    hover_rpm = np.sqrt(mass * 9.8 / (4 * kf))
    np.testing.assert_allclose(s.params.hover_rpm[:, 0], hover_rpm, rtol=1e-5)
    np.testing.assert_allclose(
        np.asarray(s.params.inertia_inv[:, 0]) @ np.asarray(s.params.inertia[:, 0]),
        np.broadcast_to(np.eye(3), (256, 3, 3)),
        atol=1e-4,
    )
    # with_derived recomputes the derived fields of edited params.
    edited = with_derived(base.replace(mass=base.mass * 2))
    np.testing.assert_allclose(edited.hover_rpm, base.hover_rpm * np.sqrt(2), rtol=1e-6)


def test_motor_time_constants_are_drawn_with_the_other_params():
    # Given in randomize: drawn per drone and episode in the range, and the motors get their dynamics.
    env = jd.make("hover", randomize={"mass": 0.1, "motor_tau_up": (0.05, 0.2)})
    assert env.config.sim.motor_dynamics and env.shared_params is None
    s = jax.vmap(env.reset)(keys(256))
    up = np.asarray(s.params.motor_tau_up[:, 0])
    assert np.all((up >= 0.05) & (up <= 0.2)) and np.ptp(up) > 0.1
    np.testing.assert_array_equal(s.params.motor_tau_down, 0.0)  # not given: the URDF's
    # From the realism: the same draw, one home (TaskConfig.param_draws).
    env = jd.make("hover", motor_tau_up=(0.05, 0.2), motor_tau_down=0.1)
    assert env.config.randomize is None and env.config.param_draws.motor_tau_up == (0.05, 0.2)
    s = jax.vmap(env.reset)(keys(64))
    assert np.ptp(np.asarray(s.params.motor_tau_up)) > 0.05
    np.testing.assert_allclose(s.params.motor_tau_down, 0.1)
    # A time constant without a range: every episode shares the params, which hold it.
    env = jd.make("hover", realism="crazyflie")
    assert env.shared_params is not None and float(env.params.motor_tau_up[0]) > 0
    with pytest.raises(ValueError, match="give them once"):
        jd.make("hover", motor_tau_up=0.1, randomize={"motor_tau_up": (0.05, 0.2)})
    with pytest.raises(ValueError, match="low <= high"):
        jd.make("hover", randomize={"motor_tau_down": (0.2, 0.1)})


def test_auto_reset_draws_fresh_episodes():
    env = AutoReset(jd.make("velocity", episode_len_s=0.2, randomize={"mass": 0.1}))
    step = jax.jit(env.step)
    s = env.reset(jax.random.key(0))
    firsts = [(np.asarray(s.sim.pos), np.asarray(s.task.data["target_vel"]), float(s.params.mass[0]))]
    for _ in range(3 * env.episode_length):
        s = step(s, jnp.zeros((1, 4)))
        if bool(s.done):
            assert int(s.steps) == 0 and int(s.info["final_steps"]) == env.episode_length
            firsts.append((np.asarray(s.sim.pos), np.asarray(s.task.data["target_vel"]), float(s.params.mass[0])))
    assert len(firsts) == 4
    for a, b in zip(firsts, firsts[1:], strict=False):
        assert not np.allclose(a[0], b[0]) and not np.allclose(a[1], b[1]) and a[2] != b[2]


def _key_free(tree):
    def data(x):
        return np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x)

    return [data(x) for x in jax.tree.leaves(tree)]


@pytest.mark.parametrize("randomize", [{}, {"randomize": {"mass": 0.1}}], ids=["shared-params", "randomized"])
def test_vmap_auto_reset_equals_vmapped_auto_reset(randomize):
    """The batched auto-reset, which resets only the finished worlds, gives the states of vmap(AutoReset) both when
    few worlds end (gathered resets: 3 of 32, at most 4) and when many do (every world reset, then chosen); with
    params shared by every world it holds them once."""
    env = jd.make("velocity", episode_len_s=0.5, ctrl_freq=30, **randomize)
    n, one, batched = 32, AutoReset(env), VmapAutoReset(env, max_resets=4)
    assert batched.params_shared == (not randomize)
    keys = jax.random.split(jax.random.key(3), n)
    a, b = jax.jit(jax.vmap(one.reset))(keys), jax.jit(batched.reset)(keys)
    step_a, step_b = jax.jit(jax.vmap(one.step)), jax.jit(batched.step)
    actions = np.random.default_rng(0).uniform(-1, 1, (40, n, 1, 4)).astype(np.float32)
    actions[5, [1, 7, 30]] = np.nan  # 3 worlds terminate: the gathered path
    actions[9, :12] = np.nan  # 12 worlds: more than 4, every world is reset
    ended = []
    for action in actions:
        a, b = step_a(a, action), step_b(b, action)
        ended.append(int(np.sum(a.done)))
        per_world = b
        if batched.params_shared:
            np.testing.assert_array_equal(b.params.mass, env.params.mass)
            per_world = b.replace(params=jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), b.params))
        for x, y in zip(_key_free(a), _key_free(per_world), strict=True):
            # Equal up to float32 rounding: XLA may compile the two programs' arithmetic differently, and 40 steps
            # of flight carry its last bits on (2.5e-6 seen, at XLA's optimisation level 0).
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-5)
    # The time limit then ends at once the 19 worlds that were never reset (all but worlds 0-11 and 30).
    assert ended[5] == 3 and ended[9] == 12 and ended[14] == n - 13
    assert not np.allclose(a.sim.pos[1], b.sim.pos[2])


@pytest.mark.parametrize("randomize", [{}, {"randomize": {"mass": 0.1}}], ids=["shared-params", "randomized"])
def test_vmap_auto_reset_with_drawn_starts(randomize):
    """With the next episodes drawn before (`VmapAutoReset.starts`), a world whose episode ends takes its drawn
    episode: the same state as a reset computed in the step from the same key chain, for a few worlds or many; the
    worlds that go on are untouched; a world that ends again before the next draw starts the same episode again."""
    env = jd.make("velocity", episode_len_s=0.5, ctrl_freq=30, **randomize)
    n, auto = 32, VmapAutoReset(env, max_resets=4)
    state = jax.jit(auto.reset)(jax.random.split(jax.random.key(3), n))
    starts = jax.jit(auto.starts)(state)
    step = jax.jit(auto.step_ended)
    actions = np.random.default_rng(0).uniform(-1, 1, (n, 1, 4)).astype(np.float32)
    for ending in ([1, 7, 30], list(range(12))):  # the gathered resets (3 <= 4) and every world reset (12 > 4)
        action = actions.copy()
        action[ending] = np.nan
        ended, computed = step(state, action)
        ended_drawn, drawn = step(state, action, starts)
        assert sorted(np.nonzero(np.asarray(ended.done))[0]) == ending
        for x, y in zip(_key_free((ended, computed)), _key_free((ended_drawn, drawn)), strict=True):
            # Equal up to float32 rounding (two programs: 1.3e-7 seen in a component near 0.02).
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    ending = np.asarray(ending)
    np.testing.assert_array_equal(drawn.sim.pos[ending], starts.sim.pos[ending])
    np.testing.assert_array_equal(drawn.sim.pos[12:], ended.sim.pos[12:])
    again = step(drawn, action, starts)[1]
    np.testing.assert_array_equal(again.sim.pos[ending], starts.sim.pos[ending])


def test_heterogeneous_team():
    env = jd.make("multi_hover", n_drones=2, model=("cf2x", "racer"))
    np.testing.assert_allclose(env.params.mass, [0.027, 0.83], rtol=1e-6)
    s = env.step(env.reset(jax.random.key(0)), jnp.zeros((2, 4)))
    np.testing.assert_allclose(s.sim.rpm, np.asarray(env.params.hover_rpm)[:, None] * np.ones((2, 4)), rtol=1e-6)


# ------------------------------------------------------------------------------------------------------------------
# brax adapter
# ------------------------------------------------------------------------------------------------------------------


def test_brax_adapter_auto_resets_with_fresh_starts():
    env = jd.make("hover", obs_type="kin", episode_len_s=0.5)
    wrapped = wrap_for_brax_training(BraxEnv(env))
    reset, step = jax.jit(wrapped.reset), jax.jit(wrapped.step)
    state = reset(jax.random.split(jax.random.PRNGKey(0), 8))  # brax passes raw uint32 keys
    assert state.obs.shape == (8, 12) and state.reward.shape == (8,)
    first = np.asarray(state.obs)
    for _k in range(env.episode_length):
        state = step(state, jnp.zeros((8, 4)))
    assert np.all(np.asarray(state.done) == 1) and np.all(np.asarray(state.info["truncation"]) == 1)
    np.testing.assert_array_equal(state.info["steps"], env.episode_length)
    assert not np.allclose(np.asarray(state.obs), first)  # a new start, not the first one replayed
    state = step(state, jnp.zeros((8, 4)))
    assert np.all(np.asarray(state.done) == 0)
    # Typed keys work too.
    typed = jax.jit(wrapped.reset)(jax.random.split(jax.random.key(0), 8))
    np.testing.assert_array_equal(typed.obs, first)


@pytest.mark.parametrize("randomize", [None, {"mass": 0.1}], ids=["shared params", "params per world"])
def test_brax_training_wrapper_steps_as_brax_vmap_wrapper(randomize):
    """`wrap_for_brax_training` resets only the worlds whose episode ended (`VmapAutoReset`); its states are those of
    brax's ``VmapWrapper`` of the same `BraxEnv`, which resets every world at every step, through two episodes."""
    from brax.envs.wrappers.training import VmapWrapper

    env = jd.make("hover", episode_len_s=0.3, randomize=randomize)
    ours, brax = wrap_for_brax_training(BraxEnv(env)), VmapWrapper(BraxEnv(env))
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    a, b = jax.jit(ours.reset)(keys), jax.jit(brax.reset)(keys)
    actions = jax.random.uniform(jax.random.key(1), (2 * env.episode_length + 1, 8, 4), minval=-1, maxval=1)
    step_a, step_b = jax.jit(ours.step), jax.jit(brax.step)
    for action in actions:
        a, b = step_a(a, action), step_b(b, action)
        fields = lambda state: (state.obs, state.reward, state.done, state.info)  # noqa: E731
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6), fields(a), fields(b))
    assert float(a.info["episode_done"].sum()) == 0 and float(a.info["steps"][0]) == 1  # just restarted


def test_brax_rejects_randomization_fn():
    with pytest.raises(ValueError, match="randomize="):
        wrap_for_brax_training(BraxEnv(jd.make("hover")), 150, randomization_fn=lambda sys: (sys, None))


# ------------------------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, overrides, message",
    [
        ("flyaway", {}, "unknown task 'flyaway'"),
        ("hovr", {}, r"unknown task 'hovr' \(did you mean 'hover'\?\)"),
        ("hover", {"action_type": "warp"}, "unknown action_type 'warp'"),
        ("hover", {"obs_type": "lidar"}, "unknown obs_type 'lidar'"),
        ("hover", {"n_drones": 2}, "hover: n_drones must be exactly 1"),
        ("leader_follower", {"n_drones": 1}, "leader_follower: n_drones must be 2 or more"),
        ("hover", {"init_pos": [[0, 0, 1], [1, 0, 1]]}, r"init_pos must be f\[1, 3\]"),
        ("multi_hover", {"n_drones": 3, "init_pos": [0, 0, 1]}, r"init_pos must be f\[3, 3\]"),
        ("hover", {"randomize": {"mass": 1.0}}, "non-positive mass"),
        ("hover", {"randomize": {"mass": -0.1}}, "randomize.mass"),
        ("hover", {"target": (0, 0, -1)}, "above the ground"),
        ("hover", {"wind": 3}, r"unknown option 'wind'; valid options are"),
        ("hover", {"ctrl_fre": 3}, r"unknown option 'ctrl_fre' \(did you mean 'ctrl_freq'\?\)"),
        ("hover", {"obs": "kin"}, r"'obs' is gym-pybullet-drones' name: here obs_type.*jaxdrones.compat"),
        ("hover", {"model": "cf3"}, "unknown drone model 'cf3'"),
        ("multi_hover", {"n_drones": 3, "model": ("cf2x", "racer")}, "one per drone"),
        ("hover", {"vision": ("rgb",), "renderer": "egl"}, "renderer needs backend='pybullet'"),
        ("hover", {"vision": ("depth",), "obstacles": "paper"}, "URDF mesh"),
        ("tune", {"action_type": "rpm"}, "tune: action_type must be 'tun'"),
        ("hover", {"start_tilt": -1.0}, "start_tilt"),
        ("hover", {"episode_len_s": 0.0}, "episode_len_s"),
        ("hover", {"action_type": "pid", "pid_target": "relative", "pid_scale": 0.0}, r"pid_scale .* \(0, 1.0\]"),
        ("hover", {"pid_scale": "far"}, "pid_scale"),
    ],
)
def test_make_bad_input(name, overrides, message):
    with pytest.raises(ValueError, match=message):
        jd.make(name, **overrides)


@pytest.mark.parametrize("shape", [(4,), (1, 3), (2, 4)])
def test_wrong_action_shape(hover, shape):
    env, _, _ = hover
    with pytest.raises(ValueError, match=r"action must have shape \(1, 4\)"):
        env.step(env.reset(jax.random.key(0)), jnp.zeros(shape))


def test_non_float_action_rejected(hover):
    env, _, _ = hover
    with pytest.raises(ValueError, match="float"):
        env.step(env.reset(jax.random.key(0)), jnp.zeros((1, 4), jnp.int32))


def test_registry_lists_every_task():
    assert set(SINGLE_AGENT) | set(MULTI_AGENT) <= set(registered())  # and any registered by the README's example
    single = {"hover", "firmware_hover", "takeoff", "velocity", "waypoints", "fly_thru_gate", "tune", "avoid"}
    assert single == set(SINGLE_AGENT)
    assert {"multi_hover", "leader_follower", "flock", "meetup", "crossing"} == set(MULTI_AGENT)
    assert set(ACTION_SIZES) == set(ACTION_TYPES)
    for name in registered():
        fields = {f.name for f in dataclasses.fields(jd.envs.get_task(name).config_cls)}
        assert {"starts", "sim", "randomize", "n_drones", "model"} <= fields


# ------------------------------------------------------------------------------------------------------------------
# PID-based action types drive the DSL PID of the circle example with the original's target rules
# ------------------------------------------------------------------------------------------------------------------


def _pid_case(action_type, action, pos=(0.2, -0.1, 0.8), **options):
    from jaxdrones.envs.actions import Reference

    env = jd.make("hover", action_type=action_type, init_pos=[pos], init_rpy=[[0.1, -0.05, 0.3]], **options)
    s = env.reset(jax.random.key(0))
    s = s.replace(sim=s.sim.replace(vel=jnp.asarray([[0.1, 0.2, -0.1]], jnp.float32)))
    action = jnp.asarray([action], jnp.float32)
    ref = env.task.reference(env.config, s.task, s.steps)
    rpm, carry = env.action_type.to_rpm(s.params, s.sim, s.ctrl, action, ref, 1 / 30)
    assert isinstance(ref, Reference)
    return env, s, rpm, carry


@pytest.mark.parametrize(
    "action_type, action, pos, target, options",
    [
        ("pid", [0.5, 0.3, 0.9], (0.2, -0.1, 0.8), [0.5, 0.3, 0.9], {}),  # within 1 m: the target itself
        ("pid", [-1.0, 0.0, 1.0], (2.0, 0.0, 1.0), [1.0, 0.0, 1.0], {}),  # 3 m away: 1 m towards it
        ("pid", [0.5, -1.0, 1.0], (0.2, -0.1, 0.8), [0.25, -0.2, 0.9], {"pid_target": "relative"}),  # pos + 0.1 a
        ("pid", [0.5, -1.0, 1.0], (0.2, -0.1, 0.8), [0.35, -0.4, 1.1], {"pid_target": "relative", "pid_scale": 0.3}),
        ("one_d_pid", [0.6], (0.2, -0.1, 0.8), [0.2, -0.1, 0.86], {}),  # pos + (0, 0, 0.1 a)
    ],
)
def test_pid_actions_follow_the_original_target_rules(action_type, action, pos, target, options):
    from jaxdrones.control.pid import PIDGains, pid_control

    env, s, rpm, carry = _pid_case(action_type, action, pos, **options)
    expected, state = pid_control(
        s.params, PIDGains.dsl(), s.ctrl, s.sim, jnp.asarray([target], jnp.float32), ctrl_dt=1 / 30
    )
    np.testing.assert_allclose(rpm, expected, rtol=1e-5)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), carry, state)


def test_vel_and_tun_actions_drive_the_dsl_pid():
    from jaxdrones.control.pid import PIDGains, pid_control, velocity_control

    env, s, rpm, _ = _pid_case("vel", [0.0, 1.0, 0.0, 0.5])
    expected, _ = velocity_control(
        s.params, PIDGains.dsl(), s.ctrl, s.sim, jnp.asarray([[0.0, 1.0, 0.0, 0.5]]), ctrl_dt=1 / 30
    )
    np.testing.assert_allclose(rpm, expected, rtol=1e-5)
    scale = np.array([0.5, -0.2, 0.1, 0.3, 0.0, -0.4], np.float32)
    env, s, rpm, _ = _pid_case("tun", scale)
    base = PIDGains.dsl()
    gains = PIDGains(
        *(
            g * (1 + scale[k])
            for k, g in enumerate((base.p_pos, base.i_pos, base.d_pos, base.p_att, base.i_att, base.d_att))
        )
    )
    expected, _ = pid_control(s.params, gains, s.ctrl, s.sim, s.task.target, ctrl_dt=1 / 30)
    np.testing.assert_allclose(rpm, expected, rtol=1e-5)


def test_thrust_actions_use_the_nnls_mixer():
    from jaxdrones.control.mixer import allocation_matrix

    env = jd.make("hover", action_type="thrust_torque")
    s = env.reset(jax.random.key(0))
    a = jnp.asarray([[0.1, 0.5, -0.3, 0.2]], jnp.float32)
    rpm, _ = env.action_type.to_rpm(s.params, s.sim, s.ctrl, a, None, 1 / 30)
    wrench = np.asarray(allocation_matrix(s.params)[0]) @ np.asarray(rpm[0], np.float64) ** 2
    p = s.params
    expected = [
        1.1 * float(p.weight[0]),
        0.05 * 0.5 * float(p.max_xy_torque[0]),
        -0.05 * 0.3 * float(p.max_xy_torque[0]),
        0.05 * 0.2 * float(p.max_z_torque[0]),
    ]
    np.testing.assert_allclose(wrench, expected, rtol=2e-4, atol=1e-9)
    env = jd.make("hover", action_type="one_d_thrust")
    rpm, _ = env.action_type.to_rpm(s.params, s.sim, s.ctrl, jnp.asarray([[-0.6]], jnp.float32), None, 1 / 30)
    np.testing.assert_allclose(rpm[0], np.full(4, np.sqrt(0.97 * float(p.weight[0]) / (4 * float(p.kf[0])))), rtol=1e-5)
