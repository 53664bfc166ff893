"""The training code users bring, run as they run it: PettingZoo's Stable-Baselines3 tutorial through SuperSuit
with worker processes, gymnasium's async vector env, pickled copies of the envs, PettingZoo's AEC API and the
``human`` render mode. Scripts run in their own process with a timeout, so that a hang fails the test."""

import os
import pickle
import subprocess
import sys
import textwrap

import gymnasium as gym
import jax
import numpy as np
import pytest
from pettingzoo.test import api_test

import jaxdrones as jd
from jaxdrones import _fork
from jaxdrones.adapters import pettingzoo as jd_pettingzoo
from jaxdrones.adapters.gymnasium import GymnasiumEnv, GymnasiumVectorEnv

#: The start of `jaxdrones._fork.check_not_forked`'s message.
FORK_MESSAGE = "it was forked from a process in which JAX had already started"


def run_script(tmp_path, source: str, *args: str, timeout: float) -> subprocess.CompletedProcess:
    """Run ``source`` as a script file (as a user would: ``python script.py ARGS``) in ``tmp_path``."""
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(source))
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MPLBACKEND": "Agg"}
    return subprocess.run(
        [sys.executable, str(script), *args], cwd=tmp_path, capture_output=True, text=True, timeout=timeout, env=env
    )


#: PettingZoo's SB3 tutorial (tutorials/SB3/waterworld/sb3_waterworld_vector.py) with this package as its env
#: module: train with SuperSuit's vector env over 2 worker processes, save, then evaluate turn by turn (AEC).
SB3_TUTORIAL = """
    import glob, os, sys, time
    import supersuit as ss
    from stable_baselines3 import PPO
    from stable_baselines3.ppo import MlpPolicy
    from jaxdrones.adapters import pettingzoo as env_fn

    def train_butterfly_supersuit(env_fn, steps, seed=0, **env_kwargs):
        env = env_fn.parallel_env(**env_kwargs)
        env.reset(seed=seed)
        print(f"Starting training on {str(env.metadata['name'])}.", flush=True)
        env = ss.pettingzoo_env_to_vec_env_v1(env)
        env = ss.concat_vec_envs_v1(env, 8, num_cpus=2, base_class="stable_baselines3")
        model = PPO(MlpPolicy, env, verbose=1, learning_rate=1e-3, batch_size=256, n_steps=256)
        model.learn(total_timesteps=steps)
        model.save(f"{env.unwrapped.metadata.get('name')}_{time.strftime('%Y%m%d-%H%M%S')}")
        print(f"trained {model.num_timesteps} steps", flush=True)
        env.close()

    def eval(env_fn, num_games, render_mode=None, **env_kwargs):
        env = env_fn.env(render_mode=render_mode, **env_kwargs)
        latest_policy = max(glob.glob(f"{env.metadata['name']}*.zip"), key=os.path.getctime)
        model = PPO.load(latest_policy)
        rewards = {agent: 0 for agent in env.possible_agents}
        for i in range(num_games):
            env.reset(seed=i)
            for agent in env.agent_iter():
                obs, reward, termination, truncation, info = env.last()
                for a in env.agents:
                    rewards[a] += env.rewards[a]
                if termination or truncation:
                    break
                act = model.predict(obs, deterministic=True)[0]
                env.step(act)
        env.close()
        print("rewards", {a: round(float(r), 1) for a, r in rewards.items()}, flush=True)

    if __name__ == "__main__":
        if sys.argv[1] != "default":
            import multiprocessing
            multiprocessing.set_start_method(sys.argv[1])
        env_kwargs = dict(task="multi_hover", n_drones=2, episode_len_s=1.0)
        train_butterfly_supersuit(env_fn, steps=4096, seed=0, **env_kwargs)
        eval(env_fn, num_games=2, render_mode=None, **env_kwargs)
        eval(env_fn, num_games=1, render_mode="human", **env_kwargs)
"""


@pytest.mark.slow
@pytest.mark.torch
def test_pettingzoo_sb3_tutorial_with_supersuit_workers(tmp_path):
    # multiprocessing's default start method on Linux (Python < 3.14) forks after JAX started: a clear error, fast.
    forked = run_script(tmp_path, SB3_TUTORIAL, "fork", timeout=120)
    assert forked.returncode != 0
    assert FORK_MESSAGE in forked.stderr and "num_cpus=0" in forked.stderr and "'spawn'" in forked.stderr
    assert "trained" not in forked.stdout
    # With 'spawn' (the fix the message names) the workers rebuild the env from its pickled task and options.
    spawned = run_script(tmp_path, SB3_TUTORIAL, "spawn", timeout=600)
    assert spawned.returncode == 0, spawned.stderr[-3000:]
    assert "Starting training on jaxdrones_multi_hover_v0." in spawned.stdout
    assert "trained 4096 steps" in spawned.stdout  # 8 copies × 2 agents × 256 steps
    assert spawned.stdout.count("rewards {'drone_0'") == 2  # both evaluations, the second in human mode
    assert glob_one(tmp_path, "jaxdrones_multi_hover_v0_*.zip")


def glob_one(directory, pattern):
    found = list(directory.glob(pattern))
    assert len(found) == 1, found
    return found[0]


#: Tianshou's PPO as its examples build it (examples/mujoco/mujoco_ppo.py, Tianshou 2.0.1, shortened): a main
#: process's env for the spaces, training envs from factories, PPO with a probabilistic actor, one epoch of 4096
#: steps. ``fork``: the examples' default vector env (SubprocVectorEnv, context "fork"); else DummyVectorEnv.
TIANSHOU_PPO = """
    import sys

    import gymnasium as gym
    import torch
    from torch.distributions import Independent, Normal

    import jaxdrones  # noqa: F401  (registers jaxdrones/Hover-v0)
    from tianshou.algorithm import PPO
    from tianshou.algorithm.modelfree.reinforce import ProbabilisticActorPolicy
    from tianshou.algorithm.optim import AdamOptimizerFactory
    from tianshou.data import Collector, CollectStats, VectorReplayBuffer
    from tianshou.env import DummyVectorEnv, SubprocVectorEnv
    from tianshou.trainer import OnPolicyTrainerParams
    from tianshou.utils.net.common import Net
    from tianshou.utils.net.continuous import ContinuousActorProbabilistic, ContinuousCritic

    if __name__ == "__main__":
        torch.set_num_threads(1)
        env = gym.make("jaxdrones/Hover-v0", action_type="one_d_rpm")  # the main process's env, for the spaces
        factories = [lambda: gym.make("jaxdrones/Hover-v0", action_type="one_d_rpm")] * 2
        if sys.argv[1] == "fork":
            training_envs = SubprocVectorEnv(factories, share_memory=True, context="fork")  # the examples' default
        else:
            training_envs = DummyVectorEnv(factories)
        test_envs = DummyVectorEnv(factories)
        shape = env.observation_space.shape
        actor = ContinuousActorProbabilistic(
            preprocess_net=Net(state_shape=shape, hidden_sizes=[64, 64], activation=torch.nn.Tanh),
            action_shape=env.action_space.shape,
            unbounded=True,
        )
        net = Net(state_shape=shape, hidden_sizes=[64, 64], activation=torch.nn.Tanh)
        critic = ContinuousCritic(preprocess_net=net)
        policy = ProbabilisticActorPolicy(
            actor=actor,
            dist_fn=lambda loc_scale: Independent(Normal(*loc_scale), 1),
            action_scaling=True,
            action_bound_method="clip",
            action_space=env.action_space,
        )
        algorithm = PPO(policy=policy, critic=critic, optim=AdamOptimizerFactory(lr=3e-4))
        result = algorithm.run_training(
            OnPolicyTrainerParams(
                training_collector=Collector[CollectStats](
                    algorithm, training_envs, VectorReplayBuffer(2048, 2), exploration_noise=True
                ),
                test_collector=Collector[CollectStats](algorithm, test_envs),
                max_epochs=1,
                epoch_num_steps=4096,
                collection_step_num_env_steps=2048,
                update_step_num_repetitions=2,
                test_step_num_episodes=2,
                batch_size=64,
                test_in_training=False,
            )
        )
        print(f"trained {result.train_step} env steps, best test reward {result.best_reward:.1f}", flush=True)
"""


@pytest.mark.slow
@pytest.mark.tianshou
def test_tianshou_ppo_trains_and_its_forked_workers_name_the_fix(tmp_path):
    forked = run_script(tmp_path, TIANSHOU_PPO, "fork", timeout=180)
    assert FORK_MESSAGE in forked.stderr
    assert "VectorEnvType.DUMMY" in forked.stderr and "DummyVectorEnv" in forked.stderr
    assert "trained" not in forked.stdout
    dummy = run_script(tmp_path, TIANSHOU_PPO, "dummy", timeout=600)
    assert dummy.returncode == 0, dummy.stderr[-3000:]
    assert "trained 4096 env steps" in dummy.stdout


ASYNC_VECTOR = """
    import sys
    import gymnasium as gym
    import jaxdrones

    if __name__ == "__main__":
        envs = gym.make_vec("jaxdrones/Hover-v0", num_envs=2, vectorization_mode="async",
                            vector_kwargs={"context": sys.argv[1]})
        obs, _ = envs.reset(seed=0)
        for _ in range(40):
            obs, reward, terminated, truncated, _ = envs.step(envs.action_space.sample())
        print("stepped", obs.shape, flush=True)
        envs.close()
"""


@pytest.mark.slow
def test_gymnasium_async_vector_env_forked_fails_fast_and_spawned_runs(tmp_path):
    forked = run_script(tmp_path, ASYNC_VECTOR, "fork", timeout=120)
    assert forked.returncode != 0 and FORK_MESSAGE in forked.stderr and "vector_entry_point" in forked.stderr
    spawned = run_script(tmp_path, ASYNC_VECTOR, "spawn", timeout=300)
    assert spawned.returncode == 0, spawned.stderr[-3000:]
    assert "stepped (2, 21)" in spawned.stdout


def test_a_process_forked_after_jax_started_is_refused_at_every_entry(monkeypatch):
    gym_env = gym.make("jaxdrones/Hover-v0").unwrapped
    vec_env = gym.make_vec("jaxdrones/Hover-v0", num_envs=2, vectorization_mode="vector_entry_point")
    pz_env = jd_pettingzoo.parallel_env("multi_hover")
    gym_env.reset(seed=0)
    monkeypatch.setattr(_fork, "_forked_after_jax", True)
    for call in (
        lambda: jd.make("hover"),
        lambda: pickle.loads(pickle.dumps(gym_env)),
        gym_env.reset,
        lambda: gym_env.step(gym_env.action_space.sample()),
        vec_env.reset,
        pz_env.reset,
    ):
        with pytest.raises(RuntimeError, match=f"{FORK_MESSAGE}.*num_cpus=0.*spawn.*vector_entry_point"):
            call()


def test_fork_before_jax_started_is_allowed(tmp_path):
    # Only a fork after JAX started is refused: a parent that imported jaxdrones but computed nothing may fork.
    done = run_script(
        tmp_path,
        """
        import os
        import jaxdrones as jd
        pid = os.fork()
        if pid == 0:
            env = jd.make("hover")
            env.reset(__import__("jax").random.key(0))
            os._exit(0)
        _, status = os.waitpid(pid, 0)
        print("child exit", os.waitstatus_to_exitcode(status))
    """,
        timeout=120,
    )
    assert done.returncode == 0 and "child exit 0" in done.stdout, done.stderr[-2000:]


@pytest.mark.parametrize(
    "make",
    [
        lambda: GymnasiumEnv(jd.make("hover", ctrl_freq=48), render_mode="rgb_array"),
        lambda: GymnasiumVectorEnv(jd.make("velocity"), num_envs=3),
        lambda: jd_pettingzoo.parallel_env("leader_follower", n_drones=3, action_type="one_d_rpm"),
    ],
    ids=["gymnasium", "vector", "pettingzoo"],
)
def test_envs_pickle_as_their_task_and_options(make):
    env = make()
    env.reset(seed=1)
    payload = pickle.dumps(env)
    assert b"jaxlib" not in payload and len(payload) < 20_000  # no JAX arrays or compiled functions
    copy = pickle.loads(payload)
    assert type(copy) is type(env) and copy is not env and copy.render_mode == env.render_mode
    assert copy.env.config == env.env.config and copy.env.task is not None
    if isinstance(env, GymnasiumVectorEnv):
        assert copy.num_envs == env.num_envs
    # The copy starts with no episode; seeded alike, it runs the same episodes as the original.
    first, _ = env.reset(seed=5)
    again, _ = copy.reset(seed=5)
    jax.tree.map(np.testing.assert_array_equal, first, again)


def test_pettingzoo_aec_env_steps_the_world_once_every_agent_acted():
    aec = jd_pettingzoo.env(task="multi_hover", n_drones=2, episode_len_s=0.2)
    parallel = jd_pettingzoo.parallel_env(task="multi_hover", n_drones=2, episode_len_s=0.2)
    aec.reset(seed=0)
    obs, _ = parallel.reset(seed=0)
    assert aec.metadata["name"] == "jaxdrones_multi_hover_v0" and aec.possible_agents == ["drone_0", "drone_1"]
    action = np.full(4, 0.1, np.float32)
    steps = 0
    for agent in aec.agent_iter():
        observation, _, termination, truncation, _ = aec.last()
        np.testing.assert_array_equal(observation, obs[agent])
        if termination or truncation:
            aec.step(None)
            continue
        aec.step(action)
        if agent == "drone_1":  # the world stepped: the same as one parallel step
            obs, rewards, *_ = parallel.step({"drone_0": action, "drone_1": action})
            steps += 1
            assert aec.rewards == pytest.approx(rewards)
    assert steps == 6  # 0.2 s at 30 Hz
    api_test(jd_pettingzoo.env(task="leader_follower", n_drones=3, episode_len_s=0.2), num_cycles=12)


def test_human_render_mode_shows_each_step(monkeypatch):
    import matplotlib.pyplot as plt

    monkeypatch.setattr(plt, "pause", lambda interval: None)  # headless: nothing to wait for
    for env in (
        gym.make("jaxdrones/Hover-v0", render_mode="human").unwrapped,
        jd_pettingzoo.parallel_env("multi_hover", render_mode="human"),
    ):
        env.reset(seed=0)
        figure = env._view._figure
        assert figure is not None and plt.fignum_exists(figure.number)
        assert env.render() is None  # gymnasium's convention: human mode draws in reset/step
        before = np.array(figure.axes[0].images[0].get_array())
        action = (
            env.action_space.sample() if isinstance(env, gym.Env) else {a: np.ones(4, np.float32) for a in env.agents}
        )
        for _ in range(5):
            env.step(action)
        after = np.array(figure.axes[0].images[0].get_array())
        assert after.shape == before.shape and (after != before).any()  # the drones moved in the window
        env.close()
        assert not plt.fignum_exists(figure.number)


#: CleanRL's main branch (gymnasium 0.29): ppo_continuous_action.py's env stack, stepped past an episode's end.
CLEANRL_029 = """
    import warnings
    import gymnasium as gym
    import numpy as np
    warnings.simplefilter("error", UserWarning)  # a failed registration would warn
    import jaxdrones
    from jaxdrones.adapters.gymnasium import GymnasiumVectorEnv

    def make_env(env_id, gamma):
        def thunk():
            env = gym.make(env_id, episode_len_s=0.5)
            env = gym.wrappers.FlattenObservation(env)
            env = gym.wrappers.RecordEpisodeStatistics(env)
            env = gym.wrappers.ClipAction(env)
            env = gym.wrappers.NormalizeObservation(env)
            env = gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -10, 10))
            env = gym.wrappers.NormalizeReward(env, gamma=gamma)
            env = gym.wrappers.TransformReward(env, lambda reward: np.clip(reward, -10, 10))
            return env
        return thunk

    print("gymnasium", gym.__version__)
    envs = gym.vector.SyncVectorEnv([make_env("jaxdrones/Hover-v0", 0.99) for _ in range(2)])
    obs, _ = envs.reset(seed=1)
    episodes = 0
    for _ in range(20):
        obs, reward, terminated, truncated, infos = envs.step(envs.action_space.sample())
        for info in infos.get("final_info", []):
            if info and "episode" in info:
                episodes += 1
    print("obs", obs.shape, "episodes", episodes)
    try:
        GymnasiumVectorEnv(jaxdrones.make("hover"), 2)
    except RuntimeError as e:
        print("vector:", e)
"""


@pytest.mark.slow
def test_gymnasium_029_registers_the_ids_for_cleanrl(tmp_path):
    target = tmp_path / "gymnasium029"
    pip = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target), "gymnasium==0.29.1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert pip.returncode == 0, pip.stderr
    script = tmp_path / "cleanrl.py"
    script.write_text(textwrap.dedent(CLEANRL_029))
    run = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(target)},
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert "gymnasium 0.29.1" in run.stdout
    assert "obs (2, 21) episodes 2" in run.stdout  # 15-step episodes: each of the 2 envs ended one
    assert "vector: jaxdrones' vector env needs gymnasium >= 1.1" in run.stdout and "SyncVectorEnv" in run.stdout


def test_old_gymnasium_warns_with_the_installed_and_required_versions(monkeypatch):
    from jaxdrones.adapters import gymnasium as adapter

    monkeypatch.setattr(adapter, "GYMNASIUM_VERSION", (0, 25))
    monkeypatch.setattr(gym, "__version__", "0.25.2")
    with pytest.warns(UserWarning, match=r"gymnasium >= 0\.26.*gymnasium 0\.25\.2 is installed"):
        adapter.register()
