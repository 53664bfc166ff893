"""Nothing a user had is lost, and nothing non-finite is written: the output folders (`jaxdrones.io.runs`: written
beside their target, moved into place when complete, ``--overwrite`` only of a folder jaxdrones wrote), strict JSON,
the run plan's checks before anything compiles (`jaxdrones.training.runs`), and the commands' answers to each bad
input of the kind a user gives."""

import json
import math
import os
import pickle
import signal
import subprocess
import sys

import numpy as np
import pytest

from jaxdrones.cli import main
from jaxdrones.io.runs import MARKER, deferred_interrupt, open_output, output_folder, write_json, written_by_jaxdrones

pytestmark = pytest.mark.unit


def user_files(folder):
    """A folder of a user's own files; returns their contents by name."""
    os.makedirs(folder, exist_ok=True)
    files = {"notes.txt": "my notes", "data.csv": "1,2,3"}
    for name, text in files.items():
        (folder / name).write_text(text)
    return files


def contents(folder):
    return {p.name: p.read_text() for p in folder.iterdir() if p.is_file()}


def test_overwrite_refuses_a_folder_jaxdrones_did_not_write(tmp_path):
    mine = tmp_path / "mine"
    files = user_files(mine)
    with pytest.raises(ValueError, match="replaces only a folder jaxdrones wrote.*mine"):
        open_output(mine, overwrite=True)
    assert contents(mine) == files and sorted(p.name for p in tmp_path.iterdir()) == ["mine"]


def test_a_complete_folder_replaces_its_target_only_when_it_is_ours(tmp_path):
    target = tmp_path / "run"
    with output_folder(target) as folder:  # a first run: the target did not exist
        assert folder.path != str(target) and not target.exists()
        (tmp_path / "run.partial-probe").mkdir()  # another process's folder is left alone
        open(os.path.join(folder.path, "summary.json"), "w").write("{}")
    assert folder.final == str(target) and written_by_jaxdrones(target)
    with output_folder(target, overwrite=True) as folder:
        open(os.path.join(folder.path, "summary.json"), "w").write('{"second": 1}')
        assert json.loads((target / "summary.json").read_text()) == {}  # the old run stays until the new is done
    assert folder.final == str(target) and json.loads((target / "summary.json").read_text()) == {"second": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "run.partial-probe"]


def test_an_incomplete_folder_never_replaces_a_run(tmp_path):
    target = tmp_path / "run"
    with output_folder(target):
        pass
    before = sorted(p.name for p in target.iterdir())
    folder = open_output(target, overwrite=True)
    assert folder.commit(complete=False) == f"{target}-1"
    assert sorted(p.name for p in target.iterdir()) == before


def test_a_failure_while_writing_keeps_the_old_folder_and_deletes_the_new(tmp_path):
    target = tmp_path / "run"
    with output_folder(target):
        pass
    with pytest.raises(RuntimeError), output_folder(target, overwrite=True) as folder:
        raise RuntimeError("a failure half-way")
    assert not os.path.exists(folder.path) and sorted(p.name for p in tmp_path.iterdir()) == ["run"]


@pytest.mark.parametrize("trailing", ["", os.sep])
def test_an_existing_folder_without_overwrite_gets_a_numbered_sibling(tmp_path, trailing):
    target = tmp_path / "run"
    with output_folder(target):
        pass
    with output_folder(f"{target}{trailing}") as folder:
        pass
    assert folder.final == f"{target}-1" and sorted(p.name for p in target.iterdir()) == [MARKER]


def test_the_current_folder_is_named_by_its_own_name(tmp_path, monkeypatch):
    """``--out .``: a sibling of the current folder by its name, never ``.-1`` or the folder's own files."""
    files = user_files(tmp_path / "work")
    monkeypatch.chdir(tmp_path / "work")
    with pytest.raises(ValueError, match="replaces only a folder jaxdrones wrote"):
        open_output(".", overwrite=True)
    with output_folder(".") as folder:
        pass
    assert folder.final == str(tmp_path / "work-1") and contents(tmp_path / "work") == files


def test_a_folder_from_before_the_marker_is_recognised(tmp_path):
    run, flight, other = tmp_path / "run", tmp_path / "flight", tmp_path / "other"
    for folder in (run, flight, other):
        folder.mkdir()
    (run / "summary.json").write_text(json.dumps({"task": "hover", "provenance": {}}))
    (flight / "metrics.json").write_text("{}")
    (flight / "flight.npz").write_bytes(b"")
    (other / "summary.json").write_text(json.dumps({"a user's": "summary"}))
    assert written_by_jaxdrones(run) and written_by_jaxdrones(flight) and not written_by_jaxdrones(other)


def test_a_ctrl_c_while_a_folder_moves_into_place_waits_for_the_move(tmp_path):
    target = tmp_path / "run"
    folder = open_output(target)
    with pytest.raises(KeyboardInterrupt), deferred_interrupt():
        os.kill(os.getpid(), signal.SIGINT)  # held until the block ends
        folder.commit()
        moved = target.exists()
    assert moved and signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_json_is_strict(tmp_path):
    path = tmp_path / "summary.json"
    write_json(path, {"value": math.nan, "values": [1.0, math.inf, -math.inf], "n": 3})

    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    assert json.loads(path.read_text(), parse_constant=refuse) == {"value": None, "values": [1.0, None, None], "n": 3}


# The command line on each bad input: a clear error, exit 2, nothing of the user's touched.


def test_train_overwrite_of_the_current_folder_keeps_the_users_files(tmp_path, monkeypatch, capsys):
    files = user_files(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert main(["train", "hover", "--out", ".", "--overwrite", "--no-progress"]) == 2
    assert "replaces only a folder jaxdrones wrote" in capsys.readouterr().err
    assert contents(tmp_path) == files and sorted(p.name for p in tmp_path.iterdir()) == sorted(files)


def test_fly_overwrite_keeps_the_users_files(tmp_path, capsys):
    files = user_files(tmp_path / "mine")
    argv = ["fly", "--duration", "2", "--no-progress", "--out", str(tmp_path / "mine"), "--overwrite"]
    assert main(argv) == 2
    assert "replaces only a folder jaxdrones wrote" in capsys.readouterr().err
    assert contents(tmp_path / "mine") == files and sorted(p.name for p in tmp_path.iterdir()) == ["mine"]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--sweep", "learning_rate=inf"], "learning_rate must be a finite number > 0, got inf"),
        (["--sweep", "max_grad_norm=1,inf"], "max_grad_norm=inf: APGConfig: max_grad_norm must be a finite number"),
        (["--sweep", "learning_rate=nan"], "learning_rate must be a finite number > 0, got nan"),
        (["--sweep", "learning_rate=-0.001"], "learning_rate must be a finite number > 0, got -0.001"),
        (["--algo", "brax_ppo", "--sweep", "learning_rate=-1e-3"], "BraxPPOConfig: learning_rate must be a finite"),
        (["--algo", "brax_ppo", "--seed", "-1"], "BraxPPOConfig: seed must be an integer >= 0, got -1"),
        (["--algo", "brax_ppo", "--sweep", "discounting=1.5"], "discounting must be a finite number in [0, 1]"),
        (["--seeds", "0"], "--seeds must be a positive integer"),
    ],
)
def test_train_refuses_a_non_finite_or_out_of_range_setting_before_compiling(tmp_path, capsys, extra, message):
    assert main(["train", "hover", "--no-progress", "--out", str(tmp_path / "run"), *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "seeds, message",
    [
        ("10", "seeds must be an integer count or a list of integer seeds, got '10'"),
        ([1.9, 2.2], "seeds must be distinct non-negative integers"),
        ([True, 2], "seeds must be distinct non-negative integers"),
        ([1, 1], "seeds must be distinct non-negative integers"),
        ([-1], "seeds must be distinct non-negative integers"),
        (2.0, "seeds must be an integer count or a list of integer seeds"),
        ({"a": 1}, "seeds must be an integer count or a list of integer seeds"),
        (0, "seeds must be a count >= 1"),
    ],
)
def test_train_task_refuses_seeds_of_the_wrong_type_with_a_value_error(tmp_path, seeds, message):
    from jaxdrones.training import train_task

    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("(", r"\(")):
        train_task("hover", str(tmp_path / "run"), seeds=seeds, progress=False)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"n_eval_episodes": 64.5}, "n_eval_episodes must be an integer >= 64"),
        ({"sweep": {"learning_rate": "1e-3"}}, "learning_rate takes a list of values"),
        ({"sweep": {"learning_rate": [True]}}, "learning_rate takes float values"),
        ({"sweep": {"horizon": [8.5]}}, "horizon takes int values"),
        ({"sweep": [("learning_rate", [1e-3])]}, "sweep must be a dict"),
        ({"sweep": {"learning_rate": [float("inf")]}}, "learning_rate must be a finite number > 0, got inf"),
        ({"out": 3}, r"out must be a folder's path \(a str or os.PathLike\), got 3"),
        ({"overwrite": "yes"}, "overwrite must be True or False, got 'yes'"),
        ({"progress": 1}, "progress must be True or False, got 1"),
        ({"env_overrides": [("model", "cf2x")]}, "env_overrides must be a dict of task config fields"),
        ({"train_env_overrides": 5}, "train_env_overrides must be a dict of task config fields, got 5"),
        ({"task": None}, "task must be a task's name"),
    ],
)
def test_train_task_refuses_bad_settings_with_a_value_error(tmp_path, kwargs, message):
    from jaxdrones.training import train_task

    kwargs = {"out": str(tmp_path / "run"), "progress": False, **kwargs}
    with pytest.raises(ValueError, match=message):
        train_task(kwargs.pop("task", "hover"), **kwargs)
    assert not any(tmp_path.iterdir())


def test_runs_that_would_not_fit_in_memory_are_refused_before_compiling(tmp_path, capsys):
    """``--seeds`` beyond what the host's memory holds: an error naming the largest program and what fits, at once
    and with nothing written (the estimate: `jaxdrones.training.runs.run_bytes`)."""
    assert main(["train", "hover", "--seeds", "1000000", "--no-progress", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "the largest program maps 1000000 runs and needs about" in err and "runs fit in one program" in err
    assert not any(tmp_path.iterdir())


def test_check_memory_names_what_fits():
    from jaxdrones.training.runs import check_memory

    check_memory(4, 2**20, (5 * 2**20, "a test's memory"))  # four runs of 1 MiB within 90 % of 5 MiB
    check_memory(10**9, 2**20, None)  # no figure of the memory free: no check
    with pytest.raises(ValueError, match=r"maps 4 runs and needs about 0.0 GiB .* at most 3 runs fit"):
        check_memory(4, 2**20, (4 * 2**20, "a test's memory"))


def nan_policy(folder):
    """A policy file whose weights hold a NaN (a run saved before jaxdrones kept the last finite parameters)."""
    folder.mkdir(parents=True, exist_ok=True)
    params = {"params": {"Dense_0": {"kernel": np.full((4, 2), np.nan, np.float32), "bias": np.zeros(2, np.float32)}}}
    payload = {"format": 1, "algo": "apg", "params": params, "env_name": "hover", "env_overrides": {}, "config": {}}
    (folder / "policy.pkl").write_bytes(pickle.dumps(payload))
    return folder


@pytest.mark.parametrize("command", ["view", "export"])
def test_view_and_export_refuse_a_policy_with_non_finite_weights(tmp_path, command, capsys):
    from jaxdrones.training import load_policy

    run = nan_policy(tmp_path / "run")
    with pytest.raises(ValueError, match="non-finite weights"):
        load_policy(run)
    assert main([command, str(run)]) == 2
    err = capsys.readouterr().err
    assert "non-finite weights" in err and "Dense_0" in err and "Traceback" not in err
    assert sorted(p.name for p in run.iterdir()) == ["policy.pkl"]


@pytest.mark.parametrize("command", ["view", "export", "load_policy"])
def test_a_folder_of_runs_is_answered_with_its_run_folders(tmp_path, command, capsys):
    from jaxdrones.training import load_policy

    for folder in ("seed_0", "seed_1", "learning_rate=0.001/seed_0"):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "policy.pkl").write_bytes(b"")
    expected = "holds no policy of its own but runs in its folders: give one of them"
    if command == "load_policy":
        with pytest.raises(ValueError, match=expected) as err:
            load_policy(tmp_path)
        message = str(err.value)
    else:
        assert main([command, str(tmp_path)]) == 2
        message = capsys.readouterr().err
    assert expected in message and "learning_rate=0.001/seed_0, seed_0, seed_1" in message


@pytest.mark.parametrize("path", [3, None, ["runs/hover"]])
def test_load_policy_refuses_a_path_of_the_wrong_type(path):
    from jaxdrones.training import load_policy

    with pytest.raises(ValueError, match="path must be a run folder or its policy.pkl"):
        load_policy(path)


def test_the_rllib_example_without_ray_says_what_to_install():
    try:
        import ray  # noqa: F401

        pytest.skip("ray is installed here: the rllib lane runs the example")
    except ModuleNotFoundError:
        pass
    result = subprocess.run(
        [sys.executable, "-m", "jaxdrones.examples.rllib_leader_follower", "--timesteps", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "needs ray[rllib], the rllib extra" in result.stderr
    assert "Traceback" not in result.stderr


def test_the_suite_refuses_abbreviated_options():
    """``benchmarks/training/suite.py --seed 0`` is not ``--seeds 0``: argparse's prefix matching is off in every
    script."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    script = os.path.join(root, "benchmarks", "training", "suite.py")
    result = subprocess.run([sys.executable, script, "--seed", "0"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "unrecognized arguments: --seed 0" in result.stderr


def test_a_ctrl_c_that_lands_in_a_garbage_collectors_callback_is_not_lost():
    """Python ignores an exception raised in a ``gc.callbacks`` function (JAX's ``_xla_gc_callback`` runs at every
    collection): the command's handler sends the signal again after it, so the Ctrl-C still stops the process."""
    code = """
import gc, os, signal, time
from jaxdrones.cli import _interrupt
signal.signal(signal.SIGINT, _interrupt)
sent = []
def callback(phase, info):
    if not sent:
        sent.append(1)
        os.kill(os.getpid(), signal.SIGINT)  # handled here, inside the callback
gc.callbacks.append(callback)
gc.collect()
try:
    time.sleep(5)
    print("lost")
except KeyboardInterrupt:
    print("stopped")
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.stdout.strip() == "stopped", result.stderr
