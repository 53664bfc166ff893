"""Readers of real Crazyflie data: a thrust stand's sweep, Neural-Swarm's flight CSV and the firmware's uSD log.

Each reader returns NumPy arrays in SI units (docs/validation.md §1 lists the sources and their columns) and raises
``ValueError`` naming the file and what it expected where a file is not what it claims (a missing column, a wrong
magic byte, a failed checksum, a truncated record).

- `read_thrust_stand`: the CSV of a Crazyflie on a load cell with the system-ID deck (IMRCLab/crazyflie-system-id,
  ``data/bitcraze2021/*.csv``, MIT): ``weight[g],pwm,vbat[V],rpm1,rpm2,rpm3,rpm4,v[V],i[A],p[W]``.
- `read_flight_csv`: a flight of aerorobotics/neural-swarm (``data/training/*/*/cf*.csv``, written by its
  ``convertData.py`` from the uSD log): 30 columns from ``time[ms]`` to ``wz[rad/s]``.
- `read_usd`: the binary log of the micro-SD card deck, in both of the firmware's formats: the event-based one of
  today's firmware (magic byte 0xBC, versions 1 and 2: ``tools/usdlog/`` of bitcraze/crazyflie-firmware) and the
  fixed-frequency one of 2019-2020 that Neural-Swarm's flights were logged in (a column count, the columns'
  ``name(type)`` list, then blocks of records, each header and block closed by a CRC-32).
- `usd_flight`: the `FlightLog` of a uSD log holding Neural-Swarm's variables (``stateEstimateZ.*``, ``motor.f1-4``,
  ``pwm.m1_pwm-m4_pwm``, ``pm.vbatMV``), for the flights whose CSV was never published.
"""

from __future__ import annotations

import dataclasses
import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np

#: Standard gravity, m/s²: grams-force to newtons, and the gravity the firmware adds to its logged z acceleration
#: (``stateCompressed.az = (acc.z + 1) · 9.81 · 1000`` in ``src/modules/src/stabilizer.c``; 9.81 there).
STANDARD_GRAVITY = 9.80665
FIRMWARE_GRAVITY = 9.81

THRUST_STAND_COLUMNS = ("weight[g]", "pwm", "vbat[V]", "rpm1", "rpm2", "rpm3", "rpm4", "v[V]", "i[A]", "p[W]")
FLIGHT_CSV_COLUMNS = tuple(
    "time[ms],x[m],y[m],z[m],vx[m/s],vy[m/s],vz[m/s],ax[m/s^2],ay[m/s^2],az[m/s^2],qx,qy,qz,qw,u1[N],u2[N],u3[N],"
    "u4[N],u1[PWM],u2[PWM],u3[PWM],u4[PWM],Vbat[V],thrust_des[g],torquex[Nm],torquey[Nm],torquez[Nm],wx[rad/s],"
    "wy[rad/s],wz[rad/s]".split(",")
)
#: Seconds per tick of Neural-Swarm's logs: µs, though its CSV header says ``time[ms]`` (its drones log at 100 Hz,
#: ``config.txt``, and their ticks step by about 9,900, over flights of 18-65 s).
TICK_S = 1e-6
#: The struct codes a uSD log's variables may have (the firmware's log types: ``src/modules/interface/log.h``).
_USD_TYPES = frozenset("bBhHiIqQef")
#: Magic byte of the event-based uSD format (``usddeck.c``; ``tools/usdlog/cfusdlog.py``).
USD_MAGIC = 0xBC


@dataclasses.dataclass(frozen=True)
class ThrustStand:
    """A thrust-stand sweep, one row per sample.

    Attributes:
        thrust: f64[N] N, the measured thrust of all four motors (the load cell's grams × `STANDARD_GRAVITY`).
        pwm: f64[N], the PWM command of every motor (0-65535).
        vbat: f64[N] V, the battery voltage the Crazyflie measures.
        rpm: f64[N, 4] rev/min, each motor's speed (motor order M1-M4).
        voltage: f64[N] V, at the system-ID deck.
        current: f64[N] A, at the system-ID deck.
        power: f64[N] W, at the system-ID deck.
        source: the file read.
    """

    thrust: np.ndarray
    pwm: np.ndarray
    vbat: np.ndarray
    rpm: np.ndarray
    voltage: np.ndarray
    current: np.ndarray
    power: np.ndarray
    source: str


@dataclasses.dataclass(frozen=True)
class FlightLog:
    """One drone's flight, one row per log sample (Neural-Swarm: 100 Hz), in SI units and the world frame (z up).

    Attributes:
        time: f64[T] s, since the drone's log started (`TICK_S` per tick). Neural-Swarm's drones start their logs
            together (one broadcast command), so their clocks agree to the first sample (about 10 ms).
        pos: f64[T, 3] m, the onboard estimate (motion capture fused by the Kalman filter).
        vel: f64[T, 3] m/s, the onboard estimate.
        acc: f64[T, 3] m/s², the estimate's acceleration in the world frame, gravity removed (the logged z
            acceleration minus the firmware's 9.81).
        quat: f64[T, 4] (x, y, z, w), body → world.
        ang_vel: f64[T, 3] rad/s, body frame.
        motor_force: f64[T, 4] N, the force the controller asked of each motor (``motor.f1-4``).
        pwm: f64[T, 4], each motor's PWM duty cycle in [0, 1] (``pwm.m1_pwm`` / 65536).
        vbat: f64[T] V, the battery voltage.
        source: the file read.
    """

    time: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    quat: np.ndarray
    ang_vel: np.ndarray
    motor_force: np.ndarray
    pwm: np.ndarray
    vbat: np.ndarray
    source: str

    def __len__(self) -> int:
        return len(self.time)

    def select(self, mask: np.ndarray) -> FlightLog:
        """The samples where ``mask`` (bool[T]) holds."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "source"}
        return FlightLog(**{k: v[mask] for k, v in fields.items()}, source=self.source)


def _path(path: str | os.PathLike) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{str(path)!r} is not a file")
    return path


def _read_csv(path: Path, columns: tuple[str, ...], what: str) -> np.ndarray:
    """The numbers of a CSV whose first line names exactly ``columns`` (a leading ``#`` allowed): f64[N, C]."""
    with path.open(encoding="utf-8", errors="replace") as f:
        header = [c.strip() for c in f.readline().lstrip("#").strip().split(",")]
    if tuple(header) != columns:
        raise ValueError(f"{str(path)!r} is not {what}: its header is {header[:12]}, expected {list(columns)}")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"{str(path)!r} is not {what}: {e}") from None
    if data.shape[0] == 0 or data.shape[1] != len(columns):
        raise ValueError(f"{str(path)!r} holds no rows of {len(columns)} columns ({what})")
    if not np.all(np.isfinite(data)):
        raise ValueError(f"{str(path)!r} holds non-finite values")
    return data


def read_thrust_stand(path: str | os.PathLike) -> ThrustStand:
    """A thrust-stand CSV of IMRCLab/crazyflie-system-id (``data/bitcraze2021/*.csv``).

    Raises:
        ValueError: not a file; a header other than `THRUST_STAND_COLUMNS`; no rows, a row of another length, a
            value that is not a finite number.
    """
    path = _path(path)
    d = _read_csv(path, THRUST_STAND_COLUMNS, "a thrust-stand CSV")
    return ThrustStand(
        thrust=d[:, 0] * STANDARD_GRAVITY / 1000.0,
        pwm=d[:, 1],
        vbat=d[:, 2],
        rpm=d[:, 3:7],
        voltage=d[:, 7],
        current=d[:, 8],
        power=d[:, 9],
        source=str(path),
    )


def read_flight_csv(path: str | os.PathLike) -> FlightLog:
    """A flight CSV of aerorobotics/neural-swarm (``data/training/<collection>/<experiment>/cf<id>_<run>.csv``).

    Raises:
        ValueError: not a file; a header other than `FLIGHT_CSV_COLUMNS`; no rows, a row of another length, a
            value that is not a finite number; time not increasing.
    """
    path = _path(path)
    d = _read_csv(path, FLIGHT_CSV_COLUMNS, "a Neural-Swarm flight CSV")
    return _flight(
        d[:, 0] * TICK_S,
        d[:, 1:4],
        d[:, 4:7],
        d[:, 7:10],
        d[:, 10:14],
        d[:, 27:30],
        d[:, 14:18],
        d[:, 18:22],
        d[:, 22],
        str(path),
    )


def _flight(time, pos, vel, logged_acc, quat, ang_vel, motor_force, pwm, vbat, source: str) -> FlightLog:
    """The `FlightLog` of arrays in SI units; ``logged_acc`` as the firmware logs it, its z with gravity added."""
    if len(time) > 1 and not np.all(np.diff(time) > 0):
        raise ValueError(f"{source!r}: the time column does not increase")
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    acc = logged_acc - np.array([0.0, 0.0, FIRMWARE_GRAVITY])
    return FlightLog(time, pos, vel, acc, quat, ang_vel, motor_force, pwm, vbat, source)


def quat_decompress(packed: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) from the firmware's 32-bit compressed form (``quatcompress.h``: the index of the
    largest component in the top two bits, then the other three as sign and 9-bit magnitude over 1/√2, the last
    component in the lowest bits): f64[..., 4] from uint[...]."""
    packed = np.asarray(packed).astype(np.uint64)
    largest = (packed >> 30).astype(np.int64)
    q = np.zeros(packed.shape + (4,))
    mask = (1 << 9) - 1
    rest = packed.copy()
    for i in range(3, -1, -1):
        here = largest != i
        mag = (rest & mask).astype(np.float64) / mask * math.sqrt(0.5)
        neg = ((rest >> 9) & 1).astype(bool)
        q[..., i] = np.where(here, np.where(neg, -mag, mag), 0.0)
        rest = np.where(here, rest >> 10, rest)
    big = np.sqrt(np.clip(1.0 - np.sum(q**2, axis=-1), 0.0, None))
    np.put_along_axis(q, largest[..., None], big[..., None], axis=-1)
    return q


def read_usd(path: str | os.PathLike) -> dict[str, dict[str, np.ndarray]]:
    """A micro-SD deck log, in either of the firmware's formats: event name → variable → f64[n], with each event's
    ``timestamp`` among its variables (ms in the event-based format).

    The event-based format (first byte `USD_MAGIC`, versions 1 and 2) keeps one entry per event type that occurs;
    the fixed-frequency format of 2019-2020 firmware gives one event, ``"fixedFrequency"``, with its columns (the
    ``tick`` column, as logged, as its ``timestamp`` where it has one: µs in Neural-Swarm's logs, `TICK_S`).

    Raises:
        ValueError: not a file; an empty file, an unknown version, a variable type the firmware does not log, a
            failed CRC-32 (of the whole file, or of the header or a block of the older format), a record cut short
            or an event id the header does not define.
    """
    path = _path(path)
    data = path.read_bytes()
    if not data:
        raise ValueError(f"{str(path)!r} is empty: not a uSD log")
    if data[0] == USD_MAGIC:
        return _read_events(data, str(path))
    return {"fixedFrequency": _read_fixed(data, str(path))}


def _name(data: bytes, idx: int, end: bytes, source: str) -> tuple[str, int]:
    stop = data.find(end, idx)
    if stop < 0:
        raise ValueError(f"{source!r}: the header ends inside a name: not a uSD log")
    try:
        return data[idx:stop].decode("ascii"), stop + 1
    except UnicodeDecodeError:
        raise ValueError(f"{source!r}: a header name is not ASCII: not a uSD log") from None


def _variable(entry: str, source: str) -> tuple[str, str]:
    """``"name(t)"`` → (name, struct code)."""
    if len(entry) < 4 or entry[-3] != "(" or entry[-1] != ")" or entry[-2] not in _USD_TYPES:
        raise ValueError(
            f"{source!r}: {entry!r} is not a variable of a uSD log (name(type), type one of "
            f"{''.join(sorted(_USD_TYPES))})"
        )
    return entry[:-3].strip(), entry[-2]


def _read_events(data: bytes, source: str) -> dict[str, dict[str, np.ndarray]]:
    if len(data) < 9:
        raise ValueError(f"{source!r} is cut short: not a uSD log")
    (expected,) = struct.unpack("<I", data[-4:])
    if zlib.crc32(data[:-4]) != expected:
        raise ValueError(f"{source!r}: the CRC-32 of the log does not match (a damaged or truncated file)")
    version, n_events = struct.unpack("<HH", data[1:5])
    if version not in (1, 2):
        raise ValueError(f"{source!r}: uSD log version {version}; the versions read are 1 and 2")
    events, idx = {}, 5
    for _ in range(n_events):
        (event_id,) = struct.unpack("<H", data[idx : idx + 2])
        name, idx = _name(data, idx + 2, b"\0", source)
        (n_vars,) = struct.unpack("<H", data[idx : idx + 2])
        idx += 2
        variables = []
        for _ in range(n_vars):
            entry, idx = _name(data, idx, b"\0", source)
            variables.append(_variable(entry, source))
        events[event_id] = (name, variables, struct.Struct("<" + "".join(t for _, t in variables)))
    head = struct.Struct("<HI" if version == 1 else "<HQ")
    rows: dict[int, list] = {k: [] for k in events}
    end = len(data) - 4
    while idx < end:
        if idx + head.size > end:
            raise ValueError(f"{source!r}: a record is cut short at byte {idx}")
        event_id, stamp = head.unpack_from(data, idx)
        if event_id not in events:
            raise ValueError(f"{source!r}: event id {event_id} at byte {idx} is not in the header")
        record = events[event_id][2]
        if idx + head.size + record.size > end:
            raise ValueError(f"{source!r}: a record is cut short at byte {idx}")
        rows[event_id].append((stamp if version == 1 else stamp / 1000.0, *record.unpack_from(data, idx + head.size)))
        idx += head.size + record.size
    out = {}
    for event_id, (name, variables, _) in events.items():
        if rows[event_id]:
            table = np.asarray(rows[event_id], dtype=np.float64)
            out[name] = {"timestamp": table[:, 0], **{v: table[:, k + 1] for k, (v, _) in enumerate(variables)}}
    return out


def _crc_ok(block: bytes, stored: bytes) -> bool:
    """The older format's check: the stored word is the complement of the block's CRC-32 (little-endian)."""
    return len(stored) == 4 and struct.unpack("<I", stored)[0] == zlib.crc32(block) ^ 0xFFFFFFFF


def _read_fixed(data: bytes, source: str) -> dict[str, np.ndarray]:
    n_columns, idx = data[0], 1
    variables = []
    for _ in range(n_columns):
        entry, idx = _name(data, idx, b",", source)
        variables.append(_variable(entry, source))
    if not variables or not _crc_ok(data[:idx], data[idx : idx + 4]):
        raise ValueError(f"{source!r}: the header's CRC-32 does not match: not a uSD log, or a damaged one")
    record = struct.Struct("<" + "".join(t for _, t in variables))
    idx += 4
    rows = []
    while idx < len(data):
        count = data[idx]
        stop = idx + 1 + count * record.size
        if stop + 4 > len(data):
            raise ValueError(f"{source!r}: a block is cut short at byte {idx}")
        if not _crc_ok(data[idx:stop], data[stop : stop + 4]):
            raise ValueError(f"{source!r}: the CRC-32 of the block at byte {idx} does not match")
        rows.extend(record.iter_unpack(data[idx + 1 : stop]))
        idx = stop + 4
    table = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(variables))
    out = {name: table[:, k] for k, (name, _) in enumerate(variables)}
    if "tick" in out:
        out["timestamp"] = out["tick"]
    return out


#: The uSD variables `usd_flight` reads (Neural-Swarm's ``config.txt``), and the scale of each to SI units
#: (``convertData.py``'s: mm → m; the rates are logged in mrad/s).
_USD_FLIGHT = {
    "pos": (("stateEstimateZ.x", "stateEstimateZ.y", "stateEstimateZ.z"), 1e-3),
    "vel": (("stateEstimateZ.vx", "stateEstimateZ.vy", "stateEstimateZ.vz"), 1e-3),
    "acc": (("stateEstimateZ.ax", "stateEstimateZ.ay", "stateEstimateZ.az"), 1e-3),
    "ang_vel": (("stateEstimateZ.rateRoll", "stateEstimateZ.ratePitch", "stateEstimateZ.rateYaw"), 1e-3),
    "motor_force": (("motor.f1", "motor.f2", "motor.f3", "motor.f4"), 1.0),
    "pwm": (("pwm.m1_pwm", "pwm.m2_pwm", "pwm.m3_pwm", "pwm.m4_pwm"), 1.0 / 65536),
}


def usd_flight(log: dict[str, dict[str, np.ndarray]], source: str = "uSD log") -> FlightLog:
    """The `FlightLog` of a decoded uSD log (`read_usd`) that holds Neural-Swarm's variables, converted as its
    ``convertData.py`` converts them (positions mm → m, the compressed quaternion unpacked, PWM / 65536).

    Raises:
        ValueError: no event holds every variable needed (they are named).
    """
    needed = [n for names, _ in _USD_FLIGHT.values() for n in names]
    needed += ["tick", "stateEstimateZ.quat", "pm.vbatMV"]
    for variables in log.values():
        if all(n in variables for n in needed):
            break
    else:
        found = sorted({v for variables in log.values() for v in variables})
        missing = [n for n in needed if n not in found]
        raise ValueError(f"{source}: no event of the log holds Neural-Swarm's flight variables; missing {missing}")
    arrays = {k: np.stack([variables[n] for n in names], axis=-1) * scale for k, (names, scale) in _USD_FLIGHT.items()}
    quat = quat_decompress(variables["stateEstimateZ.quat"].astype(np.uint64))
    return _flight(
        variables["tick"] * TICK_S,
        arrays["pos"],
        arrays["vel"],
        arrays["acc"],
        quat,
        arrays["ang_vel"],
        arrays["motor_force"],
        arrays["pwm"],
        variables["pm.vbatMV"] / 1000.0,
        source,
    )
