"""Quadrotor parameters: the `DroneParams` pytree and the host-side URDF loader.

Every constant comes from a URDF (`assets/*.urdf`): the `<properties>` element, the `base_link` inertial block and
the `prop{i}_link` inertial origins. The derived quantities (hover and maximum RPM, maximum thrust and torques,
ground-effect height clip) follow gym-pybullet-drones' `BaseAviary.__init__` (docs/physics.md §1.1).
"""

from __future__ import annotations

import dataclasses
import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from importlib import resources
from types import ModuleType
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

#: Standard gravity used by the paper's code (never 9.81), m/s².
GRAVITY = 9.8

#: Model names that ship with the package (`assets/<name>.urdf`).
MODELS = ("cf2x", "cf2p", "racer")

#: Optional ``<properties>`` attributes, 0 when absent: the motors' time constants, s (`DroneParams.motor_tau_up`).
_OPTIONAL_KEYS = ("motor_tau_up", "motor_tau_down")
_PROPERTY_KEYS = (
    "arm",
    "kf",
    "km",
    "thrust2weight",
    "max_speed_kmh",
    "gnd_eff_coeff",
    "prop_radius",
    "drag_coeff_xy",
    "drag_coeff_z",
    "dw_coeff_1",
    "dw_coeff_2",
    "dw_coeff_3",
    "frame",
    "prop_spin",
)


@struct.dataclass
class DroneParams:
    """Physical parameters of one quadrotor model, as a pytree of float arrays.

    All leaves have JAX's default float dtype (float32, or float64 under ``jax_enable_x64``). Leaves may carry
    leading batch axes, right-aligned with the state's ``[..., D]``: per-drone ``[D]`` or ``[W, D]`` for
    heterogeneous teams, per-world ``[W, 1]`` for domain randomisation (or ``vmap`` over worlds); the shapes below
    are those of one drone. Motor speed is in RPM (rev/min), as in the paper and its URDFs.

    Attributes:
        mass: f[] kg (URDF ``base_link`` inertial mass).
        arm: f[] m, the paper's arm length L (URDF ``properties/@arm``).
        inertia: f[3, 3] kg·m², body frame, J = diag(ixx, iyy, izz) plus products (URDF ``base_link`` inertia).
        inertia_inv: f[3, 3] 1/(kg·m²), J⁻¹.
        kf: f[] N/rpm², thrust per squared RPM.
        km: f[] N·m/rpm², reaction torque per squared RPM.
        thrust2weight: f[] maximum thrust over weight (-).
        max_speed_kmh: f[] km/h, the airframe's nominal maximum speed.
        prop_radius: f[] m.
        gnd_eff_coeff: f[] ground-effect coefficient C_gnd (-), paper eq. (ground).
        drag_coeff: f[3] N·s/m per rad/s, (c_xy, c_xy, c_z), paper eq. (drag).
        dw_coeff: f[3] downwash coefficients (c1 N, c2 -, c3 m), paper eq. (down).
        prop_pos: f[4, 3] m, body-frame motor positions (URDF ``prop{i}_link`` inertial origins).
        prop_spin: f[4] +1 for a counter-clockwise motor seen from above (yaw reaction -km·rpm²), -1 for clockwise.
        torque_arm: f[2, 4] m, the explicit-dynamics lever arms: body (τx, τy) = torque_arm @ thrusts.
            x frame: L/√2 along each motor's diagonal; + frame: L along its axis (docs/physics.md §3.1).
        gravity: f[] m/s², 9.8 as in the paper's code.
        collision_radius: f[] m, radius of the collision cylinder.
        collision_height: f[] m, length of the collision cylinder (centred on the base origin).
        hover_rpm: f[] RPM, √(m g / (4 kf)).
        max_rpm: f[] RPM, √(t2w · m g / (4 kf)).
        max_thrust: f[] N, 4 kf max_rpm².
        max_xy_torque: f[] N·m, 2 L kf max_rpm²/√2 (x frame) or L kf max_rpm² (+ frame).
        max_z_torque: f[] N·m, 2 km max_rpm².
        gnd_eff_h_clip: f[] m, (R/4)·√(15 C_gnd / 4): below it the ground-effect height is clipped.
        motor_tau_up: f[] s, the motors' time constant while speeding up, for first-order motor dynamics
            (`jaxdrones.physics.config.SimConfig.motor_dynamics`, docs/physics.md §3.3); 0 = the commanded speed at
            once. URDF ``properties/@motor_tau_up`` when given, else 0 (the paper's instant motors).
        motor_tau_down: f[] s, the same while slowing down (``properties/@motor_tau_down``, else 0).
    """

    mass: jax.Array
    arm: jax.Array
    inertia: jax.Array
    inertia_inv: jax.Array
    kf: jax.Array
    km: jax.Array
    thrust2weight: jax.Array
    max_speed_kmh: jax.Array
    prop_radius: jax.Array
    gnd_eff_coeff: jax.Array
    drag_coeff: jax.Array
    dw_coeff: jax.Array
    prop_pos: jax.Array
    prop_spin: jax.Array
    torque_arm: jax.Array
    gravity: jax.Array
    collision_radius: jax.Array
    collision_height: jax.Array
    hover_rpm: jax.Array
    max_rpm: jax.Array
    max_thrust: jax.Array
    max_xy_torque: jax.Array
    max_z_torque: jax.Array
    gnd_eff_h_clip: jax.Array
    motor_tau_up: jax.Array
    motor_tau_down: jax.Array

    @property
    def weight(self) -> jax.Array:
        """f[] N, m·g."""
        return self.mass * self.gravity


#: Number of trailing (per-drone) axes of each `DroneParams` field; the other fields are per-drone scalars.
CORE_NDIM = {
    "inertia": 2,
    "inertia_inv": 2,
    "prop_pos": 2,
    "torque_arm": 2,
    "drag_coeff": 1,
    "dw_coeff": 1,
    "prop_spin": 1,
}


def params_batch_shape(params: DroneParams) -> tuple[int, ...]:
    """The leading batch shape shared by all fields of ``params`` (``()`` for one model).

    Raises:
        ValueError: if the fields disagree on it.
    """
    shapes = {}
    for field in dataclasses.fields(params):
        shape = np.shape(getattr(params, field.name))  # a Python number (params.replace(kf=...)) too
        core = CORE_NDIM.get(field.name, 0)
        shapes[field.name] = tuple(shape[: len(shape) - core])
    batch = shapes["mass"]
    odd = {k: v for k, v in shapes.items() if v != batch}
    if odd:
        raise ValueError(f"DroneParams fields have different batch shapes: mass {batch}, {odd}")
    return batch


def broadcast_params(params: DroneParams, lead: tuple[int, ...], xp: ModuleType = jnp) -> DroneParams:
    """Broadcast every field of ``params`` to the batch shape ``lead`` (e.g. a state's ``[..., D]``).

    Args:
        params: DroneParams whose batch shape broadcasts to ``lead`` (right-aligned, see `params_batch_shape`).
        lead: the target batch shape.
        xp: the array module, ``jax.numpy`` (default) or ``numpy`` (host-side arrays).

    Raises:
        ValueError: if a field does not broadcast to ``lead``.
    """

    def widen(name, leaf):
        core = CORE_NDIM.get(name, 0)
        shape = tuple(lead) + tuple(leaf.shape[leaf.ndim - core :])
        try:
            return xp.broadcast_to(xp.asarray(leaf), shape)
        except ValueError:
            raise ValueError(
                f"DroneParams.{name} of shape {leaf.shape} does not broadcast to the batch shape {tuple(lead)}"
            ) from None

    return DroneParams(**{f.name: widen(f.name, getattr(params, f.name)) for f in dataclasses.fields(params)})


def align_params(params: DroneParams, ndim: int) -> DroneParams:
    """``params`` with singleton axes prepended to each field's batch shape up to ``ndim`` axes (nothing is copied).

    Per-model params ``()`` and per-drone params ``[D]`` then combine with a state's f[..., D] components at one
    rank, as `jax.numpy`'s strict rank promotion (``jax_numpy_rank_promotion="raise"``) asks; the sizes still
    broadcast right-aligned, e.g. ``[D]`` becomes ``[1, D]`` against ``[W, D]``.

    Args:
        params: DroneParams whose batch shape has at most ``ndim`` axes.
        ndim: the rank of the batch shape to reach, e.g. ``state.pos.ndim - 1``.

    Raises:
        ValueError: if the params' batch shape has more than ``ndim`` axes.
    """
    batch = params_batch_shape(params)
    if len(batch) > ndim:
        raise ValueError(f"params have batch shape {batch}, more than the {ndim} axes of the state's [..., D]")
    extra = (1,) * (ndim - len(batch))
    if not extra:
        return params
    return jax.tree.map(lambda leaf: jnp.reshape(leaf, extra + jnp.shape(leaf)), params)


def pack_params(
    params: DroneParams, lead: tuple[int, ...]
) -> tuple[jax.Array, Callable[[jax.Array | np.ndarray], DroneParams]]:
    """Pack params of batch shape ``lead`` into one array f[*lead, K], and return it with its inverse.

    Used to hand params to a host callback as a single array. The inverse takes an array f[*L, K] (``L`` may
    have extra leading axes, e.g. from ``vmap``) and returns NumPy DroneParams of batch shape ``L``.
    """
    lead = tuple(lead)
    names = [f.name for f in dataclasses.fields(params)]
    cores = [tuple(getattr(params, n).shape[len(lead) :]) for n in names]
    packed = jnp.concatenate([jnp.reshape(getattr(params, n), lead + (-1,)) for n in names], axis=-1)
    sizes = np.cumsum([math.prod(c) for c in cores])[:-1]

    def unpack(array: jax.Array | np.ndarray) -> DroneParams:
        array = np.asarray(array)
        parts = np.split(array, sizes, axis=-1)
        return DroneParams(
            **{n: part.reshape(array.shape[:-1] + core) for n, part, core in zip(names, parts, cores, strict=True)}
        )

    return packed, unpack


def model_path(name: str) -> str:
    """Path of a shipped model's URDF.

    Raises:
        ValueError: if ``name`` is not one of `MODELS`.
    """
    if name not in MODELS:
        raise ValueError(f"unknown drone model {name!r}: expected one of {MODELS} or a path to a .urdf file")
    return str(resources.files("jaxdrones.assets").joinpath(f"{name}.urdf"))


def load_params(name_or_path: str | os.PathLike = "cf2x") -> DroneParams:
    """Load a quadrotor model from a shipped name or a URDF path (host side, not jittable).

    Args:
        name_or_path: ``"cf2x"``, ``"cf2p"``, ``"racer"``, or the path of a URDF written like those in ``assets/``.

    Returns:
        DroneParams with unbatched leaves in JAX's default float dtype.

    Raises:
        ValueError: unknown model name, missing or unreadable file, malformed XML, a missing or non-numeric
            property, or a physically invalid model (mass ≤ 0, inertia not symmetric positive definite,
            kf/km/arm/prop_radius/thrust2weight ≤ 0, thrust-to-weight ≤ 1, not 4 motors, spins not ±1).
    """
    path = os.fspath(name_or_path)
    if not path.endswith(".urdf") and os.sep not in path:
        path = model_path(path)
    if not os.path.isfile(path):
        raise ValueError(f"drone model file not found: {path!r}")
    raw = _parse_urdf(path)
    return _derive(raw, path)


def _parse_urdf(path: str) -> dict:
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        raise ValueError(f"{path}: malformed URDF XML ({err})") from None
    props = root.find("properties")
    if props is None:
        raise ValueError(f"{path}: missing <properties> element with the drone constants")
    raw: dict = {}
    for key in _PROPERTY_KEYS:
        if key not in props.attrib:
            raise ValueError(f"{path}: <properties> lacks attribute {key!r}")
    for key in _PROPERTY_KEYS[:-2]:
        raw[key] = _number(path, f"properties/@{key}", props.attrib[key])
    raw["frame"] = props.attrib["frame"].strip()
    if raw["frame"] not in ("x", "+"):
        raise ValueError(f"{path}: properties/@frame must be 'x' or '+', got {raw['frame']!r}")
    raw["prop_spin"] = [_number(path, "properties/@prop_spin", s) for s in props.attrib["prop_spin"].split()]
    for key in _OPTIONAL_KEYS:  # optional: the paper's models have instant motors
        raw[key] = _number(path, f"properties/@{key}", props.attrib[key]) if key in props.attrib else 0.0

    links = {link.get("name"): link for link in root.findall("link")}
    base = links.get("base_link")
    if base is None:
        raise ValueError(f"{path}: missing link 'base_link'")
    raw["mass"] = _number(path, "base_link mass", _attr(path, base, "inertial/mass", "value"))
    inertia = base.find("inertial/inertia")
    if inertia is None:
        raise ValueError(f"{path}: base_link lacks <inertial><inertia>")
    i = {
        k: _number(path, f"base_link inertia/@{k}", inertia.get(k, "0" if k[1] != k[2] else None))
        for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")
    }
    raw["inertia"] = [[i["ixx"], i["ixy"], i["ixz"]], [i["ixy"], i["iyy"], i["iyz"]], [i["ixz"], i["iyz"], i["izz"]]]
    cyl = base.find("collision/geometry/cylinder")
    if cyl is None:
        raise ValueError(f"{path}: base_link lacks a <collision><geometry><cylinder>")
    raw["collision_radius"] = _number(path, "collision cylinder radius", cyl.get("radius"))
    raw["collision_height"] = _number(path, "collision cylinder length", cyl.get("length"))

    prop_pos = []
    for k in range(4):
        link = links.get(f"prop{k}_link")
        if link is None:
            raise ValueError(f"{path}: missing link 'prop{k}_link' (a quadrotor needs motors 0-3)")
        xyz = _attr(path, link, "inertial/origin", "xyz").split()
        if len(xyz) != 3:
            raise ValueError(f"{path}: prop{k}_link inertial origin xyz must have 3 numbers, got {xyz}")
        prop_pos.append([_number(path, f"prop{k}_link origin", v) for v in xyz])
    raw["prop_pos"] = prop_pos
    return raw


def _attr(path: str, elem: ET.Element, sub: str, attr: str) -> str:
    node = elem.find(sub)
    if node is None or node.get(attr) is None:
        raise ValueError(f"{path}: link {elem.get('name')!r} lacks <{sub} {attr}=...>")
    return node.get(attr)


def _number(path: str, what: str, text: str | None) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {what} must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{path}: {what} must be finite, got {text!r}")
    return value


def _check_physical(raw: dict, path: str) -> None:
    if raw["mass"] <= 0:
        raise ValueError(f"{path}: mass must be > 0 kg, got {raw['mass']}")
    inertia = np.asarray(raw["inertia"])
    if np.any(np.linalg.eigvalsh(inertia) <= 0):
        raise ValueError(
            f"{path}: inertia must be symmetric positive definite, got eigenvalues {np.linalg.eigvalsh(inertia)} kg·m²"
        )
    for key in ("arm", "kf", "km", "prop_radius", "collision_radius", "collision_height"):
        if raw[key] <= 0:
            raise ValueError(f"{path}: {key} must be > 0, got {raw[key]}")
    if raw["thrust2weight"] <= 1:
        raise ValueError(
            f"{path}: thrust2weight must be > 1 (the drone must be able to hover), got {raw['thrust2weight']}"
        )
    for key in ("max_speed_kmh", "gnd_eff_coeff", "drag_coeff_xy", "drag_coeff_z", "dw_coeff_1", *_OPTIONAL_KEYS):
        if raw[key] < 0:
            raise ValueError(f"{path}: {key} must be >= 0, got {raw[key]}")
    spin = raw["prop_spin"]
    if len(spin) != 4 or any(s not in (-1.0, 1.0) for s in spin):
        raise ValueError(f"{path}: prop_spin must be 4 values of +1 or -1, got {spin}")


def _torque_arm(frame: str, arm: float, prop_pos: np.ndarray) -> np.ndarray:
    """Explicit-dynamics lever arms (docs/physics.md §3.1): (τx, τy) = torque_arm @ thrusts.

    A motor at body (x, y) produces τx = y·f and τy = -x·f. The paper's explicit update places each motor at
    distance L along its diagonal (x frame, |x| = |y| = L/√2) or its axis (+ frame).
    """
    if frame == "x":
        xy = arm / math.sqrt(2.0) * np.sign(prop_pos[:, :2])
    else:
        xy = arm * np.round(prop_pos[:, :2] / np.linalg.norm(prop_pos[:, :2], axis=1, keepdims=True))
    return np.stack([xy[:, 1], -xy[:, 0]])


def _derive(raw: dict, path: str) -> DroneParams:
    _check_physical(raw, path)
    prop_pos = np.asarray(raw["prop_pos"])
    if np.any(np.linalg.norm(prop_pos[:, :2], axis=1) == 0):
        raise ValueError(f"{path}: every motor must sit off the body z axis, got positions {prop_pos.tolist()}")
    inertia = np.asarray(raw["inertia"])
    values = dict(
        mass=raw["mass"],
        arm=raw["arm"],
        inertia=inertia,
        kf=raw["kf"],
        km=raw["km"],
        thrust2weight=raw["thrust2weight"],
        max_speed_kmh=raw["max_speed_kmh"],
        prop_radius=raw["prop_radius"],
        gnd_eff_coeff=raw["gnd_eff_coeff"],
        drag_coeff=[raw["drag_coeff_xy"], raw["drag_coeff_xy"], raw["drag_coeff_z"]],
        dw_coeff=[raw["dw_coeff_1"], raw["dw_coeff_2"], raw["dw_coeff_3"]],
        prop_pos=prop_pos,
        prop_spin=raw["prop_spin"],
        torque_arm=_torque_arm(raw["frame"], raw["arm"], prop_pos),
        gravity=GRAVITY,
        collision_radius=raw["collision_radius"],
        collision_height=raw["collision_height"],
        motor_tau_up=raw["motor_tau_up"],
        motor_tau_down=raw["motor_tau_down"],
    )
    values = {k: np.asarray(v, dtype=np.float64) for k, v in values.items()}
    derived = derive_params(_PrimaryParams(**values), xp=np)  # in float64, then cast once
    dtype = np.dtype(jnp.result_type(float))
    # Cast on the host and copied once: no device program compiled (each costs a compilation on a GPU).
    return jax.device_put(DroneParams(**{k: np.asarray(v, dtype=dtype) for k, v in {**values, **derived}.items()}))


#: The `DroneParams` fields computed from the others by `derive_params`.
DERIVED_FIELDS = (
    "inertia_inv",
    "hover_rpm",
    "max_rpm",
    "max_thrust",
    "max_xy_torque",
    "max_z_torque",
    "gnd_eff_h_clip",
)


class _PrimaryParams(NamedTuple):
    """The primary fields of a model, before `derive_params` (host-side, used by the loader)."""

    mass: np.ndarray
    arm: np.ndarray
    inertia: np.ndarray
    kf: np.ndarray
    km: np.ndarray
    thrust2weight: np.ndarray
    max_speed_kmh: np.ndarray
    prop_radius: np.ndarray
    gnd_eff_coeff: np.ndarray
    drag_coeff: np.ndarray
    dw_coeff: np.ndarray
    prop_pos: np.ndarray
    prop_spin: np.ndarray
    torque_arm: np.ndarray
    gravity: np.ndarray
    collision_radius: np.ndarray
    collision_height: np.ndarray
    motor_tau_up: np.ndarray
    motor_tau_down: np.ndarray


def derive_params(params: DroneParams, xp: ModuleType = jnp) -> dict:
    """The derived quantities of a model, recomputed from its primary fields (gym-pybullet-drones
    ``BaseAviary.__init__``, main ``envs/BaseAviary.py:117-128``; docs/physics.md §1.1).

    J⁻¹ = inv(inertia); hover_rpm = √(m g / (4 kf)); max_rpm = √(t2w · m g / (4 kf)); max_thrust = 4 kf max_rpm²;
    max_xy_torque = kf max_rpm² · Σ_i max(0, torque_arm[0, i]) (= 2 L kf max_rpm²/√2 for an x frame, L kf max_rpm²
    for a + frame); max_z_torque = 2 km max_rpm²; gnd_eff_h_clip = (R/4)·√(15 C_gnd / 4).

    Use `with_derived` to get a `DroneParams` whose derived fields agree with edited primary ones (e.g. after
    changing ``mass`` or ``kf``, or sampling them for domain randomisation): batched, jittable and differentiable.

    Args:
        params: a `DroneParams` (or any object with its primary fields), possibly batched.
        xp: array module, ``jax.numpy`` (default) or ``numpy``.

    Returns:
        dict of the `DERIVED_FIELDS`, with the batch shape of ``params``.
    """
    weight = params.mass * params.gravity
    hover_rpm = xp.sqrt(weight / (4 * params.kf))
    max_rpm = xp.sqrt(params.thrust2weight * weight / (4 * params.kf))
    max_sq = max_rpm**2
    return dict(
        inertia_inv=xp.linalg.inv(params.inertia),
        hover_rpm=hover_rpm,
        max_rpm=max_rpm,
        max_thrust=4 * params.kf * max_sq,
        max_xy_torque=params.kf * max_sq * xp.sum(xp.maximum(params.torque_arm[..., 0, :], 0.0), axis=-1),
        max_z_torque=2 * params.km * max_sq,
        gnd_eff_h_clip=params.prop_radius / 4 * xp.sqrt(15 * params.gnd_eff_coeff / 4),
    )


def with_derived(params: DroneParams) -> DroneParams:
    """``params`` with its `DERIVED_FIELDS` recomputed from the primary ones by `derive_params` (jittable).

    Example: ``with_derived(params.replace(mass=params.mass * 1.1))`` also raises ``hover_rpm`` and ``max_rpm``.
    """
    return params.replace(**derive_params(params))


def stack_params(models: Sequence[str | os.PathLike | DroneParams]) -> DroneParams:
    """Params of a team, one model per drone: every field gets a leading drone axis ``[D]``.

    Args:
        models: a sequence of model names / URDF paths (see `load_params`) or of `DroneParams`.

    Returns:
        DroneParams with batch shape ``[D]`` (per-drone params, see `DroneParams`).

    Raises:
        ValueError: on an empty sequence or an unknown model.
    """
    models = list(models)
    if not models:
        raise ValueError("stack_params: expected at least one model")
    params = [m if isinstance(m, DroneParams) else load_params(m) for m in models]
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *params)
