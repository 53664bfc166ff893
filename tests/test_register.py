"""`jaxdrones.envs.register`: a task of your own reaches ``jd.make``, its gymnasium id and ``jaxdrones train``."""

import json
import textwrap

import gymnasium as gym
import jax
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.cli import main
from jaxdrones.envs import get_task, is_multi_agent, register, registered
from jaxdrones.envs.tasks.single import Hover, HoverConfig

#: A module of a user's own: a hover task 0.5 m higher, registered on import.
USER_MODULE = textwrap.dedent("""
    import dataclasses

    from jaxdrones.envs import register
    from jaxdrones.envs.tasks.single import Hover, HoverConfig


    @dataclasses.dataclass(frozen=True)
    class TallConfig(HoverConfig):
        target: tuple = (0.0, 0.0, 1.5)


    class TallHover(Hover):
        name = "tall_hover"
        config_cls = TallConfig


    HIGH_HOVER = register(TallHover())
""")


@pytest.fixture(autouse=True)
def restore_registries():
    """Each test's registrations are undone after it (the registry is the process's)."""
    from jaxdrones.adapters import gymnasium as gym_adapter
    from jaxdrones.envs import registry

    tasks, ids, gym_ids = dict(registry._REGISTRY), dict(gym_adapter.GYM_IDS), set(gym.registry)
    yield
    registry._REGISTRY.clear()
    registry._REGISTRY.update(tasks)
    gym_adapter.GYM_IDS.clear()
    gym_adapter.GYM_IDS.update(ids)
    for env_id in set(gym.registry) - gym_ids:
        del gym.registry[env_id]


class LowHover(Hover):
    name = "low_hover"
    config_cls = HoverConfig


def test_a_registered_task_reaches_make_and_gymnasium():
    task = register(LowHover())
    assert "low_hover" in registered() and get_task("low_hover") is task and not is_multi_agent("low_hover")
    assert register(task) is task  # registering the same task again changes nothing
    env = jd.make("low_hover", target=(0.0, 0.0, 0.5))
    state = jax.jit(env.reset)(jax.random.key(0))
    np.testing.assert_allclose(np.asarray(state.task.target), [[0.0, 0.0, 0.5]])
    gym_env = gym.make("jaxdrones/LowHover-v0", target=(0.0, 0.0, 0.5))
    obs, _ = gym_env.reset(seed=0)
    obs, reward, terminated, truncated, _ = gym_env.step(np.zeros(gym_env.action_space.shape, np.float32))
    assert obs.shape == gym_env.observation_space.shape and np.isfinite(reward)
    gym_env.close()


def test_bad_registrations():
    with pytest.raises(ValueError, match="Task subclass"):
        register(object())
    bad = LowHover()
    bad.name = "low hover"
    with pytest.raises(ValueError, match="identifier"):
        register(bad)
    taken = LowHover()
    taken.name = "hover"
    with pytest.raises(ValueError, match="already registered"):
        register(taken, overwrite=True)  # a built-in task is never replaced
    first, second = LowHover(), LowHover()
    first.name = second.name = "other_hover"
    register(first)
    with pytest.raises(ValueError, match="overwrite=True"):
        register(second)  # another task of the same name
    assert register(second, overwrite=True) is second and get_task("other_hover") is second


@pytest.mark.slow
def test_train_cli_trains_a_task_of_your_own(tmp_path, monkeypatch, capsys):
    """``jaxdrones train tall_hover --import my_tasks`` from the folder holding ``my_tasks.py``: a short run of a task
    the module registers, saved and judged on its own target."""
    (tmp_path / "my_tasks.py").write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))  # removed again after the test, as the folder --import adds
    assert main(["train", "tall_hover", "--no-progress"]) == 2  # not registered without the module
    assert "tall_hover" in capsys.readouterr().err
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "tall_hover",
                "--import",
                "my_tasks",
                "--algo",
                "ppo",
                "--steps",
                "20000",
                "--num-envs",
                "16",
                "--num-evals",
                "1",
                "--out",
                str(run),
                "--no-progress",
                "--eval-episodes",
                "64",
            ]
        )
        == 0
    )
    summary = json.loads((run / "summary.json").read_text())
    assert summary["task"] == "tall_hover" and summary["env_steps"] >= 20_000
    env, _ = jd.training.load_policy(run)
    assert env.task.name == "tall_hover" and env.config.target == (0.0, 0.0, 1.5)
    assert main(["train", "hover", "--import", "no_such_module", "--no-progress"]) == 2
    assert "no_such_module" in capsys.readouterr().err
