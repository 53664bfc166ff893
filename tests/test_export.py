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
from jaxdrones.export import c_source, load_payload
from jaxdrones.training import apg, checkpoint

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


def _saved_policy(folder, task="hover", **overrides) -> str:
    """An APG policy with random weights of the trained size (a trained one only moves the numbers)."""
    env = jd.make(task, **overrides)
    config = apg.APGConfig()
    network = apg.make_network(config, env)
    params = network.init(jax.random.key(3), np.zeros((1, env.observation_size), np.float32))
    params = jax.tree.map(lambda x: x * 30.0 if x.ndim == 2 and x.shape[-1] == env.action_size else x, params)
    os.makedirs(folder, exist_ok=True)
    checkpoint.save(os.path.join(folder, "policy.pkl"), "apg", params, task, overrides, config)
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
@pytest.mark.parametrize("overrides", [{}, {"action_type": "one_d_rpm", "obs_type": "kin", "action_buffer": True}])
def test_exported_c_policy_matches_jax(tmp_path, overrides):
    run = _saved_policy(str(tmp_path / "run"), **overrides)
    assert main(["export", run]) == 0
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
    out = subprocess.run([str(tmp_path / "harness")], input=obs.tobytes(), capture_output=True, check=True)
    actions = np.frombuffer(out.stdout, np.float32).reshape(1000, env.action_size)
    assert np.abs(expected).max() > 0.5  # the outputs span the range, not only ~0
    np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-5)


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
    with pytest.raises(ValueError, match="C identifier"):
        c_source(load_payload(run), name="my-policy")
    with pytest.raises(ValueError, match="no saved policy"):
        load_payload(tmp_path / "nowhere")
    payload = {**load_payload(run), "algo": "brax_ppo"}
    with pytest.raises(ValueError, match=r"'brax_ppo' are not supported yet.*\('apg', 'shac'\)"):
        c_source(payload)


def test_onnx_model_matches_jax(tmp_path):
    """``--format onnx``: onnx's checker passes and its reference evaluator gives the JAX policy's actions."""
    onnx = pytest.importorskip("onnx", reason="the onnx package (the export extra) is not installed")
    from onnx.reference import ReferenceEvaluator

    run = _saved_policy(str(tmp_path / "run"))
    assert main(["export", run, "--format", "onnx"]) == 0
    model = onnx.load(os.path.join(run, "jaxdrones_policy.onnx"))
    assert "[ 9] wx (rad/s, body)" in model.doc_string
    env, policy = checkpoint.load_policy(run)
    obs = _observations(env, 1000)
    obs[:3, 2] = [50.0, -1.0, 1e9]
    low, high = env.observation_bounds()
    expected = np.asarray(jax.vmap(lambda o: policy(o, None)[0])(np.clip(obs, low[0], high[0])))
    (actions,) = ReferenceEvaluator(model).run(None, {"obs": obs})
    np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-5)
