"""Multi-agent adapters: PettingZoo's parallel API test for every multi-agent task and drone count, seeding,
episodes to truncation, per-agent values equal to the stacked env's, the JaxMARL view under jit and vmap with its
auto-reset, and bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils import seeding
from pettingzoo.test import parallel_api_test

import jaxdrones as jd
from jaxdrones.adapters import jaxmarl
from jaxdrones.adapters.pettingzoo import PettingZooEnv, parallel_env
from jaxdrones.envs import MULTI_AGENT

#: Short episodes (0.3 s at 30 Hz: 9 control steps) so that the API test sees episodes end.
SHORT = 0.3


@pytest.mark.slow
@pytest.mark.parametrize("n_drones", [2, 3, 5])
@pytest.mark.parametrize("task", MULTI_AGENT)
def test_parallel_api_test_passes(task, n_drones, recwarn):
    env = parallel_env(task, n_drones=n_drones, episode_len_s=SHORT)
    assert env.possible_agents == [f"drone_{i}" for i in range(n_drones)]
    assert env.metadata["name"] == f"jaxdrones_{task}_v0"
    parallel_api_test(env, num_cycles=12)
    assert env.agents == []  # the episode ended within the 12 cycles
    assert not [w for w in recwarn.list if "agent" in str(w.message).lower()], [str(w.message) for w in recwarn]
    env.close()


@pytest.fixture(scope="module")
def pz():
    """leader_follower with 3 drones and 0.5 s (15-step) episodes; the leader's reward differs from the others'."""
    env = parallel_env("leader_follower", n_drones=3, episode_len_s=0.5)
    yield env
    env.close()


def test_spaces_are_per_agent_rows_of_the_stacked_bounds(pz):
    low, high = pz.env.observation_bounds()
    a_low, a_high = pz.env.action_bounds()
    for i, agent in enumerate(pz.possible_agents):
        obs_space, action_space = pz.observation_space(agent), pz.action_space(agent)
        assert obs_space is pz.observation_space(agent) and action_space is pz.action_space(agent)
        assert obs_space.shape == (pz.env.observation_size,) and obs_space.dtype == np.float32
        assert action_space.shape == (4,) and action_space.dtype == np.float32
        np.testing.assert_array_equal(obs_space.low, low[i])
        np.testing.assert_array_equal(obs_space.high, high[i])
        np.testing.assert_array_equal(action_space.low, a_low[i])
        np.testing.assert_array_equal(action_space.high, a_high[i])


def test_seeded_reset_is_reproducible(pz):
    a, infos = pz.reset(seed=3)
    assert set(a) == set(infos) == {"drone_0", "drone_1", "drone_2"} and infos["drone_0"]["crash"] == 0.0
    b, _ = pz.reset()  # continues the seeded sequence: a new start
    c, _ = pz.reset(seed=3)
    d, _ = pz.reset(seed=4)
    for agent in pz.possible_agents:
        assert a[agent].dtype == np.float32 and a[agent].shape == (pz.env.observation_size,)
        assert a[agent].flags.writeable  # torch.from_numpy takes it without a warning
        np.testing.assert_array_equal(a[agent], c[agent])
        assert not np.allclose(a[agent], b[agent]) and not np.allclose(a[agent], d[agent])
    # the three drones start at different places: the agents' rows differ
    assert not np.allclose(a["drone_0"][:3], a["drone_1"][:3])


def test_episode_runs_to_truncation_and_agents_empty(pz):
    obs, _ = pz.reset(seed=0)
    steps, live = 0, True
    while live:
        actions = {agent: np.zeros(4, np.float32) for agent in pz.agents}  # hover RPM
        obs, rewards, terminations, truncations, infos = pz.step(actions)
        steps += 1
        assert set(obs) == set(rewards) == set(terminations) == set(truncations) == set(infos) == set(actions)
        for agent in actions:
            assert pz.observation_space(agent).contains(obs[agent])
            assert np.isfinite(rewards[agent]) and rewards[agent] >= 0 and isinstance(rewards[agent], float)
        live = bool(pz.agents)
        assert live == (steps < 15)
    assert steps == pz.env.episode_length == 15
    assert all(truncations.values()) and not any(terminations.values()) and pz.agents == []
    with pytest.raises(RuntimeError, match="call reset"):
        pz.step({})


def test_per_agent_values_equal_the_stacked_env(pz):
    seed, rng = 7, np.random.default_rng(0)
    obs, _ = pz.reset(seed=seed)
    np_random, _ = seeding.np_random(seed)  # the adapter draws its key the same way
    env = pz.env
    state = jax.jit(env.reset)(jax.random.key(int(np_random.integers(2**31))))
    step = jax.jit(env.step)
    rewards_seen = []
    for _ in range(5):
        for i, agent in enumerate(pz.possible_agents):
            np.testing.assert_array_equal(obs[agent], np.asarray(state.obs[i]))
        action = rng.uniform(-1, 1, (3, 4)).astype(np.float32)
        obs, rewards, terminations, truncations, _ = pz.step({a: action[i] for i, a in enumerate(pz.agents)})
        state = step(state, action)
        reward = np.asarray(state.reward)
        assert [rewards[f"drone_{i}"] for i in range(3)] == pytest.approx(reward.tolist(), rel=0, abs=0)
        assert all(v == bool(state.terminated) for v in terminations.values())
        assert all(v == bool(state.truncated) for v in truncations.values())
        rewards_seen.append(reward)
    assert np.ptp(np.stack(rewards_seen), axis=1).max() > 1e-4  # per-drone rewards differ: the mapping matters


def test_render_rgb_array_of_a_configured_env():
    env = PettingZooEnv(jd.make("meetup", n_drones=2, action_type="one_d_rpm"), render_mode="rgb_array")
    assert env.render() is None  # no episode yet
    assert env.action_space("drone_1").shape == (1,)
    env.reset(seed=0)
    _, rewards, *_ = env.step({"drone_0": np.array([0.5], np.float32), "drone_1": np.array([-0.5], np.float32)})
    assert set(rewards) == {"drone_0", "drone_1"} and rewards["drone_0"] != rewards["drone_1"]
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[-1] == 3 and frame.std() > 0
    assert parallel_env("meetup", n_drones=2).render() is None


def test_bad_input_to_parallel_env(pz):
    pz.reset(seed=0)
    ok = {agent: np.zeros(4, np.float32) for agent in pz.agents}
    with pytest.raises(ValueError, match=r"\['drone_0', 'drone_1', 'drone_2'\]: missing \['drone_2'\]"):
        pz.step({k: v for k, v in ok.items() if k != "drone_2"})
    with pytest.raises(ValueError, match=r"unexpected \['drone_3'\]"):
        pz.step({**ok, "drone_3": np.zeros(4, np.float32)})
    with pytest.raises(ValueError, match=r"unexpected \['agent_0'\]"):
        pz.step({**{k: v for k, v in ok.items() if k != "drone_0"}, "agent_0": np.zeros(4)})
    with pytest.raises(ValueError, match="must be a dict"):
        pz.step(np.zeros((3, 4), np.float32))
    with pytest.raises(ValueError, match=r"action of drone_1 must have shape \(4,\), got \(3,\)"):
        pz.step({**ok, "drone_1": np.zeros(3, np.float32)})
    with pytest.raises(ValueError, match="action of drone_0 must be finite"):
        pz.step({**ok, "drone_0": np.array([0.0, np.nan, 0.0, 0.0], np.float32)})
    with pytest.raises(ValueError, match="action of drone_0 must be a float array"):
        pz.step({**ok, "drone_0": "up"})
    assert pz.agents == pz.possible_agents  # nothing was stepped
    with pytest.raises(ValueError, match=r"unknown agent 'drone_9'.*drone_0"):
        pz.observation_space("drone_9")
    with pytest.raises(ValueError, match=r"'hover' is a single-agent task.*multi_hover.*meetup"):
        parallel_env("hover")
    with pytest.raises(ValueError, match=r"'hovr' is not a registered task.*multi_hover"):
        parallel_env("hovr")
    with pytest.raises(ValueError, match="leader_follower: n_drones must be 2 or more, got 1"):
        parallel_env("leader_follower", n_drones=1)
    with pytest.raises(ValueError, match="render_mode must be None or one of"):
        parallel_env("flock", render_mode="window")
    with pytest.raises(ValueError, match="single-agent"):
        jaxmarl.make("velocity")


@pytest.fixture(scope="module")
def marl():
    """The JaxMARL view of flock with 3 drones and 0.2 s (6-step) episodes, its step jitted over 3 worlds."""
    view = jaxmarl.make("flock", n_drones=3, episode_len_s=0.2)
    keys = jax.random.split(jax.random.key(0), 3)
    return view, keys, jax.jit(jax.vmap(view.reset)), jax.jit(jax.vmap(view.step))


def test_jaxmarl_view_matches_the_stacked_env_under_jit_and_vmap(marl):
    marl, keys, reset, step = marl
    env, n_drones = marl.env, 3
    assert marl.num_agents == n_drones and marl.agents == ["drone_0", "drone_1", "drone_2"] and marl.name == "flock"
    assert marl.observation_space("drone_1") is marl.observation_space("drone_1")
    assert marl.action_space("drone_2").shape == (4,)
    obs, state = reset(keys)
    ref_step, ref_reset = jax.jit(jax.vmap(env.step)), jax.jit(jax.vmap(env.reset))
    ref = ref_reset(keys)
    n_steps = env.episode_length + 2
    box = marl.action_space("drone_0")  # all boxes are [-1, 1]^4
    actions_all = jax.vmap(box.sample)(jax.random.split(jax.random.key(1), n_drones * n_steps * len(keys)))
    assert bool(jnp.all(jax.vmap(box.contains)(actions_all))) and not box.contains(jnp.full(4, 1.5))
    actions_all = actions_all.reshape(n_drones, n_steps, len(keys), 4)
    for t in range(n_steps):
        for i, agent in enumerate(marl.agents):
            # Up to float32 rounding: the view's program and the stacked env's are compiled apart.
            np.testing.assert_allclose(obs[agent], ref.obs[:, i], rtol=0, atol=1e-5)
        actions = {a: actions_all[i, t] for i, a in enumerate(marl.agents)}
        obs, state, rewards, dones, infos = step(keys, state, actions)
        ref = ref_step(ref, jnp.stack([actions[a] for a in marl.agents], axis=1))
        for i, agent in enumerate(marl.agents):
            np.testing.assert_allclose(rewards[agent], ref.reward[:, i], rtol=0, atol=1e-5)
            np.testing.assert_array_equal(dones[agent], dones["__all__"])
        np.testing.assert_array_equal(dones["__all__"], np.asarray(ref.done))
        # JaxMARL's convention: every info leaf has one entry per agent, f[W, D] here
        assert set(infos) == set(ref.metrics) | {"terminated", "truncated", "final_steps"}
        assert all(v.shape == (len(keys), n_drones) for v in infos.values())
        np.testing.assert_array_equal(infos["truncated"], np.repeat(np.asarray(ref.truncated)[:, None], 3, 1))
        for name, value in ref.metrics.items():
            np.testing.assert_allclose(infos[name], np.repeat(np.asarray(value)[:, None], 3, 1), rtol=0, atol=1e-5)
        assert not np.any(ref.terminated)
        if t + 1 < env.episode_length:
            assert not np.any(dones["__all__"]) and np.all(state.steps == t + 1)
        elif t + 1 == env.episode_length:  # the last step: reported, then the world starts anew
            assert np.all(dones["__all__"]) and np.all(infos["final_steps"] == env.episode_length)
            np.testing.assert_allclose(state.info["final_obs"], ref.obs, rtol=0, atol=1e-5)
            assert np.all(state.steps == 0)
            ref = ref_reset(ref.key, ref.task)  # the auto-reset's new episode: a fresh start from the world's key
            assert np.abs(ref.obs[:, :, :3] - state.info["final_obs"][:, :1, :3]).max() > 0.01
        else:
            assert not np.any(dones["__all__"]) and np.all(state.steps == t + 1 - env.episode_length)


def test_bad_input_to_jaxmarl_view(marl):
    marl, keys, reset, step = marl
    _, state = reset(keys)
    ok = {a: jnp.zeros((3, 4)) for a in marl.agents}
    with pytest.raises(ValueError, match=r"\['drone_0', 'drone_1', 'drone_2'\]: missing \['drone_1'\]"):
        step(keys, state, {k: v for k, v in ok.items() if k != "drone_1"})
    with pytest.raises(ValueError, match=r"unexpected \['agent_1'\]"):
        step(keys, state, {**ok, "agent_1": jnp.zeros((3, 4))})
    with pytest.raises(ValueError, match=r"action of drone_1 must be a float array of shape \(4,\)"):
        step(keys, state, {**ok, "drone_1": jnp.zeros((3, 2, 4))})
    with pytest.raises(ValueError, match="action of drone_0 must be a float array"):
        step(keys, state, {**ok, "drone_0": jnp.zeros((3, 4), jnp.int32)})
    with pytest.raises(ValueError, match="unknown agent 'agent_0'"):
        marl.action_space("agent_0")
    with pytest.raises(ValueError, match="flock: n_drones must be 2 or more"):
        jaxmarl.make("flock", n_drones=1)
    # out of the box: clipped by the env, like an action at the bound
    _, _, clipped, _, _ = step(keys, state, {**ok, "drone_0": jnp.full((3, 4), 3.0, jnp.float32)})
    _, _, bound, _, _ = step(keys, state, {**ok, "drone_0": jnp.full((3, 4), 1.0, jnp.float32)})
    np.testing.assert_array_equal(clipped["drone_0"], bound["drone_0"])
    assert not np.allclose(clipped["drone_0"], step(keys, state, ok)[2]["drone_0"])


class _LogWrapper:
    """JaxMARL's ``jaxmarl.wrappers.baselines.LogWrapper`` (with ``replace_info=False``), restated: it adds episode
    returns and lengths, one entry per agent, to the env's infos."""

    def __init__(self, env):
        self._env = env

    def reset(self, key):
        obs, state = self._env.reset(key)
        zeros = jnp.zeros((self._env.num_agents,))
        return obs, (state, zeros, zeros, zeros, zeros)

    def step(self, key, log_state, action):
        state, returns, lengths, returned, returned_lengths = log_state
        obs, state, reward, done, info = self._env.step(key, state, action)
        ep_done = done["__all__"]
        returns = returns + jnp.stack([reward[a] for a in self._env.agents])
        lengths = lengths + 1
        returned = returned * (1 - ep_done) + returns * ep_done
        returned_lengths = returned_lengths * (1 - ep_done) + lengths * ep_done
        info["returned_episode_returns"] = returned
        info["returned_episode_lengths"] = returned_lengths
        info["returned_episode"] = jnp.full((self._env.num_agents,), ep_done)
        log_state = (state, returns * (1 - ep_done), lengths * (1 - ep_done), returned, returned_lengths)
        return obs, log_state, reward, done, info


def test_jaxmarl_baselines_reshape_every_info_leaf_per_actor():
    # What JaxMARL's IPPO/MAPPO baselines do inside their rollout scan: vmap a LogWrapper-ed env over worlds, then
    # reshape every info leaf to one entry per actor (W worlds × num_agents).
    view = _LogWrapper(jaxmarl.make("leader_follower", n_drones=2, episode_len_s=0.1))
    n_worlds, n_actors = 4, 4 * 2
    obs, state = jax.vmap(view.reset)(jax.random.split(jax.random.key(0), n_worlds))

    def env_step(carry, key):
        obs, state = carry
        actions = {a: jnp.zeros((n_worlds, 4)) for a in view._env.agents}
        obs, state, _, _, info = jax.vmap(view.step)(jax.random.split(key, n_worlds), state, actions)
        info = jax.tree.map(lambda x: x.reshape((n_actors,)), info)
        return (obs, state), info

    n_steps = 2 * view._env.env.episode_length
    _, infos = jax.jit(lambda k: jax.lax.scan(env_step, (obs, state), jax.random.split(k, n_steps)))(jax.random.key(1))
    assert all(v.shape == (n_steps, n_actors) for v in jax.tree.leaves(infos))
    ended = np.asarray(infos["returned_episode"])
    assert ended[view._env.env.episode_length - 1].all() and ended.sum() == 2 * n_actors
    np.testing.assert_array_equal(np.asarray(infos["returned_episode_lengths"])[-1], view._env.env.episode_length)
    np.testing.assert_array_equal(np.asarray(infos["final_steps"])[ended], view._env.env.episode_length)
