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

import os
import pathlib

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
    """The ``cffirmware`` module built from `firmware_folder` (`build_bindings`), or the test skipped with the reason
    (no firmware folder, or a build tool missing)."""
    from jaxdrones.examples.firmware_in_the_loop import build_bindings

    folder = firmware_folder()
    if folder is None:
        pytest.skip("the Crazyflie firmware's sources are not here (set JAXDRONES_FIRMWARE to the folder)")
    try:
        return build_bindings(folder, cache)
    except RuntimeError as err:
        if "needs" in str(err):
            pytest.skip(str(err))
        raise


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


def fill_c(setpoint, sensors, state, sample: dict[str, np.ndarray], i: int) -> None:
    """The bindings' ``setpoint_t``, ``sensorData_t`` and ``state_t`` set to entry ``i`` of ``sample``'s arrays
    (`random_ticks`' keys; ``sp_velocity_body`` and ``sp_acceleration`` where given)."""
    for axis, value in zip(("x", "y", "z", "roll", "pitch", "yaw", "quat"), sample["mode"][i], strict=True):
        setattr(setpoint.mode, axis, int(value))
    setpoint.attitude.roll, setpoint.attitude.pitch, setpoint.attitude.yaw = map(float, sample["sp_attitude"][i])
    setpoint.attitudeRate.roll, setpoint.attitudeRate.pitch, setpoint.attitudeRate.yaw = map(
        float, sample["sp_rate"][i]
    )
    quat = setpoint.attitudeQuaternion
    quat.x, quat.y, quat.z, quat.w = map(float, sample["sp_quat"][i])
    setpoint.thrust = float(sample["sp_thrust"][i])
    setpoint.position.x, setpoint.position.y, setpoint.position.z = map(float, sample["sp_position"][i])
    setpoint.velocity.x, setpoint.velocity.y, setpoint.velocity.z = map(float, sample["sp_velocity"][i])
    if "sp_velocity_body" in sample:
        setpoint.velocity_body = bool(sample["sp_velocity_body"][i])
    if "sp_acceleration" in sample:
        acc = setpoint.acceleration
        acc.x, acc.y, acc.z = map(float, sample["sp_acceleration"][i])
    state.attitude.roll, state.attitude.pitch, state.attitude.yaw = map(float, sample["attitude"][i])
    quat = state.attitudeQuaternion
    quat.x, quat.y, quat.z, quat.w = map(float, sample["quat"][i])
    state.position.x, state.position.y, state.position.z = map(float, sample["position"][i])
    state.velocity.x, state.velocity.y, state.velocity.z = map(float, sample["velocity"][i])
    sensors.gyro.x, sensors.gyro.y, sensors.gyro.z = map(float, sample["gyro"][i])


def run_c_pid(cf, ticks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fly ``ticks`` through the firmware's ``controllerPid``, tick i being stabilizer step i; returns the control
    after each tick: roll, pitch, yaw (int) and thrust."""
    n = len(ticks["mode"])
    cf.controllerPidInit()  # as the firmware does at start-up: the PIDs' periods and filters (idempotent)
    control, setpoint, sensors, state = cf.control_t(), cf.setpoint_t(), cf.sensorData_t(), cf.state_t()
    out = {k: np.zeros(n, np.int64) for k in ("roll", "pitch", "yaw")} | {"thrust": np.zeros(n, np.float32)}
    for i in range(n):
        fill_c(setpoint, sensors, state, ticks, i)
        cf.controllerPid(control, setpoint, sensors, state, i)
        out["roll"][i], out["pitch"][i], out["yaw"][i] = control.roll, control.pitch, control.yaw
        out["thrust"][i] = control.thrust
    return out


def run_jax_pid(ticks: dict[str, np.ndarray], batch: tuple[int, ...] = ()):
    """The same ticks through `jaxdrones.control.firmware.controller_pid` in one jitted ``lax.scan`` (each array of
    ``ticks`` with the ``batch`` axes after its first); returns the `Control` after each tick, leading axis T."""
    import jax
    import jax.numpy as jnp

    from jaxdrones.control import firmware as fw

    gains = fw.PidControllerGains.crazyflie()

    def tick(cstate, inputs):
        i, t = inputs
        setpoint = fw.Setpoint(
            mode=t["mode"],
            attitude=t["sp_attitude"],
            attitude_rate=t["sp_rate"],
            quat=t["sp_quat"],
            thrust=t["sp_thrust"],
            position=t["sp_position"],
            velocity=t["sp_velocity"],
            velocity_body=t["sp_velocity_body"],
            acceleration=t.get("sp_acceleration", jnp.zeros_like(t["sp_velocity"])),
        )
        state = fw.FirmwareState(
            attitude=t["attitude"], quat=t["quat"], position=t["position"], velocity=t["velocity"], gyro=t["gyro"]
        )
        return fw.controller_pid(gains, cstate, setpoint, state, i)

    xs = (jnp.arange(len(ticks["mode"]), dtype=jnp.int32), {k: jnp.asarray(v) for k, v in ticks.items()})
    return jax.jit(lambda xs: jax.lax.scan(tick, fw.controller_pid_init(batch), xs)[1])(xs)
