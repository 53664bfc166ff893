"""`jaxdrones.control.firmware` against the Crazyflie firmware's own C (its Python bindings, built from the firmware's
sources by `firmware_c.bindings`; marker ``firmware``, run by ``pytest -m firmware`` and by .ci/run in every lane):
the PID cascade tick by tick over random sequences of states and setpoints in every mode, and the power
distribution over random controls."""

from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from firmware_c import bindings, fill_c, prime, random_ticks, run_c_pid, run_jax_pid

from jaxdrones.control import firmware as fw
from jaxdrones.examples.firmware_in_the_loop import CONTROLLERS, fly

pytestmark = pytest.mark.firmware
#: Saved runs of jaxdrones train.
DATA = pathlib.Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def cache(request, tmp_path_factory):
    """Where the bindings are built: pytest's cache, kept between runs (a temporary folder without it)."""
    if getattr(request.config, "cache", None) is None:
        return tmp_path_factory.mktemp("firmware")
    return request.config.cache.mkdir("firmware")


@pytest.fixture(scope="module")
def cf(cache):
    return bindings(cache)


def test_the_pid_cascade_is_the_firmwares_tick_by_tick(cf):
    """10⁵ ticks of random states and setpoints (every cflib mode, far targets held until the integrators clamp,
    zero-thrust resets): the JAX cascade's outputs equal the C's to float32 rounding."""
    ticks = prime(random_ticks(np.random.default_rng(0), 100_000))
    c = run_c_pid(cf, ticks)
    controls = run_jax_pid(ticks)
    j = {k: np.asarray(getattr(controls, k)) for k in ("roll", "pitch", "yaw", "thrust")}
    thrust_err = np.max(np.abs(j["thrust"] - c["thrust"]) / np.maximum(np.abs(c["thrust"]), 1.0))
    worst = {k: int(np.max(np.abs(j[k] - c[k]))) for k in ("roll", "pitch", "yaw")}
    share = {k: float(np.mean(j[k] != c[k])) for k in ("roll", "pitch", "yaw")}
    print(f"thrust rel err {thrust_err:.2e}; int16 outputs: largest difference {worst}, share differing {share}")
    assert np.all(c["thrust"] >= 0) and np.any(c["thrust"] == 0) and np.any(c["thrust"] > 60000)
    assert np.any(np.abs(c["roll"]) == 32767)
    assert thrust_err < 1e-4
    assert max(worst.values()) <= 1 and max(share.values()) < 5e-3  # a truncation at a float32 rounding


def _motors(values) -> tuple[int, int, int, int]:
    m = values.motors
    return m.m1, m.m2, m.m3, m.m4


def test_the_power_distribution_is_the_firmwares(cf):
    """10⁵ random controls, legacy (int16 roll, pitch, yaw and thrust, up to the cap and beyond) and force-torque
    (thrusts and torques up to twice the motors' range, negative forces included), each capped: the motors' PWM
    equal the C's exactly (legacy) and within one unit (force-torque: a float32 product truncated)."""
    rng = np.random.default_rng(1)
    n = 100_000
    roll, pitch, yaw = (rng.integers(-32767, 32768, n) for _ in range(3))
    thrust = rng.uniform(0, 70000, n).astype(np.float32)
    thrust_si = rng.uniform(-0.1, 1.0, n).astype(np.float32)
    torque = (rng.normal(size=(n, 3)) * np.array([5e-3, 5e-3, 2e-3])).astype(np.float32)
    c_legacy, c_ft = np.zeros((n, 4), np.int64), np.zeros((n, 4), np.int64)
    c_legacy_capped, c_ft_capped = np.zeros((n, 4), np.int64), np.zeros((n, 4), np.int64)
    control, uncapped, pwm = cf.control_t(), cf.motors_thrust_uncapped_t(), cf.motors_thrust_pwm_t()
    for i in range(n):
        control.controlMode = cf.controlModeLegacy
        control.roll, control.pitch, control.yaw = int(roll[i]), int(pitch[i]), int(yaw[i])
        control.thrust = float(thrust[i])
        cf.powerDistribution(control, uncapped)
        cf.powerDistributionCap(uncapped, pwm)
        c_legacy[i], c_legacy_capped[i] = _motors(uncapped), _motors(pwm)
        control.controlMode = cf.controlModeForceTorque
        control.thrustSi = float(thrust_si[i])
        control.torqueX, control.torqueY, control.torqueZ = (float(v) for v in torque[i])
        cf.powerDistribution(control, uncapped)
        cf.powerDistributionCap(uncapped, pwm)
        c_ft[i], c_ft_capped[i] = _motors(uncapped), _motors(pwm)
    legacy = fw.power_distribution_legacy(
        fw.Control(roll=jnp.asarray(roll), pitch=jnp.asarray(pitch), yaw=jnp.asarray(yaw), thrust=jnp.asarray(thrust))
    )
    ft = fw.power_distribution_force_torque(jnp.asarray(thrust_si), jnp.asarray(torque))
    assert np.array_equal(np.asarray(legacy), c_legacy)
    assert np.array_equal(np.asarray(fw.power_distribution_cap(legacy)), c_legacy_capped)
    assert np.any(c_legacy.max(axis=1) > 65535) and np.any(c_legacy < 0)
    worst = int(np.max(np.abs(np.asarray(ft) - c_ft)))
    capped = int(np.max(np.abs(np.asarray(fw.power_distribution_cap(ft)) - c_ft_capped)))
    print(f"force-torque: largest difference {worst} uncapped, {capped} capped")
    assert worst <= 1 and capped <= 1 and np.any(c_ft.max(axis=1) > 65535) and np.any(c_ft == 0)


@pytest.mark.parametrize("controller", CONTROLLERS)
def test_in_closed_loop_the_jax_controller_flies_where_the_firmwares_does(cf, controller):
    """Five 10 s flights from random starts (±20 cm around 1 m, tilted up to ~10°) to random waypoints changing every
    2 s, with jaxdrones' physics at 1 kHz and first-order motors (τ = 61 ms, docs/validation.md §3): the firmware's C
    controller (PID, Mellinger, Brescianini) and power distribution (through the bindings) and the JAX ones, each in
    the loop with the same compiled physics, fly the same tracks, within 1 mm at every tick."""
    import jaxdrones as jd
    from jaxdrones.examples.firmware_in_the_loop import physics

    step, params, config = physics(motor_tau=0.061)
    rng = np.random.default_rng(2)
    n, ticks = 5, 10_000
    start = jd.init_state(
        config,
        pos=np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.2, 0.2, (n, 1, 3)),
        rpy=rng.uniform(-0.17, 0.17, (n, 1, 3)),
        rpm=np.full((n, 1, 4), float(params.hover_rpm)),
    )
    waypoints = np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.5, 0.5, (n, 5, 3))
    mode = np.broadcast_to(np.array([1, 1, 1, 0, 0, 1, 0], np.int32), (ticks, 7))
    worst, ends = [], []
    for d in range(n):
        position = np.repeat(waypoints[d], ticks // 5, axis=0).astype(np.float32)
        drone = jax.tree.map(lambda x, d=d: x[d], start)
        c_track = fly(cf, step, params, drone, mode, position, controller)
        jax_track = fly(None, step, params, drone, mode, position, controller)
        worst.append(float(np.max(np.linalg.norm(c_track - jax_track, axis=-1))))
        ends.append(float(np.linalg.norm(c_track[-1] - waypoints[d, -1])))
    print(
        f"{controller} in closed loop: largest position difference per flight (m) {worst}; to the last waypoint {ends}"
    )
    assert max(ends) < 0.1  # the flights do reach their waypoints
    assert max(worst) < 1e-3


def test_the_firmware_in_the_loop_example_flies_and_saves_its_figures(cf, cache, tmp_path, capsys):
    """``python -m jaxdrones.examples.firmware_in_the_loop --firmware PATH`` (2 s here): the C and the JAX controller
    fly the square within 1 mm of each other; flight.json and flight.png in a new folder; an existing one is kept."""
    from firmware_c import firmware_folder

    from jaxdrones.examples import firmware_in_the_loop as example

    argv = ["--firmware", str(firmware_folder()), "--seconds", "2", "--cache", str(cache)]
    result = example.main([*argv, "--out", str(tmp_path / "fil")])
    assert result["largest_difference_m"] < 1e-3
    assert sorted(p.name for p in (tmp_path / "fil").iterdir()) == ["flight.json", "flight.png"]
    with pytest.raises(SystemExit):
        example.main([*argv, "--out", str(tmp_path / "fil")])
    assert "exists" in capsys.readouterr().err
    with pytest.raises(ValueError, match="not the Crazyflie firmware's source folder"):
        example.build_bindings(tmp_path, str(cache))


def test_the_exported_policy_flies_with_the_firmwares_c_as_in_jax(cf, cache, tmp_path, capsys):
    """A policy of ``jaxdrones train firmware_hover`` (tests/data/firmware_hover: seed 0 of its recipe), flown by
    ``--policy``: its exported C (compiled by the host's cc) sending velocity setpoints to the firmware's C PID,
    power distribution and cap at every tick, against the JAX policy in its JAX env, from three starts: the two
    flights within 0.1 mm over the 5 s episode, both ending at the target (the task's 5 cm)."""
    from firmware_c import firmware_folder

    from jaxdrones.examples import firmware_in_the_loop as example

    run = str(DATA / "firmware_hover")
    argv = ["--firmware", str(firmware_folder()), "--cache", str(cache), "--policy", run]
    results = [example.main([*argv, "--seed", str(seed), "--out", str(tmp_path / f"p{seed}")]) for seed in range(3)]
    print("policy in the loop:", [(r["largest_difference_m"], r["final_distance_to_target_m"]) for r in results])
    assert all(r["largest_difference_m"] < 1e-4 and r["final_distance_to_target_m"] < 0.05 for r in results)
    assert sorted(p.name for p in (tmp_path / "p0").iterdir()) == ["flight.json", "flight.png"]
    with pytest.raises(ValueError, match="not a firmware setpoint"):
        example.fly_policy(cf, str(DATA / "crazyflie_hover"), jax.random.key(0), cache)


#: The firmware's flags for the Crazyflie 2.x (its Makefile's ARCH_CFLAGS for a release build and
#: tools/kbuild/Makefile.kbuild's KBUILD_CFLAGS), warnings as errors.
FIRMWARE_CFLAGS = (
    "-mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16 -fno-math-errno -DARM_MATH_CM4 -D__FPU_PRESENT=1 "
    "-mfp16-format=ieee -DSTM32F4XX -DSTM32F40_41xxx -DHSE_VALUE=8000000 -DUSE_STDPERIPH_DRIVER -Os -Werror "
    "-Wall -Wmissing-braces -fno-strict-aliasing -ffunction-sections -fdata-sections -Wdouble-promotion -std=gnu11 "
    "-DCRAZYFLIE_FW -D__firmware__"
).split()
#: The firmware's include folders the controller's headers reach (its Makefile's INCLUDES).
FIRMWARE_INCLUDES = (
    "src/config src/platform/interface src/drivers/interface src/hal/interface src/modules/interface "
    "src/modules/interface/kalman_core src/modules/interface/controller src/modules/interface/estimator "
    "src/utils/interface src/utils/interface/lighthouse vendor/CMSIS/CMSIS/Core/Include "
    "vendor/CMSIS/CMSIS/DSP/Include vendor/FreeRTOS/include vendor/FreeRTOS/portable/GCC/ARM_CM4F"
).split()


def test_the_out_of_tree_controller_compiles_against_the_firmware(cf, tmp_path):
    """docs/realism.md's out-of-tree controller, with `jaxdrones export`'s C file of tests/data/crazyflie_hover,
    compiles with the firmware's headers and its Cortex-M4 release flags (warnings as errors), and fits the
    STM32F405's flash; its size is docs/realism.md's."""
    import re
    import shutil
    import subprocess

    from firmware_c import ROOT, firmware_folder

    from jaxdrones.training.export import export

    gcc = shutil.which("arm-none-eabi-gcc")
    if gcc is None:
        pytest.skip("compiling for the Crazyflie needs arm-none-eabi-gcc (apt-get install gcc-arm-none-eabi)")
    firmware = firmware_folder()
    generated = pathlib.Path(cf.__file__).parent / "include" / "generated"  # the bindings' build: cf2_defconfig's
    sketch = re.search(r"```c\n(/\* OOT controller.*?)```", (ROOT / "docs" / "realism.md").read_text(), re.S)
    assert sketch is not None
    (tmp_path / "controller.c").write_text(sketch.group(1))
    export(ROOT / "tests" / "data" / "crazyflie_hover", out=tmp_path / "jaxdrones_policy.c")
    includes = [f"-I{firmware / folder}" for folder in FIRMWARE_INCLUDES] + [f"-I{generated}"]
    command = [
        gcc,
        "-c",
        "controller.c",
        "-o",
        "controller.o",
        *FIRMWARE_CFLAGS,
        "-include",
        str(generated / "autoconf.h"),
        *includes,
    ]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    size = subprocess.run([gcc.replace("gcc", "size"), "controller.o"], cwd=tmp_path, capture_output=True, text=True)
    text, data, bss = (int(v) for v in size.stdout.splitlines()[1].split()[:3])
    print(f"controller.o: text {text} B, data {data} B, bss {bss} B")
    assert 24_464 < text < 64 * 1024 and bss < 1024  # the weights and the code; the memory and the last action


def test_the_mellinger_controller_is_the_firmwares(cf):
    """10⁵ random (controller memory, state, gyro, setpoint) samples in the three mode branches (position, manual
    attitude, height hold), with integrals near and past their bounds and thrust 0 on some: the JAX controller's
    control and memory equal the C's ``controllerMellinger`` to float32 rounding."""
    rng = np.random.default_rng(4)
    n = 100_000
    f32 = np.float32
    modes = np.array([(1, 1, 1, 0, 0, 1, 0), (1, 1, 1, 0, 0, 2, 0), (0, 0, 0, 1, 1, 2, 0), (2, 2, 1, 0, 0, 2, 0),
                      (1, 1, 1, 0, 0, 0, 1)], np.int32)  # fmt: skip
    mode = modes[rng.integers(len(modes), size=n)]
    q = rng.normal(size=(n, 4))
    q[rng.random(n) < 0.7] = [0, 0, 0, 1] + rng.normal(size=(1, 4)) * 0.1  # most near level
    q = (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(f32)
    sq = rng.normal(size=(n, 4))
    sample = {
        "mode": mode,
        "sp_position": rng.uniform(-2, 2, (n, 3)).astype(f32),
        "sp_velocity": rng.uniform(-1, 1, (n, 3)).astype(f32),
        "sp_acceleration": rng.uniform(-2, 2, (n, 3)).astype(f32),
        "sp_attitude": rng.uniform(-40, 40, (n, 3)).astype(f32),
        "sp_rate": rng.uniform(-200, 200, (n, 3)).astype(f32),
        "sp_quat": (sq / np.linalg.norm(sq, axis=-1, keepdims=True)).astype(f32),
        "sp_thrust": np.where(rng.random(n) < 0.1, 0.0, rng.uniform(10000, 60000, n)).astype(f32),
        "position": rng.uniform(-2, 2, (n, 3)).astype(f32),
        "velocity": rng.uniform(-1, 1, (n, 3)).astype(f32),
        "attitude": rng.uniform(-180, 180, (n, 3)).astype(f32),
        "quat": q,
        "gyro": (rng.normal(size=(n, 3)) * 100).astype(f32),
        "i_error": (rng.uniform(-1, 1, (n, 3)) * [2.5, 2.5, 0.5]).astype(f32),
        "i_error_m": (rng.uniform(-1, 1, (n, 3)) * [1.2, 1.2, 1600]).astype(f32),
        "prev_omega": rng.normal(size=(n, 2)).astype(f32),
        "prev_setpoint_omega": rng.normal(size=(n, 2)).astype(f32),
    }
    ctrl, control, sp = cf.controllerMellinger_t(), cf.control_t(), cf.setpoint_t()
    sensors, state = cf.sensorData_t(), cf.state_t()
    c = {k: np.zeros((n, 3), np.float64) for k in ("i_error", "i_error_m")}
    c |= {"prev": np.zeros((n, 4)), "control": np.zeros((n, 4))}
    for i in range(n):
        cf.controllerMellingerInit(ctrl)
        ctrl.i_error_x, ctrl.i_error_y, ctrl.i_error_z = (float(v) for v in sample["i_error"][i])
        ctrl.i_error_m_x, ctrl.i_error_m_y, ctrl.i_error_m_z = (float(v) for v in sample["i_error_m"][i])
        ctrl.prev_omega_roll, ctrl.prev_omega_pitch = (float(v) for v in sample["prev_omega"][i])
        ctrl.prev_setpoint_omega_roll, ctrl.prev_setpoint_omega_pitch = (
            float(v) for v in sample["prev_setpoint_omega"][i]
        )
        fill_c(sp, sensors, state, sample, i)
        cf.controllerMellinger(ctrl, control, sp, sensors, state, 0)
        c["i_error"][i] = ctrl.i_error_x, ctrl.i_error_y, ctrl.i_error_z
        c["i_error_m"][i] = ctrl.i_error_m_x, ctrl.i_error_m_y, ctrl.i_error_m_z
        c["prev"][i] = (
            ctrl.prev_omega_roll,
            ctrl.prev_omega_pitch,
            ctrl.prev_setpoint_omega_roll,
            ctrl.prev_setpoint_omega_pitch,
        )
        c["control"][i] = control.roll, control.pitch, control.yaw, control.thrust
    s = {k: jnp.asarray(v) for k, v in sample.items()}
    setpoint = fw.Setpoint(
        mode=s["mode"], attitude=s["sp_attitude"], attitude_rate=s["sp_rate"], quat=s["sp_quat"],
        thrust=s["sp_thrust"], position=s["sp_position"], velocity=s["sp_velocity"],
        velocity_body=jnp.zeros(n, bool), acceleration=s["sp_acceleration"],
    )  # fmt: skip
    firmware = fw.FirmwareState(
        attitude=s["attitude"], quat=s["quat"], position=s["position"], velocity=s["velocity"], gyro=s["gyro"]
    )
    memory = fw.mellinger_init((n,)).replace(
        i_error=s["i_error"], i_error_m=s["i_error_m"], prev_omega=s["prev_omega"],
        prev_setpoint_omega=s["prev_setpoint_omega"],
    )  # fmt: skip
    new, out = jax.jit(fw.controller_mellinger)(fw.MellingerGains.crazyflie(), memory, setpoint, firmware, 0)
    ints = np.stack([np.asarray(out.roll), np.asarray(out.pitch), np.asarray(out.yaw)], -1)
    worst_int = np.max(np.abs(ints - c["control"][:, :3]))
    share = np.mean(ints != c["control"][:, :3])
    thrust = np.abs(np.asarray(out.thrust) - c["control"][:, 3])  # PWM units (a thrust vector's cancelling dot)
    scale = np.maximum(np.abs(c["i_error_m"]), 1.0)
    memory_err = max(
        np.max(np.abs(np.asarray(new.i_error) - c["i_error"])),
        np.max(np.abs(np.asarray(new.i_error_m) - c["i_error_m"]) / scale),
        np.max(
            np.abs(np.concatenate([np.asarray(new.prev_omega), np.asarray(new.prev_setpoint_omega)], -1) - c["prev"])
        ),
    )
    print(
        f"mellinger: int16 outputs within {worst_int} (differing on {share:.2%}), thrust within "
        f"{thrust.max():.2g} PWM, memory {memory_err:.1e}"
    )
    assert np.any(np.abs(c["control"][:, :3]) == 32000) and np.any(c["control"][:, 3] == 0)
    assert worst_int <= 1 and thrust.max() < 1.0 and memory_err < 1e-5 and share < 5e-3  # thrust: < 1 PWM unit


def test_the_brescianini_controller_is_the_firmwares(cf):
    """10⁵ ticks in sequence (the C keeps its memory in function statics): random states (most near level, some
    upside down), gyros, setpoints in cflib's modes with far targets (the collective acceleration past its bound,
    the fairness cut) and large rates (the heuristic): the JAX controller's thrust and torques equal the C's
    ``controllerBrescianini`` to float32 rounding, at every tick (its 100 Hz update and its 1 kHz rate loop)."""
    rng = np.random.default_rng(7)
    n = 100_000
    ticks = random_ticks(rng, n)
    near = rng.random(n) < 0.7  # most near level, the rest anywhere
    q = np.where(near[:, None], [0, 0, 0, 1] + rng.normal(size=(n, 4)) * 0.15, ticks["quat"])
    ticks["quat"] = (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32)
    ticks["gyro"] = (rng.normal(size=(n, 3)) * np.where(rng.random((n, 1)) < 0.2, 1200.0, 100.0)).astype(np.float32)
    ticks["sp_acceleration"] = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    cf.controllerBrescianiniInit()
    control, setpoint, sensors, state = cf.control_t(), cf.setpoint_t(), cf.sensorData_t(), cf.state_t()
    c = np.zeros((n, 4))
    for i in range(n):
        fill_c(setpoint, sensors, state, ticks, i)
        cf.controllerBrescianini(control, setpoint, sensors, state, i)
        c[i] = control.thrustSi, control.torqueX, control.torqueY, control.torqueZ
    gains = fw.BrescianiniGains.crazyflie()

    def tick(memory, inputs):
        i, t = inputs
        setpoint = fw.Setpoint(
            mode=t["mode"], attitude=t["sp_attitude"], attitude_rate=t["sp_rate"], quat=t["sp_quat"],
            thrust=t["sp_thrust"], position=t["sp_position"], velocity=t["sp_velocity"],
            velocity_body=t["sp_velocity_body"], acceleration=t["sp_acceleration"],
        )  # fmt: skip
        state = fw.FirmwareState(
            attitude=t["attitude"], quat=t["quat"], position=t["position"], velocity=t["velocity"], gyro=t["gyro"]
        )
        memory, out = fw.controller_brescianini(gains, memory, setpoint, state, i)
        return memory, jnp.concatenate([out.thrust[None], out.torque])

    xs = (jnp.arange(n, dtype=jnp.int32), {k: jnp.asarray(v) for k, v in ticks.items()})
    j = np.asarray(jax.jit(lambda xs: jax.lax.scan(tick, fw.brescianini_init(), xs)[1])(xs))
    thrust_err = np.max(np.abs(j[:, 0] - c[:, 0]))  # N (the output's range: 0.029-0.52)
    torque_err = np.max(np.abs(j[:, 1:] - c[:, 1:]) / np.maximum(np.abs(c[:, 1:]), 1e-4))
    print(f"brescianini: thrust within {thrust_err:.1e} N, torques within {torque_err:.1e} (relative, floor 1e-4 N·m)")
    assert np.any(c[:, 0] == 0) and np.any(np.isclose(c[:, 0], 18 * 0.029)) and np.any(np.isclose(c[:, 0], 0.029))
    assert np.max(np.abs(c[:, 1:])) > 1e-2  # torques up to the rate bounds' (30 rad/s over 15 ms, times J)
    assert thrust_err < 1e-5 and torque_err < 1e-3
