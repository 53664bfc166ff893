"""System identification under measurement noise: `jaxdrones.sysid.fit`'s relative error per fitted value.

The record: `jaxdrones.sysid.excitation_flight` (5 s of closed-loop PID flight of one cf2x at 240 Hz physics, 48 Hz
control, drag on). The noise: `jaxdrones.sysid.add_noise` with a seeded key per run, 1 mm position and 0.01 rad
attitude (the acceptance case), and with ``--vel``/``--ang-vel`` velocity and body-rate noise too. The guess: kf ×1.2,
km ×0.8, drag_coeff ×1.3. Each run fits kf, km and drag_coeff (x, y, z) twice: with the window starts estimated
(``estimate_starts=True``, the default) and taken as observed (``False``, the method before it). Printed per seed and
method: the relative error of each value, its Gauss-Newton standard error (relative), the solver steps (optimistix's
Levenberg-Marquardt, accepted or rejected) and the time of the fit (the first fit of each method includes compiling it).

Usage::

    python benchmarks/gradients/sysid_noise.py                         # seeds 0 1 2, position and attitude noise
    python benchmarks/gradients/sysid_noise.py --seeds 0 1 2 3 4 5 6 7 8 9 --vel 0.01 --ang-vel 0.05
    python benchmarks/gradients/sysid_noise.py --noise-free            # no noise at all
"""

from __future__ import annotations

import argparse
import time

VALUES = ("kf", "km", "drag_x", "drag_y", "drag_z")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="noise seeds (default 0 1 2)")
    parser.add_argument("--pos", type=float, default=1e-3, help="position noise std, m (default 1e-3)")
    parser.add_argument("--att", type=float, default=1e-2, help="attitude noise std per axis, rad (default 1e-2)")
    parser.add_argument("--vel", type=float, default=0.0, help="velocity noise std, m/s (default 0)")
    parser.add_argument("--ang-vel", type=float, default=0.0, help="body-rate noise std, rad/s (default 0)")
    parser.add_argument("--noise-free", action="store_true", help="no noise (one run; --seeds ignored)")
    parser.add_argument("--duration", type=float, default=5.0, help="flight duration, s (default 5)")
    parser.add_argument("--window", type=int, default=10, help="control steps per window (default 10)")
    parser.add_argument("--defect", type=float, default=1e-3, help="fit's defect (default 1e-3)")
    args = parser.parse_args(argv)
    if args.noise_free:
        args.seeds = [None]
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    import jax
    import numpy as np

    import jaxdrones as jd
    from jaxdrones.params import with_derived
    from jaxdrones.sysid import add_noise, excitation_flight, fit

    config = jd.SimConfig(n_drones=1, sim_freq=240, ctrl_freq=48, drag=True)
    true = jd.load_params("cf2x")
    guess = with_derived(true.replace(kf=true.kf * 1.2, km=true.km * 0.8, drag_coeff=true.drag_coeff * 1.3))
    clean = excitation_flight(config, true, args.duration)
    flat = lambda params: np.concatenate([np.ravel(getattr(params, f)) for f in ("kf", "km", "drag_coeff")])  # noqa: E731
    print(
        f"noise: pos {args.pos} m, att {args.att} rad, vel {args.vel} m/s, ang_vel {args.ang_vel} rad/s"
        f"{' (off)' if args.noise_free else ''}; {args.duration} s, window {args.window}, defect {args.defect}"
    )
    print(
        f"{'seed':>4} {'starts':>9} "
        + " ".join(f"{v + ' %':>9}" for v in VALUES)
        + "  max |err| %  "
        + " ".join(f"{'σ ' + v:>9}" for v in VALUES)
        + "  steps   time s"
    )
    worst = {}
    for seed in args.seeds:
        flight = (
            clean
            if seed is None
            else add_noise(clean, jax.random.key(seed), pos=args.pos, att=args.att, vel=args.vel, ang_vel=args.ang_vel)
        )
        for estimate in (True, False):
            start = time.perf_counter()
            params, report = fit(
                config,
                guess,
                flight.init_state,
                flight.rpms,
                flight.observed,
                window=args.window,
                defect=args.defect,
                estimate_starts=estimate,
            )
            seconds = time.perf_counter() - start
            error = 100 * (flat(params) / flat(true) - 1)
            std = 100 * np.concatenate([np.ravel(report["std"][f]) for f in ("kf", "km", "drag_coeff")]) / flat(true)
            method = "estimated" if estimate else "observed"
            worst[method] = max(worst.get(method, 0.0), float(np.abs(error).max()))
            print(
                f"{str(seed):>4} {method:>9} "
                + " ".join(f"{e:9.3f}" for e in error)
                + f"  {np.abs(error).max():11.3f}  "
                + " ".join(f"{s:9.3f}" for s in std)
                + f"  {report['steps']:5d}  {seconds:7.2f}",
                flush=True,
            )
    print(
        "largest |relative error| over the seeds, %: "
        + ", ".join(f"starts {method} {value:.2f}" for method, value in worst.items())
    )


if __name__ == "__main__":
    main()
