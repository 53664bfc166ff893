"""gym-pybullet-drones' ``DSLPIDControl`` on `jaxdrones.control.pid` (the same controller, quirks included), one
jitted call per `computeControl`."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.compat.gym_pybullet_drones.control.BaseControl import BaseControl
from jaxdrones.compat.gym_pybullet_drones.utils.enums import DroneModel
from jaxdrones.control.mixer import mixer_matrix
from jaxdrones.control.pid import (
    DSL_GAINS,
    MAX_PWM,
    MIN_PWM,
    PWM2RPM_CONST,
    PWM2RPM_SCALE,
    PIDGains,
    PIDState,
    pid_compute,
    pid_init,
)
from jaxdrones.physics.params import load_params
from jaxdrones.physics.state import DroneState

_GAINS = {
    "P_COEFF_FOR": "p_pos",
    "I_COEFF_FOR": "i_pos",
    "D_COEFF_FOR": "d_pos",
    "P_COEFF_TOR": "p_att",
    "I_COEFF_TOR": "i_att",
    "D_COEFF_TOR": "d_att",
}


class DSLPIDControl(BaseControl):
    """The DSL PID of gym-pybullet-drones for one Crazyflie (``cf2x`` or ``cf2p``): `jaxdrones.control.pid`'s
    `pid_compute`, which reproduces the original's computation (docs/physics.md §12).

    Attributes: the gains ``P_COEFF_FOR``, ``I_COEFF_FOR``, ``D_COEFF_FOR`` (position) and ``P_COEFF_TOR``,
    ``I_COEFF_TOR``, ``D_COEFF_TOR`` (attitude), f64[3] each, read at every call (`setPIDCoefficients` or plain
    assignment changes them); ``PWM2RPM_SCALE``, ``PWM2RPM_CONST``, ``MIN_PWM``, ``MAX_PWM``, ``MIXER_MATRIX``
    f[4, 3]; the memory ``integral_pos_e``, ``integral_rpy_e``, ``last_rpy`` (f64[3], zeroed by `reset`).

    Raises:
        ValueError: a drone model other than ``CF2X`` or ``CF2P`` (the gains are the Crazyflie's).
    """

    def __init__(self, drone_model: DroneModel = DroneModel.CF2X, g: float = 9.8):
        drone_model = DroneModel(drone_model)
        if drone_model not in (DroneModel.CF2X, DroneModel.CF2P):
            raise ValueError(
                f"DSLPIDControl is tuned for the Crazyflie: drone_model must be DroneModel.CF2X or "
                f"DroneModel.CF2P, got {drone_model}"
            )
        self.PWM2RPM_SCALE, self.PWM2RPM_CONST = PWM2RPM_SCALE, PWM2RPM_CONST
        self.MIN_PWM, self.MAX_PWM = MIN_PWM, MAX_PWM
        for name, field in _GAINS.items():
            setattr(self, name, np.array(DSL_GAINS[field], np.float64))
        super().__init__(drone_model=drone_model, g=g)

    @property
    def MIXER_MATRIX(self) -> np.ndarray:
        """f64[4, 3]: pwm = thrust + MIXER_MATRIX @ (τ_roll, τ_pitch, τ_yaw), derived from the airframe
        (`jaxdrones.control.mixer.mixer_matrix`)."""
        return np.asarray(jax.jit(mixer_matrix)(self._params), np.float64)

    def reset(self) -> None:
        """Zero the call counter and the controller's memory (integrals, last attitude)."""
        super().reset()
        self._state = jax.tree.map(np.asarray, pid_init((1,)))

    @property
    def integral_pos_e(self) -> np.ndarray:
        return np.asarray(self._state.integral_pos_e[0])

    @property
    def integral_rpy_e(self) -> np.ndarray:
        return np.asarray(self._state.integral_rpy_e[0])

    @property
    def last_rpy(self) -> np.ndarray:
        return np.asarray(self._state.last_rpy[0])

    def computeControl(
        self,
        control_timestep,
        cur_pos,
        cur_quat,
        cur_vel,
        cur_ang_vel,
        target_pos,
        target_rpy=np.zeros(3),
        target_vel=np.zeros(3),
        target_rpy_rates=np.zeros(3),
    ):  # noqa: B008
        """One control step (the original's ``computeControl``).

        Args:
            control_timestep: the control period, s.
            cur_pos, cur_quat, cur_vel, cur_ang_vel: the drone's position (m, world), quaternion (x, y, z, w),
                velocity (m/s, world) and angular velocity (unused, as in the original).
            target_pos: m, world; target_rpy: rad (only the yaw is used, as in the original); target_vel: m/s;
                target_rpy_rates: rad/s.

        Returns:
            (rpm f64[4] RPM, position error f64[3] m, yaw error float rad).

        Raises:
            ValueError: a non-positive ``control_timestep`` or inputs that are not 3-vectors (4 for the quaternion).
        """
        self.control_counter += 1
        if not float(control_timestep) > 0:
            raise ValueError(f"control_timestep must be a period > 0 s, got {control_timestep!r}")
        try:
            inputs = np.concatenate(
                [
                    np.asarray(v, np.float64).reshape(n)
                    for v, n in (
                        (cur_pos, 3),
                        (cur_quat, 4),
                        (cur_vel, 3),
                        (target_pos, 3),
                        (target_rpy, 3),
                        (target_vel, 3),
                        (target_rpy_rates, 3),
                    )
                ]
            )
        except ValueError as e:
            raise ValueError(f"computeControl takes 3-vectors (a 4-vector for cur_quat): {e}") from None
        gains = np.concatenate([np.asarray(getattr(self, name), np.float64).reshape(3) for name in _GAINS])
        memory = np.concatenate([np.asarray(leaf).reshape(3) for leaf in jax.tree.leaves(self._state)])
        # One array in, one out: a call from a Python loop is one dispatch and one transfer.
        out = np.asarray(_control(self.DRONE_MODEL.value, gains, memory, inputs, float(control_timestep)))
        self._state = PIDState(*(out[8 + 3 * k : 11 + 3 * k][None] for k in range(3)))
        return out[:4].astype(np.float64), out[4:7].astype(np.float64), float(out[7])

    def setPIDCoefficients(
        self, p_coeff_pos=None, i_coeff_pos=None, d_coeff_pos=None, p_coeff_att=None, i_coeff_att=None, d_coeff_att=None
    ) -> None:
        """Set any of the six gain vectors (f[3] each); None keeps a gain."""
        values = (p_coeff_pos, i_coeff_pos, d_coeff_pos, p_coeff_att, i_coeff_att, d_coeff_att)
        for name, value in zip(_GAINS, values, strict=True):
            if value is not None:
                setattr(self, name, np.asarray(value, np.float64).reshape(3))


@functools.partial(jax.jit, static_argnums=0)
def _control(model: str, gains, memory, inputs, dt):
    """Rpm f[4], pos_e f[3], yaw_e, then the new memory (integral_pos_e, integral_rpy_e, last_rpy) in one f[17]."""
    params = load_params(model)  # traced once per model: constants of the compiled call
    dtype = jnp.result_type(float)
    gains, memory, inputs = (jnp.asarray(x, dtype) for x in (gains, memory, inputs))
    pos, quat, vel = inputs[None, 0:3], inputs[None, 3:7], inputs[None, 7:10]
    target_pos, target_rpy, target_vel, target_rpy_rates = (inputs[None, 10 + 3 * k : 13 + 3 * k] for k in range(4))
    state = DroneState(
        pos=pos,
        quat=quat,
        vel=vel,
        ang_vel=jnp.zeros_like(pos),
        rpm=jnp.zeros((1, 4), dtype),
        contact=jnp.zeros((1,), jnp.int32),
    )
    pid_state = PIDState(*(memory[None, 3 * k : 3 * k + 3] for k in range(3)))
    rpm, new, info = pid_compute(
        params,
        PIDGains(*(gains[3 * k : 3 * k + 3] for k in range(6))),
        pid_state,
        state,
        target_pos,
        target_vel=target_vel,
        target_rpy=target_rpy,
        target_rpy_rates=target_rpy_rates,
        ctrl_dt=dt,
    )
    return jnp.concatenate(
        [rpm[0], info.pos_err[0], info.yaw_err, new.integral_pos_e[0], new.integral_rpy_e[0], new.last_rpy[0]]
    )
