"""jaxdrones.examples.mpc: the MPC on the CasADi model, its inputs and its closed loop (the full figure-8 runs in
notebooks/07_mpc.ipynb)."""

from __future__ import annotations

import numpy as np
import pytest

import jaxdrones as jd

pytest.importorskip("casadi", reason="casadi is not installed (the casadi extra)")
from jaxdrones.examples import mpc  # noqa: E402 (after the skip)


def test_figure8_velocity_is_the_derivative_of_the_position():
    t = np.linspace(0, 6, 601)
    pos, vel = mpc.figure8(t)
    np.testing.assert_allclose(np.gradient(pos, t, axis=0)[1:-1], vel[1:-1], atol=2e-3)
    assert pos[:, 2].min() == pos[:, 2].max() == mpc.FIGURE8["height"]


def test_short_flight_tracks_and_commands_stay_in_range(tmp_path):
    result = mpc.fly_figure8(duration_s=1.5, weights=mpc.MPCWeights(horizon=8), settle_s=1.0)
    assert result["mpc"]["rms"] < 0.05 and result["mpc"]["error"].shape == (45,)
    assert result["mpc"]["solve_s"].shape == (45,) and np.all(result["mpc"]["solve_s"] > 0)
    assert result["pid"]["pos"].shape == (45, 3)
    path = tmp_path / "mpc.png"
    mpc.plot_figure8(result, str(path))
    assert path.stat().st_size > 10_000
    with pytest.raises(FileExistsError):
        mpc.plot_figure8(result, str(path))


def test_mpc_command_is_bounded_and_holds_hover():
    params = jd.load_params("cf2x")
    controller = mpc.MPC(params, jd.SimConfig(ctrl_freq=30), mpc.MPCWeights(horizon=5))
    hover = np.r_[0, 0, 1.0, 0, 0, 0, 1, np.zeros(6), np.full(4, float(params.hover_rpm))]
    ref = np.tile([0, 0, 1.0], (6, 1))
    np.testing.assert_allclose(controller(hover, ref, np.zeros((6, 3))), float(params.hover_rpm), rtol=1e-5)
    far_below = ref + [0, 0, 5.0]  # 5 m above: full thrust, clipped to the motors' range
    rpm = controller(hover, far_below, np.zeros((6, 3)))
    assert np.all(rpm <= float(params.max_rpm) * (1 + 1e-6)) and np.all(rpm > float(params.hover_rpm))


def test_bad_input():
    params = jd.load_params("cf2x")
    with pytest.raises(ValueError, match="horizon"):
        mpc.MPCWeights(horizon=0)
    with pytest.raises(ValueError, match="weight position"):
        mpc.MPCWeights(position=-1.0)
    controller = mpc.MPC(params, jd.SimConfig(ctrl_freq=30), mpc.MPCWeights(horizon=3))
    with pytest.raises(ValueError, match=r"state must have shape \(17,\)"):
        controller(np.zeros(13), np.zeros((4, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"ref_pos must have shape \(horizon \+ 1, 3\) = \(4, 3\)"):
        controller(np.zeros(17), np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="unknown figure-8 parameter"):
        mpc.fly_figure8(radius=1.0)
    with pytest.raises(ValueError, match="settle_s"):
        mpc.fly_figure8(duration_s=1.0, settle_s=1.0)
    with pytest.raises(ValueError, match="duration_s"):
        mpc.fly_figure8(duration_s=0.01)
    with pytest.raises(ValueError, match="period_s"):
        mpc.fly_figure8(period_s=0.0)
