"""The plots of `jaxdrones.io.plotting`: each writes its PNG and leaves the user's matplotlib as it was (its backend,
e.g. a notebook's inline one, and its open figures)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxdrones.io import plotting

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
T, D = 20, 2


def _plots(tmp_path):
    """Each plot function of the module, called on small data, and its output path."""
    rng = np.random.default_rng(0)
    times = np.arange(T) / 30.0
    vec = lambda n=3: rng.normal(size=(T, D, n))  # noqa: E731
    flight = dict(times=times, pos=vec(), vel=vec(), rpy=vec(), ang_vel=vec(), rpm=vec(4), target_pos=vec())
    history = [{"env_steps": 1000 * k, "episode_reward": float(k), "success_value": 0.5 / k} for k in range(1, 5)]
    runs = {
        "with": dict(pos=vec()[:, 0], vel=vec()[:, 0], rpm=vec(4)[:, 0]),
        "without": dict(pos=vec()[:, 0], vel=vec()[:, 0], rpm=vec(4)[:, 0]),
    }
    return {
        "flight": lambda p: plotting.plot_flight(flight, p, title="t", note="n", mark_t=0.2),
        "learning_curve": lambda p: plotting.plot_learning_curve(history, p, threshold=0.05, title="t"),
        "learning_curves": lambda p: plotting.plot_learning_curves(
            [history, history], p, groups=["a", "b"], threshold=0.05
        ),
        "task_flight": lambda p: plotting.plot_task_flight(times, vec(), vec(), vec(), vec(4), p, title="t"),
        "velocity": lambda p: plotting.plot_velocity_tracking(times, vec(), vec(), p, settled=np.ones((T, D), bool)),
        "takeoff": lambda p: plotting.plot_takeoff_comparison(times, runs, np.ones(T), p, note="n"),
        "altitude": lambda p: plotting.plot_altitude_comparison(
            times, {"a": vec()[..., 0], "b": vec()[..., 0]}, np.ones(D), p, shade=np.arange(T) > 5
        ),
    }


def test_plots_write_pngs_and_leave_the_users_matplotlib_alone(tmp_path):
    matplotlib = pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    backend = "module://matplotlib_inline.backend_inline"
    pytest.importorskip("matplotlib_inline")
    before = matplotlib.get_backend()
    plt.switch_backend(backend)
    try:
        user_figure = plt.figure()
        figures = plt.get_fignums()  # the user's, and any an earlier test left open
        for name, plot in _plots(tmp_path).items():
            path = tmp_path / f"{name}.png"
            assert plot(path) == str(path)
            assert path.read_bytes().startswith(PNG_MAGIC) and path.stat().st_size > 10_000, name
            assert matplotlib.get_backend() == backend, name
            assert plt.get_fignums() == figures, name
    finally:
        plt.close(user_figure)
        plt.switch_backend(before)
