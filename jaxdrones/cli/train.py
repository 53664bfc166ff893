"""``jaxdrones train TASK``: the command line of `jaxdrones.training.run.train_task`."""

from __future__ import annotations

import argparse
import os
import sys

from jaxdrones import devices
from jaxdrones._validate import check_int
from jaxdrones.envs.config import START_RPMS
from jaxdrones.io.runs import enable_compilation_cache
from jaxdrones.training import trainers
from jaxdrones.training.recipes import recipe
from jaxdrones.training.run import train_task
from jaxdrones.training.runs import Stopped, TrainingFailed, parse_sweep, setting_label
from jaxdrones.training.trainers import ALGOS, TRAINABLE


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``train`` subcommand to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "train",
        help="train a policy with batched PPO, APG, SHAC or multi-agent PPO",
        description="Train a policy on a jaxdrones task with batched PPO (ours or brax's), through the "
        "differentiable simulator with APG or SHAC, or a team with multi-agent PPO, on every local "
        "device (and across processes with --coordinator); then evaluate it and save the policy, a "
        "learning curve, an evaluation flight plot and summary.json in a new run folder. Ctrl-C stops "
        "the run and saves the policy so far.",
    )
    parser.add_argument(
        "task",
        help=f"task to train: {', '.join(TRAINABLE)}, or one of your own that a module "
        f"given by --import registers (jaxdrones.envs.register)",
    )
    parser.add_argument(
        "--import",
        dest="imports",
        action="append",
        default=[],
        metavar="MODULE",
        help="import MODULE first (from the current folder or the installed packages), e.g. one "
        "that registers a task of your own; repeatable",
    )
    ppo = parser.add_argument_group("training")
    ppo.add_argument(
        "--algo",
        choices=ALGOS,
        default=None,
        help="apg (analytic policy gradients through the simulator), ppo (our batched PPO), brax_ppo (brax's PPO, "
        "which also takes camera images), shac (short-horizon actor-critic through the simulator), mappo "
        "(multi-agent PPO with a centralised critic) or ippo (independent PPO); default: the task's recipe "
        "(jaxdrones.training.recipes: apg for the tasks with a smooth loss)",
    )
    ppo.add_argument(
        "--defaults",
        choices=trainers.DEFAULTS,
        default=None,
        help="the trainer's default settings: cpu (few worlds, many small updates: fastest on a CPU) or "
        "gpu (thousands of worlds, few large updates: fastest where each sequential operation costs a kernel "
        "launch); default: the device's (gpu on a GPU or TPU)",
    )
    ppo.add_argument("--steps", type=int, default=None, help="env steps to train (default: the task's recipe's)")
    ppo.add_argument("--num-envs", type=int, default=None, help="parallel environments")
    ppo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ppo.add_argument(
        "--seeds",
        type=int,
        default=None,
        metavar="N",
        help="train N independent runs, seeds --seed to --seed + N - 1, as one program mapped over the seeds (brax_ppo:"
        " one after another): each seed's run in seed_<k>/ of the output folder, and there the summary of all with"
        " their median, interquartile mean and its 95%% bootstrap interval, and the share solved",
    )
    ppo.add_argument(
        "--sweep",
        action="append",
        default=[],
        metavar="NAME=V1,V2,...",
        help="train a run for each value of the trainer's setting NAME (a field of its config, e.g. learning_rate,"
        " entropy_cost, discounting; repeatable: every combination), each with the seeds of --seeds, in"
        " NAME=V/seed_<k>/ of the output folder, with each setting's aggregate in summary.json. Float settings are"
        " mapped with the seeds in one program; a setting that changes shapes or steps (num_envs, horizon, ...)"
        " trains as a program of its own, after the previous one",
    )
    ppo.add_argument(
        "--num-evals",
        type=int,
        default=None,
        help="evaluations over the run, the learning curve's points (default: the trainer's, 10)",
    )
    ppo.add_argument("--eval-episodes", type=int, default=256, help="evaluation episodes, >= 64 (default 256)")
    env = parser.add_argument_group("task")
    env.add_argument(
        "--action-type",
        default=None,
        help="action type (default: the task's): rpm, one_d_rpm (the "
        "paper's 1-D hover setting), pid, one_d_pid, vel, thrust_torque, one_d_thrust, tun, ctbr",
    )
    env.add_argument(
        "--obs-type", default=None, help="observation type (default: the task's): kin, kin_norm, kin_rotmat, neighbors"
    )
    env.add_argument(
        "--action-buffer",
        type=int,
        default=None,
        metavar="K",
        help="append the last K actions to the observation (0: none; default: the task's, none)",
    )
    env.add_argument(
        "--error-integral",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="append the integral of the task's tracking error to the observation (an integral term: cancels a "
        "constant unknown force); default off, on with --realism for hover and velocity",
    )
    env.add_argument(
        "--terminate-on-ground",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="end an episode as a crash when a drone touches the ground (default: the task's, off for hover and "
        "velocity; on with --realism for them)",
    )
    env.add_argument("--model", default=None, help="drone model name (cf2x, cf2p, racer) or URDF path")
    env.add_argument(
        "--num-drones",
        type=int,
        default=None,
        help="drones per world (single-agent tasks: 1; multi-agent tasks: 2 by default)",
    )
    env.add_argument("--ctrl-freq", type=int, default=None, help="control rate, Hz (default 30)")
    env.add_argument("--episode-len", type=float, default=None, help="episode length, s")
    env.add_argument(
        "--reward",
        choices=("shaped", "paper"),
        default=None,
        help="shaped (default, for fast learning) or the paper's reward",
    )
    for effect in ("drag", "ground-effect", "downwash"):
        env.add_argument(
            f"--{effect}",
            action=argparse.BooleanOptionalAction,
            default=None,
            help=f"aerodynamic effect {effect.replace('-', ' ')} on, or off with --no-{effect} "
            f"(default: the task's; downwash is on in crossing)",
        )
    env.add_argument(
        "--downwash-model",
        choices=("paper", "per_rotor", "bounded"),
        default=None,
        help="the downwash's model, on with it: paper (eq. down), per_rotor (a thrust change per rotor) or bounded "
        "(the paper's form fitted to real Crazyflie flights, finite as two drones' heights meet: docs/validation.md)",
    )
    env.add_argument(
        "--max-neighbors",
        type=int,
        default=None,
        metavar="K",
        help="neighbors observation of the K nearest drones only (default: every drone)",
    )
    env.add_argument(
        "--downwash-radius",
        type=float,
        default=None,
        metavar="R",
        help="downwash cut-off in m, with a neighbour list: a cost linear in the team size (default: "
        "every pair of drones within 10 m, the original)",
    )
    env.add_argument("--backend", choices=("jax", "pybullet"), default=None, help="physics backend (default jax)")
    env.add_argument(
        "--vision",
        nargs="+",
        choices=("rgb", "depth", "seg"),
        default=None,
        metavar="IMAGE",
        help="camera images in the observation (rgb, depth, seg; default: the task's, avoid: depth): "
        "trained with brax's vision PPO",
    )
    env.add_argument(
        "--image-size",
        type=int,
        nargs=2,
        default=None,
        metavar=("W", "H"),
        help="camera image size, pixels (default: the task's; avoid: 64 x 16)",
    )
    env.add_argument("--camera-freq", type=float, default=None, help="camera rate, Hz")
    env.add_argument(
        "--camera-fov",
        type=float,
        default=None,
        metavar="DEG",
        help="the cameras' vertical field of view, degrees (default: the task's; the paper's 60)",
    )
    env.add_argument(
        "--frame-stack",
        type=int,
        default=None,
        metavar="K",
        help="the last K camera frames in the observation, a memory for the policy (default: the task's, 1)",
    )
    env.add_argument(
        "--target", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"), help="hover/takeoff target, m"
    )
    env.add_argument(
        "--start-pos-range",
        type=float,
        nargs=3,
        default=None,
        metavar=("DX", "DY", "DZ"),
        help="half-widths of random start positions, m",
    )
    env.add_argument("--start-tilt", type=float, default=None, help="largest random start tilt, rad")
    env.add_argument("--start-yaw", type=float, default=None, help="half-width of the random start yaw, rad")
    env.add_argument("--start-vel", type=float, default=None, help="half-width of random start velocities, m/s")
    env.add_argument(
        "--start-ang-vel",
        type=float,
        default=None,
        help="half-width of random start body rates, rad/s (default: the task's; multi_hover trains from "
        "1 rad/s and is evaluated from its own 0.1)",
    )
    env.add_argument(
        "--start-rpm",
        choices=START_RPMS,
        default=None,
        help="the motors' speeds at an episode's start where they have dynamics (--realism): hover (default) or "
        "zero (a take-off from stopped motors)",
    )
    env.add_argument(
        "--realism",
        default=None,
        metavar="PRESET",
        help="sim-to-real preset: crazyflie (Learning to Fly in Seconds' Crazyflie: 0.15 s motor lag, "
        "observation noise, a random force and torque per episode) or crazyflie_harsh (twice its "
        "lag and noise, 1 m/s Dryden turbulence); default none, the paper's physics",
    )
    env.add_argument(
        "--realism-set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="one sim-to-real option (a field of jaxdrones.Realism), over --realism's preset: a value or "
        "a range LOW,HIGH drawn per episode, e.g. action_delay=1, motor_tau_up=0.05,0.2, "
        "turbulence=0.5; repeatable",
    )
    out = parser.add_argument_group("output")
    out.add_argument(
        "--out",
        default=None,
        help="output folder (default runs/TASK; a numbered sibling is used if it exists, unless --overwrite)",
    )
    out.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out that jaxdrones wrote (a run folder) once the new run is complete; an "
        "interrupted or failed run goes to a numbered sibling instead",
    )
    out.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    out.add_argument(
        "--no-compile-cache",
        action="store_true",
        help="do not use JAX's persistent compilation cache (default: on, in $JAXDRONES_CACHE_DIR or "
        "~/.cache/jaxdrones/xla, so that a second run compiles nothing)",
    )
    devices = parser.add_argument_group("devices and processes")
    devices.add_argument(
        "--device",
        default=None,
        metavar="PLATFORM",
        help="run on this JAX platform: cpu, gpu (cuda or rocm) or tpu (default: JAX's choice, a GPU "
        "when one is installed); the worlds are spread over all its local devices",
    )
    devices.add_argument(
        "--coordinator",
        default=None,
        metavar="HOST:PORT",
        help="train across processes with jax.distributed: the address of process 0's coordinator "
        "(with --num-processes and --process-id; or set nothing and let "
        "jax.distributed.initialize read SLURM's or the cluster's variables with --distributed)",
    )
    devices.add_argument("--num-processes", type=int, default=None, help="processes in the run (with --coordinator)")
    devices.add_argument("--process-id", type=int, default=None, help="this process's index, 0 .. N-1")
    devices.add_argument(
        "--distributed",
        action="store_true",
        help="call jax.distributed.initialize() with no arguments: it reads the coordinator, the "
        "process count and index from the cluster (SLURM, Open MPI, Cloud TPU, ...)",
    )
    devices.add_argument(
        "--distributed-timeout",
        type=int,
        default=60,
        metavar="S",
        help="seconds to wait for every process to join the coordinator before failing (default 60)",
    )
    parser.set_defaults(func=run_cli)


_ENV_OPTIONS = {
    "action_type": "action_type",
    "obs_type": "obs_type",
    "action_buffer": "action_buffer",
    "error_integral": "error_integral",
    "terminate_on_ground": "terminate_on_ground",
    "model": "model",
    "num_drones": "n_drones",
    "ctrl_freq": "ctrl_freq",
    "episode_len": "episode_len_s",
    "reward": "reward",
    "backend": "backend",
    "target": "target",
    "start_pos_range": "start_pos_range",
    "start_tilt": "start_tilt",
    "start_yaw": "start_yaw",
    "start_vel": "start_vel",
    "start_ang_vel": "start_ang_vel",
    "start_rpm": "start_rpm",
    "max_neighbors": "max_neighbors",
    "downwash_radius": "downwash_radius",
    "drag": "drag",
    "ground_effect": "ground_effect",
    "downwash": "downwash",
    "vision": "vision",
    "image_size": "image_size",
    "camera_freq": "camera_freq",
    "camera_fov": "camera_fov",
    "frame_stack": "frame_stack",
}


def realism_options(preset: str | None, settings: list[str]) -> str | dict | None:
    """``--realism`` and ``--realism-set``'s NAME=VALUE settings as a task config's ``realism`` (None, the preset's
    name, or a dict of `jaxdrones.envs.realism.Realism` fields with the preset under ``"preset"``), kept as plain data
    so that the run's summary and checkpoint record it.

    Raises:
        ValueError: a setting that is not NAME=VALUE or NAME=LOW,HIGH with numbers (the names and values are
            checked by `jaxdrones.envs.realism.resolve`).
    """
    if not settings:
        return preset
    options = {} if preset is None else {"preset": preset}
    for setting in settings:
        name, sep, text = setting.partition("=")
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if not sep or not name or len(values) not in (1, 2):
            raise ValueError(f"--realism-set takes NAME=VALUE or NAME=LOW,HIGH (numbers), got {setting!r}")
        values = tuple(int(v) if name.endswith("_delay") and v.is_integer() else v for v in values)
        options[name.strip()] = values[0] if len(values) == 1 else values
    return options


def _positive(name: str, value) -> None:
    if value is not None:
        check_int(name, value)


def _import_modules(modules) -> None:
    """Import ``--import``'s modules, the current folder first on the path (as ``python -m`` has it)."""
    import importlib
    import os

    if modules and os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    for module in modules:
        try:
            importlib.import_module(module)
        except ImportError as err:
            raise ValueError(f"--import {module}: {err}") from err


def run_cli(args: argparse.Namespace) -> int:
    """Run ``jaxdrones train``; returns the exit status (0 also when the run did not reach the threshold; 130 when
    stopped by Ctrl-C, after saving the policy so far)."""
    try:
        _import_modules(args.imports)
        _positive("--steps", args.steps)
        _positive("--num-envs", args.num_envs)
        _positive("--eval-episodes", args.eval_episodes)
        _positive("--num-evals", args.num_evals)
        _positive("--seeds", args.seeds)
        _positive("--distributed-timeout", args.distributed_timeout)
        devices.start(
            platform=args.device,
            coordinator=args.coordinator,
            num_processes=args.num_processes,
            process_id=args.process_id,
            auto=args.distributed,
            timeout_s=args.distributed_timeout,
        )
        if not args.no_compile_cache:
            enable_compilation_cache()
        env = {field: getattr(args, arg) for arg, field in _ENV_OPTIONS.items() if getattr(args, arg) is not None}
        if args.downwash_model is not None:
            if args.downwash is False:
                raise ValueError("--downwash-model turns the downwash on: drop --no-downwash")
            env["downwash"] = args.downwash_model
        realism = realism_options(args.realism, args.realism_set)
        if realism is not None:
            env["realism"] = realism
        if "target" in env and args.task not in ("hover", "takeoff"):
            raise ValueError(f"--target applies to hover and takeoff, not {args.task}")
        run = recipe(args.task, args.defaults, env, args.algo).with_options(
            seed=args.seed, steps=args.steps, num_envs=args.num_envs, num_evals=args.num_evals
        )
        summary = train_task(
            run,
            args.out,
            overwrite=args.overwrite,
            n_eval_episodes=args.eval_episodes,
            progress=not args.no_progress,
            t_start=getattr(args, "t_start", None),
            seeds=args.seeds,
            sweep=parse_sweep(args.sweep),
        )
    except (ValueError, OSError, ImportError, devices.DeviceError) as err:
        print(f"jaxdrones train: error: {err}", file=sys.stderr)
        return 2
    except TrainingFailed as err:
        if "seeds" in err.summary:
            _report_seeds(err.summary)
        print(f"jaxdrones train: error: {err}", file=sys.stderr)
        return 1
    except Stopped as stop:
        return _report_stop(stop.summary)
    except KeyboardInterrupt:  # before anything was trained: nothing written, the output folder untouched
        print("interrupted before any training: nothing saved", file=sys.stderr)
        return 130
    if "out_dir" not in summary:  # a process other than 0: process 0 reports and saves
        return 0
    if "seeds" in summary:  # several seeds or settings
        return _report_seeds(summary)
    from jaxdrones.training.evaluation import result_line

    print(result_line(summary))
    viewer = ", flight.html" if os.path.exists(os.path.join(summary["out_dir"], "flight.html")) else ""
    print(f"saved policy.pkl, learning_curve.png, flight.png{viewer}, summary.json in {summary['out_dir']}")
    return 0


def _report_seeds(summary: dict) -> int:
    """Print a run of several seeds or settings: each run's result and each setting's aggregate."""
    metric, threshold, unit = summary["success_metric"], summary["success_threshold"], summary["success_unit"]
    for label, part in [(f"{setting_label(s['setting'])}: ", s) for s in summary.get("settings", [])] or [
        ("", summary)
    ]:
        for run in part["runs"]:
            verdict = "solved" if run["success"] else "not solved"
            print(f"{label}seed {run['seed']}: {verdict}, {metric} {run['success_value']:.4g} {unit}")
        agg = part["aggregate"]
        low, high = agg["iqm_ci95"] or (None, None)
        interval = "" if low is None else f" (95% CI {low:.4g} to {high:.4g} {unit})"
        print(
            f"{label}{agg['solved_share']:.0%} of {agg['n_seeds']} seeds solved (threshold {threshold:g} {unit}); "
            f"median {agg['median']:.4g} {unit}, interquartile mean {agg['iqm']:.4g} {unit}{interval}"
        )
    folders = "NAME=V/seed_<k>/" if "settings" in summary else "seed_<k>/"
    flight = f", flight.png (seed {summary['median_seed']}, the median)" if "median_seed" in summary else ""
    print(
        f"{summary['wall_time_s']:.1f} s wall time, {summary['programs']} compiled program"
        f"{'s' * (summary['programs'] > 1)}; saved {folders} (each run's policy.pkl and summary.json), "
        f"learning_curve.png (the seeds' median, their range shaded){flight}, summary.json in {summary['out_dir']}"
    )
    return 0


def _report_stop(summary: dict) -> int:
    """Print what a Ctrl-C left saved; returns 130, the status of a process stopped by SIGINT."""
    if "seeds" in summary:
        _report_seeds(summary)
    if summary["interrupted"] and "seeds" in summary:
        print(f"interrupted: saved the runs trained so far in {summary['out_dir']}", file=sys.stderr)
    elif summary["interrupted"]:
        steps = f"{summary['env_steps']:,}"
        print(f"interrupted after {steps} env steps: saved the policy so far in {summary['out_dir']}", file=sys.stderr)
    else:
        print(f"interrupted while saving: the complete run is saved in {summary['out_dir']}", file=sys.stderr)
    return 130
