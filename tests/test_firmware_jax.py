"""`jaxdrones.control.firmware` without the firmware: batched over ``[W, D]`` as one drone at a time, jittable,
and a level hover at the thrust base (the checks against the firmware's C are tests/test_firmware.py's)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from firmware_c import prime, random_ticks, run_jax_pid

from jaxdrones.control import firmware as fw

pytestmark = pytest.mark.unit


def _level_at_1m(n: int) -> fw.FirmwareState:
    """``n`` drones level and still, 1 m up above the origin."""
    return fw.FirmwareState(
        attitude=jnp.zeros((n, 3)),
        quat=jnp.zeros((n, 4)).at[:, 3].set(1.0),
        position=jnp.zeros((n, 3)).at[:, 2].set(1.0),
        velocity=jnp.zeros((n, 3)),
        gyro=jnp.zeros((n, 3)),
    )


def test_a_batch_of_drones_flies_as_each_drone_alone():
    """2 worlds × 3 drones, each its own random sequence of 300 ticks: the batched call's outputs are each drone's
    alone, to float32 rounding (the two compile to different programs)."""
    rng = np.random.default_rng(3)
    sequences = [prime(random_ticks(rng, 300)) for _ in range(6)]
    stacked = {
        k: np.stack([s[k] for s in sequences], axis=1).reshape(301, 2, 3, *sequences[0][k].shape[1:])
        for k in sequences[0]
    }
    batched = run_jax_pid(stacked, (2, 3))
    for b, seq in enumerate(sequences):
        alone = run_jax_pid(seq)
        for name in ("roll", "pitch", "yaw", "thrust"):
            got = np.asarray(getattr(batched, name)).reshape(301, 6)[:, b]
            want = np.asarray(getattr(alone, name))
            if name == "thrust":
                np.testing.assert_allclose(got, want, rtol=1e-6, err_msg=f"drone {b}, {name}")
            else:
                assert np.max(np.abs(got - want)) <= 1, f"drone {b}, {name}"  # an int16 truncated at a rounding


def test_a_level_drone_holding_its_position_gets_the_thrust_base_and_no_torque():
    """At the setpoint, level, still: the first position tick gives thrustBase (36000) and zero roll, pitch, yaw;
    the power distribution gives each motor 36000."""
    setpoint = fw.Setpoint.zeros((4,))
    setpoint = setpoint.replace(
        mode=jnp.broadcast_to(jnp.array([1, 1, 1, 0, 0, 1, 0], jnp.int32), (4, 7)),
        position=jnp.zeros((4, 3)).at[:, 2].set(1.0),
    )
    state = _level_at_1m(4)
    _, control = fw.controller_pid(fw.PidControllerGains.crazyflie(), fw.controller_pid_init((4,)), setpoint, state, 0)
    np.testing.assert_array_equal(np.asarray(control.thrust), 36000.0)
    assert not np.any(np.asarray(control.roll)) and not np.any(np.asarray(control.yaw))
    motors = fw.power_distribution_cap(fw.power_distribution_legacy(control))
    np.testing.assert_array_equal(np.asarray(motors), 36000)


def test_the_firmware_state_of_a_drone_state_follows_the_firmwares_frames():
    """A drone pitched by +10° (about body y) and yawed by 30° reads attitude (0, −10, 30): the firmware's legacy
    frame inverts the pitch; the gyro is the body rates in deg/s."""
    import jaxdrones as jd

    state = jd.init_state(jd.SimConfig(), rpy=np.deg2rad([[0.0, 10.0, 30.0]]), ang_vel=[[1.0, 0.0, 0.0]])
    firmware = fw.firmware_state(state)
    np.testing.assert_allclose(np.asarray(firmware.attitude), [[0.0, -10.0, 30.0]], atol=1e-4)
    np.testing.assert_allclose(np.asarray(firmware.gyro), [[np.rad2deg(1.0), 0.0, 0.0]], rtol=1e-6)


def test_the_loop_refuses_a_physics_step_longer_than_a_tick():
    """`pid_tick` with the default 240 Hz physics (30 Hz control): a ValueError naming the 1 ms step it needs."""
    import jaxdrones as jd

    config = jd.SimConfig()
    loop = fw.pid_loop_init(jd.init_state(config))
    with pytest.raises(ValueError, match=r"1 ms tick: SimConfig\(sim_freq=1000, ctrl_freq=1000"):
        fw.pid_tick(
            jd.make_step(config),
            jd.load_params("cf2x"),
            fw.PidControllerGains.crazyflie(),
            loop,
            fw.Setpoint.zeros((1,)),
        )


def test_mellinger_at_its_setpoint_asks_for_the_weight_and_holds_between_its_ticks():
    """Level and still at a position setpoint: the thrust is mass_thrust · m g (132000 · 0.029 · 9.81) and no
    moment; on an odd tick the last control is held and the memory unchanged."""
    setpoint = fw.Setpoint.zeros((3,)).replace(
        mode=jnp.broadcast_to(jnp.array([1, 1, 1, 0, 0, 1, 0], jnp.int32), (3, 7)),
        position=jnp.zeros((3, 3)).at[:, 2].set(1.0),
    )
    state = _level_at_1m(3)
    gains = fw.MellingerGains.crazyflie()
    memory, control = fw.controller_mellinger(gains, fw.mellinger_init((3,)), setpoint, state, 0)
    np.testing.assert_allclose(np.asarray(control.thrust), 132000 * 0.029 * 9.81, rtol=1e-6)
    assert not np.any(np.asarray(control.roll)) and not np.any(np.asarray(control.pitch))
    moved = state.replace(position=state.position.at[:, 0].set(0.5))
    held, again = fw.controller_mellinger(gains, memory, setpoint, moved, 1)
    np.testing.assert_array_equal(np.asarray(again.thrust), np.asarray(control.thrust))
    np.testing.assert_array_equal(np.asarray(held.i_error), np.asarray(memory.i_error))


def test_many_ticks_at_once_fly_as_one_tick_at_a_time():
    """`pid_ticks` (its schedule written into the program where the start is a multiple of 10 ticks, a scan of
    `pid_tick` elsewhere) against 60 calls of `pid_tick`: 6 worlds from random starts, a position setpoint for 20
    ticks, then a velocity setpoint (a change of mode: the PIDs' reset) for 20 more, then body rates with a manual
    thrust for 20 more, from tick 0 and from tick 3. Positions within 1e-5 m, the int16 outputs within 1 (float32
    rounding: XLA fuses the two programs differently)."""
    import jax

    from jaxdrones.examples.firmware_in_the_loop import physics

    step, params, config = physics()
    rng = np.random.default_rng(5)
    import jaxdrones as jd

    start = jd.init_state(
        config,
        pos=rng.uniform(0.5, 1.5, (6, 1, 3)),
        rpy=rng.uniform(-0.2, 0.2, (6, 1, 3)),
        rpm=np.full((6, 1, 4), float(params.hover_rpm)),
    )
    gains = fw.PidControllerGains.crazyflie()
    hold = fw.Setpoint.zeros((6, 1)).replace(
        mode=jnp.broadcast_to(jnp.array([1, 1, 1, 0, 0, 1, 0], jnp.int32), (6, 1, 7)),
        position=jnp.asarray(rng.uniform(0.5, 1.5, (6, 1, 3)), jnp.float32),
    )
    move = fw.Setpoint.zeros((6, 1)).replace(
        mode=jnp.broadcast_to(jnp.array([2, 2, 2, 0, 0, 2, 0], jnp.int32), (6, 1, 7)),
        velocity=jnp.asarray(rng.uniform(-0.5, 0.5, (6, 1, 3)), jnp.float32),
        attitude_rate=jnp.zeros((6, 1, 3)).at[..., 2].set(30.0),
    )
    rates = fw.Setpoint.zeros((6, 1)).replace(  # z modeDisable, a manual thrust above 0: still on the schedule
        mode=jnp.broadcast_to(jnp.array([0, 0, 0, 2, 2, 2, 0], jnp.int32), (6, 1, 7)),
        thrust=jnp.full((6, 1), 37000.0),
        attitude_rate=jnp.asarray(rng.uniform(-30, 30, (6, 1, 3)), jnp.float32),
    )
    one = jax.jit(lambda loop, sp: fw.pid_tick(step, params, gains, loop, sp))
    many = jax.jit(lambda loop, sp: fw.pid_ticks(step, params, gains, loop, sp, 20))
    for tick in (0, 3):
        a = b = fw.pid_loop_init(start, tick=tick)
        for setpoint in (hold, move, rates):
            for _ in range(20):
                a, pwm_a = one(a, setpoint)
            b, pwm_b = many(b, setpoint)
        assert int(b.tick) == tick + 60
        np.testing.assert_allclose(np.asarray(b.drone.pos), np.asarray(a.drone.pos), atol=1e-5, err_msg=f"{tick=}")
        assert np.max(np.abs(np.asarray(pwm_a) - np.asarray(pwm_b))) <= 4, f"{tick=}"  # ±1 on each of 4 terms
        control_a, control_b = a.controller.control, b.controller.control
        for name in ("roll", "pitch", "yaw"):
            assert np.max(np.abs(np.asarray(getattr(control_a, name)) - np.asarray(getattr(control_b, name)))) <= 1
        np.testing.assert_allclose(np.asarray(control_b.thrust), np.asarray(control_a.thrust), rtol=1e-5)


def test_many_ticks_need_a_positive_count():
    """`pid_ticks` with 0 ticks: a ValueError naming a positive int."""
    import jaxdrones as jd
    from jaxdrones.examples.firmware_in_the_loop import physics

    step, params, config = physics()
    loop = fw.pid_loop_init(jd.init_state(config))
    with pytest.raises(ValueError, match="ticks must be a positive int, got 0"):
        fw.pid_ticks(step, params, fw.PidControllerGains.crazyflie(), loop, fw.Setpoint.zeros((1,)), 0)


def test_brescianini_at_its_setpoint_asks_for_the_weight_and_no_torque():
    """Level, still, at its position setpoint: the update gives the collective acceleration g, so a thrust of
    CF_MASS · 9.81 N, and no torque; z modeDisable turns the output off. With ``mixing_factor`` 0 (the reduced
    attitude control) a yaw error asks for no yaw rate; at 1 (the default, full) it does."""
    gains = fw.BrescianiniGains.crazyflie()
    setpoint = fw.Setpoint.zeros((2,)).replace(
        mode=jnp.asarray([[1, 1, 1, 0, 0, 1, 0], [1, 1, 0, 0, 0, 1, 0]], jnp.int32),
        position=jnp.zeros((2, 3)).at[:, 2].set(1.0),
    )
    state = _level_at_1m(2)
    memory, control = fw.controller_brescianini(gains, fw.brescianini_init((2,)), setpoint, state, 0)
    np.testing.assert_allclose(np.asarray(control.thrust), [0.029 * 9.81, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(control.torque), 0.0)
    turned = setpoint.replace(attitude=jnp.zeros((2, 3)).at[:, 2].set(45.0))
    full, _ = fw.controller_brescianini(gains, memory, turned, state, 10)
    reduced, _ = fw.controller_brescianini(gains.replace(mixing_factor=jnp.float32(0.0)), memory, turned, state, 10)
    assert float(full.omega[0, 2]) > 0.5 and abs(float(reduced.omega[0, 2])) < 1e-6
