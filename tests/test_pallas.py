"""The control step as a Pallas kernel (`jaxdrones.experimental.pallas.make_step`), in Pallas's
interpret mode on the CPU: the values and the reverse-mode derivatives of the XLA path (float32 to 1e-5 of each
quantity's scale, float64 to rounding) for every physics option it takes (drag, ground effect, lagged motors,
several drones, per-drone params, one or several substeps), across the RPM clip and the ground contact, under
``jax.vmap`` and through `jaxdrones.rollout`; the params' gradient (system identification) and a step with a
disturbance through the XLA path; the settings it does not take refused; and both kernels lowered through Triton
for an NVIDIA GPU without one."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.experimental import pallas
from jaxdrones.physics.params import stack_params

pytestmark = pytest.mark.unit

WORLDS = 6
OPTIONS = {  # two substeps per control step unless told (the kernel writes the substeps out: a short compilation)
    "drag_ground": {"drag": True, "ground_effect": True},
    "motors": {"drag": True, "motor_dynamics": True},
    "one_substep": {"ground_effect": True, "sim_freq": 240, "ctrl_freq": 240},
    "three_drones": {"n_drones": 3, "drag": True, "ground_effect": True},
}
VECTORS = ("pos", "quat", "vel", "ang_vel", "rpm")


def _case(options: dict, seed: int = 0, dtype=np.float32):
    """The XLA path's step and the kernel's, params (per drone, different, for several drones; lagged motors where
    asked), a start state (random pose and velocities, an unnormalised quaternion, drones at and below the rest
    height and falling) and a command (some beyond 0 and max_rpm, one exactly at 0)."""
    options = {"sim_freq": 240, "ctrl_freq": 120, **options}
    n = options.get("n_drones", 1)
    config = jd.SimConfig(**options)
    params = jd.load_params("cf2x")
    if n > 1:
        params = stack_params(["cf2x", "cf2p", "cf2x"][:n])
    if config.motor_dynamics:
        params = params.replace(motor_tau_up=jnp.asarray(0.03), motor_tau_down=jnp.asarray(0.05))
    rng = np.random.default_rng(seed)
    pos = np.concatenate([rng.uniform(-0.5, 0.5, (WORLDS, n, 2)), rng.uniform(0.0, 0.3, (WORLDS, n, 1))], -1)
    pos[:2, 0, 2] = [0.0125, 0.005]
    vel = rng.normal(size=(WORLDS, n, 3))
    vel[:2, 0, 2] = -1.0
    hover = float(np.mean(params.hover_rpm))
    state = jd.init_state(
        config,
        pos=pos.astype(dtype),
        vel=vel.astype(dtype),
        ang_vel=rng.normal(size=(WORLDS, n, 3)).astype(dtype),
        rpm=(hover * (1 + 0.1 * rng.normal(size=(WORLDS, n, 4)))).astype(dtype),
    )
    quat = rng.normal(size=(WORLDS, n, 4)) * 0.1 + [0.0, 0.0, 0.0, 1.3]
    state = state.replace(quat=jnp.asarray(quat, dtype))
    rpm = hover * (1 + 0.3 * rng.normal(size=(WORLDS, n, 4)))
    rpm[:3, 0, 0] = [-5.0, 1e6, 0.0]
    return jd.make_step(config), pallas.make_step(config), params, state, jnp.asarray(rpm, dtype)


def _cotangent(out, rng):
    def draw(x):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            return np.zeros(x.shape, jax.dtypes.float0)
        return jnp.asarray(rng.normal(size=x.shape), x.dtype)

    return jax.tree.map(draw, out)


def _value_and_vjp(step, params, state, rpm, ct):
    out, vjp = jax.vjp(lambda s, r: step(params, s, r), state, rpm)
    state_b, rpm_b = vjp(ct)
    return out, state_b, rpm_b


def _close(got, want, rtol):
    """Each quantity within ``rtol`` of its largest magnitude (float32 rounds sums of large, cancelling terms)."""
    got, want = np.asarray(got), np.asarray(want)
    np.testing.assert_allclose(got, want, rtol=0, atol=rtol * max(np.abs(want).max(), 1e-30))


@pytest.mark.parametrize("name", OPTIONS)
def test_kernel_matches_the_xla_path(name):
    config, fused, params, state, rpm = _case(OPTIONS[name])
    ct = _cotangent(config(params, state, rpm), np.random.default_rng(1))
    want = _value_and_vjp(config, params, state, rpm, ct)
    got = _value_and_vjp(fused, params, state, rpm, ct)
    for field in VECTORS:
        _close(getattr(got[0], field), getattr(want[0], field), 1e-5)
        _close(getattr(got[1], field), getattr(want[1], field), 1e-5)
    _close(got[2], want[2], 1e-5)
    np.testing.assert_array_equal(got[0].contact, want[0].contact)
    assert np.asarray(want[0].contact).any() and not np.asarray(want[0].contact).all()  # the contact is exercised


def test_kernel_matches_the_xla_path_in_float64():
    with jax.enable_x64(True):
        config, fused, params, state, rpm = _case(OPTIONS["drag_ground"], seed=2, dtype=np.float64)
        ct = _cotangent(config(params, state, rpm), np.random.default_rng(3))
        want = _value_and_vjp(config, params, state, rpm, ct)
        got = _value_and_vjp(fused, params, state, rpm, ct)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            if jnp.issubdtype(a.dtype, jnp.floating):
                _close(a, b, 1e-12)


def test_kernel_under_vmap_with_per_world_params():
    """Mapped over worlds (as the envs step), with one params field differing between worlds: the mapped axis joins
    the drones of one kernel launch, the params differ per drone."""
    config, fused, params, state, rpm = _case(OPTIONS["drag_ground"], seed=4)
    mass = params.mass * (1 + 0.2 * jnp.linspace(-1, 1, WORLDS))
    ct = _cotangent(config(params, state, rpm), np.random.default_rng(5))

    def one_world(step, mass, s, r, c):
        out, vjp = jax.vjp(lambda s, r: step(params.replace(mass=mass), s, r), s, r)
        return out, *vjp(c)

    want = jax.vmap(lambda *a: one_world(config, *a))(mass, state, rpm, ct)
    got = jax.vmap(lambda *a: one_world(fused, *a))(mass, state, rpm, ct)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        if jnp.issubdtype(a.dtype, jnp.floating):
            _close(a, b, 1e-5)


def test_params_gradient_and_disturbance_take_the_xla_path():
    config, fused, params, state, rpm = _case(OPTIONS["drag_ground"], seed=6)

    def loss(config, params, disturbance=None):
        out = config(params, state, rpm, disturbance)
        return jnp.sum(out.pos**2) + jnp.sum(out.vel * out.ang_vel)

    want, got = jax.grad(loss, 1)(config, params), jax.grad(loss, 1)(fused, params)
    for field in ("mass", "kf", "inertia", "drag_coeff"):
        _close(getattr(got, field), getattr(want, field), 1e-5)
    disturbance = jd.Disturbance(force=jnp.full((WORLDS, 1, 3), 0.01), wind=jnp.ones((WORLDS, 1, 3)))
    assert loss(fused, params, disturbance) == loss(config, params, disturbance)
    assert loss(fused, params, disturbance) != loss(fused, params)


def test_rollout_with_the_kernel():
    """`jaxdrones.rollout` through the kernel's step: the final state and the gradient of a loss of it with respect to
    the commands, as the XLA path's."""
    xla, fused, params, state, rpm = _case(OPTIONS["motors"], seed=7)
    rpms = jnp.stack([rpm * (1 + 0.01 * k) for k in range(5)])

    def loss(step, rpms):
        out = jd.rollout(step, params, state, rpms)
        return jnp.sum(out.pos[-1] ** 2) + jnp.sum(out.ang_vel[-1] ** 2)

    want, got = jax.value_and_grad(loss, 1)(xla, rpms), jax.value_and_grad(loss, 1)(fused, rpms)
    _close(got[0], want[0], 1e-5)
    _close(got[1], want[1], 1e-5)


@pytest.mark.parametrize(
    "options, why",
    [
        ({"integrator": "rk4"}, "integrator='euler'"),
        ({"kinks": "smooth"}, "kinks='exact'"),
        ({"adjoint": False}, "adjoint=True"),
        ({"n_drones": 2, "downwash": True}, "downwash=False with several drones"),
    ],
)
def test_settings_the_kernel_does_not_take_are_refused(options, why):
    with pytest.raises(ValueError, match="the Pallas control step takes") as err:
        pallas.make_step(jd.SimConfig(**options))
    assert why in str(err.value)


def test_kernels_lower_through_triton_for_a_gpu(monkeypatch):
    """Forward and gradient traced as on a GPU and lowered for CUDA (Pallas's Triton lowering; the last step, Triton to
    PTX, runs in XLA's GPU compiler): one Triton call each way."""
    pytest.importorskip("jax.experimental.pallas.triton")
    monkeypatch.setattr(pallas, "_interpret", lambda: False)
    _, step, params, state, rpm = _case(OPTIONS["drag_ground"])

    def loss(rpm, state):
        return jnp.sum(step(params, state, rpm).pos ** 2)

    device = jax.sharding.AbstractDevice(device_kind="NVIDIA H100 80GB HBM3", num_cores=None, platform="cuda")
    with jax.sharding.use_abstract_mesh(jax.sharding.AbstractMesh((1,), ("x",), abstract_device=device)):
        forward = jax.jit(lambda r, s: step(params, s, r).pos).trace(rpm, state).lower(lowering_platforms=("cuda",))
        gradient = jax.jit(jax.grad(loss)).trace(rpm, state).lower(lowering_platforms=("cuda",))
    assert forward.as_text().count("xla.gpu.triton") == 1
    assert gradient.as_text().count("xla.gpu.triton") == 2
    # Triton's loads and stores of a block are not masked: every operand and result is whole blocks of drones (the
    # drones padded; the shared params one vector of a power of two).
    calls = [line.split(" : ")[-1] for line in gradient.as_text().splitlines() if "xla.gpu.triton" in line]
    sizes = [int(size) for call in calls for size in re.findall(r"tensor<(?:\d+x)?(\d+)x[fi]\d+>", call)]
    assert sizes and all(size % pallas.BLOCK == 0 or size & (size - 1) == 0 for size in sizes)
    assert any(size % pallas.BLOCK == 0 and size > WORLDS for size in sizes)
