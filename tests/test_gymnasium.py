"""gymnasium adapters: every registered id passes gymnasium's env checker, episodes, seeding, rendering, the
vector env (one jitted call, next-step autoreset), SB3's ``make_vec_env`` keywords and bad input."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import jaxdrones  # noqa: F401  (registers the ids)
from jaxdrones.adapters.gymnasium import GYM_IDS

#: Non-default action and observation types checked on each id.
VARIANTS = [
    {},
    {"action_type": "one_d_rpm", "obs_type": "kin_norm"},
    {"action_type": "pid", "action_buffer": True},
    {"action_type": "ctbr", "obs_type": "neighbors"},
]


@pytest.mark.slow
@pytest.mark.parametrize("index, task, env_id", [(i, *item) for i, item in enumerate(GYM_IDS.items())])
def test_every_id_passes_the_env_checker(index, task, env_id):
    """Each id with its defaults and one non-default variant (the variants cycle over the ids)."""
    variants = [{}] if task == "tune" else [{}, VARIANTS[1 + index % (len(VARIANTS) - 1)]]
    for options in variants:
        env = gym.make(env_id, **options)
        check_env(env.unwrapped, skip_render_check=True)
        env.close()


def test_hover_episode_through_gymnasium():
    env = gym.make("jaxdrones/Hover-v0", init_pos=[[0.0, 0.0, 1.0]], render_mode=None)
    obs, info = env.reset(seed=3)
    assert obs.shape == (21,) and obs.dtype == np.float32 and "distance" in info
    assert np.all(np.isfinite(env.observation_space.low)) and np.all(np.isfinite(env.observation_space.high))
    obs2, _ = env.reset(seed=3)
    np.testing.assert_array_equal(obs, obs2)
    steps, truncated, terminated = 0, False, False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(np.zeros(4, np.float32))
        assert np.isfinite(reward) and reward >= 0 and env.observation_space.contains(obs)
        steps += 1
    assert truncated and not terminated and steps == 150
    with pytest.raises(ValueError, match=r"action must have shape \(4,\)"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(np.array([0.0, np.inf, 0.0, 0.0], np.float32))


def test_random_resets_differ_and_seed_reproduces():
    env = gym.make("jaxdrones/Velocity-v0")
    a, _ = env.reset(seed=0)
    b, _ = env.reset()
    c, _ = env.reset(seed=0)
    assert not np.allclose(a, b)
    np.testing.assert_array_equal(a, c)


def test_render_rgb_array():
    env = gym.make("jaxdrones/LeaderFollower-v0", n_drones=3, render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (3, env.unwrapped.env.observation_size)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[-1] == 3 and frame.std() > 0
    with pytest.raises(ValueError, match="render_mode"):
        gym.make("jaxdrones/Hover-v0", render_mode="window")


def test_module_prefix_registers_without_import():
    env = gym.make("jaxdrones:jaxdrones/Takeoff-v0")
    assert env.reset(seed=0)[0].shape == (21,)


def test_vector_env_steps_all_worlds_with_next_step_autoreset():
    n = 16
    vec = gym.make_vec("jaxdrones/Hover-v0", num_envs=n, vectorization_mode="vector_entry_point", episode_len_s=0.2)
    obs, info = vec.reset(seed=1)
    assert obs.shape == (n, 21) and obs.dtype == np.float32 and info["distance"].shape == (n,)
    length = 6
    for _k in range(length):
        obs, reward, terminated, truncated, _ = vec.step(np.zeros((n, 4), np.float32))
    assert truncated.all() and not terminated.any()
    obs_next, reward, terminated, truncated, _ = vec.step(np.zeros((n, 4), np.float32))
    # The step after the end resets: a new start (reward 0, not done).
    np.testing.assert_array_equal(reward, 0.0)
    assert not (terminated | truncated).any() and not np.allclose(obs_next, obs)
    obs2, _ = vec.reset(seed=1)
    obs3, _ = gym.make_vec("jaxdrones/Hover-v0", num_envs=n, vectorization_mode="vector_entry_point").reset(seed=1)
    np.testing.assert_array_equal(obs2, obs3)
    with pytest.raises(ValueError, match=r"action must have shape \(16, 4\)"):
        vec.step(np.zeros((n - 1, 4), np.float32))


def test_vector_env_same_step_autoreset_returns_the_final_observation():
    """``autoreset_mode="same_step"``: the step that ends an episode returns the next episode's first observation
    and the ended one's last in ``infos["final_obs"]`` (masked by ``_final_obs``), as gymnasium's SyncVectorEnv
    does in that mode; the reward and flags are those of the ended episode's last step."""
    n, length = 4, 6
    kwargs = dict(num_envs=n, vectorization_mode="vector_entry_point", episode_len_s=0.2)
    vec = gym.make_vec("jaxdrones/Hover-v0", autoreset_mode="same_step", **kwargs)
    nxt = gym.make_vec("jaxdrones/Hover-v0", **kwargs)
    assert vec.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    obs, _ = vec.reset(seed=1)
    np.testing.assert_array_equal(obs, nxt.reset(seed=1)[0])
    action = np.zeros((n, 4), np.float32)
    for k in range(length):
        obs, reward, terminated, truncated, info = vec.step(action)
        last_obs, last_reward, *_ = nxt.step(action)
        assert info["_final_obs"].tolist() == [k == length - 1] * n
    assert truncated.all() and not terminated.any()
    # The ended episode's last observation, up to float32 rounding (the two modes' programs are compiled apart).
    np.testing.assert_allclose(info["final_obs"], last_obs, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(reward, last_reward, rtol=1e-5, atol=1e-6)
    assert not np.allclose(obs, last_obs)
    assert info["final_info"]["distance"].shape == (n,)
    # The next episode's first observation: what the next-step env returns one step later.
    np.testing.assert_allclose(obs, nxt.step(action)[0], rtol=1e-5, atol=1e-6)
    obs, reward, terminated, truncated, info = vec.step(action)
    assert not info["_final_obs"].any() and not (terminated | truncated).any() and np.all(reward != 0)
    with pytest.raises(ValueError, match="autoreset_mode must be one of"):
        gym.make_vec("jaxdrones/Hover-v0", num_envs=2, vectorization_mode="vector_entry_point", autoreset_mode="x")


@pytest.mark.parametrize("mode", list(gym.vector.AutoresetMode))
def test_vector_env_takes_gymnasiums_autoreset_mode_members(mode):
    """gymnasium's own ``AutoresetMode.NEXT_STEP`` and ``SAME_STEP`` select those modes; ``DISABLED`` is refused by
    name."""
    kwargs = dict(num_envs=2, vectorization_mode="vector_entry_point", autoreset_mode=mode)
    if mode == gym.vector.AutoresetMode.DISABLED:
        with pytest.raises(ValueError, match="autoreset_mode must be one of .* got <AutoresetMode.DISABLED"):
            gym.make_vec("jaxdrones/Hover-v0", **kwargs)
        return
    assert gym.make_vec("jaxdrones/Hover-v0", **kwargs).metadata["autoreset_mode"] == mode


def test_vector_env_call_get_attr_set_attr_as_sync_vector_env():
    """`call`, `get_attr` and `set_attr` give what gymnasium's SyncVectorEnv gives over single envs: one entry per
    world (spaces of one world, the render mode, each world's frame for ``render``, the env's own attributes and
    methods); set_attr sets the shared env's attribute, and refuses different values per world."""
    n = 3
    vec = gym.make_vec("jaxdrones/Hover-v0", n, vectorization_mode="vector_entry_point", render_mode="rgb_array")
    sync = gym.make_vec("jaxdrones/Hover-v0", n, vectorization_mode="sync", render_mode="rgb_array")
    vec.reset(seed=0)
    sync.reset(seed=0)
    for name in ("observation_space", "action_space", "render_mode"):
        assert vec.get_attr(name) == sync.get_attr(name) and len(vec.get_attr(name)) == n
    frames, sync_frames = vec.call("render"), sync.call("render")
    assert len(frames) == n and all(f.shape == sync_frames[0].shape and f.dtype == np.uint8 for f in frames)
    assert vec.get_attr("n_drones") == (1,) * n == sync.get_attr("unwrapped")[0].env.n_drones * (1,) * n
    bounds = vec.call("action_bounds")
    assert len(bounds) == n and bounds[0][0].shape == (1, 4)
    vec.set_attr("user_note", "a")
    vec.set_attr("user_note", ["b"] * n)
    assert vec.get_attr("user_note") == ("b",) * n
    with pytest.raises(ValueError, match="share one env"):
        vec.set_attr("user_note", ["a", "b", "c"])
    with pytest.raises(ValueError, match="expected one value or 3 values"):
        vec.set_attr("user_note", ["a", "a"])
    with pytest.raises(AttributeError):
        vec.get_attr("no_such_attribute")
    for compiled in ("ctrl_freq", "episode_len_s", "n_drones", "config"):  # options and the env's own attributes
        with pytest.raises(ValueError, match=f"set_attr: '{compiled}' is the env's own and was compiled"):
            vec.set_attr(compiled, 10)
    assert vec.get_attr("n_drones") == (1,) * n and vec.unwrapped.env.config.sim.ctrl_freq == 30
    plain = gym.make_vec("jaxdrones/Hover-v0", num_envs=2, vectorization_mode="vector_entry_point")
    assert plain.call("render") == (None, None)


def test_sb3_style_keywords_pass_through():
    # SB3's make_vec_env calls gymnasium.make(id, render_mode=None, ...) for each env.
    env = gym.make("jaxdrones/Hover-v0", render_mode=None, action_type="one_d_rpm", ctrl_freq=48, model="cf2p")
    assert env.action_space.shape == (1,) and env.unwrapped.env.config.sim.ctrl_freq == 48


def test_bad_options_name_what_was_expected():
    with pytest.raises(ValueError, match="unknown action_type"):
        gym.make("jaxdrones/Hover-v0", action_type="warp")
    with pytest.raises(ValueError, match="num_envs must be a positive integer"):
        gym.make_vec("jaxdrones/Hover-v0", num_envs=0, vectorization_mode="vector_entry_point")
    # The adapters' own keywords are among the suggestions.
    with pytest.raises(ValueError, match="unknown option 'strict_action' \\(did you mean 'strict_actions'\\?\\)"):
        gym.make("jaxdrones/Hover-v0", strict_action=True)
    with pytest.raises(ValueError, match="did you mean 'autoreset_mode'"):
        gym.make_vec("jaxdrones/Hover-v0", num_envs=2, vectorization_mode="vector_entry_point", autoreset=1)


def test_image_observation_gives_policy_input_images():
    """`ImageObservation`: `policy_input`'s images (depth / 5 m clipped to [0, 1]) with the drone axis along the
    channels, last or first, in a Box of [0, 1] that holds them; segmentation left out; no camera: a ValueError."""
    from jaxdrones.adapters.gymnasium import ImageObservation
    from jaxdrones.envs.observations import DEPTH_SCALE

    raw = gym.make("jaxdrones/Avoid-v0", image_size=(16, 12), vision=("depth", "seg"))
    obs, _ = raw.reset(seed=3)
    for channels_first, shape in ((False, (12, 16, 1)), (True, (1, 12, 16))):
        env = ImageObservation(
            gym.make("jaxdrones/Avoid-v0", image_size=(16, 12), vision=("depth", "seg")), channels_first=channels_first
        )
        assert set(env.observation_space.spaces) == {"state", "depth"}
        assert env.observation_space["depth"].shape == shape
        seen, _ = env.reset(seed=3)
        assert env.observation_space.contains(seen)
        depth = np.moveaxis(seen["depth"], 0, -1) if channels_first else seen["depth"]
        np.testing.assert_allclose(depth[..., 0], np.clip(obs["depth"] / DEPTH_SCALE, 0, 1), rtol=1e-6)
        np.testing.assert_array_equal(seen["state"], obs["state"])
        env.close()
    raw.close()
    with pytest.raises(ValueError, match="depth or RGB camera"):
        ImageObservation(gym.make("jaxdrones/Hover-v0"))
