"""The command line: ``jaxdrones train TASK`` (a short PPO run, its outputs, run folders, reloading the policy),
its bad input, and ``jaxdrones fly``."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pickle
import re
import shutil
import signal
import subprocess
import sys

import jax
import numpy as np
import pytest
from jax.experimental.compilation_cache import compilation_cache

from jaxdrones import viz
from jaxdrones.cli import build_parser, main
from jaxdrones.io.runs import MARKER
from jaxdrones.training import evaluate, load_policy
from jaxdrones.training.trainers import TRAINABLE

#: What a training run writes (with the mark of a folder jaxdrones wrote, `jaxdrones.io.runs.MARKER`); flight.html
#: where viser (the viewer extra, in the test extra) is installed.
TRAIN_OUTPUTS = (MARKER, "policy.pkl", "learning_curve.png", "flight.png", "progress.json", "summary.json") + (
    ("flight.html",) if viz.viewer_available() else ()
)
#: What each seed's folder of a run of several seeds holds.
SEED_OUTPUTS = ("policy.pkl", "progress.json", "summary.json")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def compile_cache(tmp_path_factory):
    """A persistent compilation cache for this test only, so repeated identical runs skip XLA compilation."""
    saved = {
        name: getattr(jax.config, name)
        for name in ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    }
    compilation_cache.reset_cache()
    jax.config.update("jax_compilation_cache_dir", str(tmp_path_factory.mktemp("xla_cache")))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    yield
    for name, value in saved.items():
        jax.config.update(name, value)
    compilation_cache.reset_cache()


@pytest.fixture
def planned(monkeypatch):
    """The recipes the command line hands to `train_task` (which trains nothing here): ``main`` returns 2 after
    each, with the summary missing."""
    from jaxdrones.cli import train as cli_train

    seen = []

    def capture(run, *args, **kwargs):
        seen.append(run)
        raise ValueError("planned only")

    monkeypatch.setattr(cli_train, "train_task", capture)
    return seen


def snapshot(folder):
    """{file name: (mtime_ns, bytes)} of a folder."""
    return {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(folder.iterdir())}


def train_args(out, *extra):
    return [
        "train",
        "hover",
        "--steps",
        "20000",
        "--num-envs",
        "64",
        "--out",
        str(out),
        "--no-progress",
        "--eval-episodes",
        "64",
        *extra,
    ]


@pytest.mark.slow
def test_train_cli_outputs_run_folders_and_reload(tmp_path, capsys, compile_cache):
    run = tmp_path / "run"
    assert main(train_args(run)) == 0
    assert f"in {run}" in capsys.readouterr().out

    # Outputs.
    assert sorted(p.name for p in run.iterdir()) == sorted(TRAIN_OUTPUTS)
    for name in ("learning_curve.png", "flight.png"):
        data = (run / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000
    summary = json.loads((run / "summary.json").read_text())
    assert {"wall_time_s", "env_steps", "eval_final_pos_error_m", "success"} <= set(summary)
    assert summary["out_dir"] == str(run)
    assert 0 < summary["wall_time_s"] < 600 and summary["env_steps"] >= 20_000
    assert math.isfinite(summary["eval_final_pos_error_m"]) and summary["eval_final_pos_error_m"] >= 0
    assert summary["eval"]["n_episodes"] == 64
    assert summary["success"] == (summary["eval_final_pos_error_m"] < 0.05 and summary["eval"]["terminated_rate"] == 0)
    progress = json.loads((run / "progress.json").read_text())
    steps = [row["env_steps"] for row in progress]
    assert steps[0] > 0 and steps == sorted(steps) and steps[-1] == summary["env_steps"]
    assert all(math.isfinite(row["episode_reward"]) for row in progress)

    # The saved policy reproduces the run's evaluation (same key as `train_hover`: split(key(seed + 1))[0]).
    env, policy = load_policy(run)
    assert env.config.action_type == "rpm" and env.config.model == "cf2x"
    key_eval = jax.random.split(jax.random.key(0 + 1))[0]
    stats = evaluate(env, policy, key_eval, 64)
    assert stats["final_pos_error_m"] == pytest.approx(summary["eval_final_pos_error_m"], abs=1e-5)
    assert stats["terminated_rate"] == summary["eval"]["terminated_rate"]
    assert stats["episode_reward"] == pytest.approx(summary["eval"]["episode_reward"], rel=1e-5)
    obs = jax.vmap(env.reset)(jax.random.split(jax.random.key(5), 16)).obs.reshape(16, -1)
    actions, _ = jax.vmap(policy, in_axes=(0, None))(obs, jax.random.key(6))
    assert actions.shape == (16, 4) and np.all(np.abs(actions) <= 1.0)
    _, policy_from_file = load_policy(run / "policy.pkl")
    np.testing.assert_array_equal(jax.vmap(policy_from_file, in_axes=(0, None))(obs, jax.random.key(7))[0], actions)

    # A second identical call goes to a new folder and leaves the first untouched.
    before = snapshot(run)
    assert main(train_args(run)) == 0
    run1 = tmp_path / "run-1"
    assert f"in {run1}" in capsys.readouterr().out
    assert snapshot(run) == before
    assert sorted(p.name for p in run1.iterdir()) == sorted(TRAIN_OUTPUTS)
    summary1 = json.loads((run1 / "summary.json").read_text())
    assert summary1["out_dir"] == str(run1)
    # Same seed, same result.
    assert summary1["eval_final_pos_error_m"] == pytest.approx(summary["eval_final_pos_error_m"], abs=1e-6)

    # --overwrite replaces the folder's contents (and nothing else).
    (run / "stale.txt").write_text("from an earlier run")
    before1 = snapshot(run1)
    assert main(train_args(run, "--overwrite")) == 0
    assert sorted(p.name for p in run.iterdir()) == sorted(TRAIN_OUTPUTS)
    after = snapshot(run)
    assert all(after[name][0] > before[name][0] for name in TRAIN_OUTPUTS)
    assert snapshot(run1) == before1
    assert not (tmp_path / "run-2").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (("--eval-episodes", "10"), "n_eval_episodes must be an integer >= 64"),
        (("--steps", "-5"), "--steps must be a positive integer"),
        (("--num-envs", "0"), "--num-envs must be a positive integer"),
        (("--target", "0", "0", "-1"), "above the ground"),
        (("--action-type", "warp"), "unknown action_type 'warp'"),
        (("--num-drones", "2"), "n_drones must be exactly 1"),
    ],
)
def test_train_cli_bad_input(tmp_path, capsys, extra, message):
    args = train_args(tmp_path / "run")
    assert main(args + list(extra)) == 2
    captured = capsys.readouterr()
    assert message in captured.err and "error" in captured.err and captured.out == ""
    assert not (tmp_path / "run").exists()


def test_cli_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.startswith("jaxdrones 0.")


@pytest.mark.parametrize(
    "argv, hint",
    [
        (["train", "hover", "--defualts", "cpu"], "--defualts (did you mean '--defaults'?)"),
        (["train", "hover", "--sed", "1"], "--sed (did you mean '--seed'?)"),
        (["fly", "--durration", "3"], "--durration (did you mean '--duration'?)"),
    ],
)
def test_mistyped_options_get_the_subcommands_usage_and_the_closest_option(argv, hint, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"usage: jaxdrones {argv[0]}" in err and hint in err


def test_load_policy_rejects_missing_and_foreign_files(tmp_path):
    with pytest.raises(ValueError, match="no saved policy"):
        load_policy(tmp_path)
    (tmp_path / "policy.pkl").write_bytes(pickle.dumps({"weights": 1}))
    with pytest.raises(ValueError, match="is not a jaxdrones policy file"):
        load_policy(tmp_path)


@pytest.mark.parametrize("content", [b"", b"\x80\x05garbage", pickle.dumps({"params": 1, "env_name": "hover"})[:-9]])
@pytest.mark.parametrize("command", ["view", "export"])
def test_view_and_export_refuse_an_empty_or_damaged_policy_file(tmp_path, content, command, capsys):
    """An empty or cut ``policy.pkl``: a ValueError from `load_policy`, and the commands end with its message."""
    (tmp_path / "policy.pkl").write_bytes(content)
    with pytest.raises(ValueError, match="empty or damaged"):
        load_policy(tmp_path)
    assert main([command, str(tmp_path), "--out", str(tmp_path / "out")]) != 0
    assert "empty or damaged" in capsys.readouterr().err


def test_fly_cli(tmp_path, capsys):
    out = tmp_path / "fly"
    assert main(["fly", "--num-drones", "2", "--duration", "3", "--out", str(out)]) == 0
    assert "overall" in capsys.readouterr().out
    assert (out / "flight.png").read_bytes().startswith(PNG_MAGIC)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["settings"]["num_drones"] == 2 and metrics["settings"]["duration_s"] == 3.0
    m = metrics["metrics"]
    assert len(m["waypoint_rms_per_drone_m"]) == 2 and len(m["cross_track_rms_per_drone_m"]) == 2
    # The PID with feed-forward tracks the circle within a few centimetres after the first second.
    assert 0 < m["cross_track_rms_m"] < 0.05 and 0 < m["waypoint_rms_m"] < 0.1
    with np.load(out / "flight.npz") as flight:
        assert flight["pos"].shape == (3 * 48, 2, 3)
        assert np.all(np.isfinite(flight["pos"]))

    assert main(["fly", "--num-drones", "0", "--out", str(tmp_path / "bad")]) == 2
    assert "num_drones must be a positive integer" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["apg", "shac"])
def test_train_cli_gradient_algos_learn_save_and_reload(algo, tmp_path, capsys):
    """``--algo apg`` (analytic policy gradients) and ``--algo shac`` (short-horizon actor-critic) through the
    simulator: the evaluation distance falls, the outputs are PPO's, and the saved policy reproduces the run's
    evaluation."""
    run = tmp_path / algo
    args = [
        "train",
        "hover",
        "--algo",
        algo,
        "--steps",
        "100000",
        "--num-envs",
        "8",
        "--out",
        str(run),
        "--no-progress",
        "--eval-episodes",
        "64",
    ]
    assert main(args) == 0
    assert f"in {run}" in capsys.readouterr().out
    assert sorted(p.name for p in run.iterdir()) == sorted(TRAIN_OUTPUTS)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["algo"] == algo and summary["config"]["num_envs"] == 8 and summary["env_steps"] >= 100_000
    progress = json.loads((run / "progress.json").read_text())
    assert progress[-1]["env_steps"] == summary["env_steps"]
    assert progress[-1]["success_value"] == summary["success_value"]
    # The final distance fell below that of the first evaluation, after a ninth of the run.
    assert progress[-1]["success_value"] < 0.7 * progress[0]["success_value"]
    env, policy = load_policy(run)
    stats = evaluate(env, policy, jax.random.split(jax.random.key(0 + 1))[0], 64)
    assert stats["final_pos_error_m"] == pytest.approx(summary["eval_final_pos_error_m"], abs=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ppo"])
def test_train_cli_ppo_trainers_save_and_reload(algo, tmp_path, capsys):
    """``--algo ppo`` (ours; brax's in `test_train_cli_seeds_write_each_run_and_their_aggregate`): a short run writes
    the outputs, its summary names the trainer, and the saved policy reproduces the run's last evaluation."""
    run = tmp_path / algo
    assert (
        main(
            [
                "train",
                "hover",
                "--algo",
                algo,
                "--steps",
                "20000",
                "--num-envs",
                "16",
                "--num-evals",
                "2",
                "--out",
                str(run),
                "--no-progress",
                "--eval-episodes",
                "64",
            ]
        )
        == 0
    )
    assert f"in {run}" in capsys.readouterr().out
    assert sorted(p.name for p in run.iterdir()) == sorted(TRAIN_OUTPUTS)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["algo"] == algo and summary["env_steps"] >= 20_000 and not summary["interrupted"]
    progress = json.loads((run / "progress.json").read_text())
    assert len(progress) == 2 and progress[-1]["success_value"] == summary["success_value"]
    env, policy = load_policy(run)
    stats = evaluate(env, policy, jax.random.split(jax.random.key(0 + 1))[0], 64)
    assert stats["final_pos_error_m"] == pytest.approx(summary["eval_final_pos_error_m"], abs=1e-5)


def test_td_lambda_returns_by_hand():
    """SHAC's critic targets: λ = 0 gives one-step TD, λ → 1 the discounted return bootstrapped at the window's
    end, and an episode's end cuts the sum (its own next value, 0 if it terminated)."""
    from jaxdrones.training.shac import td_lambda_returns

    r, v = np.array([1.0, 2.0, 3.0]), np.array([10.0, 20.0, 30.0])
    ended = np.zeros(3, bool)
    g = 0.9
    np.testing.assert_allclose(td_lambda_returns(r, v, ended, g, 0.0), r + g * v)
    monte_carlo = [1 + g * 2 + g**2 * 3 + g**3 * 30, 2 + g * 3 + g**2 * 30, 3 + g * 30]
    np.testing.assert_allclose(td_lambda_returns(r, v, ended, g, 1.0), monte_carlo, rtol=1e-6)
    lam = 0.5
    g2 = 3 + g * 30
    g1 = 2 + g * ((1 - lam) * 20 + lam * g2)
    np.testing.assert_allclose(
        td_lambda_returns(r, v, ended, g, lam), [1 + g * ((1 - lam) * 10 + lam * g1), g1, g2], rtol=1e-6
    )
    cut = td_lambda_returns(r, np.array([0.0, 20.0, 30.0]), np.array([True, False, False]), g, lam)
    np.testing.assert_allclose(cut, [1.0, g1, g2], rtol=1e-6)


def test_shac_config_bad_input():
    from jaxdrones.training.shac import SHACConfig

    with pytest.raises(ValueError, match="discounting must be a finite number in"):
        SHACConfig(discounting=1.0)
    with pytest.raises(ValueError, match="critic_minibatches must be an integer"):
        SHACConfig(critic_minibatches=0)
    with pytest.raises(ValueError, match="horizon must be an integer"):
        SHACConfig(horizon=0)


def test_train_cli_unknown_algo(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "hover", "--algo", "sac"])
    assert exit_.value.code == 2 and "invalid choice: 'sac'" in capsys.readouterr().err


def test_task_loss_is_the_weighted_smooth_terms():
    """The differentiable training loss of hover: d² + 0.1 ‖v‖² + 0.01 ‖ω‖² (the velocity task: ‖v − v*‖² +
    0.01 ‖ω‖²), next to a shaped reward that is clipped at 0."""
    import jaxdrones as jd

    env = jd.make("hover")
    s = env.step(env.reset(jax.random.key(3)), jax.numpy.zeros((1, 4)))
    d2 = np.sum((np.asarray(s.sim.pos) - np.asarray(s.task.target)) ** 2, -1)
    expected = d2 + 0.1 * np.sum(np.asarray(s.sim.vel) ** 2, -1) + 0.01 * np.sum(np.asarray(s.sim.ang_vel) ** 2, -1)
    np.testing.assert_allclose(env.loss(s), expected, rtol=1e-5)
    vel = jd.make("velocity")
    s = vel.step(vel.reset(jax.random.key(4)), jax.numpy.zeros((1, 4)))
    err = np.sum((np.asarray(s.sim.vel) - np.asarray(s.task.data["target_vel"])) ** 2, -1)
    np.testing.assert_allclose(vel.loss(s), err + 0.01 * np.sum(np.asarray(s.sim.ang_vel) ** 2, -1), rtol=1e-5)


def test_gae_by_hand():
    """GAE: δ_t = r_t + γ (1 − terminated_t) V'_t − V_t, A_t = δ_t + γλ (1 − ended_t) A_{t+1}; a truncated episode
    bootstraps from its last state's value V', a terminated one from 0."""
    from jaxdrones.training.mappo import gae

    r, v, boot = np.array([1.0, 2.0, 3.0]), np.array([0.5, 1.0, 1.5]), np.array([1.0, 9.0, 2.0])
    g, lam = 0.9, 0.8
    never = np.zeros(3)
    d = r + g * boot - v
    a2 = d[2]
    a1 = d[1] + g * lam * a2
    a0 = d[0] + g * lam * a1
    np.testing.assert_allclose(gae(r, v, boot, never, never, g, lam), [a0, a1, a2], rtol=1e-6)
    # The episode ends at step 1: truncated (bootstrap 9) or terminated (0); step 0 does not see step 2.
    ended = np.array([0.0, 1.0, 0.0])
    truncated = gae(r, v, boot, never, ended, g, lam)
    np.testing.assert_allclose(truncated[1], r[1] + g * 9.0 - v[1], rtol=1e-6)
    np.testing.assert_allclose(truncated[0], d[0] + g * lam * truncated[1], rtol=1e-6)
    terminated = gae(r, v, boot, ended, ended, g, lam)
    np.testing.assert_allclose(terminated[1], r[1] - v[1], rtol=1e-6)


def test_running_observation_statistics_match_numpy():
    from jaxdrones.training.mappo import update_norm

    rng = np.random.default_rng(0)
    chunks = [rng.normal(3.0, 2.0, (50, 2, 5)), rng.normal(-1.0, 0.5, (30, 2, 5))]
    norm = {"mean": np.zeros(5), "var": np.ones(5), "count": np.zeros(())}
    for chunk in chunks:
        norm = update_norm(norm, jax.numpy.asarray(chunk))
    everything = np.concatenate([c.reshape(-1, 5) for c in chunks])
    np.testing.assert_allclose(norm["mean"], everything.mean(0), rtol=1e-5)
    np.testing.assert_allclose(norm["var"], everything.var(0), rtol=1e-4)


def test_agent_mlp_first_layer_is_the_concatenated_dense():
    """The first layer by parts (obs, id embedding, world once per world) equals one Dense layer on
    [obs, one-hot id, world] for every agent."""
    from jaxdrones.training.mappo import agent_mlp

    rng = np.random.default_rng(1)
    n_agents, n_obs, n_world = 5, 7, 30
    net = agent_mlp((16, 8), 3, n_agents, n_obs + n_agents + n_world)
    obs, world = rng.normal(size=(4, n_agents, n_obs)), rng.normal(size=(4, n_world))
    params = net.init(jax.random.key(0), obs, world)
    p = jax.tree.map(np.asarray, params["params"])
    kernel = np.concatenate([p["Dense_0"]["kernel"], p["Embed_0"]["embedding"], p["Dense_1"]["kernel"]])
    joint = np.concatenate(
        [
            obs,
            np.broadcast_to(np.eye(n_agents), (4, n_agents, n_agents)),
            np.broadcast_to(world[:, None], (4, n_agents, n_world)),
        ],
        -1,
    )
    hidden = np.tanh(np.tanh(joint @ kernel + p["Dense_0"]["bias"]) @ p["Dense_2"]["kernel"] + p["Dense_2"]["bias"])
    expected = hidden @ p["Dense_3"]["kernel"] + p["Dense_3"]["bias"]
    np.testing.assert_allclose(net.apply(params, obs, world), expected, rtol=2e-5, atol=2e-6)


def test_ppo_noise_per_window_draws_an_unrolls_noise_before_it(monkeypatch):
    """With ``noise_per_window`` (on in the ``gpu`` profile) our PPO draws the Gaussian noise of a whole unroll in one
    call before it, so that the unroll's step hashes no key; without it every step draws from its own key."""
    import jaxdrones as jd
    from jaxdrones.training import mappo

    def eqns(jaxpr):  # the equations of a jaxpr and of every jaxpr inside it
        for eqn in jaxpr.eqns:
            yield eqn
            for param in eqn.params.values():
                for sub in param if isinstance(param, (list, tuple)) else [param]:
                    inner = getattr(sub, "jaxpr", sub)
                    if isinstance(inner, jax.extend.core.Jaxpr):
                        yield from eqns(inner)

    def draws(jaxpr):
        return any(eqn.primitive.name in ("random_bits", "threefry2x32") for eqn in eqns(jaxpr))

    env = jd.make("hover")
    for per_window in (False, True):
        built = {}
        monkeypatch.setattr(
            mappo, "run_updates", lambda config, build, *a, **k: built.update(zip("iur", build(config), strict=True))
        )
        config = mappo.MAPPOConfig(
            num_timesteps=36,
            num_envs=4,
            unroll_length=3,
            minibatches=1,
            epochs=2,
            critic="local",
            num_evals=1,
            starts_per_window=True,  # else the resets drawn in the step hash keys there too
            noise_per_window=per_window,
        )
        mappo.train(env, config)
        update = jax.make_jaxpr(built["u"])(jax.eval_shape(built["i"], jax.random.key(0)), None).jaxpr
        unrolls = [e for e in eqns(update) if e.primitive.name == "scan" and e.params["length"] == 3]
        assert unrolls  # the unroll, and GAE's backward pass over it
        assert any(draws(e.params["jaxpr"].jaxpr) for e in unrolls) is not per_window
        assert draws(update)  # the minibatches' shuffle, and with noise_per_window the unroll's noise
    with pytest.raises(ValueError, match="noise_per_window must be True or False"):
        mappo.MAPPOConfig(noise_per_window="yes")


@pytest.mark.parametrize(
    "kwargs", [dict(critic="central", share_params=True), dict(critic="local", share_params=False)]
)
def test_mappo_variants_train_on_three_drones(kwargs):
    """MAPPO (shared networks with agent ids, central critic) and IPPO with per-agent networks run on a 3-drone team
    and give a policy of the team's joint action shape; the per-agent parameters carry an agent axis."""
    import jaxdrones as jd
    from jaxdrones.training import mappo

    env = jd.make("leader_follower", n_drones=3, action_type="one_d_rpm")
    config = mappo.MAPPOConfig(
        num_timesteps=2 * 8 * 4, num_envs=8, unroll_length=4, minibatches=2, num_evals=2, **kwargs
    )
    seen = []
    nets, params = mappo.train(env, config, progress=lambda steps, metrics: seen.append((steps, metrics)))
    assert [s for s, _ in seen] == [config.total_steps // 2, config.total_steps]
    assert np.isfinite(seen[-1][1]["train/value_loss"])
    leaves = jax.tree.leaves(params["actor"])
    assert all(leaf.shape[0] == 3 for leaf in leaves) == (not kwargs["share_params"])
    obs = env.reset(jax.random.key(0)).obs
    action, _ = mappo.make_policy(nets, params)(obs.reshape(-1), None)
    assert action.shape == (3 * env.action_size,) and np.all(np.isfinite(action))


@pytest.mark.slow
def test_train_cli_mappo_leader_follower_saves_and_reloads(tmp_path, capsys):
    """``jaxdrones train leader_follower``: MAPPO by default, the paper's one_d_rpm actions, every drone in the flight
    plot; the evaluation error falls and the saved policy reproduces the run's evaluation."""
    run = tmp_path / "lf"
    args = [
        "train",
        "leader_follower",
        "--steps",
        "150000",
        "--num-envs",
        "64",
        "--out",
        str(run),
        "--no-progress",
        "--eval-episodes",
        "64",
    ]
    assert main(args) == 0
    assert f"in {run}" in capsys.readouterr().out
    assert sorted(p.name for p in run.iterdir()) == sorted(TRAIN_OUTPUTS)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["algo"] == "mappo" and summary["env"]["action_type"] == "one_d_rpm"
    assert summary["env"]["n_drones"] == 2 and "final_max_altitude_error" in summary["eval"]
    progress = json.loads((run / "progress.json").read_text())
    assert progress[-1]["success_value"] < progress[0]["success_value"]
    env, policy = load_policy(run)
    stats = evaluate(env, policy, jax.random.split(jax.random.key(0 + 1))[0], 64)
    # The run's evaluation (with the flight of its plot) is another program than the standalone `evaluate`, and XLA
    # rounds float32 differently in each; the followers' millimetre errors then differ (seen: 1.14 against 1.24 mm,
    # 2.68 against 2.60 mm).
    assert stats["success_value"] == pytest.approx(summary["success_value"], rel=0.15)


@pytest.mark.slow
def test_train_multi_hover_trains_from_wider_starts_and_evaluates_the_tasks(tmp_path, monkeypatch):
    """``multi_hover`` trained by MAPPO trains from its recipe's training env (for the start fields the run does not
    set, not with 1-D actions) and is evaluated and saved with the task's own starts."""
    from jaxdrones.training import mappo
    from jaxdrones.training.recipes import RECIPES, recipe
    from jaxdrones.training.run import train_task

    wider = RECIPES["multi_hover"].cpu.tuned["mappo"].train_env
    assert wider == {"start_ang_vel": 1.0}

    trained_in = []
    real_train = mappo.train
    monkeypatch.setattr(mappo, "train", lambda env, *a, **k: trained_in.append(env) or real_train(env, *a, **k))
    tiny = mappo.MAPPOConfig(num_timesteps=8, num_envs=4, unroll_length=2, minibatches=1, num_evals=2)
    summary = train_task(
        "multi_hover",
        str(tmp_path / "run"),
        env_overrides={"n_drones": 3},
        progress=False,
        algo="mappo",
        config=tiny,
        n_eval_episodes=64,
    )
    assert summary["train_env_overrides"] == wider
    (trained,) = trained_in
    assert trained.config.starts.ang_vel == 1.0 and trained.config.starts.tilt is None
    assert summary["env"]["starts"]["ang_vel"] is None  # the evaluation env's: the task's own
    env, _ = load_policy(tmp_path / "run")
    assert env.config.starts.ang_vel is None and env.config.n_drones == 3
    # Not for the start fields the run sets, nor with 1-D actions.
    assert recipe("multi_hover", "cpu", {"n_drones": 3, "start_ang_vel": 0.5}, "mappo").train_env == {}
    assert recipe("multi_hover", "cpu", {"n_drones": 3, "action_type": "one_d_rpm"}, "mappo").train_env == {}


def test_train_cli_multi_agent_bad_team_size(capsys):
    assert main(["train", "leader_follower", "--num-drones", "1", "--no-progress"]) == 2
    assert "n_drones" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("task", TRAINABLE)
def test_every_task_trains_at_its_recipe_through_the_command_line(task, tmp_path, capsys):
    """``jaxdrones train TASK`` for every task at its recipe, for one update of 8 worlds: the run folder holds every
    output, the summary records the recipe's trainer, profile and env, and the saved policy flies in its env.
    Whether the recipe solves the task is ``benchmarks/training/suite.py``'s to say (docs/benchmarks.md)."""
    from jaxdrones.training.evaluation import act
    from jaxdrones.training.progress import AGGREGATES
    from jaxdrones.training.recipes import recipe

    plan = recipe(task, "cpu")
    run = tmp_path / task
    args = ["train", task, "--defaults", "cpu", "--steps", "1", "--num-evals", "1", "--num-envs", "8"]
    assert main([*args, "--eval-episodes", "64", "--out", str(run), "--no-progress"]) == 0
    assert "saved policy.pkl, learning_curve.png, flight.png" in capsys.readouterr().out
    assert sorted(p.name for p in run.iterdir()) == sorted(TRAIN_OUTPUTS)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["algo"] == plan.algo and summary["defaults"] == "cpu" and summary["eval"]["n_episodes"] == 64
    assert {k: summary["env"][k] for k in plan.env} == json.loads(json.dumps(dict(plan.env)))
    assert summary["train_env_overrides"] == plan.train_env
    env, policy = load_policy(run)
    at, metric = env.task.success_at, env.task.success_metric  # judged as the task says (crossing: max over time)
    assert summary["success_metric"] == f"{metric} ({AGGREGATES[at]})"
    assert summary["success_value"] == pytest.approx(summary["eval"][f"{at}_{metric}"])
    action = act(env, policy, env.reset(jax.random.key(1)).obs, jax.random.key(2))
    assert action.shape == (env.n_drones, env.action_size) and np.all(np.isfinite(action))


def test_train_cli_crossing_without_downwash(planned):
    """``jaxdrones train crossing --no-downwash``: the flag turns the task's default downwash off in the env its
    recipe's trainer (APG, ctbr actions) trains; the rest of the recipe is the task's."""
    from jaxdrones.training.recipes import recipe

    assert main(["train", "crossing", "--no-downwash", "--no-progress"]) == 2
    (run,) = planned
    assert run.algo == "apg" and run.env["downwash"] is False and run.env["action_type"] == "ctbr"
    default = recipe("crossing", "cpu")
    assert dict(run.env) == {**default.env, "downwash": False} and run.config == default.config


def test_train_cli_crossing_with_the_bounded_downwash(planned, capsys):
    """``--downwash-model bounded`` sets the env's downwash to the bounded form (docs/physics.md §6.5); with
    ``--no-downwash`` it is refused."""
    assert main(["train", "crossing", "--downwash-model", "bounded", "--no-progress"]) == 2
    (run,) = planned
    assert run.env["downwash"] == "bounded"
    assert main(["train", "crossing", "--downwash-model", "bounded", "--no-downwash", "--no-progress"]) == 2
    assert "--downwash-model turns the downwash on" in capsys.readouterr().err


def test_train_cli_bad_neighbour_options(capsys):
    assert main(["train", "multi_hover", "--downwash-radius", "-1", "--no-progress"]) == 2
    assert "downwash_radius" in capsys.readouterr().err
    assert main(["train", "multi_hover", "--max-neighbors", "0", "--no-progress"]) == 2
    assert "max_neighbors" in capsys.readouterr().err


def test_load_policy_into_another_env_checks_the_team(tmp_path):
    """A saved policy flies in an env of the same task and team with other physics (here downwash on); an env of
    another task or team size is refused."""
    import jaxdrones as jd
    from jaxdrones.training import checkpoint, mappo

    env = jd.make("leader_follower", n_drones=3, action_type="one_d_rpm")
    config = mappo.MAPPOConfig(num_timesteps=8, num_envs=4, unroll_length=2, minibatches=1, num_evals=2)
    nets, params = mappo.train(env, config)
    checkpoint.save(
        tmp_path / "policy.pkl", "mappo", params, "leader_follower", {"n_drones": 3, "action_type": "one_d_rpm"}, config
    )
    coupled = jd.make("leader_follower", n_drones=3, action_type="one_d_rpm", downwash=True)
    got, policy = load_policy(tmp_path, env=coupled)
    assert got is coupled and got.config.sim.downwash
    assert policy(coupled.reset(jax.random.key(0)).obs.reshape(-1), None)[0].shape == (3,)
    with pytest.raises(ValueError, match="trained on 'leader_follower' with 3 drones.*with 2 drones"):
        load_policy(tmp_path, env=jd.make("leader_follower", n_drones=2, action_type="one_d_rpm"))
    with pytest.raises(ValueError, match="the env given is 'multi_hover'"):
        load_policy(tmp_path, env=jd.make("multi_hover", n_drones=3, action_type="one_d_rpm"))


def test_train_cli_defaults_profiles(tmp_path, capsys):
    """``--defaults gpu`` trains with the large-batch settings on any device (here the CPU) and the summary records
    the profile; without it the device's profile is used (the CPU's here); the profiles differ where tuned."""
    from jaxdrones.training import trainers
    from jaxdrones.training.recipes import recipe

    assert trainers.default_profile() == ("cpu" if jax.default_backend() == "cpu" else "gpu")
    for algo in ("apg", "ppo", "brax_ppo"):
        cpu, gpu = (recipe("hover", d, algo=algo).config for d in trainers.DEFAULTS)
        assert gpu.num_envs >= 4096 > cpu.num_envs
    with pytest.raises(ValueError, match="defaults must be one of"):
        recipe("hover", "tpu")
    for algo in ("apg", "ppo"):  # the gpu profile builds its updates for a GPU; the CPU's as before
        cpu, gpu = (recipe("hover", d, algo=algo).config for d in trainers.DEFAULTS)
        assert gpu.starts_per_window and gpu.flat_params and not cpu.starts_per_window and not cpu.flat_params
        if algo == "ppo":  # APG draws no noise
            assert gpu.noise_per_window and not cpu.noise_per_window
        with pytest.raises(ValueError, match="flat_params must be True or False"):
            dataclasses.replace(cpu, flat_params=1)
    run = tmp_path / "run"
    args = ["train", "hover", "--steps", "1", "--num-evals", "1", "--out", str(run), "--no-progress"]
    assert recipe("hover", "cpu").algo == "apg" and recipe("hover", "gpu").algo == "ppo"
    assert main([*args, "--algo", "apg", "--defaults", "gpu", "--eval-episodes", "64"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["defaults"] == "gpu" and summary["config"]["num_envs"] == 4096
    assert summary["config"]["learning_rate"] == 1e-2 and summary["env_steps"] == 4096 * 32
    env, policy = load_policy(run)  # trained with flat parameters, saved as the network's pytree
    action, _ = policy(env.reset(jax.random.key(1)).obs.reshape(-1), jax.random.key(2))
    assert action.shape == (4,) and np.all(np.isfinite(action))
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main([*args, "--defaults", "tpu"])
    assert "invalid choice: 'tpu'" in capsys.readouterr().err


def test_train_cli_takes_the_devices_profile_by_default(planned):
    """Without ``--defaults`` the command line plans the run at the device's profile (the CPU's here)."""
    from jaxdrones.training import trainers

    assert main(["train", "hover", "--algo", "apg", "--no-progress"]) == 2
    (run,) = planned
    assert run.defaults == trainers.default_profile()
    assert run.config.learning_rate == (3e-3 if run.defaults == "cpu" else 1e-2)


def test_recipes_resolve_a_runs_options_once():
    """`recipe` gives each kind of run its setting (team size, camera images, an unknown task's kind) and
    `Recipe.with_options` applies the command line's flags through the trainer table's fields (brax's PPO: an
    evaluation before training, its batch tied to the envs); nothing else."""
    from jaxdrones.training import trainers
    from jaxdrones.training.recipes import RECIPES, recipe

    assert set(RECIPES) == set(TRAINABLE)
    brax = recipe("tune", "cpu").with_options(seed=3, steps=1000, num_envs=16, num_evals=2)
    assert (brax.config.seed, brax.config.num_timesteps, brax.config.num_evals) == (3, 1000, 3)
    assert brax.config.num_envs == brax.config.batch_size == 16
    apg = recipe("takeoff", "cpu").with_options(num_envs=16, num_evals=2)
    assert (apg.config.num_envs, apg.config.num_evals) == (16, 2) and apg.config == dataclasses.replace(
        recipe("takeoff", "cpu").config, num_envs=16, num_evals=2
    )
    assert recipe("multi_hover", "cpu", {"n_drones": 6}).algo == "apg"
    large = recipe("multi_hover", "cpu", {"n_drones": 7})
    assert large.algo == "mappo" and large.train_env == {"start_ang_vel": 1.0}
    seen = recipe("hover", "cpu", {"vision": ("depth",), "image_size": (32, 24)})
    assert seen.algo == "brax_ppo" and trainers.get(seen.algo).images and seen.config.privileged_critic
    with pytest.raises(ValueError, match="task must be one of"):
        recipe("hoover", "cpu")
    with pytest.raises(ValueError, match="algo must be one of"):
        recipe("hover", "cpu", algo="sac")
    from jaxdrones.training.run import train_task

    with pytest.raises(ValueError, match="a Recipe holds the run's settings; set them in it, not as algo"):
        train_task(recipe("hover", "cpu"), algo="apg")


@pytest.mark.pybullet
def test_recipes_on_the_pybullet_backend_take_a_trainer_that_does_not_differentiate():
    """On the PyBullet backend, which APG cannot differentiate: the first other trainer of the task's setting, else
    the default of the task's kind."""
    from jaxdrones.training.recipes import recipe

    assert recipe("hover", "cpu", {"backend": "pybullet"}).algo == "brax_ppo"
    assert recipe("multi_hover", "cpu", {"backend": "pybullet"}).algo == "mappo"
    assert recipe("takeoff", "cpu", {"backend": "pybullet"}).algo == "brax_ppo"


def test_failed_criteria_name_what_kept_a_run_from_success():
    """The verdict names the criterion a run missed: the metric above its threshold, episodes that ended early, or
    both; a solved run misses none."""
    import jaxdrones as jd
    from jaxdrones.training.evaluation import failed_criteria

    task = jd.make("hover").task
    assert failed_criteria(task, {"success_value": 0.02, "terminated_rate": 0.0, "n_episodes": 256}) == []
    crashed = failed_criteria(task, {"success_value": 0.034, "terminated_rate": 3 / 256, "n_episodes": 256})
    assert crashed == ["3 of 256 episodes ended early (crashed or left the arena; a solved run has none)"]
    both = failed_criteria(task, {"success_value": 0.07, "terminated_rate": 1 / 64, "n_episodes": 64})
    assert len(both) == 2 and "0.07 m is not below the threshold 0.05" in both[0] and "1 of 64" in both[1]


def test_result_line_gives_the_verdict_with_the_threshold():
    """The line ``jaxdrones train`` and the notebooks print: solved, or the criteria missed, then the metric with its
    unit against the threshold, for any stats with the metric, the terminated share and the episode count."""
    import jaxdrones as jd
    from jaxdrones.training.evaluation import judged, result_line

    task = jd.make("hover").task
    solved = judged(task, {"success_value": 0.02, "terminated_rate": 0.0, "n_episodes": 256})
    assert solved["success"] and solved["success_metric"] == "distance (final)"
    assert result_line({**solved, "env_steps": 604_160, "wall_time_s": 17.61}) == (
        "solved: distance (final) 0.02 m (threshold 0.05 m) over 256 random starts (0.0% terminated), 604,160 env "
        "steps, 17.6 s wall time"
    )
    missed = judged(task, {"success_value": 0.07, "terminated_rate": 1 / 64, "n_episodes": 64})
    assert not missed["success"]
    assert result_line(missed) == (
        "not solved: distance (final) 0.07 m is not below the threshold 0.05; 1 of 64 episodes ended early (crashed "
        "or left the arena; a solved run has none). distance (final) 0.07 m (threshold 0.05 m) over 64 random starts "
        "(1.6% terminated)"
    )


def test_train_cli_realism_defaults(planned):
    """Under sim-to-real options ``jaxdrones train hover`` trains as tuned for them: our PPO with its budget,
    ``ctbr`` actions, the error integral and ground contact as a crash; what the command line sets wins; the saved
    env has them."""
    from jaxdrones.training.recipes import recipe

    realism = {"realism": "crazyflie"}
    assert recipe("hover", "cpu", realism).algo == "ppo" and recipe("hover", "cpu").algo == "apg"
    plain = recipe("hover", "cpu", algo="ppo").config
    tuned = recipe("hover", "cpu", realism).config
    assert tuned.num_timesteps > plain.num_timesteps and tuned.anneal_lr and not plain.anneal_lr
    assert recipe("hover", "cpu", realism, "apg").config == recipe("hover", "cpu").config
    assert recipe("hover", "cpu", realism).env == {
        "realism": "crazyflie",
        "action_type": "ctbr",
        "error_integral": True,
        "terminate_on_ground": True,
    }
    assert recipe("hover", "cpu", {**realism, "action_type": "rpm"}).env["action_type"] == "rpm"
    parsed = build_parser().parse_args(["train", "hover", "--realism", "crazyflie", "--no-terminate-on-ground"])
    assert parsed.terminate_on_ground is False
    assert recipe("hover", "cpu", {**realism, "terminate_on_ground": False}).env["terminate_on_ground"] is False
    assert recipe("hover", "cpu").env == {}
    assert main(["train", "hover", "--realism", "crazyflie", "--no-error-integral", "--no-progress"]) == 2
    (run,) = planned  # what the command line hands to train_task (whose summary records the recipe: every task's test)
    assert run.algo == "ppo" and run.config.anneal_lr and run.env["realism"] == "crazyflie"
    assert run.env["action_type"] == "ctbr" and run.env["error_integral"] is False
    assert run.env["terminate_on_ground"] is True


def test_a_run_saved_with_the_physics_options_at_the_top_level_loads_and_flies():
    """tests/data/hover_48hz_65b4528: ``jaxdrones train hover --ctrl-freq 48`` saved at 65b4528, when the physics'
    options were fields of `TaskConfig` itself. Its flat ``ctrl_freq`` goes into the config's ``sim``, and the policy
    flies its 256 evaluation starts as it did then."""
    run = os.path.join(os.path.dirname(__file__), "data", "hover_48hz_65b4528")
    env, policy = load_policy(run)
    assert env.config.sim.ctrl_freq == 48 and env.episode_length == 240
    summary = json.loads(open(os.path.join(run, "summary.json")).read())
    stats = evaluate(env, policy, jax.random.split(jax.random.key(0 + 1))[0], 256)
    assert stats["final_pos_error_m"] == pytest.approx(summary["success_value"], abs=1e-4)
    assert stats["terminated_rate"] == 0


#: Each trainer of the table at a budget of a few updates, on a task it trains: (task, env options, config fields).
#: (ppo and ippo are `jaxdrones.training.mappo.train` with a local critic: each training function of the table once.)
SEEDED = {
    "apg": ("hover", {}, dict(num_envs=4, horizon=8)),
    "shac": ("hover", {}, dict(num_envs=4, horizon=8, critic_minibatches=2)),
    "mappo": ("leader_follower", {}, dict(num_envs=4, unroll_length=8, minibatches=2)),
}


@pytest.mark.slow
@pytest.mark.parametrize("algo", SEEDED)
def test_mapped_runs_train_what_each_single_run_trains(algo):
    """Two runs as one program mapped over them, the second with another seed and every float setting of the
    config changed: the second trains the parameters and evaluates the outcomes of its single run, within float
    rounding."""
    import jaxdrones as jd
    from jaxdrones.training import trainers
    from jaxdrones.training.evaluation import eval_program
    from jaxdrones.training.recipes import recipe

    task, options, fields = SEEDED[algo]
    trainer, env = trainers.get(algo), jd.make(task, **options)
    config = dataclasses.replace(recipe(task, "cpu", options, algo).config, **fields, num_evals=2, seed=0)
    config = dataclasses.replace(config, num_timesteps=2 * config.steps_per_update * 2)
    values = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    second = dataclasses.replace(config, seed=1, **{k: 0.9 * v for k, v in values.items() if type(v) is float})
    evaluate = eval_program(env, trainer, 64) if algo == "apg" else None  # the evaluation's seed: once is enough
    seen = {"mapped": [], "single": []}
    both = trainer.train(env, config, lambda s, m: seen["mapped"].append(m), evaluate, runs=(config, second))
    _, single = trainer.train(env, second, lambda s, m: seen["single"].append(m), evaluate)
    assert len(both) == 2 and [len(seen[k]) for k in seen] == [2, 2]
    for got, want in zip(jax.tree.leaves(both[1][1]), jax.tree.leaves(single), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    assert not np.allclose(jax.tree.leaves(both[0][1])[0], jax.tree.leaves(single)[0])  # the first is another run
    if evaluate is None:
        return
    outcomes = jax.tree.map(lambda x: x[1], seen["mapped"][-1]["eval"]["outcomes"])
    for got, want in zip(
        jax.tree.leaves(outcomes), jax.tree.leaves(seen["single"][-1]["eval"]["outcomes"]), strict=True
    ):
        np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-5)


@pytest.mark.slow
def test_train_cli_seeds_write_each_run_and_their_aggregate(tmp_path, capsys):
    """``jaxdrones train hover --seeds 3`` (APG): a run folder per seed that loads alone, and the summary of
    all: each seed's result, the median, the interquartile mean with its bootstrap interval and the share solved;
    brax's PPO runs its seeds one after another."""
    from jaxdrones.training.runs import aggregate

    run = tmp_path / "seeds"
    args = ["train", "hover", "--steps", "2048", "--num-envs", "8", "--num-evals", "2", "--eval-episodes", "64"]
    assert main([*args, "--seeds", "3", "--seed", "4", "--out", str(run), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "seed 6:" in out and "interquartile mean" in out and "95% CI" in out
    assert re.search(r"seed 6: (not )?solved, distance \(final\) [\d.e-]+ m\n", out)  # with the metric's unit
    assert re.search(r"median [\d.e-]+ m, interquartile mean [\d.e-]+ m \(95% CI [\d.e-]+ to [\d.e-]+ m\)", out)
    assert sorted(p.name for p in run.iterdir()) == [
        MARKER,
        "flight.png",
        "learning_curve.png",
        "progress.json",
        "seed_4",
        "seed_5",
        "seed_6",
        "summary.json",
    ]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["seeds"] == [4, 5, 6] and summary["mapped"] and summary["algo"] == "apg"
    values = [r["success_value"] for r in summary["runs"]]
    assert summary["aggregate"] == aggregate(values, [r["success"] for r in summary["runs"]])
    assert summary["aggregate"]["median"] == pytest.approx(np.median(values))
    assert values[[4, 5, 6].index(summary["median_seed"])] == np.median(values)  # flight.png's seed
    assert f"flight.png (seed {summary['median_seed']}, the median)" in out
    low, high = summary["aggregate"]["iqm_ci95"]
    assert min(values) <= low <= summary["aggregate"]["iqm"] <= high <= max(values)
    for seed, value in zip([4, 5, 6], values, strict=True):
        one = json.loads((run / f"seed_{seed}" / "summary.json").read_text())
        assert one["config"]["seed"] == seed and one["success_value"] == value
        assert sorted(p.name for p in (run / f"seed_{seed}").iterdir()) == sorted(SEED_OUTPUTS)
    env, policy = load_policy(run / "seed_5")
    stats = evaluate(env, policy, jax.random.split(jax.random.key(5 + 1))[0], 64)
    assert stats["success_value"] == pytest.approx(values[1], rel=1e-3)
    assert aggregate([0.1, 0.2], [True, False])["iqm_ci95"] is None  # too few seeds for an interval
    # brax's PPO (through the adapter), its seeds one after another: each run's outputs, and each saved policy
    # reproduces its run's last evaluation.
    brax = tmp_path / "brax"
    assert main([*args, "--algo", "brax_ppo", "--seeds", "2", "--out", str(brax), "--no-progress"]) == 0
    summary = json.loads((brax / "summary.json").read_text())
    assert summary["seeds"] == [0, 1] and not summary["mapped"] and summary["algo"] == "brax_ppo"
    assert summary["env_steps"][0] == summary["env_steps"][1] >= 2048 and not summary["interrupted"]
    for seed in (0, 1):
        one = json.loads((brax / f"seed_{seed}" / "summary.json").read_text())
        assert sorted(p.name for p in (brax / f"seed_{seed}").iterdir()) == sorted(SEED_OUTPUTS)
        assert len(json.loads((brax / f"seed_{seed}" / "progress.json").read_text())) == 2
        env, policy = load_policy(brax / f"seed_{seed}")
        stats = evaluate(env, policy, jax.random.split(jax.random.key(seed + 1))[0], 64)
        assert stats["final_pos_error_m"] == pytest.approx(one["eval_final_pos_error_m"], abs=1e-5)
    assert main([*args, "--seeds", "0", "--out", str(tmp_path / "none"), "--no-progress"]) == 2


@pytest.mark.slow
def test_train_cli_sweep_maps_float_settings_and_compiles_a_program_per_shape(tmp_path, capsys):
    """``--sweep learning_rate=...`` (mapped with the seeds) ``--sweep horizon=...`` (a program per horizon): a run
    folder per setting and seed, each loading alone with its own settings, and each setting's aggregate."""
    from jaxdrones.training.runs import aggregate

    run = tmp_path / "sweep"
    args = ["train", "hover", "--steps", "2048", "--num-envs", "8", "--num-evals", "2", "--eval-episodes", "64"]
    sweep = ["--sweep", "learning_rate=1e-3,4e-3", "--sweep", "horizon=8,16", "--seeds", "2"]
    assert main([*args, *sweep, "--out", str(run), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "8 runs as 2 programs" in out and "horizon changes the program" in out and "learning_rate are mapped" in out
    assert "learning_rate=0.004,horizon=16: seed 1:" in out and "2 compiled programs" in out
    settings = [f"learning_rate={lr},horizon={h}" for lr in (0.001, 0.004) for h in (8, 16)]
    assert sorted(p.name for p in run.iterdir()) == sorted(
        [MARKER, "learning_curve.png", "progress.json", "summary.json", *settings]
    )
    summary = json.loads((run / "summary.json").read_text())
    assert summary["programs"] == 2 and summary["sweep"] == {"learning_rate": [0.001, 0.004], "horizon": [8, 16]}
    assert [s["setting"] for s in summary["settings"]] == [
        {"learning_rate": lr, "horizon": h} for lr in (0.001, 0.004) for h in (8, 16)
    ]
    for label, setting in zip(settings, summary["settings"], strict=True):
        runs = setting["runs"]
        assert [r["seed"] for r in runs] == [0, 1]
        assert setting["aggregate"] == aggregate([r["success_value"] for r in runs], [r["success"] for r in runs])
        one = json.loads((run / label / "seed_1" / "summary.json").read_text())
        assert {k: one["config"][k] for k in setting["setting"]} == setting["setting"] and one["config"]["seed"] == 1
        assert one["success_value"] == runs[1]["success_value"]
    env, policy = load_policy(run / settings[-1] / "seed_1")
    stats = evaluate(env, policy, jax.random.split(jax.random.key(1 + 1))[0], 64)
    assert stats["success_value"] == pytest.approx(summary["settings"][-1]["runs"][1]["success_value"], rel=1e-3)
    assert len(json.loads((run / "progress.json").read_text())) == 8


def second_program_raises(monkeypatch, error):
    """Every trainer of the table raises ``error`` when its second program starts training (a sweep's)."""
    from jaxdrones.training import trainers

    real, calls = trainers.get, []

    def get(name):
        trainer = real(name)

        def train(*args, **kwargs):
            calls.append(1)
            if len(calls) == 2:
                raise error
            return trainer.train(*args, **kwargs)

        return dataclasses.replace(trainer, train=train)

    monkeypatch.setattr(trainers, "get", get)


@pytest.mark.slow
def test_ctrl_c_between_a_sweeps_programs_saves_the_runs_trained(tmp_path, monkeypatch):
    """Ctrl-C while a sweep's second program is being built: the first program's runs are saved and the summary is
    marked interrupted (``train_task`` raises `Stopped` with it, as it does for a stop inside a program)."""
    from jaxdrones.training.recipes import recipe
    from jaxdrones.training.run import Stopped, train_task

    second_program_raises(monkeypatch, KeyboardInterrupt)
    run = recipe("hover", "cpu").with_options(seed=0, steps=1024, num_envs=8, num_evals=1)
    with pytest.raises(Stopped) as stop:
        train_task(run, str(tmp_path / "sweep"), n_eval_episodes=64, progress=False, sweep={"horizon": [8, 16]})
    summary = stop.value.summary
    assert summary["interrupted"] and [s["setting"] for s in summary["settings"]] == [{"horizon": 8}]
    assert json.loads((tmp_path / "sweep" / "summary.json").read_text()) == summary
    assert (tmp_path / "sweep" / "horizon=8" / "seed_0" / "policy.pkl").exists()
    assert not (tmp_path / "sweep" / "horizon=16").exists()


@pytest.mark.parametrize(
    "sweep, message",
    [
        ("learning_rat=1e-3,2e-3", "did you mean 'learning_rate'"),
        ("learning_rate=fast", "takes float values"),
        ("horizon=8.5", "takes int values"),
        ("hidden_layer_sizes=64", "numbers or true/false"),
        ("seed=1,2", "--seeds"),
        ("learning_rate=1e-3,1e-3", "distinct values"),
        ("learning_rate", "NAME=V1,V2"),
    ],
)
def test_train_cli_refuses_a_bad_sweep(sweep, message, capsys):
    assert main(["train", "hover", "--sweep", sweep, "--no-progress", "--out", "unused"]) == 2
    assert message in capsys.readouterr().err


def strict(constant):
    raise ValueError(f"not strict JSON: {constant}")


@pytest.mark.slow
def test_a_run_whose_parameters_go_non_finite_keeps_its_last_finite_ones(tmp_path, capsys):
    """A step size at float32's largest makes the parameters infinite at the second update: the run stops there with
    an error naming the update and the setting, and saves the last finite parameters, which load and fly; as it is
    not complete, it replaces no run (here: a numbered sibling). In a sweep, only that setting's runs stop."""
    from jaxdrones.training.recipes import recipe
    from jaxdrones.training.run import TrainingFailed, train_task

    run = recipe("hover", "cpu").with_options(seed=0, steps=4096, num_envs=8, num_evals=2)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / MARKER).write_text("{}")  # an earlier run of jaxdrones
    bad = dataclasses.replace(run, config=dataclasses.replace(run.config, learning_rate=3e38))
    with pytest.raises(
        TrainingFailed, match=r"non-finite at update 2 \(learning_rate=3e\+38,max_grad_norm=1.0, seed 0"
    ):
        train_task(bad, str(tmp_path / "run"), overwrite=True, n_eval_episodes=64, progress=False)
    saved = tmp_path / "run-1"
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [MARKER]
    summary = json.loads((saved / "summary.json").read_text(), parse_constant=strict)
    assert summary["diverged"] == 2 and not summary["success"] and summary["success_value"] is None
    env, policy = load_policy(saved)
    obs = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), 4)).obs.reshape(4, -1)
    assert np.all(np.isfinite(jax.vmap(policy, in_axes=(0, None))(obs, jax.random.key(1))[0]))

    summary = train_task(
        run, str(tmp_path / "sweep"), n_eval_episodes=64, progress=False, seeds=2,
        sweep={"learning_rate": [1e-3, 3e38]},
    )  # fmt: skip
    good, diverged = summary["settings"]
    assert [r["diverged"] for r in good["runs"]] == [None, None] and [r["diverged"] for r in diverged["runs"]] == [2, 2]
    assert all(r["env_steps"] == 4096 for r in good["runs"]) and not any(r["success"] for r in diverged["runs"])
    assert "non-finite at update 2" in diverged["runs"][0]["failed_criteria"][0]


@pytest.mark.slow
def test_a_failure_in_a_later_program_keeps_the_runs_trained_before_it(tmp_path, monkeypatch, capsys):
    """An error while a sweep's second program trains (out of memory, brax's own assertion): the first program's
    runs are saved with the sweep's summary, which names the error; the command exits 1 with it."""
    second_program_raises(monkeypatch, RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 9 GiB"))
    args = ["train", "hover", "--steps", "1024", "--num-envs", "8", "--num-evals", "1", "--eval-episodes", "64"]
    assert main([*args, "--sweep", "horizon=8,16", "--out", str(tmp_path / "sweep"), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "RESOURCE_EXHAUSTED" in err and f"the runs trained before it are saved in {tmp_path / 'sweep'}" in err
    summary = json.loads((tmp_path / "sweep" / "summary.json").read_text())
    assert "RESOURCE_EXHAUSTED" in summary["error"] and [s["setting"] for s in summary["settings"]] == [{"horizon": 8}]
    assert (tmp_path / "sweep" / "horizon=8" / "seed_0" / "policy.pkl").exists()


@pytest.mark.slow
def test_a_ctrl_c_while_the_run_is_saved_waits_for_the_complete_run(tmp_path, monkeypatch, capsys):
    """Ctrl-C while the plots are drawn: the run is saved complete, moved into place over the run it replaces, and
    the command exits 130."""
    from jaxdrones.training import writing

    plot = writing._plot

    def interrupted_plot(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return plot(*args, **kwargs)

    args = ["train", "hover", "--steps", "1024", "--num-envs", "8", "--num-evals", "1", "--eval-episodes", "64"]
    assert main([*args, "--out", str(tmp_path / "run"), "--no-progress"]) == 0
    monkeypatch.setattr(writing, "_plot", interrupted_plot)
    assert main([*args, "--seed", "1", "--out", str(tmp_path / "run"), "--overwrite", "--no-progress"]) == 130
    assert "interrupted while saving: the complete run is saved in" in capsys.readouterr().err
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["config"]["seed"] == 1 and not summary["interrupted"]
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == sorted(TRAIN_OUTPUTS)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


@pytest.mark.slow
def test_a_ctrl_c_at_any_moment_leaves_the_old_run_or_a_complete_new_one(tmp_path):
    """``jaxdrones train hover --out R --overwrite`` over a finished run ``R``, stopped by SIGINT 0.8 s and 3 s into
    the process (imports; compilation or training, from the cache the first run filled): ``R`` holds the old run or
    a complete new one, never a mix or nothing; the exit is 130 (0 where the run had finished); an interrupted run
    with something trained is in ``R-1``; nothing half-written is left (benchmarks/training/interrupt.py: at the
    defaults)."""
    env = {**os.environ, "JAXDRONES_CACHE_DIR": str(tmp_path / "cache")}
    args = [sys.executable, "-m", "jaxdrones.cli", "train", "hover", "--steps", "100000", "--no-progress"]
    first = subprocess.run([*args, "--out", str(tmp_path / "R")], env=env, capture_output=True, timeout=300)
    assert first.returncode == 0
    for seed, after_s in enumerate((0.8, 3.0), start=1):
        old = json.loads((tmp_path / "R" / "summary.json").read_text())
        process = subprocess.Popen([*args, "--seed", str(seed), "--out", str(tmp_path / "R"), "--overwrite"], env=env)
        try:
            process.wait(timeout=after_s)
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGINT)
        status = process.wait(timeout=300)
        summary = json.loads((tmp_path / "R" / "summary.json").read_text())
        # -SIGINT: stopped during Python's imports, before the command's handler (a shell's status 130).
        assert status in (0, 130, -signal.SIGINT) and summary["config"]["seed"] in (old["config"]["seed"], seed)
        if summary["config"]["seed"] != seed:
            assert summary == old and status in (130, -signal.SIGINT)
        else:
            assert not summary["interrupted"] and sorted(p.name for p in (tmp_path / "R").iterdir()) == sorted(
                TRAIN_OUTPUTS
            )
        left = sorted(p.name for p in tmp_path.iterdir() if p.name != "cache")
        assert left in (["R"], ["R", "R-1"])
        if left == ["R", "R-1"]:
            assert json.loads((tmp_path / "R-1" / "summary.json").read_text())["interrupted"] and status == 130
            shutil.rmtree(tmp_path / "R-1")


def test_the_progress_display_says_it_compiles_until_the_first_evaluation(capsys):
    """Before the first evaluation the bar says that the programs are being compiled (or loaded) and redraws its
    elapsed time every second; the first evaluation replaces that with the training's figures and stops the redraws;
    a disabled bar starts no redraws."""
    import time

    from jaxdrones.envs import get_task
    from jaxdrones.training.progress import PREPARING, ProgressLog

    log = ProgressLog(1000, get_task("hover"))
    drawn = ""
    for _ in range(100):  # redrawn with the elapsed seconds: wait (up to 10 s on a loaded machine) for 2 s of them
        time.sleep(0.1)
        drawn += capsys.readouterr().err
        if "[00:02<?]" in drawn:
            break
    assert log.bar.postfix.endswith(PREPARING)
    assert drawn.count("compiling the programs") >= 3 and "[00:02<?]" in drawn
    log(100, {"success_value": 0.5, "terminated_rate": 0.0, "episode_reward": 1.0})
    assert "final distance 0.5 m (solved < 0.05 m)" in log.bar.postfix
    log._ticker.join(timeout=2.0)
    assert not log._ticker.is_alive()
    log.close()
    quiet = ProgressLog(1000, get_task("hover"), enabled=False)
    assert not hasattr(quiet, "_ticker")
    quiet.close()
