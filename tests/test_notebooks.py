"""Every notebook in ``notebooks/`` runs from top to bottom without error, in this interpreter (marker
``notebooks``: 7 Jupyter kernels that compile the notebooks' trainings, about 7 minutes of CPU; left out of the
default run, ``python -m pytest -m notebooks`` runs them, and ``.ci/run`` does in every lane); and the stored
notebooks hold the outputs of one whole run."""

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
TIMEOUT_S = 600  # per cell

#: Per notebook: regular expressions that its outputs must match, and the number of figures it must show.
EXPECTED_OUTPUT = {
    "01_quickstart.ipynb": [
        r"hover RPM\s+14468\.\d RPM",
        r"batched trajectory pos: \(1024, 144, 1, 3\)",
        r"jax\.grad:\s+dz/du = 6\.80\d*e-04 m/RPM",
        r"trained in [\d.]+ s",
        r"mean final distance to target: [\d.]+ cm",
        r"episode z shape: \(151,\)",
    ],
    "02_stable_baselines3.ipynb": [
        r"TOTAL_STEPS = 2,000 ",
        r"SB3 check_env: passed",
        r"trained 8,192 env steps in [\d.]+ s",  # one PPO rollout: n_steps 2048 x 4 envs
        r"mean final distance to target over 10 episodes: [\d.]+ cm",
        r"VecEnv: trained 8,192 env steps in [\d.]+ s",  # one rollout: n_steps 32 x 256 worlds
        r"VecEnv: mean final distance to target over 64 episodes: [\d.]+ cm",
    ],
    "03_gradients.ipynb": [
        r"training budget: 20,000 env steps",
        r"d z_final / d rpm: jax\.grad [\d.e+-]+ m/RPM, central difference [\d.e+-]+ m/RPM, relative difference "
        r"[\d.]+e-0[3-9]",
        r"value and gradient [\d.]+ ms: [\d.]+ x",
        r"APG: mean final distance [\d.]+ cm over 256 starts",
        r"SHAC: mean final distance [\d.]+ cm over 256 starts",
        r"PPO: mean final distance [\d.]+ cm over 256 starts",
        r"horizon   60: mean gradient norm",
        r"kf: largest relative error (0\.0e\+00|\d\.\de-0[4-9])",
        r"drag_coeff: largest relative error \d\.\de-0[4-9]",
    ],
    "04_multi_agent.ipynb": [
        r"training budget: 20,000 env steps; 3 drones",
        r"trained [\d,]+ env steps in [\d.]+ s",
        r"leader altitude error [\d.]+ cm, followers' mean altitude error [\d.]+ cm, largest [\d.]+ cm",
        r"final altitudes: \[",
    ],
    "05_vision.ipynb": [
        r"TOTAL_STEPS = 2,048 ",
        r"SB3 check_env: passed",
        r"trained 2,048 env steps in [\d.]+ s",
        r"success rate over 10 episodes: [\d.]+",
    ],
    "06_sim_to_real.ipynb": [
        r"training budget: 20,000 env steps per policy",
        r"largest relative difference from the first-order solution: \d\.\de-0[5-9]",
        r"longitudinal spectrum at 0\.\d+ Hz: [\d.]+ against Dryden's [\d.]+",
        r"trained with crazyflie: [\d.]+ s",
        r"final distance to the target \(cm\), terminated share",
    ],
    "07_mpc.ipynb": [
        r"largest difference, symbolic step vs JAX step \(float32 simulator\): \d\.\de-0[6-9]",
        r"MPC: RMS error [\d.]+ cm, solve time median [\d.]+ ms",
        r"PID: RMS error [\d.]+ cm",
    ],
}
EXPECTED_FIGURES = {
    "01_quickstart.ipynb": 2,
    "02_stable_baselines3.ipynb": 1,
    "03_gradients.ipynb": 2,
    "04_multi_agent.ipynb": 1,
    "05_vision.ipynb": 1,
    "06_sim_to_real.ipynb": 2,
    "07_mpc.ipynb": 1,
}
#: Per notebook: environment variables of its kernel (tiny training budgets for the training notebooks).
NOTEBOOK_ENV = {
    "02_stable_baselines3.ipynb": {"JAXDRONES_NB_STEPS": "2000"},
    "03_gradients.ipynb": {"JAXDRONES_NB_STEPS": "20000"},
    "04_multi_agent.ipynb": {"JAXDRONES_NB_STEPS": "20000"},
    "05_vision.ipynb": {"JAXDRONES_NB_STEPS": "2048"},
    "06_sim_to_real.ipynb": {"JAXDRONES_NB_STEPS": "20000"},
}
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


def output_text(nb) -> str:
    parts = []
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            if out.output_type == "stream":
                parts.append(out.text)
            elif "data" in out and "text/plain" in out.data:
                parts.append(out.data["text/plain"])
    return "\n".join(parts)


def test_notebooks_found():
    assert [p.name for p in NOTEBOOKS][:1] == ["01_quickstart.ipynb"]


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


@pytest.mark.slow
@pytest.mark.notebooks
@pytest.mark.parametrize(
    "path",
    [pytest.param(p, marks=[pytest.mark.torch] * (p.name in SB3_NOTEBOOKS)) for p in NOTEBOOKS],
    ids=[p.name for p in NOTEBOOKS],
)
def test_notebook_runs(path, tmp_path, monkeypatch, kernel_for_this_interpreter, users_rank_promotion):
    for name, value in NOTEBOOK_ENV.get(path.name, {}).items():
        monkeypatch.setenv(name, value)  # the kernel inherits this process's environment
    nb = nbformat.read(path, as_version=4)
    workdir = tmp_path / "work"
    workdir.mkdir()
    RUNNER.execute(nb, kernel_for_this_interpreter, workdir, TIMEOUT_S)  # raises CellExecutionError, naming the cell

    errors = [out for cell in nb.cells for out in cell.get("outputs", []) if out.output_type == "error"]
    assert not errors
    text = output_text(nb)
    for pattern in EXPECTED_OUTPUT.get(path.name, []):
        assert re.search(pattern, text), f"{path.name}: no output matches {pattern!r}"
    assert figures(nb) >= EXPECTED_FIGURES.get(path.name, 0)
    if path.name == "01_quickstart.ipynb":
        # The gradient through the rollout agrees with the finite difference.
        rel = float(re.search(r"relative difference grad vs finite difference: (\S+)", text).group(1))
        assert rel < 1e-3
    if path.name == "06_sim_to_real.ipynb":  # the sampled turbulence has Dryden's spectrum
        sampled, model = map(float, re.search(r"Hz: ([\d.]+) against Dryden's ([\d.]+)", text).groups())
        assert abs(sampled / model - 1) < 0.15
    if path.name == "07_mpc.ipynb":  # the MPC tracks the figure-8 within 5 cm RMS on the simulator
        assert float(re.search(r"MPC: RMS error ([\d.]+) cm", text).group(1)) <= 5.0
