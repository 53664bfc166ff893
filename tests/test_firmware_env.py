"""The firmware's setpoints as actions (``firmware_pos``, ``firmware_vel``; the ``firmware_hover`` task): what cflib
sends, flown by the firmware's PID cascade at every 1 ms tick inside the control step. The cascade itself is checked
against the firmware's C in tests/test_firmware.py; here, that the env flies it as `pid_tick` does, and refuses the
settings it cannot fly."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.control import firmware as fw

pytestmark = pytest.mark.unit


def test_a_velocity_action_is_cflibs_velocity_world_setpoint():
    """a = (0.5, 0, −0.5, 1): x, y, z velocity modes at (0.5, 0, −0.5) m/s, yaw rate mode at 90 deg/s, roll, pitch
    and quat disabled (crtp_commander_generic.c ``velocityDecoder``); ``firmware_pos``: x, y, z, yaw absolute."""
    env = jd.make("firmware_hover")
    setpoint = env.action_type.setpoint(jnp.array([[0.5, 0.0, -0.5, 1.0]]))
    np.testing.assert_array_equal(np.asarray(setpoint.mode), [[2, 2, 2, 0, 0, 2, 0]])
    np.testing.assert_allclose(np.asarray(setpoint.velocity), [[0.5, 0.0, -0.5]])
    np.testing.assert_allclose(np.asarray(setpoint.attitude_rate), [[0.0, 0.0, 90.0]])
    position = jd.make("firmware_hover", action_type="firmware_pos").action_type.setpoint(
        jnp.array([[0.25, -0.5, 0.5, -0.5]])
    )
    np.testing.assert_array_equal(np.asarray(position.mode), [[1, 1, 1, 0, 0, 1, 0]])
    np.testing.assert_allclose(np.asarray(position.position), [[0.5, -1.0, 1.0]])
    np.testing.assert_allclose(np.asarray(position.attitude), [[0.0, 0.0, -90.0]])


@pytest.mark.parametrize("action_type", ["firmware_vel", "firmware_pos", "firmware_ctbr"])
def test_the_env_flies_its_setpoint_as_the_firmware_loop_does(action_type):
    """Ten control steps of random actions from a random (tilted, moving) start: the env's drone where 200 ticks of
    `pid_tick` put it with the same setpoints, the same params and the controller as the env's reset leaves it
    (positions within 1e-5 m: XLA fuses the two programs differently)."""
    env = jd.make("firmware_hover", action_type=action_type)
    state = jax.jit(env.reset)(jax.random.key(4))
    actions = jax.random.uniform(jax.random.key(5), (10, 1, 4), minval=-1.0, maxval=1.0)
    if action_type == "firmware_ctbr":  # near the hover thrust and gentle rates, so that the drone stays up
        actions = (0.1 * actions).at[..., 0].add(0.19)
    step = jax.jit(env.step)
    tick_step = jd.make_step(jd.SimConfig(sim_freq=1000, ctrl_freq=1000, motor_dynamics=True))
    loop = fw.PidLoopState(drone=state.sim, controller=state.ctrl, tick=jnp.int32(0))
    one = jax.jit(lambda loop, sp: fw.pid_tick(tick_step, state.params, fw.PidControllerGains.crazyflie(), loop, sp))
    for action in actions:
        state = step(state, action)
        for _ in range(20):
            loop, _ = one(loop, env.action_type.setpoint(action))
    assert not bool(state.terminated) and int(loop.tick) == 200
    moved = float(jnp.max(jnp.abs(state.sim.pos - jax.jit(env.reset)(jax.random.key(4)).sim.pos)))
    assert moved > 0.05  # the setpoints moved the drone
    np.testing.assert_allclose(np.asarray(state.sim.pos), np.asarray(loop.drone.pos), atol=1e-5)
    np.testing.assert_allclose(np.asarray(state.sim.vel), np.asarray(loop.drone.vel), atol=1e-4)


def test_a_ctbr_action_turns_the_drone_at_its_body_rates():
    """``firmware_ctbr`` at the hover thrust with one body rate of 0.5 rad/s (a = 0.5 / 2π) at a time, for 0.5 s
    from level hover: the drone turns about that body axis in its sense (ω within 30 % of the setpoint after the
    loops' rise, yaw's through its attitude loop; the others' below 0.15 rad/s): the firmware's legacy pitch is
    handled. Thrust: 1000 PWM at a = −1, 60000 at 1 (crtp_commander_rpyt.c's range); modes: x, y, z disabled, roll,
    pitch and yaw rates."""
    env = jd.make("firmware_hover", action_type="firmware_ctbr", init_pos=[[0.0, 0.0, 1.0]], init_rpy=[[0.0] * 3])
    setpoint = env.action_type.setpoint(jnp.array([[-1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(np.asarray(setpoint.thrust), [1000.0, 60000.0])
    np.testing.assert_array_equal(np.asarray(setpoint.mode[0]), [0, 0, 0, 2, 2, 2, 0])
    hover = 2 * (36126.0 - 1000.0) / 59000.0 - 1  # cf2x's weight at the firmware's motor map, PWM per motor
    step = jax.jit(env.step)
    for axis in range(3):
        state = jax.jit(env.reset)(jax.random.key(0))
        action = jnp.zeros((1, 4)).at[0, 0].set(hover).at[0, 1 + axis].set(0.5 / (2 * np.pi))
        for _ in range(25):
            state = step(state, action)
        rates = np.asarray(state.sim.ang_vel[0])
        assert 0.35 < rates[axis] < 0.65, (axis, rates)
        assert np.all(np.abs(np.delete(rates, axis)) < 0.15), (axis, rates)


def test_the_controller_starts_at_the_drones_yaw():
    """At reset the controller's desired yaw is the drone's (as after the motors' idling), not 0: a drone started at
    yaw 120° holding a zero yaw rate keeps its heading."""
    env = jd.make("firmware_hover", init_pos=[[0.0, 0.0, 1.0]], init_rpy=[[0.0, 0.0, np.deg2rad(120.0)]])
    state = jax.jit(env.reset)(jax.random.key(0))
    np.testing.assert_allclose(float(state.ctrl.attitude_desired[0, 2]), 120.0, atol=1e-3)
    step = jax.jit(env.step)
    for _ in range(50):
        state = step(state, jnp.zeros((1, 4)))
    yaw = float(fw.firmware_state(state.sim).attitude[0, 2])
    assert abs(yaw - 120.0) < 1.0, yaw


def test_firmware_actions_refuse_what_the_firmware_cannot_fly():
    """The paper's 240 Hz physics, a 30 Hz control step (33.3 ticks), instant motors or the PyBullet backend: a
    ValueError naming what to pass; ``to_rpm`` refuses a firmware action (it is flown tick by tick)."""
    with pytest.raises(ValueError, match=r"sim_freq': 1000, 'ctrl_freq': F\} with F one of 100, 50"):
        jd.make("hover", action_type="firmware_vel")
    with pytest.raises(ValueError, match="multiple of 10 ticks per control step.*ctrl_freq=40"):
        jd.make("firmware_hover", ctrl_freq=40)
    with pytest.raises(ValueError, match=r"need motors that lag.*motor_tau_up"):
        jd.make("firmware_hover", randomize={})
    with pytest.raises(ValueError, match="backend='jax' only"):
        jd.envs.get_task("firmware_hover").config_cls(backend="pybullet")
    env = jd.make("firmware_hover")
    state = env.reset(jax.random.key(0))
    with pytest.raises(ValueError, match="firmware setpoint, flown tick by tick: use fly"):
        env.action_type.to_rpm(env.params, state.sim, state.ctrl, jnp.zeros((1, 4)), None, 0.02)
