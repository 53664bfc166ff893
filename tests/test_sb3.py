"""Stable-Baselines3 on the batched env (`jaxdrones.adapters.sb3.VecEnv`): SB3's VecEnv contract (same-step
autoreset with ``terminal_observation`` and ``TimeLimit.truncated``, seeding, attributes, SB3's wrappers), PPO
running on it, and bad input. How far PPO and sbx's PPO get on it: ``benchmarks/training/sb3_hover.py --vec
jaxdrones``."""

import pickle

import numpy as np
import pytest

pytestmark = pytest.mark.torch


@pytest.fixture(scope="module")
def VecEnv():
    from jaxdrones.adapters.sb3 import VecEnv

    return VecEnv


def test_steps_all_worlds_with_same_step_autoreset(VecEnv):
    """The step that ends an episode returns the next episode's first observation; the ended one's last is in
    ``infos[i]["terminal_observation"]``, and a time limit sets ``TimeLimit.truncated`` (SB3 then bootstraps)."""
    n = 5
    env = VecEnv("hover", num_envs=n, action_type="one_d_rpm", episode_len_s=0.2)  # 6 control steps
    assert env.num_envs == n and env.observation_space.shape == (21,) and env.action_space.shape == (1,)
    env.seed(3)
    obs = first = env.reset()
    assert obs.shape == (n, 21) and obs.dtype == np.float32 and len(env.reset_infos) == n
    action = np.zeros((n, 1), np.float32)
    for _ in range(5):
        obs, rewards, dones, infos = env.step(action)
        assert not dones.any() and all("terminal_observation" not in info for info in infos)
    last, rewards, dones, infos = env.step(action)
    assert rewards.shape == (n,) and rewards.dtype == np.float32 and np.all(rewards != 0)
    assert dones.all() and len(infos) == n
    for i, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True and info["terminal_observation"].shape == (21,)
        assert not np.allclose(info["terminal_observation"], last[i])  # the new episode starts elsewhere
        assert isinstance(info["distance"], float)
    env.seed(3)
    np.testing.assert_array_equal(env.reset(), first)  # seed() seeds the next reset
    env.seed(4)
    assert not np.allclose(env.reset(), first)


def test_crash_terminates_without_truncation(VecEnv):
    """A world that crashes ends terminated: ``TimeLimit.truncated`` False, so SB3 does not bootstrap its value."""
    env = VecEnv("hover", num_envs=2)
    env.reset()
    for _ in range(200):
        _, _, dones, infos = env.step(np.tile([1.0, 1.0, -1.0, -1.0], (2, 1)).astype(np.float32))  # it flips
        if dones.any():
            break
    ended = np.flatnonzero(dones)
    assert ended.size and all(infos[i]["crash"] == 1.0 and infos[i]["TimeLimit.truncated"] is False for i in ended)


def test_attributes_methods_and_wrappers(VecEnv, tmp_path):
    """SB3's VecEnv methods act on the env the worlds share; SB3's own wrappers and PPO take the env as theirs."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    env = VecEnv("jaxdrones/Hover-v0", num_envs=4, render_mode="rgb_array", episode_len_s=0.5)
    assert env.get_attr("render_mode") == ["rgb_array"] * 4 and env.get_attr("n_drones", indices=[1, 2]) == [1, 1]
    assert env.env_is_wrapped(Monitor) == [False] * 4 and env.has_attr("config") and not env.has_attr("nope")
    bounds = env.env_method("action_bounds", indices=0)
    assert len(bounds) == 1 and bounds[0][0].shape == (1, 4)
    env.set_attr("user_note", 1)
    assert env.get_attr("user_note") == [1] * 4
    with pytest.raises(ValueError, match="share one env"):
        env.set_attr("user_note", 2, indices=[0])
    env.reset()
    image = env.render()
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[-1] == 3  # the 4 worlds' frames tiled
    copy = pickle.loads(pickle.dumps(env))
    assert copy.num_envs == 4 and copy.reset().shape == (4, 21)
    wrapped = VecNormalize(VecMonitor(env))
    model = PPO("MlpPolicy", wrapped, n_steps=16, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(16 * 4 * 2)
    assert model.num_timesteps == 128 and len(model.ep_info_buffer) > 0  # VecMonitor saw episodes end
    action, _ = model.predict(wrapped.reset(), deterministic=True)
    assert action.shape == (4, 4) and np.all(np.abs(action) <= 1)
    model.save(tmp_path / "ppo")
    assert PPO.load(tmp_path / "ppo", env=wrapped).num_timesteps == 128


def test_bad_input_names_what_was_expected(VecEnv):
    import jaxdrones as jd

    with pytest.raises(ValueError, match="unknown task 'hovr' \\(did you mean 'hover'\\?\\)"):
        VecEnv("hovr", num_envs=2)
    with pytest.raises(
        ValueError, match="unknown gymnasium id 'jaxdrones/Hovr-v0' \\(did you mean 'jaxdrones/Hover-v0'"
    ):
        VecEnv("jaxdrones/Hovr-v0", num_envs=2)
    with pytest.raises(ValueError, match="num_envs must be a positive integer"):
        VecEnv("hover", num_envs=0)
    with pytest.raises(ValueError, match="apply to a task's name, not to an Env"):
        VecEnv(jd.make("hover"), num_envs=2, action_type="one_d_rpm")
    env = VecEnv(jd.make("hover"), num_envs=2)
    env.reset()
    with pytest.raises(ValueError, match=r"action must have shape \(2, 4\)"):
        env.step(np.zeros((3, 4), np.float32))
    with pytest.raises(RuntimeError, match="step_async"):
        env.step_wait()


def test_the_adapters_warn_once_where_torch_threads_contend_with_jax(VecEnv, recwarn):
    """torch with several threads beside JAX on the CPU: the first reset of an adapter warns once, with the fix;
    with one thread, no warning."""
    import warnings

    import gymnasium as gym
    import torch

    from jaxdrones.adapters import TorchThreadsWarning, _host
    from jaxdrones.adapters.pettingzoo import parallel_env

    threads = torch.get_num_threads()
    _host._warn_torch_threads.cache_clear()  # as in a new process
    try:
        torch.set_num_threads(2)
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")  # every warning given is recorded: the adapters give this one once
            VecEnv("hover", num_envs=2).reset()
            gym.make("jaxdrones/Hover-v0").reset(seed=0)
            parallel_env("leader_follower").reset(seed=0)
        ours = [w for w in seen if issubclass(w.category, TorchThreadsWarning)]
        assert len(ours) == 1 and "torch.set_num_threads(1)" in str(ours[0].message)
        torch.set_num_threads(1)
        with warnings.catch_warnings():
            warnings.simplefilter("error", TorchThreadsWarning)
            VecEnv("hover", num_envs=2).reset()
            parallel_env("leader_follower").reset(seed=0)
    finally:
        torch.set_num_threads(threads)
