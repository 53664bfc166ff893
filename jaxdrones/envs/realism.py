"""Sim-to-real options of the envs: motor lag, action and observation delays, observation noise and bias, wind
(constant, gusts, Dryden turbulence) and random force and torque disturbances.

`Realism` (static, hashable: part of `jaxdrones.envs.TaskConfig`) says which options are on and the range each
value is drawn from per world and episode; `RealismState` (traced, in `jaxdrones.envs.EnvState.realism`) holds the
episode's drawn values, the delay buffers, the wind's and the disturbance's processes and their PRNG key. Every
value is a traced array, so it can differ per world and episode, and every option is differentiable where it is
continuous (the delays select, the noise and the wind add). All are off by default: the paper's physics. The
equations and the sources of the values are in docs/physics.md §16.

`PRESETS` holds the named settings: ``"crazyflie"``, the values of Learning to Fly in Seconds (Eschmann et al.,
IEEE RA-L 2024, the code of arplaboratory/learning-to-fly) for a Crazyflie 2.1; ``"crazyflie_harsh"`` twice its lag
and noise with 1 m/s (horizontal) Dryden turbulence.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.typing import ArrayLike, DTypeLike

from jaxdrones._hints import did_you_mean
from jaxdrones._validate import is_real
from jaxdrones.physics.rotations import join, normalize_c, quat_integrate_c, split
from jaxdrones.physics.state import Disturbance, DroneState

#: Feet per metre, for MIL-F-8785C's low-altitude formulas (written in ft).
_FT_PER_M = 1 / 0.3048
#: The least speed at which Dryden turbulence is carried past a hovering drone, m/s (see `dryden_constants`).
MIN_AIRSPEED = 1.0
#: The observed quantities, in the order of the noise and bias fields and of `RealismState.bias`.
OBSERVED = ("pos", "att", "vel", "ang_vel")


@dataclasses.dataclass(frozen=True)
class Realism:
    """Which sim-to-real options are on, and the range each value is drawn from: a number (that value) or a pair
    ``(low, high)`` (uniform per world and episode, drawn at reset). Stored as ``(low, high)`` pairs.

    Attributes:
        motor_tau_up: s, the motors' time constant while speeding up (`jaxdrones.physics.dynamics.motor_response_c`);
            > 0 turns on first-order motor dynamics (`jaxdrones.physics.config.SimConfig.motor_dynamics`). Drawn per
            drone with the drones' other params (`jaxdrones.envs.config.TaskConfig.param_draws`).
        motor_tau_down: s, the same while slowing down.
        action_delay: control steps (integers) between the policy's action and its effect on the motors.
        obs_delay: control steps (integers) between the drone's state and the observation of it.
        obs_noise_pos: m, σ of Gaussian noise on the observed position, drawn at every step per axis.
        obs_noise_att: rad, σ of the observed attitude's error: a rotation by a Gaussian rotation vector (body).
        obs_noise_vel: m/s, σ on the observed velocity.
        obs_noise_ang_vel: rad/s, σ on the observed body rates.
        obs_bias_pos, obs_bias_att, obs_bias_vel, obs_bias_ang_vel: σ of a bias drawn per episode, per drone and
            axis, added like the noise (a calibration error).
        wind_speed: m/s, a constant wind per episode, horizontal, in a direction drawn uniformly.
        gust_speed: m/s, the peak of discrete "1 − cosine" gusts, v(t) = v_m (1 − cos(2π t / d)) / 2 over d s,
            horizontal in a uniform direction; drawn per gust.
        gust_rate: 1/s, gusts start as a Poisson process of this rate (one at a time).
        gust_duration: s, d, drawn per gust.
        turbulence: m/s, σ of the horizontal components of Dryden turbulence (MIL-F-8785C, low altitude; the
            vertical σ follows from the altitude, see `dryden_constants`), carried past the drone at the mean
            wind's speed (at least `MIN_AIRSPEED`).
        turbulence_altitude: m, the altitude of MIL-F-8785C's low-altitude length scales (RotorPy's 2 m).
        disturbance_force: N, σ of a random force per drone and axis (world frame, Gaussian).
        disturbance_torque: N·m, σ of a random torque per drone and axis (body frame, Gaussian).
        disturbance_hold: s, how long a drawn disturbance is held: 0 redraws it at every control step, ``inf``
            once per episode (as L2F), otherwise for exponentially distributed durations of this mean.

    Wind of any kind acts through the drag model (paper eq. (drag) on the velocity relative to the air), which the
    env turns on with it.

    Raises:
        ValueError: an unknown field, a value that is not a finite number ≥ 0 (``inf`` allowed for
            ``disturbance_hold`` only) or a pair with low > high, a non-integer delay.
    """

    motor_tau_up: Any = 0.0
    motor_tau_down: Any = 0.0
    action_delay: Any = 0
    obs_delay: Any = 0
    obs_noise_pos: Any = 0.0
    obs_noise_att: Any = 0.0
    obs_noise_vel: Any = 0.0
    obs_noise_ang_vel: Any = 0.0
    obs_bias_pos: Any = 0.0
    obs_bias_att: Any = 0.0
    obs_bias_vel: Any = 0.0
    obs_bias_ang_vel: Any = 0.0
    wind_speed: Any = 0.0
    gust_speed: Any = 0.0
    gust_rate: Any = 0.0
    gust_duration: Any = (0.5, 2.0)
    turbulence: Any = 0.0
    turbulence_altitude: Any = 2.0
    disturbance_force: Any = 0.0
    disturbance_torque: Any = 0.0
    disturbance_hold: Any = 0.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            pair = value if isinstance(value, (tuple, list)) else (value, value)
            integer = f.name.endswith("_delay")
            kind = "an integer number of control steps" if integer else "a number"
            if len(pair) != 2 or not all(is_real(v) for v in pair):
                raise ValueError(f"realism.{f.name} must be {kind} or a pair (low, high), got {value!r}")
            low, high = (float(v) for v in pair)
            finite = f.name == "disturbance_hold" or (math.isfinite(low) and math.isfinite(high))
            if not finite or math.isnan(low) or math.isnan(high) or low < 0 or low > high:
                raise ValueError(f"realism.{f.name} must be finite, >= 0 and, as a pair, low <= high, got {value!r}")
            if integer and not (low.is_integer() and high.is_integer()):
                raise ValueError(f"realism.{f.name} must be {kind} (or a pair of them), got {value!r}")
            if f.name == "turbulence_altitude" and self.on("turbulence") and low <= 0:
                raise ValueError(f"realism.turbulence_altitude must be > 0 m with turbulence, got {value!r}")
            if f.name == "gust_duration" and low <= 0:
                raise ValueError(f"realism.gust_duration must be > 0 s, got {value!r}")
            object.__setattr__(self, f.name, (int(low), int(high)) if integer else (low, high))

    def on(self, name: str) -> bool:
        """Whether the option ``name`` (a field) can be non-zero."""
        value = getattr(self, name)
        high = value[1] if isinstance(value, tuple) else value
        return float(high) > 0

    @property
    def motor_dynamics(self) -> bool:
        """First-order motor dynamics are on."""
        return self.on("motor_tau_up") or self.on("motor_tau_down")

    @property
    def wind(self) -> bool:
        """Some wind blows (constant, gusts or turbulence)."""
        return self.on("wind_speed") or (self.on("gust_speed") and self.on("gust_rate")) or self.on("turbulence")

    @property
    def disturbance(self) -> bool:
        """Random forces or torques act."""
        return self.on("disturbance_force") or self.on("disturbance_torque")

    @property
    def obs_noise(self) -> bool:
        return any(self.on(f"obs_noise_{k}") for k in OBSERVED)

    @property
    def obs_bias(self) -> bool:
        return any(self.on(f"obs_bias_{k}") for k in OBSERVED)

    def scaled(self, lag: float = 1.0, noise: float = 1.0) -> Realism:
        """These settings with the motors' time constants times ``lag`` and the noise and bias σ times ``noise``."""
        new = {}
        for f in dataclasses.fields(self):
            factor = (
                lag
                if f.name.startswith("motor_tau")
                else noise
                if f.name.startswith(("obs_noise", "obs_bias"))
                else None
            )
            if factor is not None:
                new[f.name] = tuple(v * factor for v in getattr(self, f.name))
        return dataclasses.replace(self, **new)


#: Learning to Fly in Seconds (Eschmann, Albani, Loianno, IEEE RA-L 2024; arplaboratory/learning-to-fly: the
#: Crazyflie's parameters in ``include/learning_to_fly/simulator/parameters/dynamics/crazy_flie.h``, its training
#: config's observation noise and disturbances): a single RPM time constant of 0.15 s; observation noise σ 0.001 m,
#: 0.001 (rotation), 0.002 m/s, 0.002 rad/s; a force σ = 0.027 kg · 9.81 m/s² / 20 = 0.0132 N and a torque
#: σ = 0.027 · 9.81 / 10000 = 2.65e-5 N·m per axis, drawn once per episode. Its latency (about 10 ms from IMU to
#: motors) is below one control step at the envs' 30 Hz: no delay.
CRAZYFLIE = Realism(
    motor_tau_up=0.15,
    motor_tau_down=0.15,
    obs_noise_pos=0.001,
    obs_noise_att=0.001,
    obs_noise_vel=0.002,
    obs_noise_ang_vel=0.002,
    disturbance_force=0.027 * 9.81 / 20,
    disturbance_torque=0.027 * 9.81 / 10000,
    disturbance_hold=math.inf,
)
#: Named settings for `jaxdrones.make`'s ``realism``.
PRESETS = {
    "crazyflie": CRAZYFLIE,
    "crazyflie_harsh": dataclasses.replace(CRAZYFLIE.scaled(lag=2.0, noise=2.0), turbulence=1.0),
}


def resolve(value: Realism | str | Mapping[str, Any] | None) -> Realism | None:
    """A `Realism` from None (off), a preset name (`PRESETS`), a `Realism`, or a dict of its fields with an optional
    ``"preset"`` key whose settings the other keys override.

    Raises:
        ValueError: an unknown preset or field (with the closest name), or an invalid value.
    """
    if value is None or isinstance(value, Realism):
        return value
    if isinstance(value, str):
        if value not in PRESETS:
            raise ValueError(
                f"unknown realism preset {value!r}{did_you_mean(value, PRESETS)}: expected one of "
                f"{tuple(PRESETS)}, a jaxdrones.realism.Realism or a dict of its fields"
            )
        return PRESETS[value]
    if isinstance(value, dict):
        fields = {f.name for f in dataclasses.fields(Realism)}
        options = dict(value)
        base = resolve(options.pop("preset", None)) or Realism()
        for name in options:
            if name not in fields:
                raise ValueError(
                    f"unknown realism option {name!r}{did_you_mean(name, fields | {'preset'})}: "
                    f"expected 'preset' or fields of jaxdrones.realism.Realism {sorted(fields)}"
                )
        return dataclasses.replace(base, **options)
    raise ValueError(
        f"realism must be None, a preset name {tuple(PRESETS)}, a jaxdrones.realism.Realism or a dict "
        f"of its fields, got {value!r}"
    )


@struct.dataclass
class RealismState:
    """What the sim-to-real options carry through an episode (one world; ``vmap`` adds the world axis).

    Attributes:
        values: the episode's drawn values, by `Realism` field: f[] per world (i32[] for the delays).
        bias: f[D, 4, 3] the episode's observation bias of position, attitude (rotation vector), velocity, rates.
        actions: f[Ka + 1, D, n_act] the last actions, oldest first (Ka = the largest action delay).
        observed: f[Ko + 1, D, 13] the last states (pos, quat, vel, ang_vel), oldest first (Ko = the largest
            observation delay).
        axis: f[2] the unit horizontal direction of the mean wind (the turbulence's longitudinal axis).
        dryden: f[5] the turbulence filters' states (u; v: two; w: two), of unit variance.
        gust: f[5] the current gust: time since its start s, duration s, peak velocity (x, y) m/s; inactive when
            the time exceeds the duration.
        disturbance: f[D, 6] the held force (world, N) and torque (body, N·m).
        hold: f[] s left before the disturbance is redrawn.
        key: PRNG key of the per-step draws.
    """

    values: dict[str, jax.Array]
    bias: jax.Array
    actions: jax.Array
    observed: jax.Array
    axis: jax.Array
    dryden: jax.Array
    gust: jax.Array
    disturbance: jax.Array
    hold: jax.Array
    key: jax.Array


def dryden_constants(
    turbulence: ArrayLike, altitude: ArrayLike, airspeed: ArrayLike
) -> tuple[tuple[ArrayLike, ArrayLike], tuple[jax.Array, jax.Array]]:
    """MIL-F-8785C's low-altitude Dryden constants (MIL-F-8785C §3.7.2.3; h < 1000 ft): σ_u = σ_v = ``turbulence``
    (m/s), σ_w = σ_u (0.177 + 0.000823 h)^0.4, L_u = L_v = h / (0.177 + 0.000823 h)^1.2, L_w = h (h in ft), and
    the filters' time constants T = L / V at the airspeed V = max(|mean wind|, `MIN_AIRSPEED`) m/s (the speed at
    which the frozen turbulence passes a hovering drone; below 1 m/s it would freeze).

    Returns:
        (σ_u, σ_w) m/s and (T_u, T_w) s, arrays like the inputs.
    """
    h_ft = altitude * _FT_PER_M
    base = 0.177 + 0.000823 * h_ft
    length_u = altitude / base**1.2
    speed = jnp.maximum(airspeed, MIN_AIRSPEED)
    return (turbulence, turbulence * base**0.4), (length_u / speed, altitude / speed)


def dryden_psd(omega: ArrayLike, sigma: ArrayLike, tau: ArrayLike, longitudinal: bool) -> jax.Array | np.ndarray:
    """The Dryden spectra in time, two-sided, Φ(ω) with ∫ Φ dω / 2π = σ² (MIL-F-8785C's forms at airspeed V with
    T = L/V): Φ_u = σ² 2T / (1 + T²ω²); Φ_v = Φ_w = σ² T (1 + 3T²ω²) / (1 + T²ω²)². ω in rad/s."""
    x = (tau * omega) ** 2
    if longitudinal:
        return sigma**2 * 2 * tau / (1 + x)
    return sigma**2 * tau * (1 + 3 * x) / (1 + x) ** 2


def _first_order(state, tau, dt, noise):
    """One exact step of the unit-variance Ornstein-Uhlenbeck process of time constant ``tau`` (Dryden's
    longitudinal filter 1 / (1 + T s) on white noise)."""
    a = jnp.exp(-dt / tau)
    return a * state + jnp.sqrt(1 - a**2) * noise


def _second_order(state, tau, dt, noise):
    """One exact step of Dryden's lateral/vertical filter (1 + √3 T s) / (1 + T s)² on white noise of intensity
    T (unit output variance), as the two cascaded first-order states z1 = η / (1 + Ts), z2 = z1 / (1 + Ts):
    x ← Φ x + w, Φ = e^{F dt}, w ~ N(0, Q) with Q the exact integral (Van Loan) in closed form. ``noise`` f[2]
    standard normal; ``state`` f[2]. Output √3 z1 + (1 − √3) z2 (`_second_order_output`)."""
    r = dt / tau
    e = jnp.exp(-r)
    z1 = e * state[0]
    z2 = e * (state[1] + r * state[0])
    # Q = (q / T²) [[I0, I1 / T], [I1 / T, I2 / T²]] with q = T and β = 2 / T, I_k = ∫_0^dt s^k e^{-βs} ds.
    e2 = e**2
    i0 = tau / 2 * (1 - e2)
    i1 = tau**2 / 4 * (1 - e2 * (1 + 2 * r))
    i2 = tau**3 / 4 * (1 - e2 * (1 + 2 * r + 2 * r**2))
    q11, q12, q22 = i0 / tau, i1 / tau**2, i2 / tau**3
    l11 = jnp.sqrt(q11)
    l21 = q12 / l11
    l22 = jnp.sqrt(jnp.maximum(q22 - l21**2, 0.0))
    return jnp.stack([z1 + l11 * noise[0], z2 + l21 * noise[0] + l22 * noise[1]])


def _second_order_output(state):
    return math.sqrt(3.0) * state[0] + (1 - math.sqrt(3.0)) * state[1]


#: Stationary covariance of the second-order filter's state (unit output variance): [[1/2, 1/4], [1/4, 1/4]].
_SECOND_ORDER_CHOL = np.linalg.cholesky(np.array([[0.5, 0.25], [0.25, 0.25]]))


class RealismModel:
    """The options of one env: `reset` draws an episode's `RealismState`, `delay_action` and `observe` act around
    the physics, `disturbance` draws the step's `jaxdrones.physics.state.Disturbance`.

    Args:
        realism: the `Realism`.
        n_drones: D.
        action_size: the action's length.
        ctrl_dt: the control period, s.
    """

    def __init__(self, realism: Realism, n_drones: int, action_size: int, ctrl_dt: float):
        self.realism, self.n_drones, self.action_size, self.ctrl_dt = realism, n_drones, action_size, ctrl_dt
        self.action_buffer = realism.action_delay[1]
        self.obs_buffer = realism.obs_delay[1]

    # -- reset ---------------------------------------------------------------------------------------------------

    def reset(self, key: jax.Array, sim: DroneState, dtype: DTypeLike) -> RealismState:
        """The episode's draws and the buffers, filled with a zero action and the start state."""
        r, n = self.realism, self.n_drones
        k_values, k_bias, k_axis, k_dryden, k_dist, key = jax.random.split(key, 6)
        values = {}
        for i, f in enumerate(dataclasses.fields(Realism)):
            low, high = getattr(r, f.name)
            k = jax.random.fold_in(k_values, i)
            if f.name.startswith("motor_tau"):  # the drones' params: drawn by `TaskConfig.param_draws`
                continue
            if f.name.endswith("_delay"):
                values[f.name] = jax.random.randint(k, (), low, high + 1, jnp.int32)
            elif low == high or math.isinf(high):
                values[f.name] = jnp.asarray(low if low == high else high, dtype)
            else:
                values[f.name] = jax.random.uniform(k, (), dtype, low, high)
        sigma = jnp.stack([values[f"obs_bias_{k}"] for k in OBSERVED])
        bias = jax.random.normal(k_bias, (n, 4, 3), dtype) * sigma[None, :, None]
        angle = jax.random.uniform(k_axis, (), dtype, 0.0, 2 * jnp.pi)
        axis = jnp.stack([jnp.cos(angle), jnp.sin(angle)])
        draws = jax.random.normal(k_dryden, (5,), dtype)  # from the filters' stationary distributions
        chol = jnp.asarray(_SECOND_ORDER_CHOL, dtype)
        dryden = jnp.concatenate([draws[:1], chol @ draws[1:3], chol @ draws[3:5]])
        gust = jnp.asarray([1.0, 0.0, 0.0, 0.0, 0.0], dtype)  # inactive: time beyond duration
        disturbance, hold = self._draw_disturbance(k_dist, values, dtype)
        actions = jnp.zeros((self.action_buffer + 1, n, self.action_size), dtype)
        observed = jnp.broadcast_to(_pack(sim), (self.obs_buffer + 1, n, 13))
        return RealismState(
            values=values,
            bias=bias,
            actions=actions,
            observed=observed,
            axis=axis,
            dryden=dryden,
            gust=gust,
            disturbance=disturbance,
            hold=hold,
            key=key,
        )

    def _draw_disturbance(self, key, values, dtype):
        k_force, k_hold = jax.random.split(key)
        sigma = jnp.concatenate(
            [jnp.broadcast_to(values["disturbance_force"], (3,)), jnp.broadcast_to(values["disturbance_torque"], (3,))]
        )
        draw = jax.random.normal(k_force, (self.n_drones, 6), dtype) * sigma[None]
        mean = values["disturbance_hold"]
        hold = jnp.where(jnp.isinf(mean), jnp.inf, mean * jax.random.exponential(k_hold, (), dtype))
        return draw, hold

    # -- step ----------------------------------------------------------------------------------------------------

    def delay_action(self, state: RealismState, action: jax.Array) -> tuple[jax.Array, RealismState]:
        """The action the motors get now (the one of ``values["action_delay"]`` steps ago; zero before the first),
        and the state with ``action`` recorded."""
        if not self.action_buffer:
            return action, state
        actions = jnp.concatenate([state.actions[1:], action[None]], axis=0)
        applied = jax.lax.dynamic_index_in_dim(actions, self.action_buffer - state.values["action_delay"], 0, False)
        return applied, state.replace(actions=actions)

    def disturbance(self, state: RealismState, sim: DroneState) -> tuple[Disturbance | None, RealismState]:
        """The step's `Disturbance` (None when no option acts on the physics) and the advanced processes."""
        r = self.realism
        if not (r.wind or r.disturbance):
            return None, state
        key, k_wind, k_dist = jax.random.split(state.key, 3)
        dtype = sim.pos.dtype
        force = torque = wind = None
        if r.wind:
            wind_xyz, state = self._wind(state, k_wind, dtype)
            wind = jnp.broadcast_to(wind_xyz, sim.pos.shape)
        if r.disturbance:
            hold = state.hold - self.ctrl_dt
            redraw = hold <= 0
            draw, new_hold = self._draw_disturbance(k_dist, state.values, dtype)
            held = jnp.where(redraw, draw, state.disturbance)
            state = state.replace(disturbance=held, hold=jnp.where(redraw, new_hold, hold))
            force, torque = (
                held[:, :3] if r.on("disturbance_force") else None,
                held[:, 3:] if r.on("disturbance_torque") else None,
            )
        return Disturbance(force=force, torque=torque, wind=wind), state.replace(key=key)

    def _wind(self, state: RealismState, key, dtype):
        r, dt, values = self.realism, self.ctrl_dt, state.values
        axis = state.axis
        horizontal = values["wind_speed"] * axis
        vertical = jnp.zeros((), dtype)
        if r.on("gust_speed") and r.on("gust_rate"):
            u = jax.random.uniform(key, (4,), dtype)
            t, duration = state.gust[0] + dt, state.gust[1]
            start = (t > duration) & (u[0] < -jnp.expm1(-values["gust_rate"] * dt))
            low, high = r.gust_duration
            angle = 2 * jnp.pi * u[2]
            speed = r.gust_speed[0] + (r.gust_speed[1] - r.gust_speed[0]) * u[3]
            fresh = jnp.stack(
                [
                    jnp.zeros((), dtype),
                    low + (high - low) * u[1],
                    speed * jnp.cos(angle),
                    speed * jnp.sin(angle),
                    jnp.zeros((), dtype),
                ]
            )
            gust = jnp.where(start, fresh, state.gust.at[0].set(t))
            active = gust[0] <= gust[1]
            shape = 0.5 * (1 - jnp.cos(2 * jnp.pi * gust[0] / jnp.where(active, gust[1], 1.0)))
            horizontal = horizontal + jnp.where(active, shape, 0.0) * gust[2:4]
            state = state.replace(gust=gust)
        if r.on("turbulence"):
            (sigma_u, sigma_w), (tau_u, tau_w) = dryden_constants(
                values["turbulence"], values["turbulence_altitude"], values["wind_speed"]
            )
            noise = jax.random.normal(jax.random.fold_in(key, 1), (5,), dtype)
            d = state.dryden
            dryden = jnp.concatenate(
                [
                    _first_order(d[:1], tau_u, dt, noise[:1]),
                    _second_order(d[1:3], tau_u, dt, noise[1:3]),
                    _second_order(d[3:5], tau_w, dt, noise[3:5]),
                ]
            )
            along, across = sigma_u * dryden[0], sigma_u * _second_order_output(dryden[1:3])
            horizontal = horizontal + along * axis + across * jnp.stack([-axis[1], axis[0]])
            vertical = sigma_w * _second_order_output(dryden[3:5])
            state = state.replace(dryden=dryden)
        return jnp.concatenate([horizontal, vertical[None]]), state

    def observe(self, state: RealismState, sim: DroneState) -> tuple[DroneState, RealismState]:
        """The state the observation shows: ``sim`` as of ``values["obs_delay"]`` steps ago, with the episode's
        bias and this step's noise; and the realism state with ``sim`` recorded (and its key advanced)."""
        r = self.realism
        seen = sim
        if self.obs_buffer:
            observed = jnp.concatenate([state.observed[1:], _pack(sim)[None]], axis=0)
            packed = jax.lax.dynamic_index_in_dim(observed, self.obs_buffer - state.values["obs_delay"], 0, False)
            seen = _unpack(packed, sim)
            state = state.replace(observed=observed)
        if not (r.obs_noise or r.obs_bias):
            return seen, state
        error = state.bias
        if r.obs_noise:
            key, k_noise = jax.random.split(state.key)
            sigma = jnp.stack([state.values[f"obs_noise_{k}"] for k in OBSERVED])
            error = error + jax.random.normal(k_noise, error.shape, error.dtype) * sigma[None, :, None]
            state = state.replace(key=key)
        return _with_error(seen, error), state

    def initial(self, state: RealismState, sim: DroneState) -> DroneState:
        """The state the first observation shows: the start with the episode's bias (no noise)."""
        if not self.realism.obs_bias:
            return sim
        return _with_error(sim, state.bias)


def _with_error(sim: DroneState, error: jax.Array) -> DroneState:
    """``sim`` as a sensor with ``error`` f[D, 4, 3] reports it: position, velocity and body rates plus their rows;
    the attitude rotated by the rotation vector of row 1 (body frame)."""
    quat = normalize_c(quat_integrate_c(split(sim.quat), split(error[:, 1]), 1.0))
    return sim.replace(
        pos=sim.pos + error[:, 0], quat=join(quat), vel=sim.vel + error[:, 2], ang_vel=sim.ang_vel + error[:, 3]
    )


def _pack(sim: DroneState) -> jax.Array:
    return jnp.concatenate([sim.pos, sim.quat, sim.vel, sim.ang_vel], axis=-1)


def _unpack(packed: jax.Array, sim: DroneState) -> DroneState:
    return sim.replace(pos=packed[..., :3], quat=packed[..., 3:7], vel=packed[..., 7:10], ang_vel=packed[..., 10:])
