"""`jaxdrones.sysid.fit`: recovering kf, km and the drag coefficients from closed-loop flight by multiple shooting,
and its bad input."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.params import with_derived
from jaxdrones.sysid import excitation_flight, fit

CONFIG = jd.SimConfig(n_drones=1, sim_freq=240, ctrl_freq=48, drag=True)
FIELDS = ("kf", "km", "drag_coeff")


@pytest.fixture(scope="module")
def flight():
    return excitation_flight(CONFIG, jd.load_params("cf2x"), duration_s=5.0)


@pytest.mark.slow
def test_fit_recovers_kf_km_and_drag_from_noise_free_closed_loop_flight(flight):
    true = jd.load_params("cf2x")
    speed = np.linalg.norm(np.asarray(flight.observed.vel), axis=-1)
    assert 0.5 < speed.max() < 1.2 and np.ptp(np.asarray(flight.observed.pos[..., 2])) > 0.4  # climbs and turns
    guess = with_derived(true.replace(kf=true.kf * 1.2, km=true.km * 0.8, drag_coeff=true.drag_coeff * 1.3))
    params, report = fit(CONFIG, guess, flight.init_state, flight.rpms, flight.observed, fields=FIELDS)
    for name in FIELDS:
        error = np.asarray(getattr(params, name)) / np.asarray(getattr(true, name)) - 1
        print(f"\nMEASURED sysid {name}: relative error {np.abs(error).max():.2e} (guess off by 20-30 %)")
        assert np.all(np.abs(error) < 0.02), (name, error)
        assert np.all(np.isfinite(report["std"][name]))
    assert report["loss"][-1] < 1e-6 * report["loss"][0] and report["windows"] == 24
    np.testing.assert_allclose(params.hover_rpm, np.sqrt(params.mass * params.gravity / (4 * params.kf)), rtol=1e-6)


def test_fit_bad_input(flight):
    params = jd.load_params("cf2x")
    args = (CONFIG, params, flight.init_state, flight.rpms, flight.observed)
    with pytest.raises(ValueError, match="fields must name DroneParams fields"):
        fit(*args, fields=("kf", "wingspan"))
    with pytest.raises(ValueError, match="rpms must have shape"):
        fit(CONFIG, params, flight.init_state, flight.rpms[:, 0], flight.observed)
    with pytest.raises(ValueError, match="observed.pos must have shape"):
        fit(CONFIG, params, flight.init_state, flight.rpms[:-1], flight.observed)
    bad = flight.observed.replace(vel=flight.observed.vel.at[3, 0, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="observed.vel contains NaN"):
        fit(CONFIG, params, flight.init_state, flight.rpms, bad)
    with pytest.raises(ValueError, match="window must be an integer"):
        fit(*args, window=0)
