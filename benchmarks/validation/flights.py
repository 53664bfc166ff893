"""Forces in flight: Neural-Swarm's Crazyflie flights against the model's ground effect, downwash, drag and motor lag
(docs/validation.md §3).

The data: aerorobotics/neural-swarm at commit 48b1851 (no license file: this script reads a clone and copies
nothing), ``data/training/``, the binary uSD logs (`jaxdrones.validation.flights.load_runs`). For each drone and
sample, the vertical residual force m (a_z + g) − R₂₂ Σ f_i (`residual_force`: smoothed over 0.1 s), less the drone's
offset over the flight (`reference` samples: above 0.25 m, nobody above within 0.3 m) is held against each effect:

- ground effect (paper eq. ground): the single-drone flights near the floor, scored where the drone flies 2-20 cm
  above its resting height; fitted on ``datacollection21_06_16_2020/{randomwalk_s, randomwalk_l, takeoff_s,
  takeoff_l}``, held out: ``datacollection23_06_23_2020/randomwalk_{s,l}_{1,2}`` and
  ``datacollection20_12_20_2019/takeoff_landing_{small,large}``;
- downwash (paper eq. down, and the bounded form of `jaxdrones.physics.aerodynamics.downwash_force`): the swaps, scored
  while another drone is above within 15 cm horizontally (`crossing`); fitted on every other swap of the repository
  (the 99 runs of ``datacollection19_12_11_2019/swap_*``, ``21_06_16_2020/swap_*``, ``22_06_19_2020/swap_*`` and
  ``23_06_23_2020/swap_lll``), held out: ``datacollection20_12_20_2019/swap_{sss,sls,lsl}``;
- drag (paper eq. drag): the horizontal residual of the same flights (ground and downwash sets, each drone's samples
  with nobody above within 30 cm and higher than 10 cm);
- motor lag: a first-order lag of the logged thrust (`lagged_thrust_z`) on the vertical residual without smoothing,
  the same samples.

Each constant is fitted by `jaxdrones.sysid.fit_forces` (Levenberg-Marquardt) on the training flights; the RMSE
(grams-force) is reported on the held-out ones, per flight and over all of them.

Usage::

    git clone https://github.com/aerorobotics/neural-swarm
    python benchmarks/validation/flights.py --clone neural-swarm --json flights.json --plots docs/images
    python benchmarks/validation/flights.py --clone neural-swarm \
        --score datacollection20_12_20_2019/random_walk_small_ground
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

#: The commit the tables of docs/validation.md were made from.
COMMIT = "48b1851"
TRAINING = "data/training"
GROUND = {
    "train": [f"datacollection21_06_16_2020/{x}" for x in ("randomwalk_s", "randomwalk_l", "takeoff_s", "takeoff_l")],
    "test": [f"datacollection23_06_23_2020/randomwalk_{x}" for x in ("s_1", "s_2", "l_1", "l_2")]
    + [f"datacollection20_12_20_2019/takeoff_landing_{x}" for x in ("small", "large")],
}
SWAPS = ("ss", "sl", "ll", "sss", "ssl", "sll", "lll")
#: Downwash: fitted on every swap of the repository but the three held out.
DOWNWASH = {
    "train": [f"datacollection21_06_16_2020/swap_{x}" for x in SWAPS]
    + [f"datacollection19_12_11_2019/swap_{x}" for x in ("small_small", "large_small", "large_large")]
    + [f"datacollection22_06_19_2020/swap_{x}" for x in ("sl", "ssl", "sll", "lll")]
    + ["datacollection23_06_23_2020/swap_lll"],
    "test": [f"datacollection20_12_20_2019/swap_{x}" for x in ("sss", "sls", "lsl")],
}
GRAMS = 1000 / 9.81


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--clone", type=Path, required=True, help="a clone of aerorobotics/neural-swarm")
    parser.add_argument("--json", type=Path, help="write every figure to this JSON file")
    parser.add_argument("--plots", type=Path, help="draw the figures (validation_*.png) into this folder")
    parser.add_argument(
        "--score",
        nargs="+",
        default=[],
        metavar="FOLDER",
        help="also score these experiment folders (relative to the clone, or absolute) with the fitted constants",
    )
    return parser.parse_args(argv)


def load(clone: Path, folders: list[str], together: bool) -> list:
    """(label, formation) of every flight in ``folders``, each label the folder's last two parts and the files."""
    from jaxdrones.validation.flights import load_runs

    forms = []
    for folder in folders:
        path = Path(folder) if Path(folder).is_absolute() else clone / TRAINING / folder
        if not path.exists() and (clone / folder).exists():
            path = clone / folder
        label = "/".join(Path(folder).parts[-2:])
        forms += [(f"{label}/{'+'.join(form.names)}", form) for form in load_runs(path, together)]
    return forms


def prepared(forms: list, kind: str) -> list[dict]:
    """Per formation: the vertical (and horizontal) residual, offsets removed, and the samples of each score."""
    import numpy as np

    from jaxdrones.validation import flights as fl

    out = []
    for label, form in forms:
        ref = fl.reference(form)
        force = fl.offset_removed(form, fl.residual_force(form), ref)
        raw = fl.offset_removed(form, fl.residual_force(form, smooth_s=0.0), ref)
        height = form.pos[..., 2] - fl.REST_HEIGHT
        scored = np.broadcast_to(form.scored, height.shape)
        free = scored & ~fl.crossing(form, radius=0.3, min_dz=0.0)
        samples = fl.near_ground(form) if kind == "ground" else fl.crossing(form) & (height > 0.2)
        out.append(
            dict(
                label=label,
                form=form,
                params=fl.model_params(form),
                z=force[..., 2],
                raw_z=raw[..., 2],
                xy=force[..., :2],
                effect=samples & scored & (free if kind == "ground" else True),
                free=free & (height > 0.2),
                drag=free & (height > 0.1),
            )
        )
    return out


def predictions(items: list[dict], model, theta, mask: str):
    """The model's prediction over the samples ``mask`` of every formation, concatenated and flat."""
    import jax.numpy as jnp

    return jnp.concatenate([jnp.ravel(model(d["form"], d["params"], theta)[d[mask]]) for d in items])


def as32(theta):
    """``theta`` as float32, the dtype of the params and the state outside `fit_forces`'s float64."""
    import jax.numpy as jnp

    return jnp.asarray(theta, jnp.float32)


def rmse(predicted, measured) -> float:
    import numpy as np

    return float(np.sqrt(np.mean((np.asarray(measured) - np.asarray(predicted)) ** 2)) * GRAMS)


def fit(model, theta0, items: list[dict], mask: str, target: str):
    import numpy as np

    from jaxdrones.sysid import fit_forces

    measured = np.concatenate([np.ravel(d[target][d[mask]]) for d in items])
    theta, report = fit_forces(lambda t, _: predictions(items, model, t, mask), theta0, 0.0, measured)
    return theta, report


def effect_table(items: list[dict], models: dict, mask: str = "effect", target: str = "z") -> dict:
    """RMSE (g) of ``target`` over ``mask`` per formation and over all: with no model and with each (model, θ)."""
    import numpy as np

    rows = {}
    for d in items:
        if not d[mask].any():
            continue
        measured = d[target][d[mask]]
        row = {"samples": int(d[mask].sum()), "none": rmse(0.0, measured)}
        for name, (model, theta) in models.items():
            row[name] = rmse(np.asarray(model(d["form"], d["params"], as32(theta)))[d[mask]], measured)
        rows[d["label"]] = row
    folders: dict[str, dict] = {}
    for label, row in rows.items():
        folders.setdefault(label.rsplit("/", 1)[0], {})[label] = row
    pooled = {folder: pool(group, ["none", *models]) for folder, group in folders.items()}
    return {"flights": rows, "folders": pooled, "all": pool(rows, ["none", *models])}


def pool(rows: dict, keys: list[str]) -> dict:
    """The RMSE over the samples of several rows (each with ``samples`` and an RMSE per key), and their count."""
    import numpy as np

    total = {"samples": int(sum(r["samples"] for r in rows.values())), "flights": len(rows)}
    for key in keys:
        total[key] = float(np.sqrt(sum(r[key] ** 2 * r["samples"] for r in rows.values()) / total["samples"]))
    return total


def ground_models(constants: dict) -> dict:
    """name → (model, θ) of the ground effect, from `ground_effect`'s constants."""
    from jaxdrones.validation.flights import ground_z

    return {"paper": (ground_z, constants["paper"]), "fitted paper form": (ground_z, constants["fitted"])}


def downwash_models(constants: dict) -> dict:
    """name → (model, θ) of the downwash, from `downwash`'s constants."""
    from jaxdrones.validation.flights import downwash_bounded_z, downwash_paper_z

    return {
        "paper": (downwash_paper_z, constants["paper"]),
        "fitted paper form": (downwash_paper_z, constants["fitted paper form"]),
        "fitted bounded form": (downwash_bounded_z, constants["fitted bounded form"]),
    }


def ground_effect(train: list[dict], test: list[dict]) -> dict:
    import numpy as np

    from jaxdrones.validation.flights import ground_z

    paper = np.array([float(train[0]["params"].gnd_eff_coeff[0])])
    fitted, report = fit(ground_z, paper, train, "effect", "z")
    constants = {"paper": paper.tolist(), "fitted": fitted.tolist(), "std": report["std"].tolist()}
    models = ground_models(constants)
    return {"constants": constants, "train": effect_table(train, models)["all"], "test": effect_table(test, models)}


def downwash(train: list[dict], test: list[dict]) -> dict:
    import numpy as np

    from jaxdrones.physics.aerodynamics import BOUNDED_DOWNWASH
    from jaxdrones.validation.flights import downwash_bounded_z, downwash_paper_z

    paper = np.asarray(train[0]["params"].dw_coeff[0], np.float64)
    fitted_paper, report_paper = fit(downwash_paper_z, paper, train, "effect", "z")
    fitted_bounded, report_bounded = fit(downwash_bounded_z, np.asarray(BOUNDED_DOWNWASH), train, "effect", "z")
    constants = {
        "paper": paper.tolist(),
        "fitted paper form": fitted_paper.tolist(),
        "fitted paper form std": report_paper["std"].tolist(),
        "fitted bounded form": fitted_bounded.tolist(),
        "fitted bounded form std": report_bounded["std"].tolist(),
    }
    models = downwash_models(constants)
    return {"constants": constants, "train": effect_table(train, models)["all"], "test": effect_table(test, models)}


def drag(train: list[dict], test: list[dict]) -> dict:
    import numpy as np

    from jaxdrones.validation.flights import drag_xy

    paper = np.array([float(train[0]["params"].drag_coeff[0, 0])])
    fitted, report = fit(drag_xy, paper, train, "drag", "xy")
    models = {"paper": (drag_xy, paper), "fitted paper form": (drag_xy, fitted)}
    return {
        "constants": {"paper": paper.tolist(), "fitted": fitted.tolist(), "std": report["std"].tolist()},
        "train": effect_table(train, models, "drag", "xy")["all"],
        "test": effect_table(test, models, "drag", "xy")["all"],
    }


def motor_lag(train: list[dict], test: list[dict]) -> dict:
    import numpy as np

    from jaxdrones.validation.flights import lagged_thrust_z

    model = lambda form, _, tau: lagged_thrust_z(form, tau)  # noqa: E731
    fitted, report = fit(model, np.array([0.05]), train, "free", "raw_z")
    models = {"fitted lag": (model, fitted)}
    return {
        "tau_s": float(fitted[0]),
        "std_s": float(report["std"][0]),
        "train": effect_table(train, models, "free", "raw_z")["all"],
        "test": effect_table(test, models, "free", "raw_z")["all"],
    }


def replays(items: list[dict], result: dict) -> dict:
    """Open-loop replays (`jaxdrones.validation.flights.replay_errors`, a start every 0.5 s) of each formation with
    no aerodynamics, the paper's (ground effect, downwash, drag) and the fitted ones (C_gnd and c_xy fitted, the
    bounded downwash): each model's median and 90th percentile over the starts and drones, per horizon."""
    import jax.numpy as jnp
    import numpy as np

    import jaxdrones as jd
    from jaxdrones.physics.aerodynamics import BOUNDED_DOWNWASH
    from jaxdrones.physics.params import with_derived
    from jaxdrones.validation.flights import HORIZONS, RATE, replay_errors

    fitted = np.asarray(result["downwash"]["constants"]["fitted bounded form"])
    if not np.allclose(fitted, BOUNDED_DOWNWASH, rtol=0.01):
        print(f"note: the bounded downwash fitted here, {fitted}, is not the simulator's {BOUNDED_DOWNWASH}")
    c_gnd, c_xy = result["ground"]["constants"]["fitted"][0], result["drag"]["constants"]["fitted"][0]
    models = {
        "no aerodynamics": {},
        "paper": dict(ground_effect=True, downwash="paper", drag=True),
        "fitted": dict(ground_effect=True, downwash="bounded", drag=True),
    }
    errors: dict[str, list] = {name: [] for name in models}
    for d in items:
        base = d["params"]
        fitted_params = with_derived(
            base.replace(
                gnd_eff_coeff=jnp.full_like(base.gnd_eff_coeff, c_gnd), drag_coeff=base.drag_coeff.at[..., :2].set(c_xy)
            )
        )
        for name, effects in models.items():
            params = fitted_params if name == "fitted" else base
            config = jd.SimConfig(n_drones=len(d["form"].ids), ctrl_freq=int(RATE), sim_freq=5 * int(RATE), **effects)
            err = replay_errors(d["form"], params, config, HORIZONS)
            errors[name].append(err[:, :, d["form"].scored].transpose(1, 0, 2).reshape(len(HORIZONS), -1))
    out = {}
    for name, parts in errors.items():
        every = np.concatenate(parts, axis=1)
        out[name] = {"median": np.median(every, axis=1).tolist(), "p90": np.percentile(every, 90, axis=1).tolist()}
    return out


def print_table(title: str, table: dict, columns: list[str]) -> None:
    """Per flight, then per folder and over all (each pooled over its samples)."""
    for rows, what in ((table["flights"], "flight"), ({**table["folders"], "all": table["all"]}, "folder")):
        print(f"\n{title}, per {what}\n| {what} | samples | " + " | ".join(columns) + " |")
        print("|---|---|" + "---|" * len(columns))
        for name, row in rows.items():
            print(f"| {name} | {row['samples']} | " + " | ".join(f"{row[c]:.1f} g" for c in columns) + " |")


def main(argv=None) -> dict:
    args = parse_args(argv)
    start = time.perf_counter()
    done = subprocess.run(["git", "-C", str(args.clone), "rev-parse", "HEAD"], capture_output=True, text=True)
    commit = done.stdout.strip() or None
    if commit and not commit.startswith(COMMIT):
        print(f"note: the clone is at {commit[:10]}, not {COMMIT}")
    ground_sets = {k: prepared(load(args.clone, v, False), "ground") for k, v in GROUND.items()}
    swap_sets = {k: prepared(load(args.clone, v, True), "downwash") for k, v in DOWNWASH.items()}
    counts = {
        name: {k: len(v) for k, v in sets.items()} for name, sets in (("ground", ground_sets), ("downwash", swap_sets))
    }
    result = {"commit": commit, "flights": counts}
    result["ground"] = ground_effect(ground_sets["train"], ground_sets["test"])
    result["downwash"] = downwash(swap_sets["train"], swap_sets["test"])
    both = {k: ground_sets[k] + swap_sets[k] for k in ("train", "test")}
    result["drag"] = drag(both["train"], both["test"])
    result["motor_lag"] = motor_lag(both["train"], both["test"])
    result["replays"] = {
        "ground": replays(ground_sets["test"], result),
        "downwash": replays(swap_sets["test"], result),
    }
    columns = ["none", "paper", "fitted paper form"]
    print_table("ground effect, vertical residual RMSE (held out)", result["ground"]["test"], columns)
    print("constants:", result["ground"]["constants"])
    columns.append("fitted bounded form")
    print_table(
        "downwash, vertical residual RMSE while a drone is above (held out)", result["downwash"]["test"], columns
    )
    print("constants:", result["downwash"]["constants"])
    for name in ("drag", "motor_lag"):
        print(f"\n{name}: {json.dumps(result[name])}")
    from jaxdrones.validation.flights import HORIZONS

    print("\nopen-loop replays of the held-out flights: position error, median (90th percentile), m")
    print("| flights | model | " + " | ".join(f"{h} s" for h in HORIZONS) + " |\n|---|---|" + "---|" * len(HORIZONS))
    for flights_name, table in result["replays"].items():
        for model, row in table.items():
            cells = " | ".join(f"{m:.3f} ({p:.3f})" for m, p in zip(row["median"], row["p90"], strict=True))
            print(f"| {flights_name} | {model} | {cells} |")
    if args.score:
        result["scored"] = score_more(args, result)
    result["wall_time_s"] = time.perf_counter() - start
    if args.json:
        from jaxdrones.io.runs import write_json

        write_json(args.json, result)
    if args.plots:
        draw(ground_sets, swap_sets, result, args.plots)
    return result


def binned(x, y, edges):
    """The mean of ``y`` in each bin of ``x`` (NaN where a bin is empty) and the bins' centres."""
    import numpy as np

    index = np.digitize(x, edges) - 1
    means = [np.mean(y[index == k]) if np.any(index == k) else np.nan for k in range(len(edges) - 1)]
    return (edges[1:] + edges[:-1]) / 2, np.array(means)


def draw(ground_sets: dict, swap_sets: dict, result: dict, folder: Path) -> None:
    """validation_ground.png (the residual as a share of the thrust against height, measured and modelled: the paper's
    ground-effect figure on these flights), validation_downwash.png (the residual against Δz and against the
    horizontal offset) and validation_swap.png (a held-out swap's lower drone against the models)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxdrones.validation.flights import REST_HEIGHT, ground_z, pairs

    folder.mkdir(parents=True, exist_ok=True)
    g = result["ground"]["constants"]
    items = ground_sets["train"] + ground_sets["test"]
    height = np.concatenate([(d["form"].pos[..., 2] - REST_HEIGHT)[d["effect"]] for d in items])
    thrust = np.concatenate([d["form"].motor_force.sum(-1)[d["effect"]] for d in items])
    edges = np.linspace(0.02, 0.2, 19)
    fig, ax = plt.subplots(figsize=(6, 4))
    centres, mean_thrust = binned(height, thrust, edges)
    measured = binned(height, np.concatenate([d["z"][d["effect"]] for d in items]), edges)[1]
    ax.plot(centres * 100, 1 + measured / mean_thrust, "ko", label="measured: 1 + residual / thrust")
    for name, coeff, style in (("paper", g["paper"], "r-"), ("fitted", g["fitted"], "b-")):
        model = np.concatenate([np.asarray(ground_z(d["form"], d["params"], as32(coeff)))[d["effect"]] for d in items])
        mean = binned(height, model, edges)[1]
        ax.plot(centres * 100, 1 + mean / mean_thrust, style, label=f"{name}: C_gnd = {coeff[0]:.2f}")
    ax.set(xlabel="height above resting, cm", ylabel="thrust ratio", title="ground effect, Neural-Swarm's flights")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(folder / "validation_ground.png", dpi=120)

    c = result["downwash"]["constants"]
    items = swap_sets["train"] + swap_sets["test"]
    styles = {"paper": "r-", "fitted paper form": "g-", "fitted bounded form": "b-"}
    models = {name: (*model, styles[name]) for name, model in downwash_models(c).items()}
    dz, d2 = [], []
    for d in items:
        delta_z, dist2 = pairs(d["form"])
        above = np.where((delta_z > 0) & (dist2 < 0.15**2), delta_z, np.inf).min(-1)
        dz.append(above[d["effect"]])
        nearest = np.where(delta_z > 0.05, dist2, np.inf).min(-1)
        d2.append(nearest[d["effect"]])
    dz, dist = np.concatenate(dz), np.sqrt(np.concatenate(d2))
    residual = np.concatenate([d["z"][d["effect"]] for d in items]) * GRAMS
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    edges = np.linspace(0.1, 0.8, 15)
    left.plot(*binned(dz, residual, edges), "ko", label="measured")
    centres_d = np.linspace(0, 0.15, 8)
    right.plot(*binned(dist, residual, centres_d), "ko", label="measured")
    for name, (model, coeff, style) in models.items():
        value = np.concatenate([np.asarray(model(d["form"], d["params"], as32(coeff)))[d["effect"]] for d in items])
        left.plot(*binned(dz, value * GRAMS, edges), style, label=name)
        right.plot(*binned(dist, value * GRAMS, centres_d), style, label=name)
    left.set(
        xlabel="Δz to the drone above, m",
        ylabel="vertical residual, g",
        ylim=(-80, 5),
        title="downwash against height difference",
    )
    right.set(
        xlabel="horizontal offset, m",
        ylabel="vertical residual, g",
        ylim=(-80, 5),
        title="downwash against horizontal offset",
    )
    for ax in (left, right):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "validation_downwash.png", dpi=120)

    d = swap_sets["test"][0]
    lower = int(np.argmin(d["form"].pos[..., 2].mean(0)))
    fig, ax = plt.subplots(figsize=(9, 3.5))
    t = d["form"].time - d["form"].time[0]
    ax.plot(t, d["z"][:, lower] * GRAMS, "k-", lw=1, label=f"measured ({d['form'].names[lower]})")
    for name, (model, coeff, style) in models.items():
        ax.plot(t, np.asarray(model(d["form"], d["params"], as32(coeff)))[:, lower] * GRAMS, style, lw=1, label=name)
    ax.set(
        xlabel="time, s",
        ylabel="vertical residual, g",
        ylim=(-150, 20),
        title=f"swap {'+'.join(d['form'].names)}: the lowest drone",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=4)
    fig.tight_layout()
    fig.savefig(folder / "validation_swap.png", dpi=120)


def score_more(args: argparse.Namespace, result: dict) -> dict:
    """Each of ``--score``'s folders, as a swap (drones together) when its name says so, else as single flights."""

    out = {}
    for folder in args.score:
        kind = "downwash" if "swap" in Path(folder).name else "ground"
        items = prepared(load(args.clone, [folder], kind == "downwash"), kind)
        models = (downwash_models if kind == "downwash" else ground_models)(result[kind]["constants"])
        out[folder] = effect_table(items, models)
        print_table(f"{folder} ({kind})", out[folder], ["none", *models])
    return out


if __name__ == "__main__":
    main()
