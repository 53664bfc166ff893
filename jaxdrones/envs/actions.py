"""Action types: how a policy's normalised action becomes motor RPMs (docs/physics.md §10).

Every action type maps an action ``f[..., D, size]`` in its box (``low``, ``high``; [-1, 1] per entry, as the
paper's RL envs) to an RPM command ``f[..., D, 4]`` for the physics step, with an explicit carry for controllers
that have memory (the DSL PID's integrals). All are pure, batched over leading ``[world, drone]`` axes and, where
the maths is, differentiable:

=================  ====  ==========================================================================================
name               size  mapping (source)
=================  ====  ==========================================================================================
``rpm``            4     rpm_i = hover_rpm · (1 + 0.05 a_i)  (gym-pybullet-drones RPM)
``one_d_rpm``      1     the same value for all four motors  (ONE_D_RPM)
``pid``            3     DSL PID to an absolute target a (m), at most 1 m from the drone per step (main's PID);
                         ``pid_target="relative"``: target = pos + 0.1 a (the paper's PID; ``pid_scale``)
``one_d_pid``      1     DSL PID to pos + (0, 0, 0.1 a)  (ONE_D_PID)
``vel``            4     DSL PID with target velocity speed_limit·|a_3|·unit(a_0:3), target pos = pos, target yaw
                         = current yaw  (VEL; 0.25 m/s for the Crazyflies)
``thrust_torque``  4     T = m g (a_0 + 1), τ = 0.05 · (max_xy_torque a_1, max_xy_torque a_2, max_z_torque a_3),
                         converted to RPM by non-negative least squares  (the paper's DYN)
``one_d_thrust``   1     T = m g (1 + 0.05 a), no torque, NNLS  (the paper's ONE_D_DYN)
``tun``            6     DSL PID tracking the task's reference, its six gain vectors scaled by (a_k + 1)
                         (the paper's TUN)
``ctbr``           4     collective thrust T = m g (a_0 + 1) and body rates ω* = `CTBR_MAX_RATE` · a_1:4 (rad/s)
                         through a body-rate controller (`jaxdrones.control.mixer.body_rate_control`)
``firmware_pos``   4     the Crazyflie firmware's position setpoint (cflib ``send_position_setpoint``): position
                         `FIRMWARE_POSITION_RANGE` · a_0:3 (m, world), yaw 180 · a_3 (deg), flown by the firmware's
                         PID cascade at 1 kHz
``firmware_vel``   4     the firmware's velocity setpoint (cflib ``send_velocity_world_setpoint``): velocity
                         `FIRMWARE_MAX_SPEED` · a_0:3 (m/s, world), yaw rate `FIRMWARE_MAX_YAW_RATE` · a_3 (deg/s),
                         flown by the firmware's PID cascade at 1 kHz
``firmware_ctbr``  4     collective thrust and body rates through the firmware's own rate loop (cflib
                         ``send_setpoint`` with roll and pitch in rate mode): thrust `FIRMWARE_MIN_THRUST` +
                         (`FIRMWARE_MAX_THRUST` − `FIRMWARE_MIN_THRUST`) (a_0 + 1) / 2 (PWM), body rates ω* =
                         `CTBR_MAX_RATE` · a_1:4 (rad/s)
=================  ====  ==========================================================================================

Unlike the original, actions are clipped to their box before mapping (the env does this), and the PID-based
types use the airframe's own mixer (the original's RL envs always build the cf2x controller).

The firmware's setpoints (``firmware_pos``, ``firmware_vel``, ``firmware_ctbr``; `ActionType.firmware`) are not mapped
to one RPM command per control step: the setpoint is held over the step while the firmware's PID cascade
(`jaxdrones.control.firmware.controller_pid`, its loops at 100 and 500 Hz), its power distribution and its motor map
drive the physics at every 1 ms tick (`fly`, `jaxdrones.control.firmware.pid_schedule`), as on a Crazyflie that
``cflib`` sends setpoints to. They need the physics at 1 kHz, a control step of a multiple of 10 ticks and first-order
motors (the firmware's gains do not hold instant motors: docs/firmware.md); `jaxdrones.envs.config.TaskConfig`
checks this.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.control.pid import PIDGains, pid_control, pid_init, speed_limit, velocity_targets
from jaxdrones.physics.params import DroneParams
from jaxdrones.physics.state import DroneState

#: Normalised RPM actions: rpm = hover_rpm · (1 + RPM_ACTION_SCALE · a) (gym-pybullet-drones RPM action).
RPM_ACTION_SCALE = 0.05
#: Largest PID target step per control step of the absolute ``pid`` action, m (main ``_calculateNextStep``).
PID_MAX_STEP = 1.0
#: Relative PID targets: target = pos + PID_RELATIVE_SCALE · a, m (the paper's PID and ONE_D_PID).
PID_RELATIVE_SCALE = 0.1
#: Torque of the ``thrust_torque`` action at |a| = 1, as a fraction of the maximum torques (the paper's DYN).
TORQUE_ACTION_SCALE = 0.05
#: Thrust change of the ``one_d_thrust`` action at |a| = 1, as a fraction of the weight (the paper's ONE_D_DYN).
ONE_D_THRUST_SCALE = 0.05
#: Body rate of the ``ctbr`` action at |a| = 1, rad/s.
CTBR_MAX_RATE = 2.0 * np.pi
#: How a ``pid`` action sets the PID's target: ``"absolute"`` (main) or ``"relative"`` (the paper).
PID_TARGETS = ("absolute", "relative")
#: ``firmware_pos``: the position setpoint at |a| = 1, m.
FIRMWARE_POSITION_RANGE = 2.0
#: ``firmware_vel``: the velocity setpoint at |a| = 1, m/s: the firmware's bound on the velocity its own position
#: loop asks for (platform_defaults.h ``PID_POS_VEL_X_MAX``, ``PID_POS_VEL_Z_MAX``, 1 m/s).
FIRMWARE_MAX_SPEED = 1.0
#: ``firmware_vel``: the yaw-rate setpoint at |a| = 1, deg/s.
FIRMWARE_MAX_YAW_RATE = 90.0
#: ``firmware_ctbr``: the thrust setpoint's range, PWM (crtp_commander_rpyt.c ``MIN_THRUST``, ``MAX_THRUST``: below the
#: least the firmware sets 0, which stops the motors and resets the controller).
FIRMWARE_MIN_THRUST, FIRMWARE_MAX_THRUST = 1000.0, 60000.0
#: The physics rate a firmware action needs, Hz: the firmware's tick (its control step must hold a multiple of its
#: position loop's period, `jaxdrones.control.firmware.loop.POSITION_PERIOD` ticks).
FIRMWARE_SIM_FREQ = 1000


class Reference(NamedTuple):
    """What the task wants the drones to do at this control step (used by ``tun``).

    Attributes:
        pos: f[..., D, 3] m, world frame.
        vel: f[..., D, 3] m/s, world frame.
    """

    pos: jax.Array
    vel: jax.Array


@dataclasses.dataclass(frozen=True)
class ActionType:
    """An action type: its size per drone, its box and its mapping to RPM (static, hashable).

    Attributes:
        name: the registered name (`ACTION_TYPES`).
        size: action entries per drone.
        pid_target: ``"absolute"`` or ``"relative"``, for ``pid`` only (see `PID_TARGETS`).
        pid_scale: ``pid`` with relative targets: target = pos + pid_scale · a, m (default the paper's
            `PID_RELATIVE_SCALE`).
    """

    name: str
    size: int
    pid_target: str = "absolute"
    pid_scale: float = PID_RELATIVE_SCALE

    @property
    def low(self) -> np.ndarray:
        """f[size], the lower bound of the box (-1)."""
        return -np.ones(self.size, np.float32)

    @property
    def high(self) -> np.ndarray:
        """f[size], the upper bound of the box (+1)."""
        return np.ones(self.size, np.float32)

    @property
    def uses_pid(self) -> bool:
        """Whether the mapping runs the DSL PID (whose state is the carry)."""
        return _TABLE[self.name].uses_pid

    @property
    def firmware(self) -> bool:
        """Whether the action is a setpoint of the Crazyflie firmware, flown tick by tick by its PID cascade (`fly`)
        rather than mapped to one RPM command per step (`to_rpm`)."""
        return _TABLE[self.name].setpoint is not None

    def init(self, params: DroneParams, sim: DroneState) -> Any:
        """The carry at reset: a zeroed `PIDState` f[..., D, 3] for the PID-based types, else ``()``; for the
        firmware's setpoints its `jaxdrones.control.firmware.PidControllerState` [..., D] as its motors' idling
        leaves it (every memory zero, the desired yaw the drone's: controllerPid's reset at zero thrust), so that a
        drone does not turn to yaw 0 at its first setpoint."""
        if self.firmware:
            from jaxdrones.control.firmware import controller_pid_init, firmware_state

            carry = controller_pid_init(sim.pos.shape[:-1])
            yaw = firmware_state(sim).attitude[..., 2]
            return carry.replace(attitude_desired=carry.attitude_desired.at[..., 2].set(yaw))
        return pid_init(sim) if self.uses_pid else ()

    def setpoint(self, action: jax.Array) -> Any:
        """The firmware's `jaxdrones.control.firmware.Setpoint` [..., D] of a firmware action f[..., D, 4] (see the
        module's table).

        Raises:
            ValueError: an action type that is not a firmware setpoint.
        """
        entry = _TABLE[self.name]
        if entry.setpoint is None:
            raise ValueError(
                f"action_type {self.name!r} is not a firmware setpoint: expected one of {FIRMWARE_ACTIONS}"
            )
        return entry.setpoint(action.astype(jnp.float32))

    def fly(
        self,
        step: Callable,
        params: DroneParams,
        sim: DroneState,
        carry: Any,
        action: jax.Array,
        ticks: int,
        disturbance: Any = None,
    ) -> tuple[DroneState, Any]:
        """Fly a firmware action (already clipped to the box) for one control step: its setpoint held for ``ticks``
        ticks of the firmware's PID cascade, power distribution and motor map, each driving ``step`` for 1 ms
        (`jaxdrones.control.firmware.pid_schedule`; the firmware's gains, `PidControllerGains.crazyflie`).

        Args:
            step: a physics step of one 1 ms substep (``SimConfig(sim_freq=1000, ctrl_freq=1000)``).
            params: per-drone DroneParams.
            sim: the drones' state before the step.
            carry: the controller's state (`init` or the previous call).
            action: f[..., D, 4].
            ticks: firmware ticks per control step, a positive multiple of 10 (``sim_freq // ctrl_freq``).
            disturbance: a `jaxdrones.physics.state.Disturbance` held over every tick, or None.

        Returns:
            (the drones after the step, the controller's state).

        Raises:
            ValueError: an action type that is not a firmware setpoint, ``ticks`` not a positive multiple of 10, or
                a ``step`` not of 1 ms.
        """
        from jaxdrones.control.firmware import PidControllerGains, check_tick_step, pid_schedule

        check_tick_step(step)
        setpoint = self.setpoint(action)
        sim, carry, _ = pid_schedule(
            step, params, PidControllerGains.crazyflie(), sim, carry, setpoint, ticks, disturbance
        )
        return sim, carry

    def to_rpm(
        self, params: DroneParams, sim: DroneState, carry: Any, action: jax.Array, ref: Reference, ctrl_dt: float
    ) -> tuple[jax.Array, Any]:
        """Map ``action`` f[..., D, size] (already clipped to the box) to an RPM command.

        Args:
            params: per-drone DroneParams (batch shape broadcasting to ``[..., D]``).
            sim: the drones' state before the step.
            carry: from `init` or the previous call.
            action: f[..., D, size].
            ref: the task's reference for this step (``tun`` tracks it).
            ctrl_dt: control period, s.

        Returns:
            (rpm f[..., D, 4] in RPM, new carry).

        Raises:
            ValueError: a firmware setpoint (`firmware`), which is flown tick by tick: `fly`.
        """
        if self.firmware:
            raise ValueError(f"action_type {self.name!r} is a firmware setpoint, flown tick by tick: use fly()")
        return _TABLE[self.name].to_rpm(self, params, sim, carry, action, ref, ctrl_dt)


def _hover_rpm(params: DroneParams, action: jax.Array) -> jax.Array:
    return params.hover_rpm[..., None] * (1.0 + RPM_ACTION_SCALE * action)


def _rpm(kind, params, sim, carry, action, ref, ctrl_dt):
    return _hover_rpm(params, jnp.broadcast_to(action, action.shape[:-1] + (4,))), carry


def _pid_to(params, sim, carry, target_pos, ctrl_dt, gains=None, **targets):
    gains = PIDGains.dsl(sim.pos.dtype) if gains is None else gains
    return pid_control(params, gains, carry, sim, target_pos, ctrl_dt=ctrl_dt, **targets)


def _pid(kind, params, sim, carry, action, ref, ctrl_dt):
    if kind.pid_target == "relative":
        target = sim.pos + kind.pid_scale * action
    else:  # move towards the absolute target by at most PID_MAX_STEP (main's _calculateNextStep)
        delta = action - sim.pos
        dist2 = jnp.sum(delta**2, axis=-1, keepdims=True)
        far = dist2 > PID_MAX_STEP**2
        dist = jnp.sqrt(jnp.where(far, dist2, 1.0))
        target = jnp.where(far, sim.pos + PID_MAX_STEP * delta / dist, action)
    return _pid_to(params, sim, carry, target, ctrl_dt)


def _one_d_pid(kind, params, sim, carry, action, ref, ctrl_dt):
    lift = jnp.concatenate([jnp.zeros_like(sim.pos[..., :2]), PID_RELATIVE_SCALE * action], axis=-1)
    return _pid_to(params, sim, carry, sim.pos + lift, ctrl_dt)


def _vel(kind, params, sim, carry, action, ref, ctrl_dt):
    target_pos, target_vel, target_rpy = velocity_targets(sim, action, speed_limit(params))
    return _pid_to(params, sim, carry, target_pos, ctrl_dt, target_vel=target_vel, target_rpy=target_rpy)


def _tun(kind, params, sim, carry, action, ref, ctrl_dt):
    base = PIDGains.dsl(sim.pos.dtype)
    scale = action + 1.0
    gains = PIDGains(
        *(
            jnp.broadcast_to(g, scale.shape[:-1] + g.shape) * scale[..., k : k + 1]
            for k, g in enumerate((base.p_pos, base.i_pos, base.d_pos, base.p_att, base.i_att, base.d_att))
        )
    )
    return _pid_to(params, sim, carry, ref.pos, ctrl_dt, gains=gains, target_vel=ref.vel)


def _wrench_rpm(params, thrust, torque):
    from jaxdrones.control.mixer import wrench_to_rpm

    return wrench_to_rpm(params, jnp.concatenate([thrust[..., None], torque], axis=-1))


def _thrust_torque(kind, params, sim, carry, action, ref, ctrl_dt):
    thrust = params.weight * (action[..., 0] + 1.0)
    limits = jnp.stack([params.max_xy_torque, params.max_xy_torque, params.max_z_torque], axis=-1)
    return _wrench_rpm(params, thrust, TORQUE_ACTION_SCALE * limits * action[..., 1:]), carry


def _one_d_thrust(kind, params, sim, carry, action, ref, ctrl_dt):
    thrust = params.weight * (1.0 + ONE_D_THRUST_SCALE * action[..., 0])
    return _wrench_rpm(params, thrust, jnp.zeros(thrust.shape + (3,), thrust.dtype)), carry


def _ctbr(kind, params, sim, carry, action, ref, ctrl_dt):
    from jaxdrones.control.mixer import body_rate_control

    thrust = params.weight * (action[..., 0] + 1.0)
    return body_rate_control(params, sim.ang_vel, CTBR_MAX_RATE * action[..., 1:], thrust), carry


def _firmware_setpoint(action: jax.Array, modes: tuple[int, ...], **fields: jax.Array) -> Any:
    """The `Setpoint` [..., D] of an action f[..., D, n] with ``modes`` and ``fields``, zero elsewhere."""
    from jaxdrones.control.firmware import Setpoint

    lead = action.shape[:-1]
    setpoint = Setpoint.zeros(lead)
    return setpoint.replace(mode=jnp.broadcast_to(jnp.asarray(modes, jnp.int32), (*lead, 7)), **fields)


def _firmware_pos(action: jax.Array) -> Any:
    """Cflib ``send_position_setpoint`` (crtp_commander_generic.c ``positionDecoder``): x, y, z, yaw absolute."""
    yaw = jnp.zeros_like(action[..., :3]).at[..., 2].set(jnp.float32(180.0) * action[..., 3])
    position = jnp.float32(FIRMWARE_POSITION_RANGE) * action[..., :3]
    return _firmware_setpoint(action, (1, 1, 1, 0, 0, 1, 0), position=position, attitude=yaw)


def _firmware_vel(action: jax.Array) -> Any:
    """Cflib ``send_velocity_world_setpoint`` (crtp_commander_generic.c ``velocityDecoder``): x, y, z velocity,
    yaw rate."""
    rate = jnp.zeros_like(action[..., :3]).at[..., 2].set(jnp.float32(FIRMWARE_MAX_YAW_RATE) * action[..., 3])
    velocity = jnp.float32(FIRMWARE_MAX_SPEED) * action[..., :3]
    return _firmware_setpoint(action, (2, 2, 2, 0, 0, 2, 0), velocity=velocity, attitude_rate=rate)


def _firmware_ctbr(action: jax.Array) -> Any:
    """Cflib ``send_setpoint`` with ``flightmode.stabModeRoll`` and ``stabModePitch`` in rate mode
    (crtp_commander_rpyt.c): the thrust manual (z modeDisable), roll, pitch and yaw rates (modeVelocity). The body
    rates ω* (rad/s) become the setpoint's deg/s, the pitch's negated (the firmware's legacy frame, whose rate loop
    compares it with −gyro.y)."""
    span = FIRMWARE_MAX_THRUST - FIRMWARE_MIN_THRUST
    thrust = jnp.float32(FIRMWARE_MIN_THRUST) + jnp.float32(span / 2) * (action[..., 0] + 1.0)
    deg = jnp.float32(CTBR_MAX_RATE * 180.0 / np.pi)
    rates = deg * jnp.stack([action[..., 1], -action[..., 2], action[..., 3]], axis=-1)
    return _firmware_setpoint(action, (0, 0, 0, 2, 2, 2, 0), thrust=thrust, attitude_rate=rates)


class _Entry(NamedTuple):
    size: int  # action entries per drone
    uses_pid: bool  # the mapping runs the DSL PID, whose state is the carry
    to_rpm: Callable | None  # (ActionType, params, sim, carry, action, ref, ctrl_dt) -> (rpm, carry); None: fly
    setpoint: Callable | None = None  # a firmware setpoint: action -> Setpoint, flown by ActionType.fly


#: Every action type (see the module docstring): its size, whether it runs the PID, its mapping.
_TABLE = {
    "rpm": _Entry(4, False, _rpm),
    "one_d_rpm": _Entry(1, False, _rpm),
    "pid": _Entry(3, True, _pid),
    "one_d_pid": _Entry(1, True, _one_d_pid),
    "vel": _Entry(4, True, _vel),
    "thrust_torque": _Entry(4, False, _thrust_torque),
    "one_d_thrust": _Entry(1, False, _one_d_thrust),
    "tun": _Entry(6, True, _tun),
    "ctbr": _Entry(4, False, _ctbr),
    "firmware_pos": _Entry(4, False, None, _firmware_pos),
    "firmware_vel": _Entry(4, False, None, _firmware_vel),
    "firmware_ctbr": _Entry(4, False, None, _firmware_ctbr),
}
#: Action entries per drone of every action type.
ACTION_SIZES = {name: entry.size for name, entry in _TABLE.items()}
#: The registered action type names.
ACTION_TYPES = tuple(ACTION_SIZES)
#: The action types that are the Crazyflie firmware's setpoints (`ActionType.firmware`).
FIRMWARE_ACTIONS = tuple(name for name, entry in _TABLE.items() if entry.setpoint is not None)


def make_action(name: str, pid_target: str = "absolute", pid_scale: float = PID_RELATIVE_SCALE) -> ActionType:
    """The `ActionType` called ``name`` (``pid_target`` and ``pid_scale``: see `ActionType`).

    Raises:
        ValueError: unknown name or ``pid_target`` (``pid_scale`` is checked by `TaskConfig`).
    """
    if name not in ACTION_SIZES:
        raise ValueError(f"unknown action_type {name!r}: expected one of {ACTION_TYPES}")
    if pid_target not in PID_TARGETS:
        raise ValueError(f"pid_target must be one of {PID_TARGETS}, got {pid_target!r}")
    return ActionType(name, ACTION_SIZES[name], pid_target, float(pid_scale))
