"""Forces in flight: the residual force of logged Crazyflie flights against the model's ground effect, downwash and
drag, their constants fitted, and open-loop replays (docs/validation.md §3-§4).

The residual force of a drone is what its logged motion needs beyond gravity and its rotors' thrust:
F = m (a + g e_z) − R (Σ f_i) e_z, with a the onboard estimate's world-frame acceleration, R its attitude and f_i the
force the controller asked of each motor (``motor.f1-4``, which the firmware turns into PWM through its own thrust
map). Neural-Swarm's flights (aerorobotics/neural-swarm, ``data/training``) put one drone near the ground
(``randomwalk_*`` and ``takeoff_*``) or several above each other (``swap_*``: two or three drones exchanging places at
different heights); their logs start together, so a flight's drones share one clock (`align`).

The model's geometry is ``cf2x``'s (the paper's Crazyflie); the logged heights are shifted so that a drone resting on
the floor sits where the model's does (`FRAMES`).
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.physics.aerodynamics import downwash_force, drag_force, ground_effect_thrust
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.params import DroneParams, broadcast_params, load_params, with_derived
from jaxdrones.physics.rotations import quat_to_rotmat
from jaxdrones.physics.state import init_state
from jaxdrones.physics.step import rollout
from jaxdrones.sim import make_step
from jaxdrones.validation.readers import FIRMWARE_GRAVITY, FlightLog, read_flight_csv, read_usd, usd_flight

#: The drones of Neural-Swarm's flights by their number (the ``cf<id>`` of a file's name): mass, kg, and the height
#: the motion capture reports for the drone resting on the floor, m (the collections' ``readme.txt``, "ground
#: plane"). CF50-52: Crazyflie 2.1, stock (33 g: ``hardware/datacollection/plotControllerTuning.py``); CF101, CF102:
#: Crazyflie 2.1 on Parrot frames (67 g: ``parrot_frame.txt``). CF100 (a Crazyflie 2.0 on a Parrot frame) is not
#: here: the readme warns that its IMU spoils its force estimate; it still counts as a source of downwash.
FRAMES = {50: (0.033, 0.05), 51: (0.033, 0.05), 52: (0.033, 0.05), 101: (0.067, 0.06), 102: (0.067, 0.06)}
#: The Parrot frames' mass and floor height, for CF100 (its own force is not scored).
PARROT = (0.067, 0.06)
#: The model's resting height, m: ``cf2x``'s collision cylinder's half-length (its URDF).
REST_HEIGHT = 0.0125
#: The log rate the flights are resampled to, Hz (the logs' own: 100 Hz, `config.txt`).
RATE = 100.0


@dataclasses.dataclass(frozen=True)
class Formation:
    """The drones of one flight on one time grid.

    Attributes:
        names: the drones' file names (``cf50_00``, ...), D of them.
        ids: i[D] each drone's number.
        time: f64[T] s.
        pos: f64[T, D, 3] m, world frame; z shifted so that the model's resting height (``cf2x``'s collision
            half-length, 0.0125 m) is the drone's on the floor.
        vel: f64[T, D, 3] m/s, world frame.
        acc: f64[T, D, 3] m/s², world frame, gravity removed.
        quat: f64[T, D, 4] (x, y, z, w), body → world.
        ang_vel: f64[T, D, 3] rad/s, body frame.
        motor_force: f64[T, D, 4] N.
        mass: f64[D] kg.
        scored: bool[D] whether the drone's own force is scored (not CF100).
        rotmat: f64[T, D, 3, 3] body → world, from ``quat``.
    """

    names: tuple[str, ...]
    ids: np.ndarray
    time: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    quat: np.ndarray
    ang_vel: np.ndarray
    motor_force: np.ndarray
    mass: np.ndarray
    scored: np.ndarray
    rotmat: np.ndarray


def drone_id(path: str | os.PathLike) -> int:
    """The drone's number in a Neural-Swarm file name (``cf101_06`` → 101).

    Raises:
        ValueError: a name not of the form ``cf<id>_<run>`` (with an optional ``.csv``).
    """
    match = re.fullmatch(r"cf(\d+)_\d+(\.csv)?", Path(path).name)
    if not match:
        raise ValueError(f"{str(path)!r} is not a Neural-Swarm flight file (cf<id>_<run>, or .csv)")
    return int(match.group(1))


def read_flight(path: str | os.PathLike) -> FlightLog:
    """A Neural-Swarm flight from its CSV (``.csv``) or its binary uSD log (the same name without it)."""
    return read_flight_csv(path) if str(path).endswith(".csv") else usd_flight(read_usd(path), str(path))


def align(flights: Sequence[FlightLog], rate: float = RATE) -> Formation:
    """The drones of one flight (each file a `FlightLog`, in any order) resampled at ``rate`` Hz over the span all of
    them logged: linear interpolation, the quaternions normalised after it.

    Raises:
        ValueError: no flights; their logs do not overlap; a file of a drone not in `FRAMES` nor CF100.
    """
    if not flights:
        raise ValueError("align: no flights given")
    ids = np.array([drone_id(f.source) for f in flights])
    unknown = [int(i) for i in ids if i not in FRAMES and i != 100]
    if unknown:
        raise ValueError(f"drones {unknown} are not among Neural-Swarm's ({sorted(FRAMES)} and 100)")
    start, stop = max(f.time[0] for f in flights), min(f.time[-1] for f in flights)
    if stop - start < 2 / rate:
        raise ValueError(f"the logs {[f.source for f in flights]} do not overlap in time")
    grid = np.arange(start, stop, 1 / rate)

    def resample(name: str) -> np.ndarray:
        out = [np.stack([np.interp(grid, f.time, c) for c in getattr(f, name).T], -1) for f in flights]
        return np.stack(out, axis=1)

    frames = np.array([FRAMES.get(int(i), PARROT) for i in ids])
    pos = resample("pos")
    pos[..., 2] -= frames[:, 1] - REST_HEIGHT
    quat = resample("quat")
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return Formation(
        names=tuple(Path(f.source).name.removesuffix(".csv") for f in flights),
        ids=ids,
        time=grid,
        pos=pos,
        vel=resample("vel"),
        acc=resample("acc"),
        quat=quat,
        ang_vel=resample("ang_vel"),
        motor_force=resample("motor_force"),
        mass=frames[:, 0],
        scored=ids != 100,
        rotmat=np.asarray(quat_to_rotmat(jnp.asarray(quat, jnp.float32)), np.float64),
    )


def residual_force(form: Formation, smooth_s: float = 0.1) -> np.ndarray:
    """f64[T, D, 3] N, world frame: m (a + g e_z) − R (Σ f_i) e_z, each component smoothed by a centred moving
    average over ``smooth_s`` s (0: none; the acceleration estimate's noise, about 3.6 g RMS on a drone alone, would
    otherwise set the floor of every error). g is the firmware's 9.81 m/s²."""
    thrust = np.sum(form.motor_force, axis=-1)[..., None] * form.rotmat[..., :, 2]
    force = form.mass[:, None] * (form.acc + np.array([0.0, 0.0, FIRMWARE_GRAVITY])) - thrust
    width = max(int(round(smooth_s * RATE)), 1)
    if width == 1:
        return force
    kernel = np.ones(width) / width
    flat = force.reshape(len(force), -1)
    smooth = np.stack([np.convolve(c, kernel, mode="same") for c in flat.T], -1)
    edge = width // 2  # the first and last samples average over fewer: left as they are
    smooth[:edge], smooth[len(smooth) - edge :] = flat[:edge], flat[len(flat) - edge :]
    return smooth.reshape(force.shape)


def model_params(form: Formation, model: str = "cf2x") -> DroneParams:
    """``model``'s params for each drone of ``form``, batch [D], with the drones' masses."""
    params = broadcast_params(load_params(model), (len(form.ids),))
    return with_derived(params.replace(mass=jnp.asarray(form.mass, params.mass.dtype)))


def motor_rpm(form: Formation, params: DroneParams) -> jax.Array:
    """f[T, D, 4] rev/min: the speed at which each motor makes its logged force with the model's kf, √(f / kf)."""
    return jnp.sqrt(jnp.maximum(jnp.asarray(form.motor_force), 0.0) / params.kf[None, :, None])


def ground_z(form: Formation, params: DroneParams, coeff: jax.Array) -> jax.Array:
    """f[T, D] N: the world-z force of the paper's ground effect (eq. ground, per propeller, on the logged heights,
    attitudes and motor forces) with coefficient ``coeff`` (f[1], C_gnd; the model's is ``params.gnd_eff_coeff``)."""
    params = with_derived(params.replace(gnd_eff_coeff=jnp.broadcast_to(coeff[0], params.gnd_eff_coeff.shape)))
    rot = jnp.asarray(form.rotmat)
    extra = ground_effect_thrust(params, jnp.asarray(form.pos), rot, jnp.asarray(form.motor_force))
    return jnp.sum(extra, axis=-1) * rot[..., 2, 2]


def downwash_paper_z(form: Formation, params: DroneParams, coeff: jax.Array) -> jax.Array:
    """f[T, D] N: the world-z force of the paper's downwash (eq. down) on each drone from the others, with constants
    ``coeff`` (f[3], c1, c2, c3; the model's are ``params.dw_coeff``)."""
    params = params.replace(dw_coeff=jnp.broadcast_to(coeff, params.dw_coeff.shape))
    return downwash_force(params, jnp.asarray(form.pos)) * jnp.asarray(form.rotmat)[..., 2, 2]


def downwash_bounded_z(form: Formation, params: DroneParams, coeff: jax.Array) -> jax.Array:
    """f[T, D] N: the world-z force of the bounded downwash (`jaxdrones.physics.aerodynamics.downwash_force` with
    ``bounded=coeff``, f[4]) on each drone from the others, at the logged thrusts."""
    thrust = jnp.sum(jnp.asarray(form.motor_force), axis=-1)
    force = downwash_force(params, jnp.asarray(form.pos), bounded=coeff, thrust=thrust)
    return force * jnp.asarray(form.rotmat)[..., 2, 2]


def drag_xy(form: Formation, params: DroneParams, coeff: jax.Array) -> jax.Array:
    """f[T, D, 2] N: the horizontal world-frame force of the paper's drag (eq. drag) at the logged velocities, with
    c_xy = ``coeff`` (f[1]), the motors at the speeds that give the logged forces with the model's kf."""
    drag = jnp.broadcast_to(jnp.stack([coeff[0], coeff[0], params.drag_coeff[..., 2].mean()]), params.drag_coeff.shape)
    return drag_force(params.replace(drag_coeff=drag), jnp.asarray(form.vel), motor_rpm(form, params))[..., :2]


def lagged_thrust_z(form: Formation, tau: jax.Array) -> jax.Array:
    """f[T, D] N: the world-z thrust the motors lag behind, R₂₂ (T_lag − T), with T the logged total force and
    T_lag it through a first-order lag of time constant ``tau`` (f[1], s), sampled at `RATE` (the residual a
    model without motor lag leaves)."""
    thrust = jnp.sum(jnp.asarray(form.motor_force), axis=-1)
    keep = jnp.exp(-1.0 / (RATE * tau[0]))

    def step(lag, command):
        lag = keep * lag + (1 - keep) * command
        return lag, lag

    _, lagged = jax.lax.scan(step, thrust[0], thrust)
    return (lagged - thrust) * jnp.asarray(form.rotmat)[..., 2, 2]


def pairs(form: Formation) -> tuple[np.ndarray, np.ndarray]:
    """(Δz f64[T, D, D], d² f64[T, D, D]): for each drone j (axis 1) and other drone i (axis 2), z_i − z_j (m) and
    the squared horizontal distance (m²); Δz is 0 on the diagonal."""
    delta = form.pos[:, None, :, :] - form.pos[:, :, None, :]
    return delta[..., 2], np.sum(delta[..., :2] ** 2, axis=-1)


def crossing(form: Formation, radius: float = 0.15, min_dz: float = 0.05) -> np.ndarray:
    """bool[T, D]: another drone is above, higher by more than ``min_dz`` m and within ``radius`` m horizontally."""
    dz, d2 = pairs(form)
    return np.any((dz > min_dz) & (d2 < radius**2), axis=-1)


def near_ground(form: Formation, height: float = 0.2, touch: float = 0.02) -> np.ndarray:
    """bool[T, D]: the drone flies below ``height`` m above its resting height, and higher than ``touch`` m above
    it (a drone on or touching the floor feels its contact force, not only the air)."""
    above = form.pos[..., 2] - REST_HEIGHT
    return (above < height) & (above > touch)


def alone(form: Formation, radius: float = 0.5) -> np.ndarray:
    """bool[T, D]: no other drone within ``radius`` m horizontally, above or below."""
    _, d2 = pairs(form)
    far = (d2 > radius**2) | np.eye(len(form.ids), dtype=bool)
    return np.all(far, axis=-1)


def reference(form: Formation, height: float = 0.25, radius: float = 0.3) -> np.ndarray:
    """bool[T, D]: the samples a drone's thrust offset is taken from: higher than ``height`` m above its resting
    height (the model's ground effect below 0.4 % of the thrust there) and no other drone above within ``radius`` m
    horizontally."""
    return (form.pos[..., 2] - REST_HEIGHT > height) & ~crossing(form, radius=radius, min_dz=0.0)


def offset_removed(form: Formation, residual: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``residual`` f[T, D, ...] less each drone's median over its ``ref`` samples (bool[T, D]): the offset of its
    thrust map and mass, which differ from drone to drone and with the battery; a drone without reference samples
    keeps its residual."""
    out = residual.copy()
    for j in range(residual.shape[1]):
        if ref[:, j].any():
            out[:, j] -= np.median(residual[ref[:, j], j], axis=0)
    return out


def load_runs(folder: str | os.PathLike, together: bool = True) -> list[Formation]:
    """The flights of one experiment folder of Neural-Swarm (its binary logs ``cf<id>_<run>``): with ``together``,
    the files of each run number as one formation (the drones flew together), else each file on its own.

    Raises:
        ValueError: a folder without logs; what `align` or the readers raise.
    """
    paths = sorted(p for p in Path(folder).glob("cf*") if p.suffix != ".csv" and re.fullmatch(r"cf\d+_\d+", p.name))
    if not paths:
        raise ValueError(f"{str(folder)!r} holds no Neural-Swarm flight logs (cf<id>_<run>)")
    groups: dict[str, list[Path]] = {}
    for p in paths:
        groups.setdefault(p.name.rsplit("_", 1)[1] if together else p.name, []).append(p)
    return [align([read_flight(p) for p in group]) for group in groups.values()]


#: The horizons of `replay_errors`, s.
HORIZONS = (0.1, 0.5, 1.0)


def replay_errors(
    form: Formation,
    params: DroneParams,
    config: SimConfig,
    horizons: Sequence[float] = HORIZONS,
    every_s: float = 0.5,
) -> np.ndarray:
    """Open-loop replays: from every ``every_s`` s of the log, the logged state of every drone stepped by the
    simulator (``config``: its rates and effects, ``ctrl_freq`` = `RATE`) under the logged motor forces (each
    motor's RPM = √(f / kf), held for a control step), the position error against the log after each horizon.

    Returns:
        f64[S, H, D] m: for each of the S starts and H horizons, each drone's distance from its logged position.

    Raises:
        ValueError: ``config.ctrl_freq`` other than `RATE` or ``config.n_drones`` other than the formation's; a log
            shorter than the longest horizon.
    """
    steps = [int(round(h * RATE)) for h in horizons]
    if config.ctrl_freq != RATE or config.n_drones != len(form.ids):
        raise ValueError(f"replay_errors: config must step {len(form.ids)} drones at {RATE:g} Hz, got {config}")
    if len(form.time) <= max(steps):
        raise ValueError(f"replay_errors: the log ({len(form.time)} samples) is shorter than {max(horizons)} s")
    starts = np.arange(0, len(form.time) - max(steps), max(int(round(every_s * RATE)), 1))
    rpm = np.asarray(motor_rpm(form, params))
    commands = np.stack([rpm[s : s + max(steps)] for s in starts], axis=1)  # [T, S, D, 4]
    state = init_state(
        config,
        pos=form.pos[starts],
        quat=form.quat[starts],
        vel=form.vel[starts],
        ang_vel=form.ang_vel[starts],
        rpm=rpm[starts],
    )
    path = np.asarray(rollout(make_step(config), params, state, jnp.asarray(commands, state.pos.dtype)).pos)
    logged = np.stack([form.pos[starts + k] for k in steps], axis=1)  # [S, H, D, 3]
    return np.linalg.norm(path[np.array(steps) - 1].transpose(1, 0, 2, 3) - logged, axis=-1)
