"""Every notebook in ``notebooks/`` runs from top to bottom without error, in this interpreter, and reaches the
result it is about at its own training budget: it prints a solved verdict with the threshold (marker ``notebooks``:
7 Jupyter kernels that train to solved results, about 15 minutes of CPU; left out of the default run, ``python -m
pytest -m notebooks`` runs them, and ``.ci/run`` does in every lane); and the stored notebooks hold the outputs of
one whole run, solved verdicts included."""

from __future__ import annotations

import importlib.util
import pathlib
import re
import sys

import nbformat
import pytest

NOTEBOOKS_DIR = pathlib.Path(__file__).resolve().parents[1] / "notebooks"
#: notebooks/execute.py, which runs and saves the stored notebooks: the suite runs them the same way.
_spec = importlib.util.spec_from_file_location("notebooks_execute", NOTEBOOKS_DIR / "execute.py")
RUNNER = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(RUNNER)

NOTEBOOKS = sorted(NOTEBOOKS_DIR.glob("*.ipynb"))
TIMEOUT_S = 1800  # per cell: 05_vision's training takes about 8 minutes on 2 idle cores

#: Per notebook: regular expressions that its outputs must match, and the number of figures it must show.
EXPECTED_OUTPUT = {
    "01_quickstart.ipynb": [
        r"hover RPM\s+14468\.\d RPM",
        r"batched trajectory pos: \(1024, 144, 1, 3\)",
        r"jax\.grad:\s+dz/du = 6\.80\d*e-04 m/RPM",
        r"run folder: runs/hover \[.*'learning_curve\.png', 'policy\.pkl', 'progress\.json', 'summary\.json'\]",
        r"episode pos shape: \(151, 1, 3\)",
    ],
    "02_stable_baselines3.ipynb": [
        r"TOTAL_STEPS = 40,960 ",
        r"SB3 check_env: passed",
        r"trained 40,960 env steps in [\d.]+ s",  # five PPO rollouts: n_steps 2048 x 4 envs
        r"VecEnv: trained 204,800 env steps in [\d.]+ s",  # 25 rollouts: n_steps 32 x 256 worlds
        r"VecEnv: solved: .* over 64 random starts",
    ],
    "03_gradients.ipynb": [
        r"d z_final / d rpm: jax\.grad [\d.e+-]+ m/RPM, central difference [\d.e+-]+ m/RPM, relative difference "
        r"[\d.]+e-0[3-9]",
        r"value and gradient [\d.]+ ms: [\d.]+ x",
        r"APG: solved: .* over 256 random starts",
        r"SHAC: solved: .* over 256 random starts",
        r"PPO: solved: .* over 256 random starts",
        r"horizon   60: mean gradient norm",
        r"kf: largest relative error (0\.0e\+00|\d\.\de-0[4-9])",
        r"drag_coeff: largest relative error \d\.\de-0[4-9]",
    ],
    "04_multi_agent.ipynb": [
        r"3 drones, observation \d+, action 1 per drone",
        r"leader altitude error [\d.]+ cm, followers' mean altitude error [\d.]+ cm",
        r"final altitudes: \[",
    ],
    "05_vision.ipynb": [
        r"'depth': \(\(16, 64\), 'float32'\)",
        r"solved: failure \(final\) [\d.e+-]+ share \(threshold 0\.1 share\) over 256 random starts",
        r"SB3 check_env: passed",
        r"SB3: trained 2,048 env steps in [\d.]+ s",
    ],
    "06_sim_to_real.ipynb": [
        r"largest relative difference from the first-order solution: \d\.\de-0[5-9]",
        r"longitudinal spectrum at 0\.\d+ Hz: [\d.]+ against Dryden's [\d.]+",
        r"trained with paper: (not )?solved: ",
        r"trained with crazyflie: solved: ",
        r"final distance to the target \(cm\), share of episodes ended early",
    ],
    "07_mpc.ipynb": [
        r"largest difference, symbolic step vs JAX step \(float32 simulator\): \d\.\de-0[6-9]",
        r"MPC: RMS error [\d.]+ cm, solve time median [\d.]+ ms",
        r"PID: RMS error [\d.]+ cm",
        r"solved: MPC RMS tracking error [\d.]+ cm \(threshold 5 cm, the hover task's\)",
    ],
}
EXPECTED_FIGURES = {
    "01_quickstart.ipynb": 4,
    "02_stable_baselines3.ipynb": 1,
    "03_gradients.ipynb": 3,
    "04_multi_agent.ipynb": 2,
    "05_vision.ipynb": 2,
    "06_sim_to_real.ipynb": 2,
    "07_mpc.ipynb": 1,
}
#: The order the notebooks run in: the longest (05_vision, 8 minutes of training) first, so that pytest-xdist's other
#: worker runs the rest beside it rather than after it.
RUN_ORDER = sorted(NOTEBOOKS, key=lambda p: p.name != "05_vision.ipynb")
#: The notebooks that train with Stable-Baselines3, which needs torch (the test extra installs it on Python 3.11).
SB3_NOTEBOOKS = ("02_stable_baselines3.ipynb", "05_vision.ipynb")


@pytest.fixture
def kernel_for_this_interpreter():
    """A kernelspec that starts ``sys.executable`` (notebooks/execute.py's, which saves the stored notebooks)."""
    import ipykernel  # noqa: F401  (the kernel runs in this interpreter, so it must have ipykernel)
    from jupyter_client.kernelspec import KernelSpecManager

    with RUNNER.kernel_for_this_interpreter() as name:
        assert KernelSpecManager().get_kernel_spec(name).argv[0] == sys.executable
        yield name


def test_notebooks_found():
    assert [p.name for p in NOTEBOOKS][:1] == ["01_quickstart.ipynb"]


def check_solved(name: str, text: str) -> None:
    """The notebook printed at least one verdict; each is a solved one, with its threshold."""
    found = RUNNER.verdicts(text)
    assert found, f"{name}: no verdict line (solved: ... (threshold ...)) in its outputs"
    for verdict, line in found:
        assert verdict == "solved" and "(threshold " in line, f"{name}: {line}"


def figures(nb) -> int:
    return sum("image/png" in out.get("data", {}) for cell in nb.cells for out in cell.get("outputs", []))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_stored_outputs_are_one_whole_run(path):
    """The docs site and GitHub show the notebooks as stored (``python notebooks/execute.py`` runs and saves them):
    the outputs of one run from top to bottom, every code cell executed in order, without an error, with the
    figures."""
    nb = nbformat.read(path, as_version=4)
    counts = [cell.execution_count for cell in nb.cells if cell.cell_type == "code"]
    assert counts == list(range(1, len(counts) + 1)), f"{path.name}: run it with notebooks/execute.py"
    assert not [out for cell in nb.cells for out in cell.get("outputs", []) if out.output_type == "error"]
    assert figures(nb) >= EXPECTED_FIGURES.get(path.name, 0)
    check_solved(path.name, RUNNER.output_text(nb))


def test_the_verdict_check_fails_on_an_unsolved_or_missing_verdict():
    check_solved("a", "APG: solved: distance (final) 0.02 m (threshold 0.05 m) over 256 random starts")
    for text in ("trained in 3 s", "solved: x (threshold 1)\nnot solved: y. x (threshold 1)", "solved: 0.1 cm"):
        with pytest.raises(AssertionError):
            check_solved("a", text)


@pytest.mark.slow
@pytest.mark.notebooks
@pytest.mark.parametrize(
    "path",
    [pytest.param(p, marks=[pytest.mark.torch] * (p.name in SB3_NOTEBOOKS)) for p in RUN_ORDER],
    ids=[p.name for p in RUN_ORDER],
)
def test_notebook_runs(path, tmp_path, kernel_for_this_interpreter, users_rank_promotion, users_xla_flags):
    """At its own budget and with XLA's flags as a user has them (as stored), each notebook runs and prints solved
    verdicts."""
    nb = nbformat.read(path, as_version=4)
    workdir = tmp_path / "work"
    workdir.mkdir()
    RUNNER.execute(nb, kernel_for_this_interpreter, workdir, TIMEOUT_S)  # raises CellExecutionError, naming the cell

    errors = [out for cell in nb.cells for out in cell.get("outputs", []) if out.output_type == "error"]
    assert not errors
    text = RUNNER.output_text(nb)
    for pattern in EXPECTED_OUTPUT.get(path.name, []):
        assert re.search(pattern, text), f"{path.name}: no output matches {pattern!r}"
    assert figures(nb) >= EXPECTED_FIGURES.get(path.name, 0)
    check_solved(path.name, text)
    if path.name == "01_quickstart.ipynb":
        # The gradient through the rollout agrees with the finite difference.
        rel = float(re.search(r"relative difference grad vs finite difference: (\S+)", text).group(1))
        assert rel < 1e-3
    if path.name == "06_sim_to_real.ipynb":  # the sampled turbulence has Dryden's spectrum
        sampled, model = map(float, re.search(r"Hz: ([\d.]+) against Dryden's ([\d.]+)", text).groups())
        assert abs(sampled / model - 1) < 0.15
    if path.name == "07_mpc.ipynb":  # the MPC tracks the figure-8 within 5 cm RMS on the simulator
        assert float(re.search(r"MPC: RMS error ([\d.]+) cm", text).group(1)) <= 5.0
