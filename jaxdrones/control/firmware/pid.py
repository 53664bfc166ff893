"""The firmware's PID object (``src/utils/src/pid.c``) and its second-order low-pass filter (``lpf2p*``,
``src/utils/src/filter.c``), as pure functions of float32 pytrees, batched over any leading axes.

Each function follows the C statement by statement, in the same order of float32 operations, so that its results
are the C's to float32 rounding (the firmware's ``CONFIG_CONTROLLER_PID_FILTER_ALL`` off, as in ``cf2_defconfig``).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

#: pid.h: the integral's limit a PID starts with (``DEFAULT_PID_INTEGRATION_LIMIT``) and its output's (0: none).
DEFAULT_INTEGRATION_LIMIT = 5000.0
DEFAULT_OUTPUT_LIMIT = 0.0


@struct.dataclass
class PidGains:
    """A ``PidObject``'s constants.

    Attributes:
        kp, ki, kd, kff: f32[...] gains (``kff`` multiplies the desired value).
        i_limit: f32[...] the integral's bound (0: none).
        output_limit: f32[...] the output's bound (0: none).
        dt: f32[...] s, the update period.
        lpf: f32[5, ...], the derivative filter's b0, b1, b2, a1, a2 (`lpf2p_coefficients`), first.
        filtered: whether the derivative is low-pass filtered (``enableDFilter``); static.
    """

    kp: jax.Array
    ki: jax.Array
    kd: jax.Array
    kff: jax.Array
    i_limit: jax.Array
    output_limit: jax.Array
    dt: jax.Array
    lpf: jax.Array
    filtered: bool = struct.field(pytree_node=False, default=False)


@struct.dataclass
class PidState:
    """A ``PidObject``'s memory: ``integ``, ``prevMeasured`` and the derivative filter's two delay elements, each
    f32[...]."""

    integ: jax.Array
    prev_measured: jax.Array
    delay1: jax.Array
    delay2: jax.Array

    @classmethod
    def zeros(cls, shape: tuple[int, ...] = ()) -> PidState:
        z = jnp.zeros(shape, jnp.float32)
        return cls(integ=z, prev_measured=z, delay1=z, delay2=z)


def lpf2p_coefficients(sample_freq: float, cutoff_freq: float) -> np.ndarray:
    """f32[5]: b0, b1, b2, a1, a2 of ``lpf2pSetCutoffFreq`` (filter.c), computed in float32 as the C does."""
    f32 = np.float32
    fr = f32(sample_freq) / f32(cutoff_freq)
    pi = f32(math.pi)
    ohm = f32(np.tan(pi / fr, dtype=f32))
    cos = f32(np.cos(pi / f32(4.0), dtype=f32))
    c = f32(1.0) + f32(2.0) * cos * ohm + ohm * ohm
    b0 = ohm * ohm / c
    a1 = f32(2.0) * (ohm * ohm - f32(1.0)) / c
    a2 = (f32(1.0) - f32(2.0) * cos * ohm + ohm * ohm) / c
    return np.array([b0, f32(2.0) * b0, b0, a1, a2], f32)


def pid_gains(
    kp: float,
    ki: float,
    kd: float,
    kff: float,
    dt: float,
    sample_freq: float,
    cutoff_freq: float,
    filtered: bool,
    i_limit: float = DEFAULT_INTEGRATION_LIMIT,
    output_limit: float = DEFAULT_OUTPUT_LIMIT,
) -> PidGains:
    """A `PidGains` as ``pidInit`` (pid.c) sets it, with the limits ``pidSetIntegralLimit`` and the controllers set."""
    f = np.float32
    lpf = lpf2p_coefficients(sample_freq, cutoff_freq) if filtered and cutoff_freq > 0 else np.zeros(5, f)
    return PidGains(
        kp=jnp.float32(kp),
        ki=jnp.float32(ki),
        kd=jnp.float32(kd),
        kff=jnp.float32(kff),
        i_limit=jnp.float32(i_limit),
        output_limit=jnp.float32(output_limit),
        dt=jnp.float32(f(dt)),
        lpf=jnp.asarray(lpf),
        filtered=bool(filtered and cutoff_freq > 0),
    )


def constrain(value: jax.Array, low: jax.Array | float, high: jax.Array | float) -> jax.Array:
    """num.c ``constrain``: ``fminf(high, fmaxf(low, value))`` (a NaN value gives ``low``)."""
    return jnp.fmin(high, jnp.fmax(low, value))


def wrap_180(angle: jax.Array) -> jax.Array:
    """One step of ±360° toward (-180, 180], as ``pidUpdate`` wraps a yaw error (one subtraction, not a modulo)."""
    return jnp.where(angle > 180.0, angle - 360.0, jnp.where(angle < -180.0, angle + 360.0, angle))


def lpf2p_apply(lpf: jax.Array, state: PidState, sample: jax.Array) -> tuple[PidState, jax.Array]:
    """``lpf2pApply`` (filter.c): one sample through the biquad; a non-finite intermediate restarts from the
    sample."""
    b0, b1, b2, a1, a2 = (lpf[k] for k in range(5))
    d0 = sample - state.delay1 * a1 - state.delay2 * a2
    d0 = jnp.where(jnp.isfinite(d0), d0, sample)
    out = d0 * b0 + state.delay1 * b1 + state.delay2 * b2
    return state.replace(delay2=state.delay1, delay1=d0), out


def pid_update(
    gains: PidGains, state: PidState, desired: jax.Array, measured: jax.Array, is_yaw: bool | np.ndarray = False
) -> tuple[PidState, jax.Array]:
    """``pidSetDesired`` then ``pidUpdate`` (pid.c): P on the error, D on the measurement's change (filtered when
    ``gains.filtered``; NaN gives 0), I clamped to ``i_limit``, FF on the desired value, the sum clamped to
    ``output_limit`` (each limit 0: none); ``is_yaw`` (a bool, or bool[...] per element of the last axis) wraps
    the error and the change by one turn.

    Returns:
        (the new `PidState`, the output f32[...]).
    """
    yaw = np.asarray(is_yaw)
    error = desired - measured
    if yaw.any():
        error = jnp.where(yaw, wrap_180(error), error)
    output = gains.kp * error
    delta = -(measured - state.prev_measured)
    if yaw.any():
        delta = jnp.where(yaw, wrap_180(delta), delta)
    deriv = delta / gains.dt
    if gains.filtered:
        state, deriv = lpf2p_apply(gains.lpf, state, deriv)
    deriv = jnp.where(jnp.isnan(deriv), 0.0, deriv)
    output = output + gains.kd * deriv
    integ = state.integ + error * gains.dt
    integ = jnp.where(gains.i_limit != 0, constrain(integ, -gains.i_limit, gains.i_limit), integ)
    output = output + gains.ki * integ
    output = output + gains.kff * desired
    output = jnp.where(gains.output_limit != 0, constrain(output, -gains.output_limit, gains.output_limit), output)
    return state.replace(integ=integ, prev_measured=measured), output


def pid_reset(state: PidState, actual: jax.Array) -> PidState:
    """``pidReset`` (pid.c): the integral zeroed and the last measurement set; the filter is left as it is."""
    return state.replace(integ=jnp.zeros_like(state.integ), prev_measured=actual + jnp.zeros_like(state.integ))


def filter_reset(state: PidState) -> PidState:
    """``filterReset`` of a filtered PID (``lpf2pInit``): the filter's delay elements zeroed."""
    return state.replace(delay1=jnp.zeros_like(state.delay1), delay2=jnp.zeros_like(state.delay2))
