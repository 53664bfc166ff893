"""The motors' thrust map against a Crazyflie 2.1 on a thrust stand (docs/validation.md §2).

The data: IMRCLab/crazyflie-system-id at commit 76a64de (MIT; the repository is emptied at its head),
``data/bitcraze2021/cf2.1-stock-prop.csv`` (sweep A: 2,573 samples, PWM 0 → 65,500 → 0 in steps of 500-3,000) and
``cf21_stock2.csv`` (sweep B: 1,735 samples, PWM 0 → 45,000 → 0 in steps of 5,000), each a Crazyflie 2.1 with its
stock (legacy) propellers on a load cell, logging the thrust of all four motors, the PWM command, the battery voltage
and each motor's RPM. Every figure is over the steady samples (`jaxdrones.validation.thrust.steady`: the last half of
each run at one PWM, the motors turning), the load cell's zero taken at rest (`tare`).

Each model is scored on each sweep by its thrust RMSE as a percentage of the mean measured thrust:

- the simulator's square law f = kf·rpm² at the shipped models' kf (``cf2x`` and ``cf2p``: 3.16e-10 N/rpm², the
  paper's), from the measured RPM;
- the firmware's map from PWM and battery voltage (the motor-voltage cubic of ``platform_defaults_cf2.h``, legacy and
  2.1+ propellers), as a Crazyflie flies;
- the same three forms fitted (`fit_kf`, `fit_thrust_map`: PWM and battery voltage → RPM → thrust, `fit_cubic`) on
  the other sweep: held out.

Usage::

    python benchmarks/validation/thrust_stand.py --clone PATH          # PATH: a clone of IMRCLab/crazyflie-system-id
    python benchmarks/validation/thrust_stand.py --files A.csv B.csv   # any stand CSVs of that format
    python benchmarks/validation/thrust_stand.py --clone PATH --json out.json --plot thrust.png
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

#: The commit whose files the tables of docs/validation.md were made from.
COMMIT = "76a64de"
FILES = ("data/bitcraze2021/cf2.1-stock-prop.csv", "data/bitcraze2021/cf21_stock2.csv")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--clone", type=Path, help="a clone of IMRCLab/crazyflie-system-id (at commit 76a64de)")
    source.add_argument("--files", type=Path, nargs=2, metavar="CSV", help="two thrust-stand CSVs (A and B)")
    parser.add_argument("--json", type=Path, help="write the figures to this JSON file")
    parser.add_argument("--plot", type=Path, help="draw thrust against RPM and against PWM to this PNG")
    return parser.parse_args(argv)


def sources(args: argparse.Namespace) -> tuple[list[Path], str | None]:
    """The two CSVs and, for a clone, the commit it is at (a warning where it is not `COMMIT`)."""
    if args.files:
        return list(args.files), None
    done = subprocess.run(["git", "-C", str(args.clone), "rev-parse", "HEAD"], capture_output=True, text=True)
    commit = done.stdout.strip() or None
    if commit and not commit.startswith(COMMIT):
        print(f"note: the clone is at {commit[:10]}, not {COMMIT}: its data/bitcraze2021 may differ or be gone")
    return [args.clone / f for f in FILES], commit


def score(stands: list, masks: list) -> dict:
    """model → [RMSE % on sweep A, on sweep B]; and the fitted constants of each sweep."""
    import numpy as np

    import jaxdrones as jd
    from jaxdrones.validation import thrust as th

    rows: dict[str, list[float]] = {}
    kf = {name: float(jd.load_params(name).kf) for name in ("cf2x", "cf2p")}
    fitted = [{"map": th.fit_thrust_map(s, m), "cubic": th.fit_cubic(s, m)} for s, m in zip(stands, masks, strict=True)]
    for k, (stand, mask) in enumerate(zip(stands, masks, strict=True)):
        measured, rpm = stand.thrust[mask], stand.rpm[mask]
        pwm, vbat = stand.pwm[mask], stand.vbat[mask]
        other = fitted[1 - k]
        predictions = {
            f"cf2x, cf2p: kf·rpm², kf = {kf['cf2x']:.3g} (URDF)": kf["cf2x"] * np.sum(rpm**2, -1),
            "firmware: cubic in motor voltage, legacy propellers": 4 * th.firmware_thrust(pwm, vbat, "legacy"),
            "firmware: cubic in motor voltage, 2.1+ propellers": 4 * th.firmware_thrust(pwm, vbat, "cf21_plus"),
            "fitted on the other sweep: kf·rpm² (measured RPM)": other["map"].kf * np.sum(rpm**2, -1),
            "fitted on the other sweep: PWM, vbat → RPM → kf·rpm²": 4 * other["map"].thrust(pwm, vbat),
            "fitted on the other sweep: cubic in motor voltage": 4
            * np.maximum(np.polyval(other["cubic"][::-1], th.motor_voltage(pwm, vbat)), 0),
        }
        for name, predicted in predictions.items():
            rows.setdefault(name, []).append(th.rmse_percent(predicted, measured))
    constants = [
        {
            "kf": f["map"].kf,
            "rpm_offset": f["map"].rpm_offset,
            "rpm_per_volt": f["map"].rpm_per_volt,
            "cubic": list(f["cubic"]),
        }
        for f in fitted
    ]
    return {"rmse_percent": rows, "fitted": constants, "model_kf": kf}


def plot(stands: list, masks: list, result: dict, path: Path) -> None:
    """Measured thrust against the mean RPM (with the square laws) and against the motor voltage (with the
    firmware's cubic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxdrones.validation import thrust as th

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for stand, mask, label in zip(stands, masks, "AB", strict=True):
        rpm = np.sqrt(np.mean(stand.rpm[mask] ** 2, -1))
        left.plot(rpm, stand.thrust[mask] / 4 * 1000 / 9.80665, ".", ms=2, label=f"sweep {label}")
        right.plot(
            th.motor_voltage(stand.pwm[mask], stand.vbat[mask]),
            stand.thrust[mask] / 4 * 1000 / 9.80665,
            ".",
            ms=2,
            label=f"sweep {label}",
        )
    grid = np.linspace(0, 25000, 100)
    kf = result["model_kf"]["cf2x"]
    left.plot(grid, kf * grid**2 * 1000 / 9.80665, "k-", label=f"cf2x kf = {kf:.3g}")
    fit = result["fitted"][0]["kf"]
    left.plot(grid, fit * grid**2 * 1000 / 9.80665, "k--", label=f"fitted kf = {fit:.3g} (sweep A)")
    volts = np.linspace(0, 3.3, 100)
    right.plot(volts, th.firmware_thrust(volts * th.PWM_MAX, 1.0) * 1000 / 9.80665, "k-", label="firmware, legacy")
    left.set(xlabel="motor speed (RMS of the four), rpm", ylabel="thrust per motor, g", title="thrust against speed")
    right.set(xlabel="motor voltage vbat·pwm/65535, V", ylabel="thrust per motor, g", title="thrust against voltage")
    for ax in (left, right):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> dict:
    args = parse_args(argv)
    from jaxdrones.validation import readers, thrust

    paths, commit = sources(args)
    stands = [thrust.tare(readers.read_thrust_stand(p)) for p in paths]
    masks = [thrust.steady(s) for s in stands]
    result = score(stands, masks)
    result.update(files=[str(p) for p in paths], commit=commit, steady_samples=[int(m.sum()) for m in masks])
    print(f"steady samples: sweep A {result['steady_samples'][0]}, sweep B {result['steady_samples'][1]}")
    print("| model | thrust RMSE, sweep A | sweep B |\n|---|---|---|")
    for name, (a, b) in result["rmse_percent"].items():
        print(f"| {name} | {a:.1f} % | {b:.1f} % |")
    for label, f in zip("AB", result["fitted"], strict=True):
        cubic = ", ".join(f"{c:.4g}" for c in f["cubic"])
        print(
            f"fitted on sweep {label}: kf {f['kf']:.4g} N/rpm², rpm = {f['rpm_offset']:.0f} + "
            f"{f['rpm_per_volt']:.0f}·v, cubic ({cubic})"
        )
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, allow_nan=False))
    if args.plot:
        plot(stands, masks, result, args.plot)
    return result


if __name__ == "__main__":
    main()
