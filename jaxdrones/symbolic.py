"""The JAX core's physics as a CasADi symbolic model, for model predictive control (optional extra ``[casadi]``).

The paper names "an analytical model that could be leveraged by model predictive control" (symbolic dynamics through
CasADi) as its extension (iii). This module writes the JAX core's equations once more in CasADi, from the same
`jaxdrones.physics.params.DroneParams` and `jaxdrones.physics.config.SimConfig`:

- `continuous_dynamics`: ẋ = f(x, u), the explicit model (docs/physics.md §3-§4: thrust kf·rpm², the x/+ mixer, the
  yaw reaction, Euler's equation with the gyroscopic term ω × Jω, q̇ = ½ q ⊗ (ω, 0)) with drag (§6.2) and ground
  effect (§6.1) where the config turns them on, and first-order motor dynamics (§3.3) with
  ``config.motor_dynamics``. The ground contact (§5.6) is not in it (it is a reset, not a flow).
- `discrete_step`: x⁺ = F(x, u), the control step the JAX core takes (`jaxdrones.sim.make_step`), operation for
  operation: the RPM clip to [0, max_rpm], ``sim_freq // ctrl_freq`` physics substeps of the config's integrator
  (semi-implicit Euler with the exact quaternion exponential map, or RK4), the motors' exact first-order response
  per substep, drag on the previous substep's RPM, and the ground contact. It equals the JAX step to float64
  rounding (tests/test_symbolic.py).
- `observation`: the paper's kinematic observation of the state (pos, quat, rpy, vel, ang_vel).
- `SymbolicModel`: the three above with their Jacobians, in the shape of safe-control-gym's ``SymbolicModel``
  (``fc_func``, ``fd_func``, ``g_func``, ``df_func``, ``dg_func``, ``loss``, ``nx``, ``nu``, ``dt``) so that MPC code
  written for it runs on this model.
- `symbolic_dynamics` and `crazyflow_params`: crazyflow's (drone_models') first-principles
  ``symbolic_dynamics(model_rotor_vel, model_dist_f, model_dist_t, *, mass, L, ...)`` signature, state order and
  return value ``(X_dot, X, U, Y)``, with our airframe's parameter set, so MPC code written against crazyflow runs.

The state vector is crazyflow's order: pos (3, m, world), quat (4, x y z w, body→world), vel (3, m/s, world),
ang_vel (3, rad/s, body), then, where the step needs it, the rotors' speeds (4, RPM: the previous command, which
drag reads, or the motors' actual speeds with motor dynamics); the input is the 4 motor RPM commands (motor order of
docs/physics.md §2). The model is of one drone (the downwash between drones is not in it).

Without casadi installed every function raises one ModuleNotFoundError naming the extra (`require_casadi`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.rotations import GIMBAL_SNAP, OMEGA_EPS, quat_mul_c, quat_to_rotmat_c
from jaxdrones.physics.state import DroneState

if TYPE_CHECKING:
    import casadi  # optional (the casadi extra): named in the hints only

__all__ = [
    "STATE_NAMES",
    "ROTOR_NAMES",
    "INPUT_NAMES",
    "OBSERVATION_NAMES",
    "SymbolicModel",
    "continuous_dynamics",
    "crazyflow_params",
    "discrete_step",
    "observation",
    "require_casadi",
    "state_vector",
    "symbolic_dynamics",
]

#: The kinematic state's entries, in order (crazyflow's order).
STATE_NAMES = ("x", "y", "z", "qx", "qy", "qz", "qw", "vx", "vy", "vz", "wx", "wy", "wz")
#: The rotor speeds appended to the state where the step needs them (`SymbolicModel.rotor_state`).
ROTOR_NAMES = ("rpm0", "rpm1", "rpm2", "rpm3")
#: The input's entries: the 4 motor RPM commands.
INPUT_NAMES = ("rpm_cmd0", "rpm_cmd1", "rpm_cmd2", "rpm_cmd3")
#: The observation's entries (`observation`): the paper's KIN observation of one drone (docs/physics.md §8.2).
OBSERVATION_NAMES = ("x", "y", "z", "qx", "qy", "qz", "qw", "roll", "pitch", "yaw", "vx", "vy", "vz", "wx", "wy", "wz")
RPM_TO_RAD_S = 2 * math.pi / 60


def require_casadi() -> ModuleType:
    """The ``casadi`` module, or a ModuleNotFoundError that names the extra to install."""
    try:
        import casadi
    except ModuleNotFoundError as error:
        raise ModuleNotFoundError(
            "jaxdrones.symbolic needs casadi, which is not installed: pip install 'jaxdrones[casadi]'"
        ) from error
    return casadi


@dataclass(frozen=True)
class _Airframe:
    """One drone's parameters as float64 NumPy arrays (from `DroneParams`)."""

    mass: float
    gravity: float
    kf: float
    km: float
    max_rpm: float
    inertia: np.ndarray
    inertia_inv: np.ndarray
    torque_arm: np.ndarray
    prop_spin: np.ndarray
    prop_pos: np.ndarray
    prop_radius: float
    gnd_eff_coeff: float
    gnd_eff_h_clip: float
    drag_coeff: np.ndarray
    collision_height: float
    motor_tau_up: float
    motor_tau_down: float
    hover_rpm: float
    arm: float


_SHAPES = {
    "inertia": (3, 3),
    "inertia_inv": (3, 3),
    "torque_arm": (2, 4),
    "prop_spin": (4,),
    "prop_pos": (4, 3),
    "drag_coeff": (3,),
}


def _airframe(params: DroneParams) -> _Airframe:
    if not isinstance(params, DroneParams):
        raise ValueError(f"expected DroneParams (jaxdrones.load_params), got {type(params).__name__}")
    values = {}
    for name in _Airframe.__dataclass_fields__:
        value = np.asarray(getattr(params, name), np.float64)
        shape = _SHAPES.get(name, ())
        if value.shape != shape:
            raise ValueError(
                f"the symbolic model is of one drone: DroneParams.{name} must have shape {shape}, got "
                f"{value.shape} (pick one drone's params, e.g. jax.tree.map(lambda x: x[0], params))"
            )
        if not np.all(np.isfinite(value)):
            raise ValueError(f"DroneParams.{name} is not finite: {value}")
        values[name] = value if shape else float(value)
    return _Airframe(**values)


def _check_config(config: SimConfig) -> SimConfig:
    if not isinstance(config, SimConfig):
        raise ValueError(f"expected a SimConfig, got {type(config).__name__}")
    if config.kinks.mode == "smooth":
        raise ValueError(
            "the symbolic model has the original's kinks (SimConfig(kinks='exact' or "
            "'straight_through')); smooth kinks change the values"
        )
    return config


# The equations, on CasADi column vectors (SX or MX), each as in the JAX core (jaxdrones.dynamics).

# The component-form functions of `jaxdrones.physics.rotations` that are plain arithmetic take CasADi entries as they
# take arrays: the Hamilton product and the rotation matrix are written once, there.


def _entries(v) -> tuple:
    """A CasADi column vector as the tuple of its entries (the component form of `jaxdrones.physics.rotations`)."""
    return tuple(v[i] for i in range(v.shape[0]))


def _quat_mul(a, b):
    """A ⊗ b (`jaxdrones.physics.rotations.quat_mul_c`) of CasADi 4-vectors (x, y, z, w)."""
    return require_casadi().vertcat(*quat_mul_c(_entries(a), _entries(b)))


def _normalize(v):
    cs = require_casadi()
    return v / cs.sqrt(cs.dot(v, v))


def _rotmat(q):
    """R(q), body→world, of a unit quaternion (x, y, z, w) (`jaxdrones.physics.rotations.quat_to_rotmat_c`), 3 x 3."""
    cs = require_casadi()
    return cs.vertcat(*(cs.horzcat(*row) for row in quat_to_rotmat_c(_entries(q), unit=True)))


def _accelerations(a: _Airframe, config: SimConfig, pos, quat, vel, ang_vel, rpm, rpm_prev):
    """World linear and body angular accelerations (docs/physics.md §4.2-4.4) for motor speeds ``rpm`` and the
    previous substep's ``rpm_prev`` (drag), ``quat`` of unit norm."""
    cs = require_casadi()
    rot = _rotmat(quat)
    thrust = a.kf * rpm**2
    lift = thrust
    if config.ground_effect:  # §6.1: g_i = f_i C (r / 4 h_i)², h_i clipped below, while upright
        rot_z = rot[2, :].T
        upright = cs.logic_and(rot[2, 2] > 0, cs.fabs(rot[2, 0]) < GIMBAL_SNAP)
        height = pos[2] + cs.mtimes(cs.DM(a.prop_pos), rot_z)
        height = cs.fmax(height, a.gnd_eff_h_clip)
        gain = a.gnd_eff_coeff * (a.prop_radius / (4 * height)) ** 2
        lift = thrust + cs.if_else(upright, thrust * gain, cs.DM.zeros(4))
    force = rot[:, 2] * cs.sum1(lift) + cs.vertcat(0, 0, -a.mass * a.gravity)
    if config.drag:  # §6.2: -(Σ ω_i) c ⊙ v, ω in rad/s
        force = force - cs.sum1(rpm_prev) * RPM_TO_RAD_S * (cs.DM(a.drag_coeff) * vel)
    yaw = -cs.dot(cs.DM(a.prop_spin * a.km), rpm**2)
    torque = cs.vertcat(cs.mtimes(cs.DM(a.torque_arm), lift), yaw)
    gyro = cs.cross(ang_vel, cs.mtimes(cs.DM(a.inertia), ang_vel))
    return force / a.mass, cs.mtimes(cs.DM(a.inertia_inv), torque - gyro)


def _quat_integrate(quat, ang_vel, dt: float):
    """Q ⊗ (sin(θ) ω/|ω|, cos θ), θ = ½ dt |ω| (docs/physics.md §4.6); below |ω| = OMEGA_EPS the first-order update
    q ⊗ (½ dt ω, 1): q itself at rest, as the JAX core's value, within ½ dt OMEGA_EPS of it below, and with the
    derivative the JAX core gives there (`jaxdrones.physics.rotations.quat_integrate_c`), so that a solver's
    gradients reach the attitude from a drone at rest (held at q, a level hover is a stationary point of any
    tracking cost: the MPC never tilts)."""
    cs = require_casadi()
    sq = cs.dot(ang_vel, ang_vel)
    moving = sq > OMEGA_EPS**2
    norm = cs.sqrt(cs.if_else(moving, sq, 1.0))
    theta = 0.5 * dt * norm
    sin_over_norm = cs.if_else(moving, cs.sin(theta) / norm, 0.5 * dt)
    delta = cs.vertcat(sin_over_norm * ang_vel, cs.if_else(moving, cs.cos(theta), 1.0))
    return _quat_mul(quat, delta)


def _euler(a, config, pos, quat, vel, ang_vel, rpm, rpm_prev, dt):
    """The semi-implicit Euler substep (docs/physics.md §4.5-4.6), ``quat`` of unit norm."""
    acc, ang_acc = _accelerations(a, config, pos, quat, vel, ang_vel, rpm, rpm_prev)
    vel = vel + dt * acc
    ang_vel = ang_vel + dt * ang_acc
    quat = _normalize(_quat_integrate(quat, ang_vel, dt))
    return pos + dt * vel, quat, vel, ang_vel


def _rk4(a, config, pos, quat, vel, ang_vel, rpm, rpm_prev, dt):
    """Classical RK4 with the motors held (docs/physics.md §4.11); the stages' quaternions normalised for R."""
    cs = require_casadi()

    def deriv(p, q, v, w, unit):
        acc, ang_acc = _accelerations(a, config, p, q if unit else _normalize(q), v, w, rpm, rpm_prev)
        return v, 0.5 * _quat_mul(q, cs.vertcat(w, 0)), acc, ang_acc

    x = (pos, quat, vel, ang_vel)
    k1 = deriv(*x, True)
    k, total = k1, k1
    for h, weight in ((dt / 2, 2.0), (dt / 2, 2.0), (dt, 1.0)):
        k = deriv(*(xi + h * ki for xi, ki in zip(x, k, strict=True)), False)
        total = tuple(t + weight * ki for t, ki in zip(total, k, strict=True))
    pos, quat, vel, ang_vel = (xi + dt / 6 * t for xi, t in zip(x, total, strict=True))
    return pos, _normalize(quat), vel, ang_vel


def _ground_contact(a, pos, vel, ang_vel):
    """The ground at z = 0 (docs/physics.md §5.6): below the rest height the base is put back at it, the velocity
    becomes (0, 0, max(v_z, 0)) and the angular velocity 0."""
    cs = require_casadi()
    rest = 0.5 * a.collision_height
    touching = pos[2] < rest
    pos = cs.vertcat(pos[0], pos[1], cs.fmax(pos[2], rest))
    vel = cs.if_else(touching, cs.vertcat(0, 0, cs.fmax(vel[2], 0)), vel)
    ang_vel = cs.if_else(touching, cs.DM.zeros(3), ang_vel)
    return pos, vel, ang_vel


def _motor_decay(tau: float, dt: float) -> float:
    """`jaxdrones.physics.dynamics.motor_decay` on a float, in float64 whatever JAX's precision: exp(-dt/τ), 0 for τ
    <= 0."""
    return math.exp(-dt / tau) if tau > 0 else 0.0


def _motor_rate(tau: float) -> float:
    """1/τ, the first-order motor model's rate (1/s); 0 for instant motors (τ <= 0)."""
    return 1.0 / tau if tau > 0 else 0.0


def _split_state(x, rotor_state: bool):
    return x[0:3], x[3:7], x[7:10], x[10:13], (x[13:17] if rotor_state else None)


def _symbols(kind: str, rotor_state: bool):
    cs = require_casadi()
    sym = getattr(cs, kind).sym
    x = sym("x", 13 + 4 * rotor_state)
    u = sym("u", 4)
    return x, u


def _step_expression(a: _Airframe, config: SimConfig, x, u, rotor_state: bool):
    cs = require_casadi()
    pos, quat, vel, ang_vel, rotor = _split_state(x, rotor_state)
    command = cs.fmin(cs.fmax(u, 0), a.max_rpm)  # the RPM clip of make_step
    quat = _normalize(quat)
    dt = 1.0 / config.sim_freq
    integrate = {"euler": _euler, "rk4": _rk4}[config.integrator]
    rpm_prev = rotor if rotor is not None else command
    up, down = _motor_decay(a.motor_tau_up, dt), _motor_decay(a.motor_tau_down, dt)
    for _ in range(config.n_substeps):
        if config.motor_dynamics:  # §3.3: the exact first-order response over the substep, then applied
            rpm = command + (rpm_prev - command) * cs.if_else(
                command > rpm_prev, up * cs.DM.ones(4), down * cs.DM.ones(4)
            )
        else:
            rpm = command
        pos, quat, vel, ang_vel = integrate(a, config, pos, quat, vel, ang_vel, rpm, rpm_prev, dt)
        pos, vel, ang_vel = _ground_contact(a, pos, vel, ang_vel)
        rpm_prev = rpm
    parts = [pos, quat, vel, ang_vel] + ([rpm_prev] if rotor_state else [])
    return cs.vertcat(*parts)


def _continuous_expression(a: _Airframe, config: SimConfig, x, u, rotor_state: bool):
    cs = require_casadi()
    pos, quat, vel, ang_vel, rotor = _split_state(x, rotor_state)
    command = cs.fmin(cs.fmax(u, 0), a.max_rpm)
    if config.motor_dynamics:
        if rotor is None:
            raise ValueError("motor dynamics need the rotor speeds in the state (rotor_state=True)")
        if not (a.motor_tau_up > 0 and a.motor_tau_down > 0):
            raise ValueError(
                "the continuous model with motor dynamics needs positive motor time constants, got "
                f"motor_tau_up={a.motor_tau_up}, motor_tau_down={a.motor_tau_down}"
            )
        rpm = rotor
        rotor_dot = (command - rotor) * cs.if_else(
            command > rotor, _motor_rate(a.motor_tau_up) * cs.DM.ones(4), _motor_rate(a.motor_tau_down) * cs.DM.ones(4)
        )
    else:
        rpm = command
        rotor_dot = None if rotor is None else cs.DM.zeros(4)
    unit = _normalize(quat)
    acc, ang_acc = _accelerations(a, config, pos, unit, vel, ang_vel, rpm, rpm)
    parts = [vel, 0.5 * _quat_mul(quat, cs.vertcat(ang_vel, 0)), acc, ang_acc]
    return cs.vertcat(*parts, *([rotor_dot] if rotor_dot is not None else []))


def _euler_angles(q):
    """Roll, pitch, yaw of a unit quaternion as ``getEulerFromQuaternion`` (docs/physics.md §0.4), with its snap
    near pitch ±π/2."""
    cs = require_casadi()
    x, y, z, w = q[0], q[1], q[2], q[3]
    s = -2.0 * (x * z - w * y)
    low, high = s <= -GIMBAL_SNAP, s >= GIMBAL_SNAP
    snap = cs.logic_or(low, high)
    sign = cs.if_else(low, 1.0, -1.0)
    roll = cs.if_else(snap, 0.0, cs.atan2(2 * (y * z + w * x), w * w - x * x - y * y + z * z))
    pitch = cs.if_else(
        low, -math.pi / 2, cs.if_else(high, math.pi / 2, cs.asin(cs.fmin(cs.fmax(s, -GIMBAL_SNAP), GIMBAL_SNAP)))
    )
    yaw = cs.if_else(
        snap, 2 * cs.atan2(sign * x, -sign * y), cs.atan2(2 * (x * y + w * z), w * w + x * x - y * y - z * z)
    )
    return cs.vertcat(roll, pitch, yaw)


def _observation_expression(x, rotor_state: bool):
    cs = require_casadi()
    pos, quat, vel, ang_vel, _ = _split_state(x, rotor_state)
    return cs.vertcat(pos, quat, _euler_angles(quat), vel, ang_vel)


def _rotor_state(config: SimConfig, rotor_state: bool | None) -> bool:
    """Whether the state carries the rotor speeds: as asked, or (None) where the step reads them (drag acts on the
    previous substep's RPM, motor dynamics start from the motors' speeds)."""
    needed = bool(config.drag or config.motor_dynamics)
    if rotor_state is None:
        return needed
    if needed and not rotor_state:
        raise ValueError(
            "this config reads the rotor speeds from the state (drag on the previous RPM, or motor "
            "dynamics): rotor_state must be True (or None)"
        )
    return bool(rotor_state)


def _names(rotor_state: bool) -> list[str]:
    return list(STATE_NAMES) + (list(ROTOR_NAMES) if rotor_state else [])


def state_vector(state: DroneState, rotor_state: bool = True) -> np.ndarray:
    """One drone's `jaxdrones.physics.state.DroneState` (leading shape ``[1]`` or none) as this module's state vector
    f64[17] (pos, quat, vel, ang_vel, rpm; `STATE_NAMES`, `ROTOR_NAMES`), or f64[13] without the rotor speeds."""
    fields = ("pos", "quat", "vel", "ang_vel") + (("rpm",) if rotor_state else ())
    return np.concatenate([np.asarray(getattr(state, k), np.float64).reshape(-1) for k in fields])


def continuous_dynamics(
    params: DroneParams, config: SimConfig = SimConfig(), rotor_state: bool | None = None, kind: str = "SX"
) -> casadi.Function:
    """ẋ = f(x, u) of one drone as a ``casadi.Function`` ``f(x, u) -> xdot``.

    The explicit model of docs/physics.md §3-§4 (thrust kf·rpm², torques from the mixer's lever arms and the yaw
    reaction, Euler's equation with ω × Jω, q̇ = ½ q ⊗ (ω, 0)) with drag (§6.2, on the motors' current speeds) and
    ground effect (§6.1, with its clip and attitude condition) where ``config`` turns them on; with
    ``config.motor_dynamics`` the rotor speeds follow τ ṙpm = cmd - rpm (§3.3, rise and fall constants). The
    commands are clipped to [0, max_rpm] as the step does. The ground contact is not part of the flow.

    Args:
        params: one drone's `DroneParams` (scalars, f[3, 3] inertia, ...), e.g. ``jaxdrones.load_params("cf2x")``.
        config: the `SimConfig` whose effects apply (its rates are not used here).
        rotor_state: append the rotor speeds (4, RPM) to the state. None: where ``config`` needs them (drag or motor
            dynamics). Without motor dynamics their derivative is 0.
        kind: ``"SX"`` or ``"MX"``, the CasADi symbol type.

    Returns:
        ``casadi.Function`` named ``"f"``, inputs ``x`` (13 or 17) and ``u`` (4 RPM), output ``xdot``.

    Raises:
        ValueError: params not of one drone or not finite; smooth kinks; ``rotor_state=False`` where the config
            needs it; motor dynamics with a non-positive time constant.
        ModuleNotFoundError: casadi is not installed (the ``[casadi]`` extra).
    """
    cs = require_casadi()
    a, config = _airframe(params), _check_config(config)
    rotor_state = _rotor_state(config, rotor_state)
    x, u = _symbols(kind, rotor_state)
    return cs.Function("f", [x, u], [_continuous_expression(a, config, x, u, rotor_state)], ["x", "u"], ["xdot"])


def discrete_step(
    params: DroneParams, config: SimConfig, rotor_state: bool | None = None, kind: str = "SX"
) -> casadi.Function:
    """x⁺ = F(x, u): the JAX core's control step of ``1 / config.ctrl_freq`` s as a ``casadi.Function``.

    The same operations as `jaxdrones.sim.make_step`'s step (on one drone, no disturbance): the commands clipped to
    [0, max_rpm], the quaternion normalised, then ``config.n_substeps`` substeps of ``1 / config.sim_freq`` s, each
    the motors' exact first-order response (with ``config.motor_dynamics``), the integrator (``"euler"``: the
    paper code's semi-implicit Euler with the quaternion exponential map, §4.5-4.6; ``"rk4"``: §4.11) and the
    ground contact (§5.6). Drag reads the previous substep's RPM: in the first substep the state's rotor speeds.

    Args:
        params, rotor_state, kind: as in `continuous_dynamics`; the rotor speeds of the state are the
            ``DroneState.rpm`` of the JAX core.
        config: the `SimConfig` (rates, effects, integrator, motor dynamics).

    Returns:
        ``casadi.Function`` named ``"F"``, inputs ``x`` and ``u``, output ``xf``.

    Raises:
        ValueError, ModuleNotFoundError: as `continuous_dynamics`.
    """
    cs = require_casadi()
    a, config = _airframe(params), _check_config(config)
    rotor_state = _rotor_state(config, rotor_state)
    x, u = _symbols(kind, rotor_state)
    return cs.Function("F", [x, u], [_step_expression(a, config, x, u, rotor_state)], ["x", "u"], ["xf"])


def observation(rotor_state: bool = False, kind: str = "SX") -> casadi.Function:
    """Y = g(x): the paper's KIN observation of one drone (pos, quat, rpy as ``getEulerFromQuaternion``, vel,
    ang_vel; `OBSERVATION_NAMES`, docs/physics.md §8.2), as a ``casadi.Function`` ``g(x) -> y`` (16 outputs) of a
    state with or without the rotor speeds."""
    cs = require_casadi()
    x, _ = _symbols(kind, rotor_state)
    return cs.Function("g", [x], [_observation_expression(x, rotor_state)], ["x"], ["y"])


class SymbolicModel:
    """The JAX core's model of one drone for MPC, in the shape of safe-control-gym's ``SymbolicModel``.

    Attributes (as safe-control-gym's, on CasADi ``MX`` symbols):
        x_sym, u_sym: the state (`state_names`) and input (4 RPM commands) symbols; nx, nu, ny their sizes.
        x_dot: the continuous dynamics' expression (`continuous_dynamics`); y_sym: the observation's
            (`observation`).
        dt: the control step, s (``1 / config.ctrl_freq``).
        fc_func: ``f(x, u) -> f``, continuous; fd_func: ``fd(x0, p) -> xf``, the discrete control step of the JAX
            core (`discrete_step`: called as safe-control-gym's integrator, ``fd_func(x0=x, p=u)["xf"]``);
            g_func: ``g(x, u) -> g``.
        df_func: ``df(x, u) -> (dfdx, dfdu)``; dfd_func: ``dfd(x, u) -> (dfdx, dfdu)``, the discrete step's
            Jacobians; dg_func: ``dg(x, u) -> (dgdx, dgdu)``.
        loss: ``loss(x, u, Xr, Ur, Q, R) -> (l, l_x, l_xx, l_u, l_uu, l_xu)``, the quadratic cost
            ½ (x - Xr)ᵀ Q (x - Xr) + ½ (u - Ur)ᵀ R (u - Ur) and its derivatives, as safe-control-gym's.
        x_eq, u_eq: hover 1 m above the origin (level, at rest, at the hover RPM; out of ground effect and
            contact), as NumPy arrays.
        rotor_state: whether the state ends with the rotor speeds; state_names: the state's entry names.

    Args:
        params: one drone's `DroneParams`.
        config: the `SimConfig` (default: the paper's physics at its rates, 240 Hz physics and control).
        rotor_state: as in `continuous_dynamics`.

    Raises:
        ValueError, ModuleNotFoundError: as `continuous_dynamics`.
    """

    def __init__(self, params: DroneParams, config: SimConfig = SimConfig(), rotor_state: bool | None = None):
        cs = require_casadi()
        a, config = _airframe(params), _check_config(config)
        self.config = config
        self.rotor_state = _rotor_state(config, rotor_state)
        self.state_names = _names(self.rotor_state)
        self.x_sym, self.u_sym = _symbols("MX", self.rotor_state)
        x, u = self.x_sym, self.u_sym
        self.dt = 1.0 / config.ctrl_freq
        self.x_dot = _continuous_expression(a, config, x, u, self.rotor_state)
        self.x_next = _step_expression(a, config, x, u, self.rotor_state)
        self.y_sym = _observation_expression(x, self.rotor_state)
        self.nx, self.nu, self.ny = x.shape[0], u.shape[0], self.y_sym.shape[0]
        self.fc_func = cs.Function("fc", [x, u], [self.x_dot], ["x", "u"], ["f"])
        self.fd_func = cs.Function("fd", [x, u], [self.x_next], ["x0", "p"], ["xf"])
        self.g_func = cs.Function("g", [x, u], [self.y_sym], ["x", "u"], ["g"])
        self.dfdx, self.dfdu = cs.jacobian(self.x_dot, x), cs.jacobian(self.x_dot, u)
        self.df_func = cs.Function("df", [x, u], [self.dfdx, self.dfdu], ["x", "u"], ["dfdx", "dfdu"])
        self.dfd_func = cs.Function(
            "dfd", [x, u], [cs.jacobian(self.x_next, x), cs.jacobian(self.x_next, u)], ["x", "u"], ["dfdx", "dfdu"]
        )
        self.dgdx, self.dgdu = cs.jacobian(self.y_sym, x), cs.jacobian(self.y_sym, u)
        self.dg_func = cs.Function("dg", [x, u], [self.dgdx, self.dgdu], ["x", "u"], ["dgdx", "dgdu"])
        xr, ur = cs.MX.sym("Xr", self.nx), cs.MX.sym("Ur", self.nu)
        q, r = cs.MX.sym("Q", self.nx, self.nx), cs.MX.sym("R", self.nu, self.nu)
        cost = 0.5 * cs.bilin(q, x - xr, x - xr) + 0.5 * cs.bilin(r, u - ur, u - ur)
        l_x, l_u = cs.jacobian(cost, x), cs.jacobian(cost, u)
        self.loss = cs.Function(
            "loss",
            [x, u, xr, ur, q, r],
            [cost, l_x, cs.jacobian(l_x, x), l_u, cs.jacobian(l_u, u), cs.jacobian(l_x, u)],
            ["x", "u", "Xr", "Ur", "Q", "R"],
            ["l", "l_x", "l_xx", "l_u", "l_uu", "l_xu"],
        )
        self.u_eq = np.full(4, a.hover_rpm)
        self.x_eq = np.concatenate(
            [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0], np.zeros(6)] + ([self.u_eq] if self.rotor_state else [])
        )

    def __repr__(self) -> str:
        return f"SymbolicModel(nx={self.nx}, nu={self.nu}, ny={self.ny}, dt={self.dt}, config={self.config})"


def crazyflow_params(params: DroneParams) -> dict[str, Any]:
    """Our airframe in the parameter set of crazyflow's (drone_models') first-principles ``symbolic_dynamics``.

    Exact for the paper's explicit model without drag and ground effect (which crazyflow's model does not have in
    this form): quadratic thrust and torque curves ``rpm2thrust = rpm2torque`` ``[0, 0, kf]`` / ``[0, 0, km]``
    (N and N·m per RPM²), a mixing matrix whose rows give (τx, τy) = L·mixing[:2] @ f (our ``torque_arm / L``) and
    τz = mixing[2] @ (km rpm²) (``-prop_spin``), no propeller inertia (the paper's model has no propeller
    gyroscopic term), the first-order rotor dynamics ``[1/τ_up, 0, 1/τ_down, 0]`` (1/s; 0 for instant motors, for
    which ``model_rotor_vel=False`` applies), and no linear drag (``drag_matrix`` 0; the paper's drag scales with
    the rotor speeds: `continuous_dynamics` with ``drag=True`` has it).

    Returns:
        dict of NumPy arrays: mass, L, prop_inertia, gravity_vec, J, J_inv, rpm2thrust, rpm2torque, mixing_matrix,
        rotor_dyn_coef, drag_matrix.
    """
    a = _airframe(params)
    return {
        "mass": a.mass,
        "L": a.arm,
        "prop_inertia": 0.0,
        "gravity_vec": np.array([0.0, 0.0, -a.gravity]),
        "J": a.inertia,
        "J_inv": a.inertia_inv,
        "rpm2thrust": np.array([0.0, 0.0, a.kf]),
        "rpm2torque": np.array([0.0, 0.0, a.km]),
        "mixing_matrix": np.vstack([a.torque_arm / a.arm, -a.prop_spin[None]]),
        "rotor_dyn_coef": np.array([_motor_rate(a.motor_tau_up), 0.0, _motor_rate(a.motor_tau_down), 0.0]),
        "drag_matrix": np.zeros((3, 3)),
    }


def symbolic_dynamics(
    model_rotor_vel: bool = True,
    model_dist_f: bool = False,
    model_dist_t: bool = False,
    *,
    mass: float,
    L: float,
    prop_inertia: float,
    gravity_vec: ArrayLike,
    J: ArrayLike,
    J_inv: ArrayLike,
    rpm2thrust: ArrayLike,
    rpm2torque: ArrayLike,
    mixing_matrix: ArrayLike,
    rotor_dyn_coef: ArrayLike,
    drag_matrix: ArrayLike,
) -> tuple[casadi.MX, casadi.MX, casadi.MX, casadi.MX]:
    """Crazyflow's (drone_models') first-principles ``symbolic_dynamics``: the same signature, state order and
    return value, so MPC code written against it runs here with `crazyflow_params`' parameter set.

    The model (McKinnon and Schoellig, "Estimating and reacting to forces and torques resulting from common
    aerodynamic disturbances acting on quadrotors", RAS 2020, the quaternion model crazyflow cites): motor force
    and torque curves a + b·rpm + c·rpm², body torques L·mixing[:2] @ f and mixing[2] @ τ_motor, propeller gyroscopic
    torque with ``prop_inertia``, linear body-frame drag R D Rᵀ v, gravity ``gravity_vec``, Euler's equation with
    ω × Jω, q̇ = ½ q ⊗ (ω, 0) (x, y, z, w), and with ``model_rotor_vel`` rotor dynamics
    ṙ = k1 (c - r) + k2 (c² - r²) while speeding up (k3, k4 while slowing down). ``model_dist_f`` /
    ``model_dist_t`` append a world-frame force (N) / torque (N·m) disturbance to the state (constant: zero
    derivative), acting on the centre of mass.

    Returns:
        ``(X_dot, X, U, Y)`` CasADi ``MX``: the state derivative; the state pos(3), quat(4), vel(3), ang_vel(3),
        [rotor_vel(4) RPM], [dist_f(3)], [dist_t(3)]; the input, 4 RPM commands; the output pos and quat.
    """
    cs = require_casadi()
    pos, quat, vel, ang_vel = (cs.MX.sym(n, k) for n, k in (("pos", 3), ("quat", 4), ("vel", 3), ("ang_vel", 3)))
    command = cs.MX.sym("cmd_rotor_vel", 4)
    state = [pos, quat, vel, ang_vel]
    J, J_inv, mixing = (np.asarray(m, np.float64) for m in (J, J_inv, mixing_matrix))
    thrust_c, torque_c, dyn = (np.asarray(c, np.float64).ravel() for c in (rpm2thrust, rpm2torque, rotor_dyn_coef))
    if model_rotor_vel:
        rotor = cs.MX.sym("rotor_vel", 4)
        state.append(rotor)
        rotor_dot = cs.if_else(
            command > rotor,
            dyn[0] * (command - rotor) + dyn[1] * (command**2 - rotor**2),
            dyn[2] * (command - rotor) + dyn[3] * (command**2 - rotor**2),
        )
    else:
        rotor, rotor_dot = command, cs.DM.zeros(4)
    rot = _rotmat(quat / cs.norm_2(quat))
    forces = thrust_c[0] + thrust_c[1] * rotor + thrust_c[2] * rotor**2
    torques = torque_c[0] + torque_c[1] * rotor + torque_c[2] * rotor**2
    force = (
        rot @ cs.vertcat(0, 0, cs.sum1(forces))
        + np.asarray(gravity_vec, np.float64).reshape(3, 1) * mass
        + rot @ (np.asarray(drag_matrix, np.float64) @ (rot.T @ vel))
    )
    spin = cs.DM(mixing[2])
    torque = cs.vertcat(
        L * cs.mtimes(cs.DM(mixing[0:1]), forces),
        L * cs.mtimes(cs.DM(mixing[1:2]), forces),
        cs.mtimes(cs.DM(mixing[2:3]), torques),
    ) + prop_inertia * cs.vertcat(
        -ang_vel[1] * cs.dot(spin, rotor * RPM_TO_RAD_S),
        -ang_vel[0] * cs.dot(spin, rotor * RPM_TO_RAD_S),
        cs.dot(spin, rotor_dot * RPM_TO_RAD_S),
    )
    if model_dist_f:
        state.append(cs.MX.sym("dist_f", 3))
        force = force + state[-1]
    if model_dist_t:
        state.append(cs.MX.sym("dist_t", 3))
        torque = torque + rot.T @ state[-1]
    ang_acc = cs.mtimes(J_inv, torque - cs.cross(ang_vel, cs.mtimes(J, ang_vel)))
    x_dot = [vel, 0.5 * _quat_mul(quat, cs.vertcat(ang_vel, 0)), force / mass, ang_acc]
    if model_rotor_vel:
        x_dot.append(rotor_dot)
    x_dot += [cs.DM.zeros(3)] * (int(model_dist_f) + int(model_dist_t))
    return cs.vertcat(*x_dot), cs.vertcat(*state), command, cs.vertcat(pos, quat)
