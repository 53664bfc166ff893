"""The MPC on the CasADi model against the DSL PID on the figure-8 (`jaxdrones.examples.mpc`): tracking error and
the MPC's solve time per control step, for a few MPC settings, in one run.

Each setting flies `jaxdrones.examples.mpc.fly_figure8` (the JAX simulator at 240 Hz physics and 30 Hz control,
drag and ground effect, one lap of the figure-8 unless stated): the MPC whose model is the simulator's step, the
same with a model without drag, the same with a 10-step horizon, and the DSL PID (velocity feed-forward) on the
same reference. RMS: the distance to the moving reference after the first second; solve time: the wall clock of
each IPOPT call (median, 95th percentile, max), on this machine.

Usage::

    python benchmarks/experiments/mpc.py    # writes benchmarks/results/mpc.json, prints a markdown table
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results")
DEFAULT_OUT = os.path.join(RESULTS, "mpc.json")
SETTINGS = {  # name: fly_figure8 keywords
    "MPC, model = simulator": {},
    "MPC, model without drag": {"model_drag": False},
    "MPC, horizon 10": {"horizon": 10},
}


def main(argv=None) -> int:
    from jaxdrones.examples import mpc

    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=6.0, help="flight time, s (default 6: one lap)")
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON output (default: %(default)s)")
    args = parser.parse_args(argv)
    rows, pid = [], None
    for name, options in SETTINGS.items():
        options = dict(options)
        weights = mpc.MPCWeights(horizon=options.pop("horizon", mpc.MPCWeights.horizon))
        result = mpc.fly_figure8(args.duration, weights=weights, **options)
        solve_ms = 1e3 * result["mpc"]["solve_s"]
        rows.append(
            {
                "setting": name,
                "rms_cm": 100 * result["mpc"]["rms"],
                "solve_ms_median": float(np.median(solve_ms)),
                "solve_ms_p95": float(np.percentile(solve_ms, 95)),
                "solve_ms_max": float(solve_ms.max()),
            }
        )
        pid = 100 * result["pid"]["rms"]
    rows.append({"setting": "DSL PID, velocity feed-forward", "rms_cm": pid})
    print(
        f"figure-8 {mpc.FIGURE8}, {args.duration:g} s, 30 Hz control; {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores"
    )
    print("| controller | RMS error | MPC solve per step: median / 95th percentile / max |\n|---|---|---|")
    for r in rows:
        solve = (
            f"{r['solve_ms_median']:.1f} / {r['solve_ms_p95']:.1f} / {r['solve_ms_max']:.0f} ms"
            if "solve_ms_median" in r
            else "-"
        )
        print(f"| {r['setting']} | {r['rms_cm']:.2f} cm | {solve} |")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"duration_s": args.duration, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
