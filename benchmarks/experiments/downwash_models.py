"""The paper's downwash example under both downwash models, on both backends: what the lower drone does while the
upper one passes over it.

The example (`jaxdrones.examples.downwash`, gym-pybullet-drones examples/downwash.py; docs/physics.md §13.2): two
cf2x track x = 0.5 cos(2πt/5) m half a period apart, at 1 m and 0.5 m, with the DSL PID (240 Hz physics, 48 Hz
control, 12 s), so that they pass over each other near t = 1.7, 4.3, 6.7, 9.3 and 11.7 s. It is flown with the
paper's downwash (``SimConfig(downwash="paper")``: one force along the lower drone's body −z at its centre of mass,
docs/physics.md §6.3) and with the per-rotor model (``downwash="per_rotor"``: the upper drone's jet sampled at each
rotor of the lower one, a thrust change per rotor and hence a torque, §6.4), each once with the downwash and once
without, on the JAX core and on the PyBullet backend.

For the lower drone, over each pass (the control steps where the drones are less than 0.1 m apart horizontally,
`jaxdrones.examples.downwash.PASS_RADIUS_M`) and the 0.5 s after it (`RECOVERY_S`), the largest over all passes of:

- ``dip_m``: its altitude dip, z_target − z (the example's ``max_dip_m``), and ``dip_response_m``, that dip less the
  one of the flight without downwash;
- ``peak_pitch_deg``: its |pitch| (PyBullet's Euler angles), and ``pitch_response_deg``: |pitch − pitch without
  downwash| at the same time, the part of the pitch the downwash causes (the PID pitches the drone to track x in
  both flights);
- ``vx_response_mps``: |v_x − v_x without downwash|, the change of its x-velocity;
- ``roll_response_deg``: |roll − roll without downwash| (the drones cross along x, so the roll should stay small).

    python benchmarks/experiments/downwash_models.py            # writes benchmarks/results/downwash_models.json
    python benchmarks/experiments/downwash_models.py --backends jax --duration 6
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results")
MODELS = ("paper", "per_rotor")
BACKENDS = ("jax", "pybullet")


def pass_windows(times: np.ndarray, pos: np.ndarray) -> list[tuple[int, int]]:
    """[first, end) step ranges: each pass of the drones over each other and the `RECOVERY_S` after it."""
    from jaxdrones.examples.downwash import RECOVERY_S, find_passes

    return [(first, int(np.searchsorted(times, times[last] + RECOVERY_S + 1e-9))) for first, last in find_passes(pos)]


def response(result: dict) -> dict:
    """The lower drone's figures (module docstring) from a `jaxdrones.examples.downwash.fly` result."""
    on, off = result["runs"]["on"], result["runs"]["off"]
    metrics = result["metrics"]
    lower = metrics["on"]["lower_drone"]
    windows = pass_windows(on["times"], on["pos"])

    def peak(values: np.ndarray) -> float:
        return max((float(np.max(np.abs(values[a:b]))) for a, b in windows), default=0.0)

    return {
        "passes": len(windows),
        "pass_times_s": metrics["on"]["pass_times_s"],
        "dip_m": metrics["on"]["max_dip_m"],
        "dip_response_m": metrics["max_dip_m"]["difference"],
        "dips_m": metrics["on"]["dips_m"],
        "peak_pitch_deg": peak(np.degrees(on["rpy"][:, lower, 1])),
        "pitch_response_deg": peak(np.degrees(on["rpy"][:, lower, 1] - off["rpy"][:, lower, 1])),
        "vx_response_mps": peak(on["vel"][:, lower, 0] - off["vel"][:, lower, 0]),
        "roll_response_deg": peak(np.degrees(on["rpy"][:, lower, 0] - off["rpy"][:, lower, 0])),
        "upper_max_error_m": metrics["on"]["upper_max_error_m"],
    }


def run(models=MODELS, backends=BACKENDS, duration_s: float = 12.0) -> dict:
    """Fly the example for each model and backend; the lower drone's figures and the wall time of each."""
    import jax

    jax.config.update("jax_enable_x64", True)  # both backends in float64, as the agreement tests
    from jaxdrones.examples.downwash import fly

    rows = []
    for backend in backends:
        for model in models:
            start = time.perf_counter()
            result = fly(duration_s, backend=backend, downwash=model)
            rows.append(
                {
                    "model": model,
                    "backend": backend,
                    **response(result),
                    "wall_s": round(time.perf_counter() - start, 2),
                }
            )
            print(
                f"{backend:8s} {model:9s} dip {100 * rows[-1]['dip_m']:6.2f} cm "
                f"(response {100 * rows[-1]['dip_response_m']:+6.2f} cm), peak pitch "
                f"{rows[-1]['peak_pitch_deg']:5.2f} deg (response {rows[-1]['pitch_response_deg']:5.2f} deg), "
                f"v_x response {rows[-1]['vx_response_mps']:.3f} m/s",
                flush=True,
            )
    return {
        "what": __doc__.split("\n\n")[0],
        "definitions": "\n\n".join(__doc__.split("\n\n")[2:4]),
        "settings": {
            "example": "downwash",
            "drone": "cf2x",
            "duration_s": duration_s,
            "sim_freq": 240,
            "ctrl_freq": 48,
            "dtype": "float64",
            "python": platform.python_version(),
            "jax": jax.__version__,
        },
        "rows": rows,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", nargs="+", choices=MODELS, default=list(MODELS))
    parser.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    parser.add_argument("--duration", type=float, default=12.0, help="flight time, s (the original's 12 s)")
    parser.add_argument("--out", default=os.path.join(RESULTS, "downwash_models.json"))
    args = parser.parse_args(argv)
    results = run(args.models, args.backends, args.duration)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=2)
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()
