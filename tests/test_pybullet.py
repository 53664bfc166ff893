"""The PyBullet backend: agreement with the JAX core, collisions and contacts, resources, bad input."""

import gc
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from optional import needs

needs("pybullet")
pytestmark = pytest.mark.pybullet

import pybullet  # noqa: E402

import jaxdrones as jd  # noqa: E402
from jaxdrones.backends.pybullet import PyBulletStep  # noqa: E402
from jaxdrones.rotations import quat_to_rotmat  # noqa: E402
from jaxdrones.scene import PAPER_OBSTACLES, Obstacle  # noqa: E402
from jaxdrones.state import CONTACT_DRONE, CONTACT_GROUND, CONTACT_OBSTACLE  # noqa: E402

MODELS = ("cf2x", "cf2p", "racer")


def numpy_state(state):
    return jax.tree.map(np.asarray, state)


def angle_between(q1, q2):
    """Rotation angle (rad) between unit quaternions [..., 4]."""
    return 2 * np.arccos(np.clip(np.abs(np.sum(q1 * q2, axis=-1)), 0.0, 1.0))


def free_flight(model, effects):
    """Three drones for 1 s (240 Hz physics, 48 Hz control): tilted, spinning, moving, with ±3 % RPM wobbles.

    With effects on, drone 0 starts 8 cm above the ground (ground effect), drone 1 0.4 m above it and 0.15 m
    aside (downwash on drone 0), and drone 2 moves at 1-2 m/s (drag).
    """
    config = jd.SimConfig(n_drones=3, sim_freq=240, ctrl_freq=48, drag=effects, ground_effect=effects, downwash=effects)
    params = jd.load_params(model)
    low = 0.08 if effects else 1.0
    state = jd.init_state(
        config,
        pos=np.array([[0.0, 0.0, low], [0.15, -0.02, low + 0.4], [1.0, 1.0, 1.5]]),
        rpy=np.array([[0.05, -0.04, 0.3], [0.1, 0.05, -0.2], [-0.2, 0.1, 1.0]]),
        vel=np.array([[0.1, 0.0, 0.05], [0.0, 0.2, 0.0], [1.5, -1.0, 0.3]]),
        ang_vel=np.array([[0.3, -0.2, 0.5], [0.0, 0.4, -1.0], [1.0, 0.5, 2.0]]),
    )
    steps = config.ctrl_freq
    phase = np.random.default_rng(0).uniform(0, 2 * np.pi, (1, 3, 4))
    # drone 0 near hover RPM: it lifts off slowly in ground effect and stays below drone 1 (the racer's larger
    # propellers feel a stronger ground effect)
    lift_off = {"cf2x": 1.03, "cf2p": 1.03, "racer": 0.92}[model] if effects else 1.0
    base = np.array([lift_off, 1.01, 1.0])[None, :, None]
    rpms = float(params.hover_rpm) * (base + 0.03 * np.sin(0.4 * np.arange(steps)[:, None, None] + phase))
    return config, params, state, rpms


@pytest.mark.parametrize("effects", [False, True], ids=["effects_off", "effects_on"])
@pytest.mark.parametrize("model", MODELS)
def test_backends_agree_in_free_flight(x64, model, effects):
    """Same state and RPM sequence for 1 s: PyBullet and the JAX core agree to ≤ 1 mm and ≤ 0.01 rad (acceptance),
    and in fact to round-off, because both integrate the same forces with semi-implicit Euler."""
    config, params, state, rpms = free_flight(model, effects)
    jax_states = jd.rollout(jd.make_step(config), params, state, rpms)
    with jd.make_step(config, backend="pybullet") as step:
        s = numpy_state(state)
        for rpm in rpms:
            s = step(params, s, rpm)
            assert not s.contact.any(), "the scenario must stay in free flight"
    pos_err = np.max(np.linalg.norm(s.pos - np.asarray(jax_states.pos[-1]), axis=-1))
    att_err = np.max(angle_between(s.quat, np.asarray(jax_states.quat[-1])))
    vel_err = np.max(np.abs(s.vel - np.asarray(jax_states.vel[-1])))
    print(
        f"\nMEASURED {model} effects={effects}: after 1 s, position {pos_err:.2e} m, attitude {att_err:.2e} rad, "
        f"velocity {vel_err:.2e} m/s; travelled {np.linalg.norm(s.pos - np.asarray(state.pos), axis=-1).max():.2f} m"
    )
    assert pos_err <= 1e-3 and att_err <= 0.01
    assert pos_err <= 1e-9 and att_err <= 1e-7  # what is reached: float64 round-off
    if effects:  # the effects were actually in play
        assert float(np.asarray(jax_states.pos[:, 0, 2]).min()) < 0.12


def test_effects_change_the_pybullet_flight(x64):
    """Each effect moves the drones in Bullet as in the JAX core (a check that they are applied at all)."""
    _, params, state, rpms = free_flight("cf2x", True)
    finals = {}
    for name in ("none", "drag", "ground_effect", "downwash"):
        config = jd.SimConfig(n_drones=3, sim_freq=240, ctrl_freq=48, **({} if name == "none" else {name: True}))
        with jd.make_step(config, backend="pybullet") as step:
            s = numpy_state(state)
            for rpm in rpms[:24]:
                s = step(params, s, rpm)
        finals[name] = s.pos
    assert finals["ground_effect"][0, 2] > finals["none"][0, 2] + 1e-3  # lifts the low drone
    assert finals["downwash"][0, 2] < finals["none"][0, 2] - 1e-3  # pushes the lower drone down
    moving = np.asarray(state.vel[2])
    slowdown = (finals["none"][2] - finals["drag"][2]) @ moving
    assert slowdown > 1e-4  # drag opposes the motion


def test_angular_velocity_is_body_frame(x64):
    """A drone yawed by 90° spinning about its body x: Bullet's world-frame rate is converted back to body x."""
    config = jd.SimConfig()
    params = jd.load_params("cf2x")
    state = numpy_state(jd.init_state(config, pos=[[0, 0, 1.0]], rpy=[[0, 0, np.pi / 2]], ang_vel=[[2.0, 0, 0]]))
    hover = np.full((1, 4), float(params.hover_rpm))
    with jd.make_step(config, backend="pybullet") as step:
        out = step(params, state, hover)
    np.testing.assert_allclose(out.ang_vel, [[2.0, 0.0, 0.0]], atol=1e-9)


def test_rollout_jit_and_vmap_match_eager_calls(x64):
    """Inside lax.scan (jd.rollout) and jit∘vmap the step runs as a host callback and gives the same states."""
    config = jd.SimConfig(n_drones=2, sim_freq=240, ctrl_freq=48, drag=True, downwash=True)
    params = jd.load_params("cf2x")
    state = jd.init_state(config, pos=np.array([[[0, 0, 1.0], [0.02, 0, 1.3]], [[1, 0, 2.0], [1, 0.1, 2.5]]]))
    rpms = np.full((10, 2, 2, 4), 1.02 * float(params.hover_rpm))
    with jd.make_step(config, backend="pybullet") as step:
        scanned = jd.rollout(step, params, state, rpms)
        s = numpy_state(state)
        for rpm in rpms:
            s = step(params, s, rpm)
        mapped = jax.jit(jax.vmap(lambda st, r: step(params, st, r)))(state, rpms[0])
        assert step.n_worlds == 2
    assert isinstance(scanned.pos, jax.Array)
    np.testing.assert_allclose(np.asarray(scanned.pos[-1]), s.pos, atol=1e-12)
    np.testing.assert_allclose(np.asarray(mapped.pos), np.asarray(scanned.pos[0]), atol=1e-12)


def test_concrete_inputs_give_numpy():
    config = jd.SimConfig(n_drones=2)
    params = jd.load_params("cf2x")
    state = jd.init_state(config)
    with jd.make_step(config, backend="pybullet") as step:
        out_jax = step(params, state, jnp.zeros((2, 4)))
        out_np = step(params, numpy_state(state), np.zeros((2, 4), np.float32))
    assert isinstance(out_jax.pos, np.ndarray) and isinstance(out_np.pos, np.ndarray)  # host arrays either way
    assert out_np.pos.dtype == state.pos.dtype and out_np.contact.dtype == np.int32
    np.testing.assert_allclose(np.asarray(out_jax.pos), out_np.pos)


# ------------------------------------------------------------------------------------------------ collisions


def fly(step, params, state, rpm, n):
    states = []
    for _ in range(n):
        state = step(params, state, rpm)
        states.append(state)
    return jax.tree.map(lambda *xs: np.stack(xs), *states)


@pytest.mark.parametrize("model", MODELS)
def test_dropped_drone_rests_on_the_ground(model):
    config = jd.SimConfig(sim_freq=240, ctrl_freq=48)
    params = jd.load_params(model)
    state = numpy_state(jd.init_state(config, pos=[[0, 0, 1.0]]))
    with jd.make_step(config, backend="pybullet") as step:
        track = fly(step, params, state, np.zeros((1, 4)), 150)  # 3 s
    rest = float(params.collision_height) / 2
    assert abs(track.pos[-1, 0, 2] - rest) < 1e-3
    assert np.all(np.abs(track.pos[-24:, 0, 2] - rest) < 1e-3)  # still for the last 0.5 s
    assert np.linalg.norm(track.vel[-1]) < 1e-2
    assert track.contact[-1, 0] == CONTACT_GROUND and bool(track.ground_contact[-1, 0])
    # Hitting the ground at 4.4 m/s (1.8 cm per 240 Hz step), Bullet's contact lets the cylinder sink up to ~3 cm
    # for a step or two before pushing it out: it never falls through and is back above the ground at once.
    below = np.flatnonzero(track.pos[:, 0, 2] < 0)
    assert track.pos[:, 0, 2].min() > rest - 0.035 and len(below) <= 2


@pytest.mark.parametrize("yaw", [0.0, np.pi / 4], ids=["yaw0", "yaw45"])
def test_drone_flown_into_a_wall_stops_and_reports_it(yaw):
    """At 2 m/s into a wall the drone stops at the wall, propellers included, and reports an obstacle contact."""
    config = jd.SimConfig(sim_freq=240, ctrl_freq=48)
    params = jd.load_params("cf2x")
    face = 0.95
    wall = Obstacle("box", size=(0.1, 2.0, 2.0), pos=(face + 0.05, 0.0, 1.0))
    state = numpy_state(jd.init_state(config, pos=[[0, 0, 1.0]], rpy=[[0, 0, yaw]], vel=[[2.0, 0, 0]]))
    hover = np.full((1, 4), float(params.hover_rpm))
    with jd.make_step(config, backend="pybullet", obstacles=[wall]) as step:
        track = fly(step, params, state, hover, 48)  # 1 s
    # The farthest x of each propeller disk (centre c = p + R r_i, normal n = R e_z, radius ρ): c_x + ρ √(1 - n_x²).
    rotmat = np.asarray(quat_to_rotmat(jnp.asarray(track.quat[:, 0])))
    centres = track.pos[:, 0, None, :] + np.einsum("tij,kj->tki", rotmat, np.asarray(params.prop_pos))
    tips = centres[..., 0] + float(params.prop_radius) * np.sqrt(1 - rotmat[:, None, 0, 2] ** 2)
    print(f"\nMEASURED wall at x = {face} m, yaw {yaw:.2f}: farthest propeller tip x = {tips.max():.4f} m")
    assert tips.max() < face + 5e-3  # no propeller entered the wall beyond Bullet's contact tolerance at 2 m/s
    assert np.any(track.contact[:, 0] & CONTACT_OBSTACLE) and bool(track.collided.any())
    assert track.vel[-1, 0, 0] < 0.5  # stopped (or bounced back)


def test_drones_flown_into_each_other_collide():
    config = jd.SimConfig(n_drones=2, sim_freq=240, ctrl_freq=48)
    params = jd.load_params("cf2x")
    state = numpy_state(jd.init_state(config, pos=[[-0.5, 0, 1.0], [0.5, 0, 1.0]], vel=[[1.5, 0, 0], [-1.5, 0, 0]]))
    hover = np.full((2, 4), float(params.hover_rpm))
    with jd.make_step(config, backend="pybullet") as step:
        track = fly(step, params, state, hover, 30)
    gap = track.pos[:, 1, 0] - track.pos[:, 0, 0]
    assert gap.min() > 2 * float(params.collision_radius) - 5e-3  # never interpenetrate, never pass
    hit = track.contact & CONTACT_DRONE
    assert np.any(hit[:, 0]) and np.any(hit[:, 1])
    assert track.vel[-1, 0, 0] < 0.5 and track.vel[-1, 1, 0] > -0.5


def test_paper_obstacles_load_and_are_reported():
    """A drone dropped onto the paper scene's first box reports an obstacle contact, not a ground one."""
    config = jd.SimConfig(sim_freq=240, ctrl_freq=48)
    params = jd.load_params("cf2x")
    box = PAPER_OBSTACLES[0]
    top = box.pos[2] + box.size[2] / 2
    state = numpy_state(jd.init_state(config, pos=[[box.pos[0], box.pos[1], top + 0.2]]))
    with jd.make_step(config, backend="pybullet", obstacles="paper") as step:
        track = fly(step, params, state, np.zeros((1, 4)), 48)
    assert abs(track.pos[-1, 0, 2] - (top + float(params.collision_height) / 2)) < 2e-3
    assert track.contact[-1, 0] == CONTACT_OBSTACLE


def test_damping_is_off_unless_asked():
    """Coasting at 1 m/s with gravity balanced: no velocity loss by default; Bullet's 0.04/s damping if asked."""
    config = jd.SimConfig(sim_freq=240, ctrl_freq=240)
    params = jd.load_params("cf2x")
    state = numpy_state(jd.init_state(config, pos=[[0, 0, 1.0]], vel=[[1.0, 0, 0]]))
    hover = np.full((1, 4), float(params.hover_rpm))
    speeds = {}
    for damping in (False, True):
        with jd.make_step(config, backend="pybullet", damping=damping) as step:
            speeds[damping] = fly(step, params, state, hover, 240).vel[-1, 0, 0]
    assert abs(speeds[False] - 1.0) < 1e-5
    assert speeds[True] < 0.97  # docs/physics.md §5.2: a = -(0.04 + 0.04|v|) v


def test_params_changes_reach_the_bodies(x64):
    """Heavier params (per world) give the Bullet bodies the new mass, as in the JAX core."""
    config = jd.SimConfig()
    base = jd.load_params("cf2x")
    heavy = base.replace(mass=base.mass * 1.5)
    team = jax.tree.map(lambda a, b: jnp.stack([a, b])[:, None], base, heavy)  # per-world params [2, 1]
    state = jd.init_state(config, pos=np.array([[[0, 0, 1.0]], [[0, 0, 1.0]]]))
    rpm = np.full((2, 1, 4), float(base.hover_rpm))
    expected = jd.rollout(jd.make_step(config), team, state, np.stack([rpm] * 24))
    with jd.make_step(config, backend="pybullet") as step:
        step(base.replace(mass=base.mass * 0.5), state, rpm)  # bodies built with other params first
        got = jd.rollout(step, team, state, np.stack([rpm] * 24))
    np.testing.assert_allclose(np.asarray(got.pos), np.asarray(expected.pos), atol=1e-12)
    assert float(got.pos[-1, 1, 0, 2]) < 0.99 < float(got.pos[-1, 0, 0, 2])  # the heavy one sinks


# ------------------------------------------------------------------------------------------------ resources


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_no_leaked_clients_or_files_over_1000_cycles():
    config = jd.SimConfig(n_drones=2)
    params = jd.load_params("cf2x")
    state = numpy_state(jd.init_state(config))
    rpm = np.zeros((2, 4))
    with jd.make_step(config, backend="pybullet") as warm:  # first use loads shared libraries and data
        warm(params, state, rpm)
    fds = open_fds()
    clients = set()
    for cycle in range(1000):
        if cycle % 2:
            with jd.make_step(config, backend="pybullet", obstacles="paper") as step:
                step(params, state, rpm)
                clients.update(step.clients)
        else:
            step = jd.make_step(config, backend="pybullet")
            step(params, state, rpm)
            clients.update(step.clients)
            step.close()
        assert not step.clients
    probe = pybullet.connect(pybullet.DIRECT)
    pybullet.disconnect(probe)
    print(
        f"\nMEASURED 1000 create/step/close cycles: {len(clients)} distinct client ids used, open files "
        f"{fds} -> {open_fds()}, next new client id {probe}"
    )
    assert probe <= 1, f"a new client got id {probe}: earlier clients were not released"
    assert open_fds() <= fds
    assert clients and all(not pybullet.isConnected(c) for c in clients)


def test_garbage_collected_step_releases_its_worlds():
    config = jd.SimConfig()
    params = jd.load_params("cf2x")
    step = jd.make_step(config, backend="pybullet")
    step(params, numpy_state(jd.init_state(config)), np.zeros((1, 4)))
    (client,) = step.clients
    assert pybullet.isConnected(client)
    del step
    gc.collect()
    assert not pybullet.isConnected(client)


def test_a_failing_world_does_not_take_the_others_down():
    config = jd.SimConfig()
    params = jd.load_params("cf2x")
    state = numpy_state(jd.init_state(config, pos=np.array([[[0, 0, 1.0]]] * 3)))
    hover = np.full((3, 1, 4), float(params.hover_rpm))
    with jd.make_step(config, backend="pybullet") as step:
        good = step(params, state, hover)
        bad = jax.tree.map(np.copy, state)
        bad.pos[1] = np.nan
        out = step(params, bad, hover)
        assert np.all(np.isnan(out.pos[1])) and np.all(np.isfinite(out.pos[[0, 2]]))
        np.testing.assert_allclose(out.pos[[0, 2]], good.pos[[0, 2]])
        pybullet.disconnect(step.clients[1])  # a Bullet world that dies
        out = step(params, state, hover)
        assert np.all(np.isnan(out.pos[1])) and np.all(np.isfinite(out.pos[[0, 2]]))
        out = step(params, state, hover)  # rebuilt
        np.testing.assert_allclose(out.pos, good.pos)


# ------------------------------------------------------------------------------------------------ bad input


def test_bad_options_and_calls():
    config = jd.SimConfig(n_drones=2)
    params = jd.load_params("cf2x")
    state = numpy_state(jd.init_state(config))
    with pytest.raises(ValueError, match="unknown PyBullet backend option"):
        jd.make_step(config, backend="pybullet", obstacle=True)
    with pytest.raises(ValueError, match="jax backend takes no options"):
        jd.make_step(config, obstacles=True)
    with pytest.raises(ValueError, match="unknown backend"):
        jd.make_step(config, backend="bullet")
    with pytest.raises(ValueError, match="renderer"):
        jd.make_step(config, backend="pybullet", renderer="vulkan")
    with pytest.raises(ValueError, match="not found"):
        jd.make_step(config, backend="pybullet", obstacles=["/no/such/file.urdf"])
    with pytest.raises(ValueError, match="obstacles"):
        jd.make_step(config, backend="pybullet", obstacles=[3.0])
    with pytest.raises(ValueError, match="size"):
        Obstacle("box", size=(0.1, 0.1))
    step = jd.make_step(config, backend="pybullet")
    with pytest.raises(ValueError, match=r"rpm must have shape \(2, 4\)"):
        step(params, state, np.zeros((1, 4)))
    with pytest.raises(ValueError, match="NaN"):
        step(params, state, np.full((2, 4), np.nan))
    with pytest.raises(ValueError, match="real"):
        step(params, state, np.zeros((2, 4), bool))
    with pytest.raises(ValueError, match="diagonal inertia"):
        inertia = np.asarray(params.inertia).copy()
        inertia[0, 1] = inertia[1, 0] = 1e-6
        step(params.replace(inertia=jnp.asarray(inertia)), state, np.zeros((2, 4)))
    step.close()
    with pytest.raises(RuntimeError, match="closed"):
        step(params, state, np.zeros((2, 4)))
    assert isinstance(step, PyBulletStep)
