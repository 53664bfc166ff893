"""The hand-written adjoint of the Euler substep (`jaxdrones.adjoint`): the control step that uses it
(``SimConfig(adjoint=True)``, the default) has the values and the reverse-mode derivatives of JAX's derived ones
(``adjoint=False``): for the state and the command through the hand-written pass (params closed over), with and
without drag, ground effect and downwash (the paper's force and the per-rotor thrust changes), over one or several
substeps, across the RPM clip and the ground contact; for the params too through the rule's fallback to JAX's
derived pass (differentiating the params selects it); forward mode is refused with JAX's own error and works with
``adjoint=False``."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones import adjoint

pytestmark = pytest.mark.unit

WORLDS = 16
EFFECTS = {
    "none": {},
    "drag_ground": {"drag": True, "ground_effect": True},
    "all": {"drag": True, "ground_effect": True, "downwash": True},
    "all_per_rotor": {"drag": True, "ground_effect": True, "downwash": "per_rotor"},
    "all_bounded": {"drag": True, "ground_effect": True, "downwash": "bounded"},
}


def _case(effects: dict, substeps: int, seed: int = 0):
    """A config, params, a start state (random pose, velocities and previous RPM, an unnormalised quaternion, some
    drones at or below the rest height) and a command (some beyond 0 and max_rpm, one exactly at 0)."""
    n = 3 if effects.get("downwash") else 1
    config = jd.SimConfig(n_drones=n, sim_freq=240 * substeps, ctrl_freq=240, **effects)
    params = jd.load_params("cf2x")
    rng = np.random.default_rng(seed)
    pos = np.concatenate([rng.uniform(-0.05, 0.05, (WORLDS, n, 2)), rng.uniform(0.0, 0.3, (WORLDS, n, 1))], -1)
    pos[:2, 0, 2] = [0.0125, 0.005]  # at the rest height, below it, and falling
    vel = rng.normal(size=(WORLDS, n, 3))
    vel[:2, 0, 2] = -1.0
    state = jd.init_state(
        config,
        pos=pos,
        vel=vel,
        ang_vel=rng.normal(size=(WORLDS, n, 3)),
        rpm=float(params.hover_rpm) * (1 + 0.1 * rng.normal(size=(WORLDS, n, 4))),
    )
    quat = rng.normal(size=(WORLDS, n, 4)) * 0.1 + [0.0, 0.0, 0.0, 1.3]
    state = state.replace(quat=jnp.asarray(quat, state.quat.dtype))
    rpm = float(params.hover_rpm) * (1 + 0.1 * rng.normal(size=(WORLDS, n, 4)))
    rpm[:3, 0, 0] = [-5.0, 1e6, 0.0]
    return config, params, state, jnp.asarray(rpm, state.pos.dtype)


def _cotangent(out, rng):
    return jax.tree.map(
        lambda x: (
            np.zeros(x.shape, jax.dtypes.float0)
            if x.dtype == jnp.int32
            else jnp.asarray(rng.normal(size=x.shape), x.dtype)
        ),
        out,
    )


def _compare_vjps(config, params, state, rpm, with_params: bool, rng) -> set[str]:
    """The control step's values and cotangents with the hand-written adjoint (the default config) against JAX's
    derived ones (``adjoint=False``), float64: values equal to rounding, cotangents within 1e-10 relative. Without
    ``with_params`` the params are closed over, so the rule's hand-written pass runs; with it they are differentiated
    too, which makes the rule fall back to JAX's derived pass (system identification). Returns the paths of the
    nonzero cotangents checked."""
    assert adjoint.supported(config) and not adjoint.supported(dataclasses.replace(config, adjoint=False))
    results = []
    for use in (False, True):
        step = jd.make_step(dataclasses.replace(config, adjoint=use))
        if with_params:
            results.append(jax.vjp(lambda s, r, p, step=step: step(p, s, r), state, rpm, params))
        else:
            results.append(jax.vjp(lambda s, r, step=step: step(params, s, r), state, rpm))
    (out_ref, vjp_ref), (out, vjp) = results
    for a, b in zip(jax.tree.leaves(out_ref), jax.tree.leaves(out), strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-14, atol=1e-15)
    assert bool(out.ground_contact[:2, 0].all()), "the drones at and below the rest height touch the ground"
    ct = _cotangent(out_ref, rng)
    checked = set()
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(vjp_ref(ct)), jax.tree.leaves(vjp(ct)), strict=True):
        if a.dtype == jax.dtypes.float0:
            continue
        scale = float(jnp.max(jnp.abs(a)))
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-12 * scale, err_msg=jax.tree_util.keystr(path))
        if scale > 0:
            checked.add(jax.tree_util.keystr(path))
    return checked


#: The cases of `test_adjoint_matches_derived_derivative` without downwash whose float64 checks take longest (11 s each
#: on 2 cores): in the ``slow`` tier; the others stay ``fast``.
LONG = (("drag_ground", 1), ("drag_ground", 4))


# The cases with downwash (3 drones per world, the per-rotor jets) compile for 20-60 s each: slow, and run with 4
# substeps only (which run the single substep's pass 4 times, and the loop around it).
@pytest.mark.parametrize(
    "effects, substeps",
    [
        pytest.param(e, n, marks=pytest.mark.slow) if "downwash" in EFFECTS[e] or (e, n) in LONG else (e, n)
        for e in EFFECTS
        for n in (1, 4)
        if n == 4 or "downwash" not in EFFECTS[e]
    ],
)
def test_adjoint_matches_derived_derivative(x64, effects, substeps):
    """float64, the hand-written pass (params closed over): values equal to rounding and the cotangents of the
    state and the command within 1e-10 relative of JAX's derived ones."""
    config, params, state, rpm = _case(EFFECTS[effects], substeps)
    checked = _compare_vjps(config, params, state, rpm, False, np.random.default_rng(1))
    expected = {"[0].pos", "[0].quat", "[0].vel", "[0].ang_vel", "[1]"}
    if config.drag:  # drag acts on the previous substep's speeds: the state's RPM
        expected.add("[0].rpm")
    assert checked == expected, checked


@pytest.mark.slow
@pytest.mark.parametrize("effects, substeps", [("drag_ground", 4)])
def test_params_cotangents_fall_back_to_the_derived_derivative(x64, effects, substeps):
    """float64, params differentiated too (system identification): the rule's fallback to JAX's derived pass gives
    every cotangent, the params' included, within 1e-10 relative of ``adjoint=False``."""
    config, params, state, rpm = _case(EFFECTS[effects], substeps)
    checked = _compare_vjps(config, params, state, rpm, True, np.random.default_rng(1))
    assert {"[2].mass", "[2].kf", "[2].km", "[2].drag_coeff", "[2].inertia", "[0].pos", "[1]"} <= checked, checked


@pytest.mark.slow
def test_adjoint_gradient_without_params_matches_derived_in_float32():
    """float32, the case APG and SHAC run: the gradient w.r.t. state and command alone (the hand-written pass
    proper, params not perturbed) agrees with JAX's derived one within float32 rounding."""
    config, params, state, rpm = _case(EFFECTS["drag_ground"], 1, seed=2)
    grads = []
    for use in (False, True):
        step = jd.make_step(dataclasses.replace(config, adjoint=use))

        def loss(pos, quat, vel, ang_vel, r, step=step):
            out = step(params, state.replace(pos=pos, quat=quat, vel=vel, ang_vel=ang_vel), r)
            return jnp.sum(out.pos**2) + jnp.sum(out.vel**2) + jnp.sum(out.quat[..., :3] ** 2) + jnp.sum(out.ang_vel)

        grads.append(jax.grad(loss, argnums=tuple(range(5)))(state.pos, state.quat, state.vel, state.ang_vel, rpm))
    for a, b in zip(grads[0], grads[1], strict=True):
        assert b.dtype == jnp.float32 and float(jnp.max(jnp.abs(a))) > 0
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5 * float(jnp.max(jnp.abs(a))))


def test_forward_mode_needs_adjoint_false(x64):
    """jax.jacfwd through the default step raises JAX's custom_vjp error; with adjoint=False it works and agrees
    with jax.jacrev through the default step."""
    config, params, state, rpm = _case(EFFECTS["drag_ground"], 1)

    def final_pos(step):
        return lambda r: step(params, state, r).pos

    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jacfwd(final_pos(jd.make_step(config)))(rpm)
    forward = jax.jacfwd(final_pos(jd.make_step(dataclasses.replace(config, adjoint=False))))(rpm)
    reverse = jax.jacrev(final_pos(jd.make_step(config)))(rpm)
    np.testing.assert_allclose(reverse, forward, rtol=1e-10, atol=1e-14)
    assert float(jnp.max(jnp.abs(forward))) > 0


@pytest.mark.parametrize("bad", [1, "yes", None])
def test_adjoint_must_be_a_bool(bad):
    with pytest.raises(ValueError, match="SimConfig.adjoint must be True or False"):
        jd.SimConfig(adjoint=bad)
