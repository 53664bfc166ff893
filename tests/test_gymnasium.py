import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import jaxdrones  # noqa: F401  (registers jaxdrones/Hover-v0)


def test_hover_passes_gymnasium_env_checker():
    env = gym.make("jaxdrones/Hover-v0")
    check_env(env.unwrapped, skip_render_check=True)


def test_hover_episode_through_gymnasium():
    env = gym.make("jaxdrones/Hover-v0", action_type="rpm", init_vz=0.0)
    obs, info = env.reset(seed=3)
    assert obs.shape == (12,) and obs.dtype == np.float32 and "distance" in info
    obs2, _ = env.reset(seed=3)
    np.testing.assert_array_equal(obs, obs2)
    steps, truncated, terminated = 0, False, False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(np.zeros(4, np.float32))
        assert np.isfinite(reward) and reward >= 0
        steps += 1
    assert truncated and not terminated and steps == 150
    with pytest.raises(ValueError, match=r"action must have shape \(4,\)"):
        env.step(np.zeros(3))
