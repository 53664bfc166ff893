"""`jaxdrones export --format c`: the C file compiles with the system's compiler and computes the JAX policy's
actions to 1e-5 on 1,000 observations, clip included; bad input."""

import os
import shutil
import subprocess

import jax
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.cli import main
from jaxdrones.training import apg, checkpoint, mappo
from jaxdrones.training.export import c_source, load_payload

CC = shutil.which("cc") or shutil.which("gcc")

HARNESS = """
#include <stdio.h>
#include "policy.c"
int main(void) {
  float obs[JAXDRONES_POLICY_N_OBS], act[JAXDRONES_POLICY_N_ACT];
  while (fread(obs, sizeof(float), JAXDRONES_POLICY_N_OBS, stdin) == JAXDRONES_POLICY_N_OBS) {
    jaxdrones_policy(obs, act);
    fwrite(act, sizeof(float), JAXDRONES_POLICY_N_ACT, stdout);
  }
  return 0;
}
"""


def _saved_policy(folder, task="hover", algo="apg", **overrides) -> str:
    """A policy with random weights of the trained size (a trained one only moves the numbers): APG's, or our PPO's
    with observation statistics far from (0, 1) and a mean action beyond the box's ±1 at times."""
    env = jd.make(task, **overrides)
    scale = {"apg": 30.0, "ppo": 300.0}[algo]
    if algo == "apg":
        config = apg.APGConfig()
        params = apg.make_network(config, env).init(jax.random.key(3), np.zeros((1, env.observation_size), np.float32))
    else:
        config = mappo.MAPPOConfig(critic="local")
        params = mappo.make_network(config, env).init(jax.random.key(3))
        rng = np.random.default_rng(1)
        params["norm"] = {
            "mean": rng.normal(0.0, 0.3, env.observation_size).astype(np.float32),
            "var": rng.uniform(0.01, 4.0, env.observation_size).astype(np.float32),
            "count": np.float32(1e6),
        }
    params = jax.tree.map(lambda x: x * scale if x.ndim == 2 and x.shape[-1] == env.action_size else x, params)
    os.makedirs(folder, exist_ok=True)
    checkpoint.save(os.path.join(folder, "policy.pkl"), algo, params, task, overrides, config)
    return folder


def _observations(env, n: int) -> np.ndarray:
    """n observations: states of random flights, and random points of the observation box's central part."""
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), n // 2))
    step = jax.jit(jax.vmap(env.step))
    for _ in range(20):
        state = step(state, 0.3 * np.ones((n // 2, 1, env.action_size), np.float32))
    flown = np.asarray(state.obs, np.float32).reshape(n // 2, -1)
    low, high = env.observation_bounds()
    rng = np.random.default_rng(0)
    box = rng.uniform(0.1 * low[0], 0.1 * high[0], (n - n // 2, env.observation_size)).astype(np.float32)
    return np.concatenate([flown, box])


@pytest.mark.skipif(CC is None, reason="no C compiler (cc or gcc) on this machine")
@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"action_type": "one_d_rpm", "obs_type": "kin", "action_buffer": True},
        {"algo": "ppo", "task": "velocity", "action_type": "ctbr", "error_integral": True, "action_buffer": 2},
    ],
)
def test_exported_c_policy_matches_jax(tmp_path, overrides):
    run = _saved_policy(str(tmp_path / "run"), **overrides)
    assert main(["export", run]) == 0
    if overrides.get("action_type") == "ctbr":  # the source says the constants of the action's mapping
        with open(os.path.join(run, "jaxdrones_policy.c")) as f:
            assert "CTBR_MAX_RATE = 6.28319 · a_1:4 (rad/s)" in f.read()
    shutil.copy(os.path.join(run, "jaxdrones_policy.c"), tmp_path / "policy.c")
    (tmp_path / "harness.c").write_text(HARNESS)
    subprocess.run(
        [CC, "-O2", "-std=c99", "-Wall", "-Werror", "harness.c", "-o", "harness", "-lm"], cwd=tmp_path, check=True
    )
    env, policy = checkpoint.load_policy(run)
    obs = _observations(env, 1000)
    obs[:5, 0] = [50.0, -50.0, 1e9, -1e9, 25.0]  # beyond the box: the C function clips as the env does
    low, high = env.observation_bounds()
    expected = np.asarray(jax.vmap(lambda o: policy(o, None)[0])(np.clip(obs, low[0], high[0])))
    if overrides.get("algo") == "ppo":  # a Gaussian's mean: the env clips it to the box, the C function too
        assert np.abs(expected).max() > 1.5
        expected = np.clip(expected, -1.0, 1.0)
    out = subprocess.run([str(tmp_path / "harness")], input=obs.tobytes(), capture_output=True, check=True)
    actions = np.frombuffer(out.stdout, np.float32).reshape(1000, env.action_size)
    assert np.abs(expected).max() > 0.5  # the outputs span the range, not only ~0
    # Float32 rounding: the C compiler and XLA sum the layers' products in their own orders (1.04e-5 seen, jax 0.12
    # with LLVM's optimisation level 0).
    np.testing.assert_allclose(actions, expected, rtol=0, atol=3e-5)


def test_export_header_sizes_and_bad_input(tmp_path, capsys):
    run = _saved_policy(str(tmp_path / "run"))
    source, sizes = c_source(load_payload(run))
    assert sizes == {
        "n_obs": 21,
        "n_act": 4,
        "multiply_adds": 21 * 64 + 64 * 64 + 64 * 4,
        "weight_bytes": 4 * (21 * 64 + 64 * 64 + 64 * 4 + 64 + 64 + 4 + 2 * 21),
    }
    assert "[ 9] wx (rad/s, body)" in source and "hover_rpm = 14468" in source
    assert main(["export", run]) == 0 and main(["export", run]) == 2  # never overwritten without asking
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(["export", run, "--overwrite"]) == 0
    theirs = tmp_path / "controller.c"  # a user's file: --overwrite replaces only a file export wrote
    theirs.write_text("int main(void) { return 0; }\n")
    assert main(["export", run, "--out", str(theirs), "--overwrite"]) == 2
    assert "replaces only a file jaxdrones wrote" in capsys.readouterr().err
    assert theirs.read_text() == "int main(void) { return 0; }\n"
    with pytest.raises(ValueError, match="C identifier"):
        c_source(load_payload(run), name="my-policy")
    with pytest.raises(ValueError, match="no saved policy"):
        load_payload(tmp_path / "nowhere")
    payload = {**load_payload(run), "algo": "brax_ppo"}
    with pytest.raises(ValueError, match=r"'brax_ppo' are not supported yet.*\('apg', 'shac', 'ppo'\)"):
        c_source(payload)


@pytest.mark.parametrize("algo", ["apg", "ppo"])
def test_onnx_model_matches_jax(tmp_path, algo):
    """``--format onnx``: onnx's checker passes and its reference evaluator gives the JAX policy's actions (our
    PPO's clipped to the box, as the env clips them)."""
    onnx = pytest.importorskip("onnx", reason="the onnx package (the export extra) is not installed")
    from onnx.reference import ReferenceEvaluator

    run = _saved_policy(str(tmp_path / "run"), algo=algo)
    assert main(["export", run, "--format", "onnx"]) == 0
    model = onnx.load(os.path.join(run, "jaxdrones_policy.onnx"))
    assert "[ 9] wx (rad/s, body)" in model.doc_string
    env, policy = checkpoint.load_policy(run)
    obs = _observations(env, 1000)
    obs[:3, 2] = [50.0, -1.0, 1e9]
    low, high = env.observation_bounds()
    expected = np.clip(np.asarray(jax.vmap(lambda o: policy(o, None)[0])(np.clip(obs, low[0], high[0]))), -1, 1)
    (actions,) = ReferenceEvaluator(model).run(None, {"obs": obs})
    np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-5)


def _error(env, obs: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The tracking error the C policy's caller gives it, from the observation as the firmware would from its
    state estimate and setpoint: hover's target - (x, y, z); velocity's command - (vx, vy, vz)."""
    if env.task.name == "velocity":
        return target - obs[..., 6:9]
    return target - obs[..., 0:3]


@pytest.mark.skipif(CC is None, reason="no C compiler (cc or gcc) on this machine")
def test_exported_c_policy_flies_closed_loop(tmp_path):
    """Software in the loop: the C file's ``jaxdrones_policy_step``, compiled and called through ctypes at every
    control step of 5 s flights from 16 random starts under the ``crazyflie`` preset, memory included, flies as the
    JAX policy flies: the same actions (1e-5) and positions within 1e-4 m. The policy was trained by ``jaxdrones
    train hover --realism crazyflie`` (tests/data)."""
    import ctypes

    run = str(tmp_path / "run")
    shutil.copytree(os.path.join(os.path.dirname(__file__), "data", "crazyflie_hover"), run)
    assert main(["export", run]) == 0
    source = open(os.path.join(run, "jaxdrones_policy.c")).read()
    assert "jaxdrones_policy_step(jaxdrones_policy_memory *m" in source and "control step (30 Hz)" in source
    subprocess.run(
        [CC, "-O2", "-std=c99", "-Wall", "-Werror", "-shared", "-fPIC", "jaxdrones_policy.c", "-o", "policy.so", "-lm"],
        cwd=run,
        check=True,
    )
    lib = ctypes.CDLL(os.path.join(run, "policy.so"))
    env, policy = checkpoint.load_policy(run)
    assert env.config.realism is not None and env.integral_size == 3
    n_worlds, n_act, n_obs = 16, env.action_size, env.observation_size
    n_base = env.obs_type.size - env.obs_type.buffer_len * n_act
    n_task, n_memory = env.task.obs_size, env.obs_type.buffer_len * n_act + 3

    class Memory(ctypes.Structure):
        _fields_ = [("actions", ctypes.c_float * max(n_memory - 3, 1)), ("integral", ctypes.c_float * 3)]

    floats = ctypes.POINTER(ctypes.c_float)
    lib.jaxdrones_policy_step.argtypes = [ctypes.POINTER(Memory), floats, floats, floats]
    lib.jaxdrones_policy_reset.argtypes = [ctypes.POINTER(Memory)]
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    act = jax.jit(jax.vmap(lambda o: policy(o, None)[0]))
    keys = jax.random.split(jax.random.key(7), n_worlds)

    def fly(controller):
        state, flown = reset(keys), []
        for _ in range(env.episode_length):
            state = step(state, controller(state).reshape(n_worlds, 1, n_act))
            flown.append(np.asarray(state.sim.pos))
        return np.stack(flown), state

    memories = [Memory() for _ in range(n_worlds)]
    for m in memories:
        lib.jaxdrones_policy_reset(ctypes.byref(m))
    gaps = []

    def c_controller(state):
        obs = np.asarray(state.obs, np.float32).reshape(n_worlds, n_obs)
        target = np.asarray(state.task.target if env.task.name != "velocity" else state.task.data["target_vel"])
        error = np.ascontiguousarray(_error(env, obs, target.reshape(n_worlds, 3)), np.float32)
        states = np.ascontiguousarray(
            np.concatenate([obs[:, :n_base], obs[:, n_obs - n_task - 3 : n_obs - 3]], axis=1), np.float32
        )
        out = np.zeros((n_worlds, n_act), np.float32)
        for w in range(n_worlds):
            lib.jaxdrones_policy_step(
                ctypes.byref(memories[w]),
                states[w].ctypes.data_as(floats),
                error[w].ctypes.data_as(floats),
                out[w].ctypes.data_as(floats),
            )
        expected = np.clip(np.asarray(act(obs)), -1.0, 1.0)  # the JAX policy on the env's observation, as the env clips
        gaps.append(np.abs(out - expected).max())
        return out

    jax_flight, jax_end = fly(lambda s: act(s.obs.reshape(n_worlds, n_obs)))
    c_flight, c_end = fly(c_controller)
    assert not np.any(jax_end.terminated) and not np.any(c_end.terminated)  # 16 full flights
    assert max(gaps) <= 1e-5, max(gaps)
    assert np.abs(c_flight - jax_flight).max() <= 1e-4
    assert np.abs(np.asarray(c_end.obs)[..., -3:]).max() > 1e-3  # the integral took part
