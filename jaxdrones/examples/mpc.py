"""Model predictive control with the CasADi model: a figure-8 flown in closed loop on the JAX simulator, beside the
DSL PID on the same reference (``python -m jaxdrones.examples.mpc``; needs the ``[casadi]`` extra).

The MPC (`MPC`) is a multiple-shooting nonlinear program written with CasADi's ``Opti`` and solved by IPOPT at every
control step: the prediction model is `jaxdrones.symbolic.discrete_step` of the simulator's own config (the JAX
core's control step, drag and ground effect included, state with the rotors' speeds), over ``horizon`` control
steps; the cost weighs the position error to the reference, the velocity error to its derivative, the tilt and
yaw (the quaternion's vector part), the body rates and the RPM deviation from hover; the RPM commands are bounded to
[0, max_rpm]. Each solve is warm-started from the previous solution shifted by one step, and the whole program is
one ``casadi.Function`` (``Opti.to_function``), so a step costs one IPOPT call.

The reference is a figure-8 (a lemniscate of Gerono) at ``height``:
``p(t) = (A sin ωt, A sin ωt cos ωt, height)``, ω = 2π / period, and its derivative as the velocity reference.
The drone starts at rest at the figure's centre, where the reference already moves: the first ``settle_s`` seconds
(the transient) are left out of the RMS errors.

`fly_figure8` flies both controllers on ``jaxdrones.make_step(SimConfig(ctrl_freq, drag, ground_effect))`` (240 Hz
physics) and returns, per controller, the positions, the distance to the moving reference at each control step and
its RMS, and for the MPC the solve time of each step (wall clock of the IPOPT call, this machine).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from jaxdrones._validate import check_int, check_real
from jaxdrones.control.pid import PIDGains
from jaxdrones.examples.closed_loop import check_steps, initial_carry, jax_closed_loop, track_position
from jaxdrones.physics.params import DroneParams, load_params
from jaxdrones.physics.state import init_state
from jaxdrones.sim import SimConfig, make_step
from jaxdrones.symbolic import discrete_step, require_casadi, state_vector

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["FIGURE8", "MPC", "MPCWeights", "figure8", "fly_figure8", "plot_figure8", "main"]

#: The figure-8 of the example: amplitude A (m), period (s), height (m).
FIGURE8 = {"amplitude": 0.5, "period_s": 6.0, "height": 0.5}


def figure8(
    times: ArrayLike,
    amplitude: float = FIGURE8["amplitude"],
    period_s: float = FIGURE8["period_s"],
    height: float = FIGURE8["height"],
) -> tuple[np.ndarray, np.ndarray]:
    """The figure-8 reference at ``times`` (f[T] s): positions f[T, 3] m and velocities f[T, 3] m/s, world frame."""
    t = np.asarray(times, np.float64)
    w = 2 * math.pi / period_s
    pos = np.stack([amplitude * np.sin(w * t), amplitude * np.sin(w * t) * np.cos(w * t), np.full_like(t, height)], -1)
    vel = np.stack([amplitude * w * np.cos(w * t), amplitude * w * np.cos(2 * w * t), np.zeros_like(t)], -1)
    return pos, vel


@dataclasses.dataclass(frozen=True)
class MPCWeights:
    """The MPC's horizon and cost weights (per control step; positions in m, velocities in m/s, the quaternion's
    vector part, rates in rad/s, and the RPM as a fraction of the hover RPM)."""

    horizon: int = 15
    position: float = 100.0
    velocity: float = 1.0
    attitude: float = 1.0
    rates: float = 0.01
    rpm: float = 0.1
    max_iter: int = 100

    def __post_init__(self):
        check_int("horizon", self.horizon, what="control steps")
        for name in ("position", "velocity", "attitude", "rates", "rpm"):
            check_real(f"the weight {name}", getattr(self, name), 0, what="a finite number")


class MPC:
    """Nonlinear MPC of one drone on `jaxdrones.symbolic.discrete_step` (see the module docstring).

    Args:
        params: one drone's `DroneParams`.
        config: the `SimConfig` whose control step is the prediction model (its ``ctrl_freq`` the MPC's rate).
        weights: `MPCWeights`.

    Call ``mpc(x, ref_pos, ref_vel)`` with the state vector ``x`` (`jaxdrones.symbolic` order, f[nx]) and the
    reference over the horizon, f[horizon + 1, 3] each (from the current time on): it returns the RPM command f[4]
    for this step. `jaxdrones.symbolic.state_vector` turns a `DroneState` of one drone into ``x``.
    """

    def __init__(self, params: DroneParams, config: SimConfig, weights: MPCWeights = MPCWeights()):
        cs = require_casadi()
        step = discrete_step(params, config, rotor_state=True)
        self.weights, self.nx, self.horizon = weights, step.size1_in(0), weights.horizon
        self.hover_rpm, self.max_rpm = float(params.hover_rpm), float(params.max_rpm)
        n, opti = weights.horizon, cs.Opti()
        x, du = opti.variable(self.nx, n + 1), opti.variable(4, n)  # du: the RPM over hover, minus 1
        x0, ref_pos, ref_vel = opti.parameter(self.nx), opti.parameter(3, n + 1), opti.parameter(3, n + 1)
        opti.subject_to(x[:, 0] == x0)
        cost = 0
        for k in range(n):
            opti.subject_to(x[:, k + 1] == step(x[:, k], self.hover_rpm * (1 + du[:, k])))
            cost += (
                weights.position * cs.sumsqr(x[0:3, k + 1] - ref_pos[:, k + 1])
                + weights.velocity * cs.sumsqr(x[7:10, k + 1] - ref_vel[:, k + 1])
                + weights.attitude * cs.sumsqr(x[3:6, k + 1])
                + weights.rates * cs.sumsqr(x[10:13, k + 1])
                + weights.rpm * cs.sumsqr(du[:, k])
            )
        opti.subject_to(opti.bounded(-1, du, self.max_rpm / self.hover_rpm - 1))
        opti.minimize(cost)
        opti.solver(
            "ipopt",
            {
                "print_time": False,
                "ipopt.print_level": 0,
                "ipopt.sb": "yes",
                "ipopt.max_iter": weights.max_iter,
                "ipopt.tol": 1e-6,
            },
        )
        # One Function: (state, references, initial guesses) -> (first command, predicted states, commands).
        self._solve = opti.to_function("mpc", [x0, ref_pos, ref_vel, x, du], [du[:, 0], x, du])
        self.reset()

    def reset(self, x: ArrayLike | None = None) -> None:
        """Forget the warm start (the next solve starts from hover at ``x``, or at the first call's state)."""
        self._x_guess = None if x is None else np.tile(np.asarray(x, np.float64)[:, None], (1, self.horizon + 1))
        self._du_guess = np.zeros((4, self.horizon))

    def __call__(self, x, ref_pos, ref_vel) -> np.ndarray:
        x = np.asarray(x, np.float64)
        if x.shape != (self.nx,):
            raise ValueError(f"the MPC's state must have shape ({self.nx},), got {x.shape}")
        for name, ref in (("ref_pos", ref_pos), ("ref_vel", ref_vel)):
            if np.shape(ref) != (self.horizon + 1, 3):
                raise ValueError(
                    f"{name} must have shape (horizon + 1, 3) = ({self.horizon + 1}, 3), got {np.shape(ref)}"
                )
        if self._x_guess is None:
            self.reset(x)
        du0, xs, dus = self._solve(
            x, np.asarray(ref_pos, np.float64).T, np.asarray(ref_vel, np.float64).T, self._x_guess, self._du_guess
        )
        xs, dus = np.asarray(xs), np.asarray(dus)
        self._x_guess = np.concatenate([xs[:, 1:], xs[:, -1:]], axis=1)  # shifted by one step
        self._du_guess = np.concatenate([dus[:, 1:], dus[:, -1:]], axis=1)
        return self.hover_rpm * (1 + np.asarray(du0).ravel())


def fly_figure8(
    duration_s: float = 6.0,
    ctrl_freq: int = 30,
    drag: bool = True,
    ground_effect: bool = True,
    weights: MPCWeights = MPCWeights(),
    settle_s: float = 1.0,
    params: DroneParams | None = None,
    model_drag: bool | None = None,
    model_ground_effect: bool | None = None,
    **figure: float,
) -> dict:
    """Fly the figure-8 with the MPC and with the DSL PID (position and velocity feed-forward) on the JAX core.

    Args:
        duration_s: flight time, s (whole control steps).
        ctrl_freq: control rate of both controllers, Hz (physics at 240 Hz).
        drag, ground_effect: the simulator's effects.
        model_drag, model_ground_effect: the effects of the MPC's model (default: the simulator's; False flies the
            MPC with a model that lacks the effect, to see what the mismatch costs).
        weights: the MPC's `MPCWeights`.
        settle_s: the initial transient left out of the RMS errors, s.
        params: the drone (default cf2x).
        **figure: ``amplitude``, ``period_s``, ``height`` of the figure-8 (default `FIGURE8`).

    Returns:
        dict with ``times`` f[T] s, ``reference`` f[T, 3] m (at each time), and per controller (``"mpc"``,
        ``"pid"``) a dict with ``pos`` f[T, 3] m, ``error`` f[T] m (distance to the reference), ``rms`` m (over
        t >= settle_s); the MPC's also has ``solve_s`` f[T] (wall clock of each solve).

    Raises:
        ValueError: a duration shorter than one control step, a settle time outside [0, duration), bad weights,
            an unknown figure parameter or a non-positive period.
        ModuleNotFoundError: casadi is not installed (the ``[casadi]`` extra).
    """
    unknown = sorted(set(figure) - set(FIGURE8))
    if unknown:
        raise ValueError(f"unknown figure-8 parameter(s) {unknown}: expected some of {sorted(FIGURE8)}")
    figure = {**FIGURE8, **figure}
    if not figure["period_s"] > 0:
        raise ValueError(f"period_s must be positive, got {figure['period_s']!r}")
    n_steps = check_steps(duration_s, ctrl_freq)
    if not 0 <= settle_s < n_steps / ctrl_freq:
        raise ValueError(f"settle_s must be in [0, duration_s), got {settle_s!r}")
    params = load_params("cf2x") if params is None else params
    config = SimConfig(ctrl_freq=ctrl_freq, drag=drag, ground_effect=ground_effect)
    model = SimConfig(
        ctrl_freq=ctrl_freq,
        drag=drag if model_drag is None else model_drag,
        ground_effect=ground_effect if model_ground_effect is None else model_ground_effect,
    )
    mpc = MPC(params, model, weights)
    dt = 1.0 / ctrl_freq
    times = dt * np.arange(1, n_steps + 1)
    reference, reference_vel = figure8(times, **figure)
    start_pos, start_vel = figure8(np.zeros(1), **figure)  # the reference at t = 0
    start = init_state(config, pos=jnp.asarray(start_pos))

    step, state, positions, solve_s = make_step(config), start, [], []
    horizon_times = dt * np.arange(mpc.horizon + 1)
    for k in range(n_steps):  # the command of step k is computed from the state at k dt, applied until (k + 1) dt
        ref_pos, ref_vel = figure8(k * dt + horizon_times, **figure)
        t0 = time.perf_counter()
        rpm = mpc(state_vector(state), ref_pos, ref_vel)
        solve_s.append(time.perf_counter() - t0)
        state = step(params, state, jnp.asarray(rpm[None], state.pos.dtype))
        positions.append(np.asarray(state.pos[0], np.float64))

    # The PID: the same loop as the paper's examples (`jaxdrones.examples.closed_loop`): the command computed at
    # time t (from the state reached then) targets the reference at t, its velocity fed forward.
    dtype = start.pos.dtype
    xs = (jnp.asarray(reference[:, None], dtype), jnp.asarray(reference_vel[:, None], dtype))
    x_first = (jnp.asarray(start_pos, dtype), jnp.asarray(start_vel, dtype))
    fixed = (jnp.zeros((1, 3), dtype), jnp.asarray(1.0, dtype))
    _, (states, _) = jax_closed_loop(config, track_position)(
        params, PIDGains.dsl(), initial_carry(start), xs, fixed, x_first
    )
    settled = times >= settle_s - 1e-9

    def summary(pos):
        error = np.linalg.norm(pos - reference, axis=-1)
        return {"pos": pos, "error": error, "rms": float(np.sqrt(np.mean(error[settled] ** 2)))}

    return {
        "times": times,
        "reference": reference,
        "settle_s": settle_s,
        "ctrl_freq": ctrl_freq,
        "figure": figure,
        "model": {"drag": model.drag, "ground_effect": model.ground_effect},
        "mpc": {**summary(np.stack(positions)), "solve_s": np.asarray(solve_s)},
        "pid": summary(np.asarray(states.pos[:, 0], np.float64)),
    }


def plot_figure8(result: dict, path: str | None = None) -> Figure:
    """The flights' paths in the horizontal plane, their distance to the reference over time, and the MPC's solve
    time per step; saved to ``path`` (PNG) when given (refusing to overwrite a file). Returns the figure."""
    import matplotlib.pyplot as plt

    if path is not None and os.path.exists(path):
        raise FileExistsError(f"{path} exists: choose another path or remove it")
    fig, (paths, errors, solves) = plt.subplots(1, 3, figsize=(15, 4.2))
    paths.plot(result["reference"][:, 0], result["reference"][:, 1], "k--", lw=1, label="reference")
    for name, style in (("mpc", "C0"), ("pid", "C1")):
        flight = result[name]
        paths.plot(flight["pos"][:, 0], flight["pos"][:, 1], style, label=f"{name.upper()}")
        errors.plot(
            result["times"], 100 * flight["error"], style, label=f"{name.upper()}: RMS {100 * flight['rms']:.2f} cm"
        )
    errors.axvline(result["settle_s"], color="grey", lw=0.8, ls=":")
    paths.set(xlabel="x (m)", ylabel="y (m)", title="figure-8, top view", aspect="equal")
    errors.set(
        xlabel="time (s)",
        ylabel="distance to the reference (cm)",
        yscale="log",
        title=f"tracking error (RMS after {result['settle_s']:g} s)",
    )
    solve_ms = 1e3 * result["mpc"]["solve_s"]
    solves.plot(result["times"], solve_ms, "C0.", ms=3)
    solves.axhline(1e3 / result["ctrl_freq"], color="grey", lw=0.8, ls=":", label="control period")
    solves.set(
        xlabel="time (s)", ylabel="IPOPT solve (ms)", title=f"MPC solve time, median {np.median(solve_ms):.0f} ms"
    )
    for ax in (paths, errors, solves):
        ax.legend(fontsize=8)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


def summary_lines(result: dict) -> list[str]:
    """The comparison as text lines: RMS error per controller and the MPC's solve times."""
    solve_ms = 1e3 * result["mpc"]["solve_s"]
    return [
        (
            f"figure-8 {result['figure']}, {result['times'][-1]:.1f} s at {result['ctrl_freq']} Hz control, "
            f"RMS after {result['settle_s']:g} s (the MPC's model: {result['model']}):"
        ),
        (
            f"  MPC: RMS error {100 * result['mpc']['rms']:.2f} cm, solve time median {np.median(solve_ms):.1f} ms, "
            f"95th percentile {np.percentile(solve_ms, 95):.1f} ms, max {solve_ms.max():.1f} ms"
        ),
        f"  PID: RMS error {100 * result['pid']['rms']:.2f} cm",
    ]


def main(argv: Sequence[str] | None = None) -> int:
    """Fly the figure-8 with the MPC and the PID, print the summary and write the plot (``python -m
    jaxdrones.examples.mpc --help``); returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=6.0, help="flight time, s (default 6: one lap)")
    parser.add_argument("--ctrl-freq", type=int, default=30, help="control rate, Hz (default 30)")
    parser.add_argument("--horizon", type=int, default=MPCWeights.horizon, help="MPC horizon, control steps")
    parser.add_argument("--no-model-drag", action="store_true", help="the MPC's model without drag")
    parser.add_argument("--plot", help="save the figure to this PNG (not overwritten)")
    args = parser.parse_args(argv)
    result = fly_figure8(
        args.duration,
        args.ctrl_freq,
        weights=MPCWeights(horizon=args.horizon),
        model_drag=False if args.no_model_drag else None,
    )
    print("\n".join(summary_lines(result)))
    if args.plot:
        plot_figure8(result, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
