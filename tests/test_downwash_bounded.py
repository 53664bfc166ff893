"""The bounded downwash (``SimConfig(downwash="bounded")``, `jaxdrones.physics.aerodynamics.downwash_force` with
``bounded=BOUNDED_DOWNWASH``, docs/physics.md §6.5): hand-computed force and step, the thrusts' part, the neighbour
list, the hand-written adjoint against JAX's derivative, and the PyBullet backend against the JAX core."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.physics import aerodynamics
from jaxdrones.physics.aerodynamics import BOUNDED_DOWNWASH, DOWNWASH_THRUST_REF

pytestmark = pytest.mark.unit


def _expected(params, pos, thrust):
    """The bounded form in NumPy: per lower drone j, the sum over the drones i above it (docs/physics.md §6.5)."""
    c1, c2, c3, soft = BOUNDED_DOWNWASH
    out = np.zeros(len(pos))
    for j in range(len(pos)):
        for i in range(len(pos)):
            dz = pos[i, 2] - pos[j, 2]
            if dz <= 0:
                continue
            d2 = np.sum((pos[i, :2] - pos[j, :2]) ** 2)
            scale = thrust[j] / DOWNWASH_THRUST_REF * np.sqrt(thrust[i] / DOWNWASH_THRUST_REF)
            alpha = c1 * (float(params.prop_radius) / 4) ** 2 * scale / (dz**2 + soft**2)
            out[j] -= alpha * np.exp(-0.5 * d2 / (c2 * dz + c3) ** 2)
    return out


def test_hand_computed_force_and_step(x64):
    """Three drones stacked loosely, each at its own thrust: the force equals the NumPy formula to 1e-12, the top
    drone feels none, a heavier thrust above pushes harder; one step from rest at hover RPM accelerates each drone by
    (Σ kf rpm² + F) / m − g."""
    params = jd.load_params("cf2x")
    pos = np.array([[0.0, 0.0, 0.5], [0.04, -0.02, 0.8], [0.01, 0.03, 1.1]])
    thrust = np.array([0.26, 0.30, 0.40])
    force = np.asarray(aerodynamics.downwash_force(params, jnp.asarray(pos), bounded=BOUNDED_DOWNWASH, thrust=thrust))
    np.testing.assert_allclose(force, _expected(params, pos, thrust), rtol=1e-12)
    assert force[2] == 0.0 and force[0] < force[1] < 0
    heavier = aerodynamics.downwash_force(params, jnp.asarray(pos), bounded=BOUNDED_DOWNWASH, thrust=thrust * [1, 1, 2])
    assert float(heavier[0]) < force[0]

    config = jd.SimConfig(n_drones=3, sim_freq=240, ctrl_freq=240, downwash="bounded")
    hover = float(params.hover_rpm)
    state = jd.init_state(config, pos=pos, rpm=np.full((3, 4), hover))
    out = jd.make_step(config)(params, state, jnp.full((3, 4), hover))
    lift = 4 * float(params.kf) * hover**2
    push = _expected(params, pos, np.full(3, lift))
    acc = (lift + push) / float(params.mass) - float(params.gravity)
    np.testing.assert_allclose(np.asarray(out.vel[:, 2]), config.dt * acc, rtol=1e-9, atol=1e-15)


def test_neighbor_list_matches_all_pairs(x64, rng):
    """A 64-drone swarm 0.12 m apart at random heights and thrusts: the cell list's force equals the all-pairs one
    with the same cut-off to 1e-12 (the upper drones' thrusts gathered with their positions)."""
    from jaxdrones.physics.neighbors import cell_candidates

    params = jd.load_params("cf2x")
    xy = np.stack(np.meshgrid(np.arange(8), np.arange(8)), -1).reshape(-1, 2) * 0.12
    pos = jnp.asarray(np.concatenate([xy, rng.uniform(0.5, 1.5, (len(xy), 1))], -1))
    thrust = jnp.asarray(rng.uniform(0.2, 0.4, len(xy)))
    cand = cell_candidates(pos[:, 0], pos[:, 1], 0.25, 16)
    kw = dict(bounded=BOUNDED_DOWNWASH, thrust=thrust, cutoff=0.25)
    full = aerodynamics.downwash_force(params, pos, **kw)
    near = aerodynamics.downwash_force(params, pos, neighbors=cand, **kw)
    assert float(jnp.min(full)) < -1e-3
    np.testing.assert_allclose(near, full, rtol=1e-12, atol=1e-18)


def test_adjoint_matches_the_derived_derivative(x64):
    """The hand-written adjoint takes the downwash as an input, which now depends on the RPM through the thrusts:
    its gradient w.r.t. the commands and the start state equals JAX's derived one (``adjoint=False``) to 1e-10."""
    config = jd.SimConfig(n_drones=2, sim_freq=240, ctrl_freq=48, downwash="bounded", ground_effect=True)
    params = jd.load_params("cf2x")
    state = jd.init_state(config, pos=np.array([[0.0, 0.0, 0.4], [0.02, 0.01, 0.7]]))
    rpm = jnp.full((2, 4), float(params.hover_rpm)) * jnp.array([[1.0], [1.05]])

    def loss(step, rpm, pos):
        out = step(params, state.replace(pos=pos), rpm)
        return jnp.sum(out.vel[..., 2] + out.pos[..., 0])

    grads = [
        jax.grad(lambda r, p, a=a: loss(jd.make_step(dataclasses.replace(config, adjoint=a)), r, p), (0, 1))(
            rpm, state.pos
        )
        for a in (True, False)
    ]
    for ours, derived in zip(grads[0], grads[1], strict=True):
        np.testing.assert_allclose(ours, derived, rtol=1e-10, atol=1e-12 * float(jnp.max(jnp.abs(derived))))
    assert float(jnp.abs(grads[1][0][0, 0])) > 0  # the lower drone's push depends on its own RPM


def test_chosen_by_name():
    assert jd.SimConfig(downwash="bounded").effects.downwash == "bounded"
    assert jd.make("crossing", downwash="bounded").config.sim.downwash == "bounded"
    with pytest.raises(ValueError, match=r"'bounded' \(the paper's form fitted to real flights\).*did you mean"):
        jd.SimConfig(downwash="bounde")


@pytest.mark.pybullet
def test_jax_and_pybullet_agree(x64):
    """Two drones 0.3 m apart in height, 2 cm aside, for 0.25 s (240 Hz physics, 48 Hz control) on both backends:
    the states agree to round-off, and the lower drone sank against the flight without downwash."""
    config = jd.SimConfig(n_drones=2, sim_freq=240, ctrl_freq=48, downwash="bounded")
    params = jd.load_params("cf2x")
    state = jd.init_state(config, pos=np.array([[0.0, 0.0, 1.5], [0.02, 0.0, 1.2]]))
    rpms = np.full((12, 2, 4), float(params.hover_rpm))
    jax_states = jd.rollout(jd.make_step(config), params, state, rpms)
    off = jd.rollout(jd.make_step(dataclasses.replace(config, downwash=False)), params, state, rpms)
    with jd.make_step(config, backend="pybullet") as step:
        s = jax.tree.map(np.asarray, state)
        for rpm in rpms:
            s = step(params, s, rpm)
    assert np.max(np.abs(s.pos - np.asarray(jax_states.pos[-1]))) <= 1e-9
    assert float(jax_states.pos[-1, 1, 2]) < float(off.pos[-1, 1, 2]) - 1e-4
