"""The Crazyflie firmware's own C, through its Python bindings, as the oracle of `jaxdrones.control.firmware`.

`bindings()` builds ``cffirmware`` from the firmware's sources (``make cf2_defconfig && make bindings_python`` in a
copy: swig and a C compiler) once per firmware folder into pytest's cache, and imports it; the folder is
``$JAXDRONES_FIRMWARE`` or ``../shared/vendor/crazyflie-firmware`` beside the checkout (bitcraze/crazyflie-firmware
at 2a18fc29, GPL-3: read and built here, never copied into the package). Where the folder or the tools are absent,
the tests that need it skip with the reason.

`random_ticks` draws sequences of firmware ticks (states, sensors, setpoints in every mode, segments that hold far
targets until the integrators clamp, zero-thrust ticks); `run_c_pid` flies them through ``controllerPid``.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def firmware_folder() -> pathlib.Path | None:
    """The firmware's source folder, or None."""
    candidates = [os.environ.get("JAXDRONES_FIRMWARE"), ROOT.parent / "shared" / "vendor" / "crazyflie-firmware"]
    for candidate in candidates:
        if candidate and (pathlib.Path(candidate) / "bindings" / "setup.py").exists():
            return pathlib.Path(candidate)
    return None


def bindings(cache: pathlib.Path):
    """The ``cffirmware`` module built from `firmware_folder` (skips the test where it cannot be)."""
    folder = firmware_folder()
    if folder is None:
        pytest.skip("the Crazyflie firmware's sources are not here (set JAXDRONES_FIRMWARE to the folder)")
    for tool in ("swig", "make", "gcc"):
        if shutil.which(tool) is None:
            pytest.skip(f"building the firmware's bindings needs {tool} (apt-get install swig build-essential)")
    key = hashlib.sha256(str(folder.resolve()).encode() + sys.version.encode()).hexdigest()[:12]
    built = cache / f"cffirmware-{key}"
    if not built.exists():
        work = pathlib.Path(tempfile.mkdtemp(prefix="cffirmware-", dir=cache))
        source = work / "firmware"
        shutil.copytree(folder, source, symlinks=True)
        env = {**os.environ, "PATH": f"{pathlib.Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
        for target in ("cf2_defconfig", "bindings_python"):
            result = subprocess.run(["make", target], cwd=source, env=env, capture_output=True, text=True)
            if result.returncode != 0:
                pytest.fail(f"make {target} failed in {source}:\n{result.stdout[-2000:]}{result.stderr[-2000:]}")
        try:
            (source / "build").rename(built)
        except OSError:  # another worker built it first
            pass
        shutil.rmtree(work, ignore_errors=True)
    if str(built) not in sys.path:
        sys.path.insert(0, str(built))
    return importlib.import_module("cffirmware")


#: The setpoint modes drawn, (x, y, z, roll, pitch, yaw, quat): what cflib's commands set (position, velocity with
#: height or vertical velocity, attitude with thrust or height, rates, a quaternion's yaw).
MODES = np.array(
    [
        (1, 1, 1, 0, 0, 1, 0),  # position, absolute yaw (cflib send_position_setpoint)
        (2, 2, 1, 0, 0, 2, 0),  # velocity with height hold (send_hover_setpoint)
        (2, 2, 2, 0, 0, 2, 0),  # world velocity (send_velocity_world_setpoint)
        (0, 0, 0, 1, 1, 2, 0),  # attitude and thrust (send_setpoint)
        (0, 0, 1, 1, 1, 1, 0),  # attitude and height (send_zdistance_setpoint)
        (0, 0, 0, 2, 2, 2, 0),  # body rates and thrust
        (1, 1, 1, 0, 0, 0, 1),  # full state: the quaternion's yaw
    ],
    np.int32,
)


def random_ticks(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    """``n`` ticks: per tick a state, a gyro and a setpoint, float32, in segments of 10-400 ticks each with one
    mode and target (some far, so that the integrators reach their clamps; some with thrust 0)."""
    f32 = np.float32
    ticks = {
        "mode": np.zeros((n, 7), np.int32),
        "sp_attitude": np.zeros((n, 3), f32),
        "sp_rate": np.zeros((n, 3), f32),
        "sp_quat": np.zeros((n, 4), f32),
        "sp_thrust": np.zeros(n, f32),
        "sp_position": np.zeros((n, 3), f32),
        "sp_velocity": np.zeros((n, 3), f32),
        "sp_velocity_body": np.zeros(n, bool),
    }
    start = 0
    while start < n:
        end = min(n, start + int(rng.integers(10, 400)))
        far = rng.random() < 0.3
        scale = 50.0 if far else 1.0
        ticks["mode"][start:end] = MODES[rng.integers(len(MODES))]
        ticks["sp_attitude"][start:end] = rng.uniform(-30, 30, 3) * (3 if far else 1)
        ticks["sp_attitude"][start:end, 2] = rng.uniform(-540, 540)
        ticks["sp_rate"][start:end] = rng.uniform(-200, 200, 3) * (5 if far else 1)
        q = rng.normal(size=4)
        ticks["sp_quat"][start:end] = q / np.linalg.norm(q)
        ticks["sp_thrust"][start:end] = 0.0 if rng.random() < 0.1 else rng.uniform(10000, 60000)
        ticks["sp_position"][start:end] = rng.uniform(-2, 2, 3) * scale
        ticks["sp_velocity"][start:end] = rng.uniform(-1, 1, 3) * scale
        ticks["sp_velocity_body"][start:end] = rng.random() < 0.3
        start = end
    walk = np.cumsum(rng.normal(size=(n, 3)) * 0.01, axis=0)
    ticks["position"] = (walk + rng.normal(size=(n, 3)) * 0.001).astype(f32)
    ticks["velocity"] = (rng.normal(size=(n, 3)) * 0.5).astype(f32)
    ticks["attitude"] = np.column_stack(
        [rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), np.cumsum(rng.normal(size=n)) % 360 - 180]
    ).astype(f32)
    ticks["gyro"] = (rng.normal(size=(n, 3)) * 100).astype(f32)
    q = rng.normal(size=(n, 4))
    ticks["quat"] = (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(f32)
    return ticks


def prime(ticks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``ticks`` after one tick every mode off with thrust 0: a tick that resets the C controller's memory (the
    zero-thrust reset) wherever it was, so that it starts where `controller_pid_init` does."""
    first = {k: np.zeros_like(v[:1]) for k, v in ticks.items()}
    first["sp_quat"][:, 3] = 1.0
    first["quat"][:, 3] = 1.0
    return {k: np.concatenate([first[k], v]) for k, v in ticks.items()}


def run_c_pid(cf, ticks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fly ``ticks`` through the firmware's ``controllerPid``, tick i being stabilizer step i; returns the control
    after each tick: roll, pitch, yaw (int) and thrust."""
    n = len(ticks["mode"])
    cf.controllerPidInit()  # as the firmware does at start-up: the PIDs' periods and filters (idempotent)
    control, setpoint, sensors, state = cf.control_t(), cf.setpoint_t(), cf.sensorData_t(), cf.state_t()
    out = {k: np.zeros(n, np.int64) for k in ("roll", "pitch", "yaw")} | {"thrust": np.zeros(n, np.float32)}
    names = ("x", "y", "z", "roll", "pitch", "yaw", "quat")
    for i in range(n):
        for axis, value in zip(names, ticks["mode"][i], strict=True):
            setattr(setpoint.mode, axis, int(value))
        a, r, q = ticks["sp_attitude"][i], ticks["sp_rate"][i], ticks["sp_quat"][i]
        setpoint.attitude.roll, setpoint.attitude.pitch, setpoint.attitude.yaw = (float(v) for v in a)
        setpoint.attitudeRate.roll, setpoint.attitudeRate.pitch, setpoint.attitudeRate.yaw = (float(v) for v in r)
        sq = setpoint.attitudeQuaternion
        sq.x, sq.y, sq.z, sq.w = (float(v) for v in q)
        setpoint.thrust = float(ticks["sp_thrust"][i])
        setpoint.position.x, setpoint.position.y, setpoint.position.z = (float(v) for v in ticks["sp_position"][i])
        setpoint.velocity.x, setpoint.velocity.y, setpoint.velocity.z = (float(v) for v in ticks["sp_velocity"][i])
        setpoint.velocity_body = bool(ticks["sp_velocity_body"][i])
        state.attitude.roll, state.attitude.pitch, state.attitude.yaw = (float(v) for v in ticks["attitude"][i])
        sq = state.attitudeQuaternion
        sq.x, sq.y, sq.z, sq.w = (float(v) for v in ticks["quat"][i])
        state.position.x, state.position.y, state.position.z = (float(v) for v in ticks["position"][i])
        state.velocity.x, state.velocity.y, state.velocity.z = (float(v) for v in ticks["velocity"][i])
        sensors.gyro.x, sensors.gyro.y, sensors.gyro.z = (float(v) for v in ticks["gyro"][i])
        cf.controllerPid(control, setpoint, sensors, state, i)
        out["roll"][i], out["pitch"][i], out["yaw"][i] = control.roll, control.pitch, control.yaw
        out["thrust"][i] = control.thrust
    return out


def run_pid_loop(cf, step, params, drone, setpoints: dict[str, np.ndarray]):
    """One drone flown in the loop with jaxdrones' physics, tick by tick, by the firmware's C ``controllerPid`` and
    power distribution (``cf``, the bindings) or, with ``cf`` None, by `fw.controller_pid` and its power
    distribution, through the same compiled physics: per tick, the firmware's state of the drone (`firmware_state`),
    the controller's motor commands, the motor map (`motor_rpm`) and 1 ms of physics. ``setpoints`` holds per tick
    ``mode`` i32[7] and ``sp_position`` f32[3]; tick i is stabilizer step i. Returns the positions f32[T, 3] after
    each tick."""
    import jax
    import jax.numpy as jnp

    from jaxdrones.control import firmware as fw

    observe = jax.jit(fw.firmware_state)
    advance = jax.jit(lambda drone, pwm: step(params, drone, fw.motor_rpm(params, pwm)))
    gains = fw.PidControllerGains.crazyflie()
    jax_control = jax.jit(
        lambda c, sp, s, t: (lambda c, u: (c, fw.power_distribution_cap(fw.power_distribution_legacy(u))))(
            *fw.controller_pid(gains, c, sp, s, t)
        )
    )
    cstate, jax_setpoint = fw.controller_pid_init((1,)), fw.Setpoint.zeros((1,))
    if cf is not None:
        cf.controllerPidInit()
        control, setpoint, sensors, state = cf.control_t(), cf.setpoint_t(), cf.sensorData_t(), cf.state_t()
        uncapped, pwm = cf.motors_thrust_uncapped_t(), cf.motors_thrust_pwm_t()
        cf.controllerPid(control, setpoint, sensors, state, 0)  # every mode off, thrust 0: the C's memory reset
        control = cf.control_t()
    names = ("x", "y", "z", "roll", "pitch", "yaw", "quat")
    positions = []
    for i in range(len(setpoints["mode"])):
        seen = observe(drone)
        if cf is None:
            target = jax_setpoint.replace(
                mode=jnp.asarray(setpoints["mode"][i][None]), position=jnp.asarray(setpoints["sp_position"][i][None])
            )
            cstate, motors = jax_control(cstate, target, seen, i)
        else:
            for axis, value in zip(names, setpoints["mode"][i], strict=True):
                setattr(setpoint.mode, axis, int(value))
            sp = setpoints["sp_position"][i]
            setpoint.position.x, setpoint.position.y, setpoint.position.z = (float(v) for v in sp)
            a, p, v, g = (np.asarray(x)[0] for x in (seen.attitude, seen.position, seen.velocity, seen.gyro))
            state.attitude.roll, state.attitude.pitch, state.attitude.yaw = (float(x) for x in a)
            state.position.x, state.position.y, state.position.z = (float(x) for x in p)
            state.velocity.x, state.velocity.y, state.velocity.z = (float(x) for x in v)
            sensors.gyro.x, sensors.gyro.y, sensors.gyro.z = (float(x) for x in g)
            cf.controllerPid(control, setpoint, sensors, state, i)
            cf.powerDistribution(control, uncapped)
            cf.powerDistributionCap(uncapped, pwm)
            m = pwm.motors
            motors = np.array([[m.m1, m.m2, m.m3, m.m4]], np.int32)
        drone = advance(drone, motors)
        positions.append(np.asarray(drone.pos[0]))
    return np.stack(positions)
