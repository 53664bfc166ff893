"""`jaxdrones.sysid.fit`: recovering kf, km and the drag coefficients from closed-loop flight by multiple shooting,
noise-free and with measurement noise (`jaxdrones.sysid.add_noise`), and its bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.params import with_derived
from jaxdrones.rotations import quat_mul
from jaxdrones.sysid import add_noise, excitation_flight, fit

CONFIG = jd.SimConfig(n_drones=1, sim_freq=240, ctrl_freq=48, drag=True)
FIELDS = ("kf", "km", "drag_coeff")


@pytest.fixture(scope="module")
def flight():
    return excitation_flight(CONFIG, jd.load_params("cf2x"), duration_s=5.0)


def _guess(true):
    """kf, km and drag_coeff 20-30 % off."""
    return with_derived(true.replace(kf=true.kf * 1.2, km=true.km * 0.8, drag_coeff=true.drag_coeff * 1.3))


@pytest.mark.slow
@pytest.mark.parametrize("estimate_starts", [True, False])
def test_fit_recovers_kf_km_and_drag_from_noise_free_closed_loop_flight(flight, estimate_starts):
    true = jd.load_params("cf2x")
    speed = np.linalg.norm(np.asarray(flight.observed.vel), axis=-1)
    assert 0.5 < speed.max() < 1.2 and np.ptp(np.asarray(flight.observed.pos[..., 2])) > 0.4  # climbs and turns
    params, report = fit(
        CONFIG,
        _guess(true),
        flight.init_state,
        flight.rpms,
        flight.observed,
        fields=FIELDS,
        estimate_starts=estimate_starts,
    )
    for name in FIELDS:
        error = np.asarray(getattr(params, name)) / np.asarray(getattr(true, name)) - 1
        print(
            f"\nMEASURED sysid {name}: relative error {np.abs(error).max():.2e} (guess off by 20-30 %, "
            f"estimate_starts={estimate_starts})"
        )
        assert np.all(np.abs(error) < 0.02), (name, error)
        assert np.all(np.isfinite(report["std"][name]))
    assert len(report["loss"]) == 2 and report["loss"][-1] < 1e-6 * report["loss"][0] and report["windows"] == 24
    assert 0 < report["steps"] <= 100  # optimistix's Levenberg-Marquardt steps, within the default iterations
    np.testing.assert_allclose(params.hover_rpm, np.sqrt(params.mass * params.gravity / (4 * params.kf)), rtol=1e-6)


# 1 mm position and 0.01 rad attitude noise, velocity and body rate as recorded (the acceptance case); then with
# 0.01 m/s velocity and 0.05 rad/s body-rate noise too.
NOISES = {"pos+att": {}, "pos+att+vel+ang_vel": {"vel": 0.01, "ang_vel": 0.05}}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("case", NOISES)
def test_fit_recovers_kf_km_and_drag_within_10_percent_from_noisy_flight(flight, case, seed):
    true = jd.load_params("cf2x")
    noisy = add_noise(flight, jax.random.key(seed), **NOISES[case])
    params, report = fit(CONFIG, _guess(true), noisy.init_state, noisy.rpms, noisy.observed, fields=FIELDS)
    for name in FIELDS:
        error = np.asarray(getattr(params, name)) / np.asarray(getattr(true, name)) - 1
        std = report["std"][name] / np.asarray(getattr(true, name))
        print(
            f"\nMEASURED sysid noisy {name}: relative error {np.array2string(error, precision=4)} "
            f"(standard error {np.array2string(std, precision=4)}; {case} noise, seed {seed})"
        )
        assert np.all(np.abs(error) < 0.10), (name, error)
        assert np.all(np.abs(error) < 4 * std), (name, error, std)  # the standard errors are honest
    # At the fit, the residuals are the noise: in noise units, mean square 1 for the noisy position and attitude.
    assert 0.2 < report["loss"][-1] < 1.0


@pytest.mark.slow
def test_fit_identifies_mass_with_kf_from_noisy_flight(flight):
    """mass with kf, km and drag: the rotational dynamics (known inertia) give kf, the translational ones kf/m, so
    the mass is identifiable from the same flight (guess 10 % off), here with position and attitude noise."""
    true = jd.load_params("cf2x")
    noisy = add_noise(flight, jax.random.key(0))
    guess = _guess(true).replace(mass=true.mass * 1.1)
    fields = ("mass",) + FIELDS
    params, report = fit(CONFIG, with_derived(guess), noisy.init_state, noisy.rpms, noisy.observed, fields=fields)
    for name in fields:
        error = np.asarray(getattr(params, name)) / np.asarray(getattr(true, name)) - 1
        print(f"\nMEASURED sysid noisy with mass {name}: relative error {np.array2string(error, precision=4)}")
        assert np.all(np.abs(error) < 0.10), (name, error)
    assert abs(float(params.mass / true.mass) - 1) < 0.01 and np.isfinite(report["std"]["mass"]).all()


def test_add_noise_has_the_stated_standard_deviations(flight):
    noisy = add_noise(flight, jax.random.key(0), pos=1e-3, att=1e-2, vel=0.0, ang_vel=0.05)
    np.testing.assert_array_equal(noisy.rpms, flight.rpms)
    np.testing.assert_array_equal(noisy.observed.vel, flight.observed.vel)
    assert abs(np.std(noisy.observed.pos - flight.observed.pos) / 1e-3 - 1) < 0.1
    assert abs(np.std(noisy.observed.ang_vel - flight.observed.ang_vel) / 0.05 - 1) < 0.1
    conjugate = flight.observed.quat.at[..., :3].multiply(-1.0)
    relative = np.asarray(quat_mul(conjugate, noisy.observed.quat))  # body-frame rotation: ≈ (r / 2, 1)
    assert np.all(relative[..., 3] > 0.99) and abs(np.std(2 * relative[..., :3]) / 1e-2 - 1) < 0.1
    assert not np.allclose(noisy.init_state.pos, flight.init_state.pos)


def test_fit_with_no_iterations_returns_the_guess(flight):
    guess = _guess(jd.load_params("cf2x"))
    params, report = fit(CONFIG, guess, flight.init_state, flight.rpms, flight.observed, fields=FIELDS, iterations=0)
    for name in FIELDS:
        np.testing.assert_allclose(getattr(params, name), getattr(guess, name), rtol=1e-6)
    assert report["steps"] == 0 and report["loss"][0] == report["loss"][1] > 1e3


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
    with pytest.raises(ValueError, match="iterations must be an integer"):
        fit(*args, iterations=-1)
    with pytest.raises(ValueError, match="defect must be a number > 0"):
        fit(*args, defect=0.0)
    with pytest.raises(ValueError, match="noise must map some of"):
        fit(*args, noise={"position": 1e-3})
    with pytest.raises(ValueError, match="noise must map some of"):
        fit(*args, noise={"pos": -1e-3})
