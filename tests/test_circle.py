"""The paper's circle example (docs/physics.md §13): 4 Crazyflies track the circle with the DSL PID controller.

Metric (documented in `jaxdrones.examples.circle`): RMS over the control steps with t ≥ 1 s of the 3-D distance
to the moving way-point, and to the nearest point of each drone's reference circle (cross-track).
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from jaxdrones.cli import fly
from jaxdrones.examples import circle

TOLERANCE_M = 0.05


@pytest.fixture(scope="module")
def flights():
    """The default 4-drone flight with and without velocity feed-forward (one compilation for both)."""
    return {ff: circle.fly_circle(num_drones=4, feedforward=ff) for ff in (True, False)}


def test_setup_is_the_papers():
    setup = circle.circle_setup(4)
    np.testing.assert_allclose(setup["init_pos"][:, 2], [0.1, 0.15, 0.2, 0.25])
    np.testing.assert_allclose(setup["init_pos"][0, :2], [0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(setup["init_rpy"][:, 2], np.arange(4) * np.pi / 8)
    assert setup["num_wp"] == 480
    np.testing.assert_array_equal(setup["wp_start"], [0, 80, 160, 240])
    # Each drone starts on its first way-point.
    np.testing.assert_allclose(setup["waypoints"][setup["wp_start"]], setup["init_pos"][:, :2], atol=1e-12)


def test_default_flight_tracks_within_5cm(flights):
    result = flights[circle.DEFAULT_FEEDFORWARD]
    m = result["metrics"]
    assert result["pos"].shape == (576, 4, 3) and result["rpm"].shape == (576, 4, 4)
    assert np.all(np.isfinite(result["pos"]))
    assert m["settle_s"] == 1.0
    assert m["waypoint_rms_m"] < TOLERANCE_M, m
    assert m["cross_track_rms_m"] < TOLERANCE_M, m
    assert max(m["waypoint_rms_per_drone_m"]) < TOLERANCE_M, m
    # The first action is 0 RPM; every later command lies in the PID's output range.
    np.testing.assert_array_equal(result["rpm"][0], 0.0)
    assert np.all((result["rpm_cmd"] >= 9440.3 - 1e-2) & (result["rpm_cmd"] <= 21666.45 + 1e-2))


def test_without_feedforward_lags_like_the_original(flights):
    """The original (no feed-forward) lags its moving way-point by ≈ 9 cm (docs/physics.md §12) but stays on the
    circle."""
    m = flights[False]["metrics"]
    assert 0.07 < m["waypoint_rms_m"] < 0.11, m
    assert m["cross_track_rms_m"] < TOLERANCE_M, m
    assert flights[True]["metrics"]["waypoint_rms_m"] < 0.5 * m["waypoint_rms_m"]


def test_cli_writes_a_new_run_folder(tmp_path, flights, capsys):
    """`jaxdrones fly` writes plot + metrics into a fresh folder and never overwrites an earlier run.

    Uses the default drone count and duration, so the flight compiled for ``flights`` is reused.
    """
    import argparse

    parser = argparse.ArgumentParser(prog="jaxdrones")
    fly.register(parser.add_subparsers(dest="command", required=True))
    out = tmp_path / "fly"
    out.mkdir()
    (out / "earlier.txt").write_text("an earlier run")
    args = parser.parse_args(["fly", "--out", str(out)])
    assert args.func(args) == 0
    assert (out / "earlier.txt").read_text() == "an earlier run" and len(os.listdir(out)) == 1
    new = tmp_path / "fly-1"
    assert os.path.getsize(new / "flight.png") > 10_000
    metrics = json.loads((new / "metrics.json").read_text())
    assert metrics["settings"]["num_drones"] == 4 and metrics["settings"]["feedforward"] == circle.DEFAULT_FEEDFORWARD
    assert metrics["metrics"]["waypoint_rms_m"] == pytest.approx(
        flights[circle.DEFAULT_FEEDFORWARD]["metrics"]["waypoint_rms_m"]
    )
    printed = capsys.readouterr().out
    assert "overall" in printed and "drone 3" in printed


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="num_drones"):
        circle.fly_circle(num_drones=0)
    with pytest.raises(ValueError, match="duration_s"):
        circle.fly_circle(duration_s=0.0)
    with pytest.raises(ValueError, match="settle_s"):
        circle.fly_circle(duration_s=1.0, settle_s=2.0)
    with pytest.raises(ValueError, match="drone model"):
        circle.fly_circle(model="nope")
