"""Training on several devices and processes, and stopping a run: every trainer on 2 forced CPU devices gives the
result of one device; ``jaxdrones train`` over 2 processes (`jax.distributed`, CPU collectives over loopback) gives
the result of one process with the same worlds; bad device and process settings fail fast with clear errors; Ctrl-C
saves the policy so far."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxdrones.cli import main

#: Trains each trainer briefly (3 chunks) on the CPU devices forced by argv[1] and saves its policy's actions and
#: values on fixed observations (the result a user sees), and the devices its parameters were spread over.
_TRAIN_ON_DEVICES = """
import dataclasses, os, sys
os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=" + sys.argv[1]
import jax, numpy as np
import jaxdrones as jd
from jaxdrones.training import trainers
from jaxdrones.training.recipes import recipe
from jaxdrones.training.evaluation import episode_outcomes

out = {}
cases = (("ppo", "ppo", "hover", {}, dict(num_envs=8, unroll_length=4, minibatches=2)),
         ("ppo_gpu_build", "ppo", "hover", {},
          dict(num_envs=8, unroll_length=4, minibatches=2, **trainers.gpu_build(trainers.get("ppo").config_cls))),
         ("mappo", "mappo", "leader_follower", {"n_drones": 3, "action_type": "one_d_rpm"},
          dict(num_envs=8, unroll_length=4, minibatches=2)),
         ("apg", "apg", "hover", {}, dict(num_envs=8, horizon=4)),
         ("shac", "shac", "hover", {}, dict(num_envs=8, horizon=4)),
         ("apg_seeds", "apg", "hover", {}, dict(num_envs=8, horizon=4)))  # seeds 0, 1 mapped: seed 1's
for name, algo, task, env_kw, kw in cases:
    trainer = trainers.get(algo)
    env = jd.make(task, **env_kw)
    config = dataclasses.replace(recipe(task, "cpu", env_kw, algo).config, **kw, num_timesteps=96, num_evals=4)
    keys = jax.random.split(jax.random.key(3), 8)
    seen = []
    outcomes = lambda n, p, seed: episode_outcomes(env, trainer.make_policy(n, p), keys)[0]
    if name.endswith("_seeds"):
        runs = tuple(dataclasses.replace(config, seed=s) for s in (0, 1))
        network, params = trainer.train(env, config, lambda steps, m: seen.append(m["eval"]), outcomes, runs=runs)[1]
        seen = [jax.tree.map(lambda x: x[1], m) for m in seen]
    else:
        network, params = trainer.train(env, config, lambda steps, m: seen.append(m["eval"]), outcomes)
    obs = jax.vmap(env.reset)(jax.random.split(jax.random.key(4), 64)).obs.reshape(64, -1)
    actions = jax.vmap(lambda o: trainer.make_policy(network, params)(o, None)[0])(obs)
    out[name] = np.asarray(actions)
    out[name + "_eval"] = np.asarray(seen[-1]["distance"] if "distance" in seen[-1] else
                                     seen[-1]["max_altitude_error"])
    out[name + "_devices"] = len(jax.tree.leaves(params)[0].sharding.device_set)
np.savez(sys.argv[2], **out)
"""


@pytest.mark.slow
@pytest.mark.devices
def test_every_trainer_gives_one_devices_result_on_two_devices(tmp_path):
    """PPO (also built as the ``gpu`` profile builds it: `trainers.gpu_build`), MAPPO, APG and SHAC spread their
    worlds over 2 forced CPU devices (parameters replicated on both; APG's two mapped seeds, one per device) and train
    the policy of one device: its actions
    on 64 observations agree to 1e-4 and the evaluation after the last chunk (final distances of 8 episodes, flown
    in closed loop) to 1e-3 relative."""
    results, runs = {}, {}
    for devices in ("1", "2"):  # both at once (each mostly compiles, on one core)
        runs[devices] = subprocess.Popen(
            [sys.executable, "-c", _TRAIN_ON_DEVICES, devices, str(tmp_path / f"devices_{devices}.npz")],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
    for devices, run in runs.items():
        _, err = run.communicate(timeout=900)
        assert run.returncode == 0, err[-3000:]
        results[devices] = dict(np.load(tmp_path / f"devices_{devices}.npz"))
    for algo in ("ppo", "ppo_gpu_build", "mappo", "apg", "shac", "apg_seeds"):
        # (flat parameters come back split on the host: `common.param_maps`)
        spread = 1 if algo == "ppo_gpu_build" else 2
        assert int(results["1"][algo + "_devices"]) == 1 and int(results["2"][algo + "_devices"]) == spread
        assert np.abs(results["1"][algo]).max() > 1e-3  # the policy acts (its outputs are not all zero)
        # Float32 rounding of the world means taken in two halves, amplified by 3 chunks of updates: seen up to 2e-6
        # for MAPPO's actions on jax 0.10.2 and 1.7e-5 on jax 0.12.0.1 (with the suite's XLA flags), of actions of
        # about 0.5; a device that trained on its own half only would differ by far more.
        np.testing.assert_allclose(results["2"][algo], results["1"][algo], rtol=1e-4, atol=1e-4, err_msg=algo)
        # The evaluation flies each policy 150 steps in closed loop, which amplifies float32 rounding: seen 2e-6
        # relative for one drone, 1.4e-4 for MAPPO's 3 drones following a leader (jax 0.10.2): 1e-3 relative.
        np.testing.assert_allclose(
            results["2"][algo + "_eval"], results["1"][algo + "_eval"], rtol=1e-3, atol=1e-6, err_msg=algo
        )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from jaxdrones.cli import main; sys.exit(main(sys.argv[1:]))", *args]


def _train_args(out, *extra) -> list[str]:
    """A short run: 2 updates of 16 worlds (one evaluation, after them)."""
    return [
        "train",
        "hover",
        "--steps",
        "320",
        "--num-envs",
        "16",
        "--num-evals",
        "1",
        "--eval-episodes",
        "64",
        "--no-progress",
        "--out",
        str(out),
        *extra,
    ]


@pytest.mark.slow
@pytest.mark.devices
def test_two_processes_train_one_process_result(tmp_path):
    """``jaxdrones train hover`` over 2 processes joined by ``--coordinator`` (each with its 8 of the 16 worlds on
    its own CPU device, collectives over loopback) trains the policy that one process with 16 worlds trains:
    the same evaluation to 1e-6. Process 0 writes the run; ``summary.json`` records 2 processes and both
    devices."""
    one = subprocess.run(_cli(*_train_args(tmp_path / "one")), capture_output=True, text=True, timeout=600)
    assert one.returncode == 0, one.stderr[-3000:]
    port = _free_port()
    procs = [
        subprocess.Popen(
            _cli(
                *_train_args(
                    tmp_path / "two",
                    "--coordinator",
                    f"127.0.0.1:{port}",
                    "--num-processes",
                    "2",
                    "--process-id",
                    str(k),
                )
            ),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for k in (0, 1)
    ]
    outputs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err[-3000:] for _, err in outputs]
    summary_one = json.loads((tmp_path / "one" / "summary.json").read_text())
    summary_two = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert summary_two["provenance"]["num_processes"] == 2 and len(summary_two["provenance"]["devices"]) == 2
    assert summary_one["provenance"]["num_processes"] == 1
    assert summary_two["env_steps"] == summary_one["env_steps"]
    for key in ("final_distance", "mean_distance", "episode_reward"):
        assert summary_two["eval"][key] == pytest.approx(summary_one["eval"][key], abs=1e-6), key
    assert "saved policy.pkl" in outputs[0][0] and "saved" not in outputs[1][0]  # process 0 writes the run


@pytest.mark.parametrize(
    "extra, message",
    [
        (
            ("--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "2"),
            "--process-id must be in [0, 1]",
        ),
        (("--coordinator", "127.0.0.1:1", "--num-processes", "2"), "go together"),
        (("--coordinator", "nohost", "--num-processes", "2", "--process-id", "1"), "HOST:PORT"),
        (("--device", "abacus"), "unknown device 'abacus'"),
    ],
)
def test_bad_device_and_process_settings(tmp_path, capsys, extra, message):
    assert main(_train_args(tmp_path / "run", *extra)) == 2
    err = capsys.readouterr().err
    assert message in err and "error" in err
    assert not (tmp_path / "run").exists()


def test_unreachable_coordinator_fails_within_the_timeout(tmp_path):
    """Process 1 of 2 with no coordinator listening: exit status 2 and a message naming the address, after the
    ``--distributed-timeout`` (2 s here), not a hang."""
    port = _free_port()
    start = time.perf_counter()
    run = subprocess.run(
        _cli(
            *_train_args(
                tmp_path / "run",
                "--coordinator",
                f"127.0.0.1:{port}",
                "--num-processes",
                "2",
                "--process-id",
                "1",
                "--distributed-timeout",
                "2",
            )
        ),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2 and f"127.0.0.1:{port} could not be reached within 2 s" in run.stderr
    assert time.perf_counter() - start < 60
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_ctrl_c_saves_the_policy_so_far(tmp_path):
    """SIGINT (Ctrl-C) during ``jaxdrones train``: exit status 130, one line on stderr after the progress bar, and a
    run folder with the policy after the last finished chunk, its learning curve and a summary marked
    interrupted."""
    from jaxdrones.training import load_policy

    run = tmp_path / "run"
    # Chunks of 50k env steps (100 evaluations), so that the first is soon shown and the one running at Ctrl-C
    # soon ends.
    args = [
        "train",
        "hover",
        "--steps",
        "5000000",
        "--num-envs",
        "64",
        "--num-evals",
        "100",
        "--out",
        str(run),
        "--eval-episodes",
        "64",
    ]
    # SIGINT's default action restored in the child: test runners' workers may ignore it, and children inherit that.
    proc = subprocess.Popen(
        _cli(*args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    os.set_blocking(proc.stderr.fileno(), False)
    seen, deadline = "", time.monotonic() + 300
    while "final distance" not in seen:  # the progress bar shows a first evaluation: a chunk has finished
        assert proc.poll() is None and time.monotonic() < deadline, seen[-2000:]
        try:
            seen += os.read(proc.stderr.fileno(), 1 << 16).decode(errors="replace")
        except BlockingIOError:
            pass
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    os.set_blocking(proc.stderr.fileno(), True)
    out, err = proc.communicate(timeout=300)
    out, err = out.decode(), err.decode()
    err = (seen + err).split("\r")[-1]
    assert proc.returncode == 130, err[-3000:]
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert lines[-1].startswith("interrupted after ") and f"saved the policy so far in {run}" in lines[-1]
    assert "Traceback" not in err
    summary = json.loads((run / "summary.json").read_text())
    assert summary["interrupted"] is True and 0 < summary["env_steps"] < 5_000_000
    assert {"policy.pkl", "progress.json", "learning_curve.png", "flight.png"} <= {p.name for p in run.iterdir()}
    env, policy = load_policy(run)
    assert policy(env.reset(__import__("jax").random.key(0)).obs.reshape(-1), None)[0].shape == (4,)


@pytest.mark.slow
def test_second_run_loads_the_traced_program_and_trains_the_same(tmp_path):
    """With the compilation cache on, a run saves its traced init, chunk and evaluation
    (`jaxdrones.training.programs`); an identical second run loads them instead of tracing, compiles no other
    program (each would cost a compilation on a GPU) and gives the same result; another setting gets programs of its
    own; a damaged file is traced anew."""
    cache = tmp_path / "cache"
    env = {**os.environ, "JAXDRONES_CACHE_DIR": str(cache)}
    args = [
        "train",
        "hover",
        "--algo",
        "apg",
        "--steps",
        "2048",
        "--num-envs",
        "8",
        "--num-evals",
        "2",
        "--eval-episodes",
        "64",
        "--no-progress",
    ]

    def run(name, *extra):
        done = subprocess.run(
            _cli(*args, "--out", str(tmp_path / name), *extra),
            capture_output=True,
            text=True,
            env={**env, "JAX_LOG_COMPILES": "1"},
            timeout=600,
        )
        assert done.returncode == 0, done.stderr[-3000:]
        return json.loads((tmp_path / name / "summary.json").read_text()), done.stderr

    programs = cache / "jaxdrones-programs"
    traced = re.compile(r"Finished tracing (\+ transforming )?traced_program")  # the log's words vary with jax
    first, log_first = run("first")
    assert len(list(programs.glob("*.jaxexport"))) == 3  # the init, the chunk of updates and the evaluation
    assert traced.search(log_first)
    # One compilation of each program for all its calls: the first call's input (from init) and the later calls'
    # (the chunk's own output) are committed to the device alike.
    assert len(re.findall(r"compilation of jit\(call\)", log_first)) == 3, log_first[-3000:]
    second, log_second = run("second")
    assert not traced.search(log_second) and "init_run" not in log_second  # loaded from disk, not traced
    # Nothing else is compiled: no eager operation in the env's construction, the trainer's setup or its result.
    assert re.findall(r"compilation of jit\((\w+)\)", log_second) == ["call"] * 3, log_second[-3000:]
    assert second["eval"] == first["eval"]
    run("other", "--seed", "1")
    assert len(list(programs.glob("*.jaxexport"))) == 6
    for path in programs.glob("*.jaxexport"):
        path.write_bytes(b"damaged")
    third, log_third = run("third")
    assert traced.search(log_third) and third["eval"] == first["eval"]
