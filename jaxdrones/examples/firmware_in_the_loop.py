"""The Crazyflie firmware's own C controller in the loop with jaxdrones' physics, beside its JAX re-implementation.

As gym-pybullet-drones' ``CFAviary`` does for one drone, every firmware tick (1 ms) hands the firmware's
``controllerPid`` the state of the simulated drone, runs its power distribution and cap, and steps the physics at the
motor speeds its commands give (`jaxdrones.control.firmware.motor_rpm`). The C comes from the firmware's Python
bindings, built from its sources by `build_bindings` (``make cf2_defconfig && make bindings_python`` in a copy: swig
and a C compiler; bitcraze/crazyflie-firmware, GPL-3.0, which jaxdrones neither ships nor copies). The same setpoints
flown by `jaxdrones.control.firmware.controller_pid` through the same compiled physics give the difference between
the two (docs/firmware.md); ``--controller`` flies Mellinger's or Brescianini's instead, and ``--policy RUN`` a run of
``jaxdrones train firmware_hover``: its exported C policy sending setpoints to the firmware's C (`fly_policy`)::

    python -m jaxdrones.examples.firmware_in_the_loop --firmware PATH/crazyflie-firmware --out fil
    python -m jaxdrones.examples.firmware_in_the_loop --firmware PATH/crazyflie-firmware --policy RUN --out fil_policy
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib
import importlib.util
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
from types import ModuleType

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.control import firmware as fw
from jaxdrones.physics.params import DroneParams, load_params
from jaxdrones.physics.state import DroneState, init_state
from jaxdrones.sim import SimConfig, StepFn, make_step

#: The modes of a position setpoint (cflib's ``send_position_setpoint``): x, y, z and yaw absolute.
POSITION_MODE = (1, 1, 1, 0, 0, 1, 0)
#: The setpoints' field names of the bindings' ``setpoint_mode_t``, in `jaxdrones.control.firmware.MODE_AXES` order.
_MODE_FIELDS = fw.types.MODE_AXES


def build_bindings(firmware: str | os.PathLike, cache: str | os.PathLike) -> ModuleType:
    """The firmware's ``cffirmware`` module, built once per firmware folder and Python into ``cache`` and imported.

    Raises:
        ValueError: ``firmware`` is not the firmware's source folder (no ``bindings/setup.py``).
        RuntimeError: a tool is missing (swig, make, a C compiler, setuptools for this Python) or the build fails
            (with make's output).
    """
    folder = pathlib.Path(firmware).resolve()
    if not (folder / "bindings" / "setup.py").exists():
        raise ValueError(f"{folder} is not the Crazyflie firmware's source folder (no bindings/setup.py)")
    missing = [tool for tool in ("swig", "make", "gcc") if shutil.which(tool) is None]
    if importlib.util.find_spec("setuptools") is None:
        missing.append("setuptools (pip install setuptools)")
    if missing:
        raise RuntimeError(
            f"building the firmware's bindings needs {', '.join(missing)} (apt-get install swig gcc make)"
        )
    cache = pathlib.Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    key = hashlib.sha256(f"{folder}{sys.version}".encode()).hexdigest()[:12]
    built = cache / f"cffirmware-{key}"
    if not built.exists():
        work = pathlib.Path(tempfile.mkdtemp(prefix="cffirmware-", dir=cache))
        try:
            source = work / "firmware"
            shutil.copytree(folder, source, symlinks=True)
            env = {**os.environ, "PATH": f"{pathlib.Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
            for target in ("cf2_defconfig", "bindings_python"):
                command = ["make", target, f"PYTHON={sys.executable}"]
                result = subprocess.run(command, cwd=source, env=env, capture_output=True, text=True)
                if result.returncode != 0:
                    raise RuntimeError(f"make {target} failed:\n{result.stdout[-2000:]}{result.stderr[-2000:]}")
            try:
                (source / "build").rename(built)
            except OSError:  # built meanwhile by another process
                pass
        finally:
            shutil.rmtree(work, ignore_errors=True)
    if str(built) not in sys.path:
        sys.path.insert(0, str(built))
    return importlib.import_module("cffirmware")


#: The controllers `fly` flies: the firmware's default PID cascade, Mellinger and Brescianini.
CONTROLLERS = ("pid", "mellinger", "brescianini")


def fly(
    cf: ModuleType | None,
    step: StepFn,
    params: DroneParams,
    drone: DroneState,
    mode: np.ndarray,
    position: np.ndarray,
    controller: str = "pid",
) -> np.ndarray:
    """One drone flown tick by tick: by the firmware's C (``cf``, the bindings) or, with ``cf`` None, by
    `jaxdrones.control.firmware`'s JAX controller, each through the same compiled physics.

    Args:
        cf: the bindings (`build_bindings`) or None.
        step: a physics step of 1 ms (``make_step(SimConfig(sim_freq=1000, ctrl_freq=1000, ...))``).
        params: `DroneParams` of the drone.
        drone: `DroneState` of one drone, batch ``[1]``.
        mode: i32[T, 7], each tick's setpoint modes (x, y, z, roll, pitch, yaw, quat).
        position: f32[T, 3] m, each tick's position setpoint, world frame.
        controller: one of `CONTROLLERS`: ``controllerPid`` (`controller_pid`), ``controllerMellinger``
            (`controller_mellinger`) or ``controllerBrescianini`` (`controller_brescianini`), each with the power
            distribution its control mode takes (legacy; force-torque for Brescianini) and the cap.

    Returns:
        f32[T, 3] m, the drone's position after each tick (tick i is the firmware's stabilizer step i).

    Raises:
        ValueError: an unknown ``controller``.
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller {controller!r}: expected one of {CONTROLLERS}")
    observe = jax.jit(fw.firmware_state)
    advance = jax.jit(lambda drone, pwm: step(params, drone, fw.motor_rpm(params, pwm)))
    jax_motors, memory = _jax_controller(controller)
    jax_setpoint = fw.Setpoint.zeros((1,))
    if cf is not None:
        c_tick = _c_controller(cf, controller)
        setpoint, sensors, state = cf.setpoint_t(), cf.sensorData_t(), cf.state_t()
        uncapped, pwm = cf.motors_thrust_uncapped_t(), cf.motors_thrust_pwm_t()
    positions = []
    for i in range(len(mode)):
        seen = observe(drone)
        if cf is None:
            target = jax_setpoint.replace(mode=jnp.asarray(mode[i][None]), position=jnp.asarray(position[i][None]))
            memory, motors = jax_motors(memory, target, seen, i)
        else:
            for axis, value in zip(_MODE_FIELDS, mode[i], strict=True):
                setattr(setpoint.mode, axis, int(value))
            setpoint.position.x, setpoint.position.y, setpoint.position.z = (float(v) for v in position[i])
            _fill_state(state, sensors, seen)
            control = c_tick(setpoint, sensors, state, i)
            cf.powerDistribution(control, uncapped)
            cf.powerDistributionCap(uncapped, pwm)
            m = pwm.motors
            motors = np.array([[m.m1, m.m2, m.m3, m.m4]], np.int32)
        drone = advance(drone, motors)
        positions.append(np.asarray(drone.pos[0]))
    return np.stack(positions)


def _jax_controller(controller: str):
    """(a jitted (memory, setpoint, state, tick) → (memory, motors' PWM i32[1, 4]), the fresh memory of one drone)."""
    if controller == "brescianini":
        gains = fw.BrescianiniGains.crazyflie()

        def motors(memory, setpoint, seen, tick):
            memory, control = fw.controller_brescianini(gains, memory, setpoint, seen, tick)
            return memory, fw.power_distribution_cap(fw.power_distribution_force_torque(control.thrust, control.torque))

        return jax.jit(motors), fw.brescianini_init((1,))
    if controller == "mellinger":
        gains, run, memory = fw.MellingerGains.crazyflie(), fw.controller_mellinger, fw.mellinger_init((1,))
    else:
        gains, run, memory = fw.PidControllerGains.crazyflie(), fw.controller_pid, fw.controller_pid_init((1,))

    def legacy(memory, setpoint, seen, tick):
        memory, control = run(gains, memory, setpoint, seen, tick)
        return memory, fw.power_distribution_cap(fw.power_distribution_legacy(control))

    return jax.jit(legacy), memory


def _c_controller(cf: ModuleType, controller: str, state=None):
    """The firmware's C controller as (setpoint, sensors, state, tick) → its ``control_t``, its memory fresh (as
    `_jax_controller`'s); the PID's reset at zero thrust sees ``state`` (a ``state_t``; None: zeros)."""
    control = cf.control_t()
    if controller == "mellinger":
        memory = cf.controllerMellinger_t()
        cf.controllerMellingerInit(memory)
        return lambda sp, sensors, state, i: (cf.controllerMellinger(memory, control, sp, sensors, state, i), control)[
            1
        ]
    if controller == "brescianini":  # its memory is statics, all set by its first update (tick 0)
        cf.controllerBrescianiniInit()
        return lambda sp, sensors, state, i: (cf.controllerBrescianini(control, sp, sensors, state, i), control)[1]
    cf.controllerPidInit()
    off = cf.setpoint_t()  # every mode off, thrust 0: the C's memory reset, where controller_pid_init starts
    cf.controllerPid(control, off, cf.sensorData_t(), cf.state_t() if state is None else state, 0)
    return lambda sp, sensors, state, i: (cf.controllerPid(control, sp, sensors, state, i), control)[1]


def fly_policy(
    cf: ModuleType, run: str | os.PathLike, key: jax.Array, cache: str | os.PathLike
) -> tuple[np.ndarray, np.ndarray]:
    """A policy of the firmware's setpoints (a run of ``jaxdrones train firmware_hover``) flown twice from the same
    start: its exported C (`jaxdrones.training.export.c_source`, compiled by the host's C compiler) sending setpoints
    to the firmware's C ``controllerPid`` (the bindings) at every tick, and its JAX policy in its JAX env.

    The C flight computes the observation as the env does (`jaxdrones.envs.observations.ObsType.observe`), calls the
    C policy once per control step, and holds its setpoint (`ActionType.setpoint`) for the step's ticks of the C
    controller, power distribution and cap, each driving 1 ms of the env's physics with the env's params.

    Args:
        cf: the bindings (`build_bindings`).
        run: the run folder (or its policy.pkl); its env's action must be a firmware setpoint, its observation the
            drone's own (no task entries, action buffer or error integral).
        key: the env's reset key (the start).
        cache: a folder for the compiled policy.

    Returns:
        (the C flight's positions f32[T, 3] m after each control step, the JAX flight's), T the episode's steps.

    Raises:
        ValueError: a run whose env does not take the firmware's setpoints or whose observation has more than the
            drone's own; RuntimeError: no C compiler, or the policy does not compile.
    """
    import ctypes

    from jaxdrones.training.checkpoint import load_policy
    from jaxdrones.training.evaluation import rollout_policy
    from jaxdrones.training.export import c_source, load_payload

    env, policy = load_policy(run)
    if not env.action_type.firmware:
        raise ValueError(f"fly_policy: the run's action_type is {env.action_type.name!r}, not a firmware setpoint")
    if env.task.obs_size or env.integral_size or env.obs_type.buffer_len or env.config.vision:
        raise ValueError("fly_policy: policies that observe only their drone (no task entries, buffer or integral)")
    source, _ = c_source(load_payload(run))
    library = _compile_policy(source, pathlib.Path(cache))
    c_policy = library.jaxdrones_policy
    c_policy.argtypes = [ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_float)]
    c_policy.restype = None

    start = jax.jit(env.reset)(key)
    states = jax.jit(lambda s: rollout_policy(env, policy, key, s))(start)
    jax_track = np.asarray(states.sim.pos[1:, 0], np.float32)

    config = env.config.sim
    ticks = config.sim_freq // config.ctrl_freq
    step = make_step(dataclasses.replace(config, ctrl_freq=config.sim_freq))
    advance = jax.jit(lambda drone, pwm: step(start.params, drone, fw.motor_rpm(start.params, pwm)))
    observe = jax.jit(lambda drone: env.obs_type.observe(drone, jnp.zeros((1, 0, env.action_size), env.dtype)))
    seen_of = jax.jit(fw.firmware_state)
    drone = start.sim
    setpoint, sensors, state = cf.setpoint_t(), cf.sensorData_t(), cf.state_t()
    uncapped, pwm = cf.motors_thrust_uncapped_t(), cf.motors_thrust_pwm_t()
    _fill_state(state, sensors, seen_of(drone))
    c_tick = _c_controller(cf, "pid", state)  # its memory as the env's reset leaves it: the desired yaw the drone's
    obs, action = np.zeros(env.observation_size, np.float32), np.zeros(env.action_size, np.float32)
    positions = []
    for t in range(env.episode_length):
        obs[:] = np.asarray(observe(drone))[0]
        c_policy(
            obs.ctypes.data_as(ctypes.POINTER(ctypes.c_float)), action.ctypes.data_as(ctypes.POINTER(ctypes.c_float))
        )
        target = jax.tree.map(lambda x: np.asarray(x)[0], env.action_type.setpoint(jnp.asarray(action[None])))
        _fill_setpoint(setpoint, target)
        for k in range(ticks):
            _fill_state(state, sensors, seen_of(drone))
            control = c_tick(setpoint, sensors, state, t * ticks + k)
            cf.powerDistribution(control, uncapped)
            cf.powerDistributionCap(uncapped, pwm)
            m = pwm.motors
            drone = advance(drone, np.array([[m.m1, m.m2, m.m3, m.m4]], np.int32))
        positions.append(np.asarray(drone.pos[0], np.float32))
    return np.stack(positions), jax_track


def _compile_policy(source: str, cache: pathlib.Path):
    """The exported C policy compiled by the host's ``cc`` as a shared library (kept in ``cache`` by its source's
    hash), loaded with ctypes."""
    import ctypes

    compiler = shutil.which(os.environ.get("CC", "cc"))
    if compiler is None:
        raise RuntimeError("compiling the exported policy needs a C compiler (apt-get install gcc)")
    cache.mkdir(parents=True, exist_ok=True)
    digest = hashlib.sha256(source.encode()).hexdigest()[:12]
    library = cache / f"policy-{digest}.so"
    if not library.exists():
        work = pathlib.Path(tempfile.mkdtemp(prefix="policy-", dir=cache))
        try:
            (work / "policy.c").write_text(source)
            command = [
                compiler,
                "-O2",
                "-shared",
                "-fPIC",
                "-o",
                str(work / "policy.so"),
                str(work / "policy.c"),
                "-lm",
            ]
            result = subprocess.run(command, capture_output=True, text=True)
            if result.returncode != 0:
                raise RuntimeError(f"the exported policy does not compile:\n{result.stderr[-2000:]}")
            os.replace(work / "policy.so", library)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return ctypes.CDLL(str(library))


def _fill_state(state, sensors, seen: fw.FirmwareState) -> None:
    """The bindings' ``state_t`` and ``sensorData_t`` of one drone's `FirmwareState` (batch ``[1]``)."""
    a, q, p, v, g = (np.asarray(x)[0] for x in (seen.attitude, seen.quat, seen.position, seen.velocity, seen.gyro))
    state.attitude.roll, state.attitude.pitch, state.attitude.yaw = (float(x) for x in a)
    quat = state.attitudeQuaternion
    quat.x, quat.y, quat.z, quat.w = (float(x) for x in q)
    state.position.x, state.position.y, state.position.z = (float(x) for x in p)
    state.velocity.x, state.velocity.y, state.velocity.z = (float(x) for x in v)
    sensors.gyro.x, sensors.gyro.y, sensors.gyro.z = (float(x) for x in g)


def _fill_setpoint(setpoint, target: fw.Setpoint) -> None:
    """The bindings' ``setpoint_t`` of one drone's `Setpoint` (NumPy leaves, no batch axes)."""
    for axis, value in zip(_MODE_FIELDS, target.mode, strict=True):
        setattr(setpoint.mode, axis, int(value))
    setpoint.position.x, setpoint.position.y, setpoint.position.z = (float(v) for v in target.position)
    setpoint.velocity.x, setpoint.velocity.y, setpoint.velocity.z = (float(v) for v in target.velocity)
    setpoint.attitude.roll, setpoint.attitude.pitch, setpoint.attitude.yaw = (float(v) for v in target.attitude)
    rate = setpoint.attitudeRate
    rate.roll, rate.pitch, rate.yaw = (float(v) for v in target.attitude_rate)


def physics(motor_tau: float = fw.CRAZYFLIE_MOTOR_TAU) -> tuple[StepFn, DroneParams, SimConfig]:
    """A 1 ms physics step of the ``cf2x`` with first-order motors of time constant ``motor_tau`` s (61 ms,
    `CRAZYFLIE_MOTOR_TAU`: docs/validation.md §3; the firmware's gains need lagging motors, docs/firmware.md)."""
    config = SimConfig(sim_freq=1000, ctrl_freq=1000, motor_dynamics=True)
    tau = jnp.float32(motor_tau)
    return make_step(config), load_params("cf2x").replace(motor_tau_up=tau, motor_tau_down=tau), config


def square(seconds: float, side: float = 0.5, height: float = 1.0) -> np.ndarray:
    """f32[T, 3]: a position setpoint per tick, the corners of a square of ``side`` m at ``height`` m in turn, a
    quarter of ``seconds`` each."""
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32)
    ticks = int(round(seconds * fw.RATE_MAIN_LOOP))
    index = np.minimum(np.arange(ticks) * 4 // ticks, 3)
    return np.column_stack([corners[index], np.full(ticks, height, np.float32)]).astype(np.float32)


def main(argv: list[str] | None = None) -> dict:
    """The command line: an ``--seconds`` flight around a 0.5 m square by the C and by the JAX ``--controller``, or
    with ``--policy RUN`` that run's exported policy and the firmware's C PID against its JAX policy and env; prints
    their largest difference and writes `write`'s folder; returns the figures."""
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--firmware", required=True, help="the Crazyflie firmware's source folder")
    parser.add_argument("--controller", choices=CONTROLLERS, default="pid", help="the firmware's controller")
    parser.add_argument("--seconds", type=float, default=8.0, help="the square's flight, s (default 8)")
    parser.add_argument(
        "--policy", help="a run of `jaxdrones train firmware_hover` (or its policy.pkl): fly its exported C instead"
    )
    parser.add_argument("--seed", type=int, default=0, help="--policy: the episode's start (the env's reset key)")
    parser.add_argument("--out", default="firmware_in_the_loop", help="folder for flight.json and flight.png")
    parser.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "jaxdrones-firmware"))
    args = parser.parse_args(argv)
    if not args.seconds > 0:
        parser.error("--seconds must be positive")
    if os.path.exists(args.out):
        parser.error(f"{args.out} exists: choose another --out (nothing was written)")
    cf = build_bindings(args.firmware, args.cache)
    if args.policy is not None:
        return _main_policy(cf, args)
    step, params, config = physics()
    position = square(args.seconds)
    mode = np.broadcast_to(np.array(POSITION_MODE, np.int32), (len(position), 7))
    drone = init_state(config, pos=[[0.0, 0.0, 1.0]], rpm=np.full((1, 4), float(params.hover_rpm)))
    c_track = fly(cf, step, params, drone, mode, position, args.controller)
    jax_track = fly(None, step, params, drone, mode, position, args.controller)
    difference = np.linalg.norm(c_track - jax_track, axis=-1)
    result = {
        "controller": args.controller,
        "seconds": args.seconds,
        "largest_difference_m": float(difference.max()),
        "final_distance_to_setpoint_m": float(np.linalg.norm(c_track[-1] - position[-1])),
    }
    print(
        f"{args.seconds:g} s of a 0.5 m square: the firmware's C and jaxdrones' JAX {args.controller} controller "
        f"{result['largest_difference_m'] * 1e6:.1f} µm apart at most; the C's flight ends "
        f"{result['final_distance_to_setpoint_m'] * 100:.1f} cm from its setpoint"
    )
    write(args.out, result, position, c_track, jax_track, 1.0 / fw.RATE_MAIN_LOOP)
    return result


def _main_policy(cf: ModuleType, args: argparse.Namespace) -> dict:
    """``--policy``: `fly_policy` from the start of ``--seed``; prints and writes the figures."""
    from jaxdrones.training.checkpoint import load_policy

    env, _ = load_policy(args.policy)
    c_track, jax_track = fly_policy(cf, args.policy, jax.random.key(args.seed), args.cache)
    target = np.broadcast_to(np.asarray(env.default_task_params().target[0], np.float32), c_track.shape)
    result = {
        "policy": os.path.abspath(args.policy),
        "seed": args.seed,
        "seconds": len(c_track) / env.config.sim.ctrl_freq,
        "largest_difference_m": float(np.linalg.norm(c_track - jax_track, axis=-1).max()),
        "final_distance_to_target_m": float(np.linalg.norm(c_track[-1] - target[-1])),
    }
    print(
        f"{result['seconds']:g} s of {env.task.name}: the exported C policy with the firmware's C controller and the "
        f"JAX policy in its env {result['largest_difference_m'] * 1e6:.1f} µm apart at most; the C's flight ends "
        f"{result['final_distance_to_target_m'] * 100:.2f} cm from the target"
    )
    write(args.out, result, target, c_track, jax_track, 1.0 / env.config.sim.ctrl_freq)
    return result


def write(out: str, result: dict, position: np.ndarray, c_track: np.ndarray, jax_track: np.ndarray, dt: float) -> None:
    """``flight.json`` (the figures) and ``flight.png`` (both tracks from above and their distance; ``dt`` s between
    samples) in a new folder ``out``, moved into place when complete (an existing ``out`` is left as it is)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if os.path.exists(out):
        raise SystemExit(f"{out} exists: choose another --out (nothing was written)")
    tmp = tempfile.mkdtemp(prefix=".firmware-", dir=os.path.dirname(os.path.abspath(out)))
    with open(os.path.join(tmp, "flight.json"), "w") as f:
        json.dump(result, f, indent=2, allow_nan=False)
    fig, (top, side) = plt.subplots(1, 2, figsize=(10, 4))
    top.plot(position[:, 0], position[:, 1], "k:", label="setpoint")
    top.plot(c_track[:, 0], c_track[:, 1], label="firmware's C")
    top.plot(jax_track[:, 0], jax_track[:, 1], "--", label="jaxdrones' JAX")
    top.set(xlabel="x, m", ylabel="y, m", aspect="equal", title="from above")
    top.legend()
    t = np.arange(1, len(c_track) + 1) * dt
    side.plot(t, np.linalg.norm(c_track - jax_track, axis=-1) * 1e6)
    side.set(xlabel="time, s", ylabel="distance between the two, µm", title="C against JAX")
    fig.tight_layout()
    fig.savefig(os.path.join(tmp, "flight.png"), dpi=110)
    plt.close(fig)
    os.rename(tmp, out)
    print(f"saved flight.json, flight.png in {out}")


if __name__ == "__main__":
    main()
