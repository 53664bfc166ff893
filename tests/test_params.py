"""The shipped airframes: URDF constants (docs/physics.md §1), derived constants (§1.1), lever arms (§3.1), dtypes."""

from __future__ import annotations

import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_dyn as ref

import jaxdrones as jd
from jaxdrones.params import model_path

pytestmark = pytest.mark.unit

MODELS = ("cf2x", "cf2p", "racer")
DERIVED = ("hover_rpm", "max_rpm", "max_thrust", "max_xy_torque", "max_z_torque", "gnd_eff_h_clip")


def _printed_tolerance(value: float) -> float:
    """Half a unit in the last significant digit of a number printed with 6-9 significant digits in the table."""
    text = repr(value)
    mantissa = text.split("e")[0].replace("-", "").replace(".", "").lstrip("0")
    exponent = math.floor(math.log10(abs(value)))
    return 0.5 * 10.0 ** (exponent - len(mantissa) + 1)


@pytest.mark.parametrize("model", MODELS)
def test_derived_constants_match_the_documented_table(model, x64):
    """docs/physics.md §1.1 table, to ~1e-6 relative (or half a unit of the last printed digit where it has fewer)."""
    params = jd.load_params(model)
    for name, expected in ref.DERIVED_TABLE[model].items():
        actual = float(getattr(params, name))
        tol = max(1e-6 * abs(expected), _printed_tolerance(expected))
        assert abs(actual - expected) <= tol, (name, actual, expected)
        assert tol <= 1e-5 * abs(expected)


@pytest.mark.parametrize("model", MODELS)
def test_derived_constants_match_formulas(model, x64):
    """The docs/physics.md §1.1 formulas evaluated on the §1 table agree to float64 round-off."""
    params = jd.load_params(model)
    frame = ref.AIRFRAMES[model]
    for name in DERIVED:
        np.testing.assert_allclose(float(getattr(params, name)), getattr(frame, name), rtol=1e-13, err_msg=name)
    np.testing.assert_allclose(float(params.weight), frame.weight, rtol=1e-15)
    # At the clip height the ground-effect gain C (R / 4h)² is 4/15.
    gain = frame.gnd_eff_coeff * (frame.prop_radius / (4 * float(params.gnd_eff_h_clip))) ** 2
    assert gain == pytest.approx(4 / 15, rel=1e-13)


@pytest.mark.parametrize("model", MODELS)
def test_urdf_constants_match_the_documented_table(model, x64):
    params = jd.load_params(model)
    frame = ref.AIRFRAMES[model]
    np.testing.assert_allclose(params.mass, frame.mass, rtol=1e-15)
    np.testing.assert_allclose(params.arm, frame.arm, rtol=1e-15)
    np.testing.assert_allclose(params.inertia, np.diag(frame.inertia), rtol=1e-15, atol=0)
    np.testing.assert_allclose(params.inertia_inv @ params.inertia, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(params.kf, frame.kf, rtol=1e-15)
    np.testing.assert_allclose(params.km, frame.km, rtol=1e-15)
    np.testing.assert_allclose(params.thrust2weight, frame.thrust2weight, rtol=1e-15)
    np.testing.assert_allclose(params.prop_radius, frame.prop_radius, rtol=1e-15)
    np.testing.assert_allclose(params.gnd_eff_coeff, 11.36859, rtol=1e-15)
    np.testing.assert_allclose(params.drag_coeff, [9.1785e-7, 9.1785e-7, 10.311e-7], rtol=1e-15)
    np.testing.assert_allclose(params.dw_coeff, [2267.18, 0.16, -0.11], rtol=1e-15)
    np.testing.assert_allclose(params.max_speed_kmh, {"racer": 200.0}.get(model, 30.0), rtol=1e-15)
    # The original's cylinder (r = 0.06 m) let the propellers stick out; ours covers every propeller disk.
    prop_reach = np.max(np.linalg.norm(np.asarray(params.prop_pos)[:, :2], axis=1)) + float(params.prop_radius)
    assert prop_reach <= float(params.collision_radius) < prop_reach + 1e-3
    np.testing.assert_allclose(params.collision_height, 0.025, rtol=1e-15)
    assert float(params.gravity) == 9.8


#: docs/physics.md §2 motor positions (body frame, m) and spins: +1 = CCW seen from above (yaw reaction -km rpm²).
PROP_POS = {
    "cf2x": [(0.028, -0.028), (-0.028, -0.028), (-0.028, 0.028), (0.028, 0.028)],
    "cf2p": [(0.0397, 0), (0, 0.0397), (-0.0397, 0), (0, -0.0397)],
    "racer": [(0.085, 0.0675), (-0.085, 0.0675), (-0.085, -0.0675), (0.085, -0.0675)],
}
PROP_SPIN = {"cf2x": (1, -1, 1, -1), "cf2p": (1, -1, 1, -1), "racer": (-1, 1, -1, 1)}


@pytest.mark.parametrize("model", MODELS)
def test_motor_layout_matches_the_documented_layout(model, x64):
    params = jd.load_params(model)
    expected = np.concatenate([np.array(PROP_POS[model], dtype=np.float64), np.zeros((4, 1))], axis=1)
    np.testing.assert_allclose(params.prop_pos, expected, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(params.prop_spin, PROP_SPIN[model])


@pytest.mark.parametrize("model", MODELS)
def test_torque_arm_matches_explicit_mixer(model, x64):
    """docs/physics.md §3.1: (τx, τy) = torque_arm @ (f0..f3) with the explicit arms L/√2 (x frame) or L (+ frame)."""
    params = jd.load_params(model)
    arm = ref.AIRFRAMES[model].arm
    a = arm / math.sqrt(2)
    expected = {
        "cf2x": [[-a, -a, a, a], [-a, a, a, -a]],
        "racer": [[a, a, -a, -a], [-a, a, a, -a]],
        "cf2p": [[0, arm, 0, -arm], [-arm, 0, arm, 0]],
    }[model]
    np.testing.assert_allclose(params.torque_arm, expected, rtol=1e-15, atol=1e-18)
    # And against the reference's spelled-out formulas for a generic thrust vector.
    rpm = np.array([13000.0, 14000.0, 15000.0, 16000.0])
    _, torque = ref.forces_torques(ref.AIRFRAMES[model], rpm)
    np.testing.assert_allclose(np.asarray(params.torque_arm) @ (params.kf * rpm**2), torque[:2], rtol=1e-14)
    # The maximum xy torque is the arm times the thrust of two motors at max rpm (docs/physics.md §1.1).
    np.testing.assert_allclose(
        np.abs(np.asarray(params.torque_arm)).sum(1) / 2 * params.kf * params.max_rpm**2,
        params.max_xy_torque,
        rtol=1e-14,
    )


def test_load_by_path_equals_load_by_name(x64):
    by_name = jd.load_params("cf2p")
    for path in (model_path("cf2p"), pathlib.Path(model_path("cf2p"))):
        by_path = jd.load_params(path)
        for a, b in zip(jax.tree.leaves(by_name), jax.tree.leaves(by_path), strict=True):
            np.testing.assert_array_equal(a, b)


def test_dtype_follows_x64_setting():
    with jax.enable_x64(False):
        params = jd.load_params("cf2x")
        state = jd.init_state(jd.SimConfig(n_drones=2))
        leaves = jax.tree.leaves(params) + [state.pos, state.quat, state.vel, state.ang_vel, state.rpm]
        assert {x.dtype for x in leaves} == {jnp.dtype(jnp.float32)}
        assert state.contact.dtype == jnp.int32
    with jax.enable_x64(True):
        params = jd.load_params("cf2x")
        state = jd.init_state(jd.SimConfig(n_drones=2))
        leaves = jax.tree.leaves(params) + [state.pos, state.quat, state.vel, state.ang_vel, state.rpm]
        assert {x.dtype for x in leaves} == {jnp.dtype(jnp.float64)}
        # No weak types: they would recompile when mixed with strongly typed arrays.
        assert not any(getattr(x, "weak_type", False) for x in leaves)
        out = jd.make_step(jd.SimConfig(n_drones=2))(params, state, np.full((2, 4), 14000.0))
        assert out.pos.dtype == jnp.float64 and out.quat.dtype == jnp.float64


def test_params_are_a_stackable_pytree():
    """DroneParams can carry a leading axis (heterogeneous teams, domain randomisation)."""
    team = jax.tree.map(lambda *xs: jnp.stack(xs), *(jd.load_params(m) for m in MODELS))
    assert team.mass.shape == (3,) and team.inertia.shape == (3, 3, 3) and team.torque_arm.shape == (3, 2, 4)
    np.testing.assert_allclose(team.mass, [0.027, 0.027, 0.830], rtol=1e-6)


def test_align_params_prepends_singleton_batch_axes_and_steps_any_batch_shape():
    """`align_params` gives params the state's batch rank without copying or changing a value, so that a step with
    params of batch shape (), [D] or [W, D] on a [W, D] state needs no implicit rank promotion (the suite runs with
    ``jax_numpy_rank_promotion="raise"``); more batch axes than the state has raise a ValueError."""
    from jaxdrones.physics.params import align_params

    one = jd.load_params("cf2x")
    aligned = align_params(one, 2)
    assert (
        aligned.mass.shape == (1, 1) and aligned.inertia.shape == (1, 1, 3, 3) and aligned.dw_coeff.shape == (1, 1, 3)
    )
    np.testing.assert_array_equal(aligned.prop_pos[0, 0], one.prop_pos)
    team = jax.tree.map(lambda x: jnp.stack([x, x]), one)  # [D = 2]
    assert align_params(team, 2).mass.shape == (1, 2) and align_params(team, 1) is team
    with pytest.raises(ValueError, match=r"batch shape \(2,\), more than the 0 axes"):
        align_params(team, 0)

    config = jd.SimConfig(n_drones=2, downwash=True)
    step = jd.make_step(config)
    state = jd.init_state(config)
    worlds = jax.tree.map(lambda x: jnp.stack([x, x, x]), state)  # [W = 3, D = 2]
    rpm = jnp.full((3, 2, 4), float(one.hover_rpm))
    with jax.numpy_rank_promotion("raise"):
        outs = [step(p, worlds, rpm) for p in (one, team, jax.tree.map(lambda x: jnp.stack([x, x, x]), team))]
    for out in outs[1:]:
        np.testing.assert_array_equal(out.pos, outs[0].pos)
    np.testing.assert_array_equal(outs[0].pos[1], step(one, state, rpm[0]).pos)


def test_default_start_pose(x64):
    """docs/physics.md §1.1: drone i starts at (4iL, 4iL, collision_height/2 + 0.1), L = 0.0397 m, level, at rest."""
    state = jd.init_state(jd.SimConfig(n_drones=3))
    i = np.arange(3)[:, None]
    np.testing.assert_allclose(
        state.pos, np.concatenate([4 * i * 0.0397, 4 * i * 0.0397, 0.1125 + 0 * i], 1), rtol=1e-15
    )
    np.testing.assert_array_equal(state.quat, np.tile([0.0, 0.0, 0.0, 1.0], (3, 1)))
    for field in (state.vel, state.ang_vel, state.rpm, state.contact):
        np.testing.assert_array_equal(field, 0)
