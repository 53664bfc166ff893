"""The action convention of the gymnasium, vector, PettingZoo and JaxMARL views: actions outside the box are
clipped to it and counted (``clipped_actions``), as an unclipped Gaussian policy needs; ``strict_actions=True``
refuses them; NaN and inf are always refused (a jitted step ends the episode as invalid instead)."""

import warnings

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones  # noqa: F401  (registers the ids)
from jaxdrones.adapters import jaxmarl
from jaxdrones.adapters.pettingzoo import parallel_env

pytestmark = pytest.mark.unit

#: Standard deviation of the Gaussian policy: about half its entries fall outside [-1, 1].
SIGMA = 1.5


def _outside(a):
    return np.sum(np.abs(a) > 1.0, axis=-1)


def test_gaussian_policy_on_the_gymnasium_env_equals_its_clipped_actions():
    """A whole episode of N(0, 1.5²) actions runs; each step equals the step of the clipped action, and
    ``info["clipped_actions"]`` is the number of entries outside the box."""
    rng = np.random.default_rng(0)
    env = gym.make("jaxdrones/Hover-v0")
    ref = gym.make("jaxdrones/Hover-v0", strict_actions=True)
    obs, info = env.reset(seed=1)
    ref_obs, _ = ref.reset(seed=1)
    assert info["clipped_actions"] == 0
    counts, done = [], False
    while not done:
        action = rng.normal(0.0, SIGMA, 4).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        ref_obs, ref_reward, *_ = ref.step(np.clip(action, -1, 1))
        np.testing.assert_array_equal(obs, ref_obs)
        assert reward == ref_reward
        assert isinstance(info["clipped_actions"], int) and info["clipped_actions"] == _outside(action)
        counts.append(info["clipped_actions"])
        done = terminated or truncated
    assert sum(counts) > 0 and len(counts) > 10
    with pytest.raises(ValueError, match=r"action must lie in the action space \[-1, 1\] \(strict_actions=True\)"):
        ref.step(np.full(4, 1.5, np.float32))
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(ValueError, match="action must be finite, got 1 NaN or inf"):
            env.step(np.array([0.0, bad, 0.0, 0.0], np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and no overflow warning of NumPy's before the error
        with pytest.raises(ValueError, match=r"action must lie within float32's range .* the largest 1e\+39"):
            env.step(np.array([0.0, 1e39, 0.0, 0.0]))  # finite in float64


def test_gaussian_policy_on_the_vector_env():
    """``make_vec`` with N(0, 1.5²) actions: per-world counts (int) and the same worlds as with clipped actions,
    through autoresets (the step after an episode's end resets the world and ignores its action)."""
    rng = np.random.default_rng(1)
    kwargs = dict(num_envs=4, vectorization_mode="vector_entry_point", episode_len_s=0.3)
    env = gym.make_vec("jaxdrones/Hover-v0", **kwargs)
    ref = gym.make_vec("jaxdrones/Hover-v0", strict_actions=True, **kwargs)
    env.reset(seed=2)
    ref.reset(seed=2)
    ended = np.zeros(4, bool)
    for _ in range(20):  # two episodes of 9 steps and their autoresets
        action = rng.normal(0.0, SIGMA, (4, 4)).astype(np.float32)
        obs, reward, terminated, truncated, infos = env.step(action)
        ref_obs, ref_reward, _, ref_truncated, _ = ref.step(np.clip(action, -1, 1))
        np.testing.assert_array_equal(obs, ref_obs)
        np.testing.assert_array_equal(reward, ref_reward)
        np.testing.assert_array_equal(truncated, ref_truncated)
        assert infos["clipped_actions"].dtype == np.int64
        # the step after an episode's end resets that world and ignores its action
        np.testing.assert_array_equal(infos["clipped_actions"], np.where(ended, 0, _outside(action)))
        ended = terminated | truncated
    with pytest.raises(ValueError, match=r"\(strict_actions=True\)"):
        ref.step(np.full((4, 4), -1.2, np.float32))
    with pytest.raises(ValueError, match="actions must be finite|action must be finite"):
        env.step(np.full((4, 4), np.nan, np.float32))


def test_gaussian_policy_on_pettingzoo():
    rng = np.random.default_rng(2)
    env = parallel_env("multi_hover", n_drones=2)
    ref = parallel_env("multi_hover", n_drones=2, strict_actions=True)
    env.reset(seed=3)
    ref.reset(seed=3)
    for _ in range(10):
        actions = {a: rng.normal(0.0, SIGMA, 4).astype(np.float32) for a in env.agents}
        obs, rewards, _, _, infos = env.step(actions)
        ref_obs, ref_rewards, _, _, _ = ref.step({a: np.clip(v, -1, 1) for a, v in actions.items()})
        for a in actions:
            np.testing.assert_array_equal(obs[a], ref_obs[a])
            assert rewards[a] == ref_rewards[a]
            assert infos[a]["clipped_actions"] == _outside(actions[a])
    with pytest.raises(ValueError, match=r"action of drone_1 must lie in the action space.*strict_actions=True"):
        ref.step({"drone_0": np.zeros(4, np.float32), "drone_1": np.full(4, 2.0, np.float32)})
    with pytest.raises(ValueError, match="action of drone_0 must be finite"):
        env.step({"drone_0": np.full(4, np.nan, np.float32), "drone_1": np.zeros(4, np.float32)})


@pytest.mark.slow
def test_gaussian_policy_on_jaxmarl_vmapped():
    """Three worlds under jit and vmap: per-agent counts; with ``strict_actions`` an action outside the box ends
    its world's episode as invalid, and the others go on."""
    env = jaxmarl.make("multi_hover", n_drones=2)
    strict = jaxmarl.make("multi_hover", n_drones=2, strict_actions=True)
    keys = jax.random.split(jax.random.key(0), 3)
    _, state = jax.vmap(env.reset)(keys)
    actions = {
        a: SIGMA * jax.random.normal(k, (3, 4)) for a, k in zip(env.agents, jax.random.split(keys[0]), strict=True)
    }
    step = jax.jit(jax.vmap(env.step))
    _, _, rewards, dones, infos = step(keys, state, actions)
    clipped = {a: jnp.clip(v, -1, 1) for a, v in actions.items()}
    _, _, ref_rewards, _, _ = step(keys, state, clipped)
    for i, a in enumerate(env.agents):
        np.testing.assert_array_equal(rewards[a], ref_rewards[a])
        np.testing.assert_array_equal(infos["clipped_actions"][:, i], _outside(np.asarray(actions[a])))
    assert not np.any(dones["__all__"])
    one_out = {a: jnp.zeros((3, 4)).at[1, 2].set(1.5 if a == "drone_1" else 0.0) for a in env.agents}
    _, _, _, dones, infos = jax.jit(jax.vmap(strict.step))(keys, state, one_out)
    np.testing.assert_array_equal(dones["__all__"], [False, True, False])
    np.testing.assert_array_equal(infos["invalid_action"][:, 0], [0.0, 1.0, 0.0])
