"""Bad input is rejected on the host with a ValueError that names the problem."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.params import model_path

pytestmark = pytest.mark.unit

CF2X_URDF = open(model_path("cf2x")).read()


def write_urdf(tmp_path, text: str, name: str = "edited.urdf") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def edit(old: str, new: str) -> str:
    """The shipped cf2x URDF with one exact substring replaced (which must occur exactly once)."""
    assert CF2X_URDF.count(old) == 1, old
    return CF2X_URDF.replace(old, new)


@pytest.fixture(scope="module")
def setup():
    config = jd.SimConfig(n_drones=2)
    return config, jd.load_params("cf2x"), jd.init_state(config), jd.make_step(config)


# ------------------------------------------------------------------------------------------------------------------
# The step's RPM argument
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(4,), (1, 4), (2, 3), (2, 4, 1), (3, 2, 4)])
def test_rpm_wrong_shape(setup, shape):
    _, params, state, step = setup
    with pytest.raises(ValueError, match=re.escape("rpm must have shape (2, 4)") + ".*" + re.escape(str(shape))):
        step(params, state, np.full(shape, 14000.0))


@pytest.mark.parametrize("dtype", [bool, np.complex64, np.complex128])
def test_rpm_non_real_dtype_rejected(setup, dtype):
    _, params, state, step = setup
    with pytest.raises(ValueError, match="rpm must be a real .* got dtype " + np.dtype(dtype).name):
        step(params, state, np.ones((2, 4), dtype=dtype))


def test_rpm_int_accepted_and_cast(setup):
    _, params, state, step = setup
    as_int = step(params, state, np.full((2, 4), 14468, dtype=np.int32))
    as_float = step(params, state, np.full((2, 4), 14468.0, dtype=np.float32))
    assert as_int.rpm.dtype == state.pos.dtype
    for a, b in zip(jax.tree.leaves(as_int), jax.tree.leaves(as_float), strict=True):
        np.testing.assert_array_equal(a, b)
    python_list = step(params, state, [[14468] * 4] * 2)
    np.testing.assert_array_equal(python_list.pos, as_float.pos)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_rpm_non_finite_rejected_outside_jit(setup, bad):
    _, params, state, step = setup
    rpm = np.full((2, 4), 14000.0)
    rpm[1, 2] = bad
    with pytest.raises(ValueError, match="rpm contains NaN or inf"):
        step(params, state, rpm)


def test_rpm_nan_propagates_inside_jit(setup):
    """Inside jit no exception can be raised: NaN propagates into the state of the affected drone (documented)."""
    _, params, state, step = setup
    rpm = np.full((2, 4), 14000.0)
    rpm[1, 2] = np.nan
    out = jax.jit(step)(params, state, rpm)
    assert np.all(np.isnan(np.asarray(out.vel[1])))
    assert np.all(np.isfinite(np.asarray(out.vel[0])))


def test_rollout_rpms_wrong_shape(setup):
    _, params, state, step = setup
    with pytest.raises(ValueError, match=re.escape("rpms must have shape [T, 2, 4]")):
        jd.rollout(step, params, state, np.zeros((10, 1, 4)))
    with pytest.raises(ValueError, match="rpms must have shape"):
        jd.rollout(step, params, state, np.zeros((2, 4)))


def test_state_for_other_drone_count(setup):
    _, params, _, step = setup
    state3 = jd.init_state(jd.SimConfig(n_drones=3))
    with pytest.raises(ValueError, match=r"expected \[\.\.\., 2, 3\].*n_drones=2"):
        step(params, state3, np.zeros((3, 4)))


def test_make_step_bad_arguments():
    with pytest.raises(ValueError, match="make_step expects a SimConfig"):
        jd.make_step({"n_drones": 1})
    with pytest.raises(ValueError, match="unknown backend 'mujoco'"):
        jd.make_step(jd.SimConfig(), backend="mujoco")


# ------------------------------------------------------------------------------------------------------------------
# SimConfig
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("sim_freq, ctrl_freq", [(240, 50), (240, 7), (100, 240)])
def test_sim_freq_not_multiple_of_ctrl_freq(sim_freq, ctrl_freq):
    with pytest.raises(
        ValueError,
        match=rf"sim_freq \({sim_freq} Hz\) must be a multiple of ctrl_freq "
        rf"\({ctrl_freq} Hz\)",
    ):
        jd.SimConfig(sim_freq=sim_freq, ctrl_freq=ctrl_freq)


def test_unknown_integrator():
    with pytest.raises(ValueError, match="integrator must be one of .*'euler'.*'rk4'.*got 'rk45'"):
        jd.SimConfig(integrator="rk45")


@pytest.mark.parametrize(
    "field, value", [("n_drones", 0), ("n_drones", 1.5), ("sim_freq", -240), ("ctrl_freq", True), ("ctrl_freq", "48")]
)
def test_non_positive_or_non_integer_counts(field, value):
    with pytest.raises(ValueError, match=f"SimConfig.{field} must be a positive integer"):
        jd.SimConfig(**{field: value})


# ------------------------------------------------------------------------------------------------------------------
# Models and URDF files
# ------------------------------------------------------------------------------------------------------------------


def test_unknown_model_name():
    with pytest.raises(ValueError, match="unknown drone model 'cf3'.*cf2x"):
        jd.load_params("cf3")


def test_missing_file(tmp_path):
    missing = tmp_path / "nowhere.urdf"
    with pytest.raises(ValueError, match="drone model file not found.*nowhere.urdf"):
        jd.load_params(missing)
    with pytest.raises(ValueError, match="not found"):
        jd.load_params(str(tmp_path / "sub" / "model"))


def test_shipped_urdf_copy_loads(tmp_path):
    """Control for the edits below: an unedited copy of the shipped URDF loads and equals the shipped model."""
    params = jd.load_params(write_urdf(tmp_path, CF2X_URDF))
    np.testing.assert_array_equal(params.kf, jd.load_params("cf2x").kf)


def test_malformed_xml(tmp_path):
    truncated = CF2X_URDF[: len(CF2X_URDF) // 2]
    with pytest.raises(ValueError, match="malformed URDF XML"):
        jd.load_params(write_urdf(tmp_path, truncated))
    with pytest.raises(ValueError, match="malformed URDF XML"):
        jd.load_params(write_urdf(tmp_path, edit("<robot name", "<robot <name")))


@pytest.mark.parametrize("prop", ["kf", "km", "arm", "thrust2weight", "dw_coeff_3", "prop_spin"])
def test_urdf_missing_property(tmp_path, prop):
    match = re.search(rf' {prop}="[^"]*"', CF2X_URDF)
    text = CF2X_URDF.replace(match.group(0), "", 1)
    with pytest.raises(ValueError, match=f"<properties> lacks attribute '{prop}'"):
        jd.load_params(write_urdf(tmp_path, text))


def test_urdf_missing_elements(tmp_path):
    no_props = re.sub(r"<properties[^>]*/>", "", CF2X_URDF)
    with pytest.raises(ValueError, match="missing <properties> element"):
        jd.load_params(write_urdf(tmp_path, no_props))
    no_mass = edit('<mass value="0.027"/>', "")
    with pytest.raises(ValueError, match="base_link.*lacks <inertial/mass value"):
        jd.load_params(write_urdf(tmp_path, no_mass))
    no_prop3 = CF2X_URDF.replace('name="prop3_link"', 'name="prop9_link"')
    with pytest.raises(ValueError, match="missing link 'prop3_link'"):
        jd.load_params(write_urdf(tmp_path, no_prop3))


@pytest.mark.parametrize(
    "text, match",
    [
        (' kf="abc"', "properties/@kf must be a number, got 'abc'"),
        (' kf="nan"', "properties/@kf must be finite"),
    ],
)
def test_urdf_non_numeric_property(tmp_path, text, match):
    with pytest.raises(ValueError, match=re.escape(match)):
        jd.load_params(write_urdf(tmp_path, edit(' kf="3.16e-10"', text)))


@pytest.mark.parametrize("mass", ["0", "-0.027", "0.0"])
def test_mass_not_positive(tmp_path, mass):
    with pytest.raises(ValueError, match="mass must be > 0"):
        jd.load_params(write_urdf(tmp_path, edit('<mass value="0.027"/>', f'<mass value="{mass}"/>')))


@pytest.mark.parametrize(
    "inertia",
    [
        'ixx="-1.4e-05" ixy="0.0" ixz="0.0" iyy="1.4e-05" iyz="0.0" izz="2.17e-05"',  # negative diagonal
        'ixx="1.4e-05" ixy="0.0" ixz="0.0" iyy="1.4e-05" iyz="0.0" izz="0"',  # singular
        'ixx="1.4e-05" ixy="3e-05" ixz="0.0" iyy="1.4e-05" iyz="0.0" izz="2.17e-05"',  # indefinite
    ],
)
def test_inertia_not_positive_definite(tmp_path, inertia):
    shipped = 'ixx="1.4e-05" ixy="0.0" ixz="0.0" iyy="1.4e-05" iyz="0.0" izz="2.17e-05"'
    with pytest.raises(ValueError, match="inertia must be symmetric positive definite"):
        jd.load_params(write_urdf(tmp_path, edit(shipped, inertia)))


@pytest.mark.parametrize(
    "old, new, match",
    [
        (' thrust2weight="2.25"', ' thrust2weight="0.9"', "thrust2weight must be > 1"),
        (' kf="3.16e-10"', ' kf="-3.16e-10"', "kf must be > 0"),
        (' frame="x"', ' frame="y"', "frame must be 'x' or '\\+'"),
        (' prop_spin="1 -1 1 -1"', ' prop_spin="1 -1 1"', "prop_spin must be 4 values of \\+1 or -1"),
        (' prop_spin="1 -1 1 -1"', ' prop_spin="1 -1 2 -1"', "prop_spin must be 4 values"),
    ],
)
def test_urdf_physically_invalid(tmp_path, old, new, match):
    with pytest.raises(ValueError, match=match):
        jd.load_params(write_urdf(tmp_path, edit(old, new)))


# ------------------------------------------------------------------------------------------------------------------
# init_state
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("pos", np.zeros((3, 3)), r"pos must have shape \[\.\.\., 2, 3\] for n_drones=2, got \(3, 3\)"),
        ("pos", np.zeros(3), r"pos must have shape \[\.\.\., 2, 3\].*got \(3,\)"),
        ("vel", np.zeros((2, 4)), r"vel must have shape \[\.\.\., 2, 3\].*got \(2, 4\)"),
        ("ang_vel", np.zeros((2, 2)), r"ang_vel must have shape \[\.\.\., 2, 3\]"),
        ("rpm", np.zeros((2, 3)), r"rpm must have shape \[\.\.\., 2, 4\].*got \(2, 3\)"),
        ("quat", np.zeros((2, 3)), r"quat must have shape \[\.\.\., 2, 4\]"),
        ("rpy", np.zeros((2, 4)), r"rpy must have shape \[\.\.\., 2, 3\]"),
    ],
)
def test_init_state_wrong_shapes(field, value, match):
    with pytest.raises(ValueError, match=match):
        jd.init_state(jd.SimConfig(n_drones=2), **{field: value})


def test_init_state_other_errors():
    config = jd.SimConfig(n_drones=2)
    with pytest.raises(ValueError, match="either rpy or quat, not both"):
        jd.init_state(config, rpy=np.zeros((2, 3)), quat=np.tile([0, 0, 0, 1.0], (2, 1)))
    with pytest.raises(ValueError, match="quat must have non-zero norm"):
        jd.init_state(config, quat=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="pos contains non-finite values"):
        jd.init_state(config, pos=[[0, 0, np.nan], [0, 0, 1]])
    with pytest.raises(ValueError, match="leading \\(world\\) shapes do not broadcast"):
        jd.init_state(config, pos=np.zeros((3, 2, 3)), vel=np.zeros((4, 2, 3)))


def test_init_state_valid_batched_input_broadcasts():
    """Control for the errors above: world axes broadcast and a non-unit quaternion is normalised."""
    state = jd.init_state(jd.SimConfig(n_drones=2), pos=np.zeros((5, 2, 3)), quat=[[0, 0, 0, 2.0], [0, 0, 1, 1]])
    assert state.pos.shape == (5, 2, 3) and state.quat.shape == (5, 2, 4) and state.ground_contact.shape == (5, 2)
    np.testing.assert_allclose(jnp.linalg.norm(state.quat, axis=-1), 1.0, rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(num_envs=0), "num_envs must be an integer >= 1"),
        (dict(num_envs=3), "multiple of num_envs"),
        (dict(learning_rate_schedule="cosine"), "learning_rate_schedule must be None, 'NONE' or 'ADAPTIVE_KL'"),
        (dict(desired_kl=0.0), "desired_kl must be a finite number > 0"),
        (dict(privileged_critic="yes"), "privileged_critic must be True or False"),
    ],
)
def test_brax_ppo_config_out_of_range(kwargs, match):
    from jaxdrones.training.brax_ppo import BraxPPOConfig

    with pytest.raises(ValueError, match=match):
        BraxPPOConfig(**kwargs)


@pytest.mark.parametrize("field, value", [("drag", 1), ("ground_effect", "yes"), ("adjoint", "no")])
def test_effect_flags_must_be_bools(field, value):
    """A string or number is not taken as a switch."""
    with pytest.raises(ValueError, match=rf"SimConfig.{field} must be True or False, got {value!r}"):
        jd.SimConfig(**{field: value})
    with pytest.raises(ValueError, match=rf"{field} must be True or False"):
        jd.make("multi_hover", n_drones=2, **{field: value})
    assert getattr(jd.SimConfig(**{field: np.bool_(True)}), field) is True


@pytest.mark.parametrize("field", ["error_integral", "terminate_on_ground"])
def test_task_switches_must_be_bools(field):
    with pytest.raises(ValueError, match=rf"{field} must be True or False, got 'no'"):
        jd.make("hover", **{field: "no"})


@pytest.mark.parametrize("value", ["no", -1, 1.5])
def test_action_buffer_is_a_switch_or_a_count(value):
    with pytest.raises(ValueError, match=r"action_buffer must be True \(the last ctrl_freq // 2 actions\), False, or"):
        jd.make("hover", action_buffer=value)
