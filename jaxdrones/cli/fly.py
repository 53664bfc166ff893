"""``jaxdrones fly``: the command line of the paper's control examples (`jaxdrones.examples.circle`,
`jaxdrones.examples.velocity`, `jaxdrones.examples.ground_effect`, `jaxdrones.examples.downwash`)."""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from jaxdrones.examples import downwash as downwash_example
from jaxdrones.examples import ground_effect as ground_effect_example
from jaxdrones.examples import velocity as velocity_example
from jaxdrones.examples.circle import (
    DEFAULT_FEEDFORWARD,
    DEFAULT_SETTLE_S,
    DEFAULT_VIDEO_FPS,
    DEFAULT_VIDEO_SIZE,
    check_flight,
    fly_circle,
    plot_flight,
)
from jaxdrones.examples.closed_loop import BACKENDS
from jaxdrones.io.runs import write_json
from jaxdrones.io.video import video_format
from jaxdrones.physics.params import MODELS

#: The examples of ``jaxdrones fly --example`` (paper §V-A); every one but the circle is a module of
#: `jaxdrones.examples` with the same interface (``check``, ``fly``, ``plot``, ``summary``, ``arrays``,
#: ``CLI_OPTIONS``, ``DEFAULT_DURATION_S``, ``DEFAULT_OUT``).
EXAMPLES = {
    "circle": None,
    "velocity": velocity_example,
    "ground-effect": ground_effect_example,
    "downwash": downwash_example,
}
#: Options of ``jaxdrones fly`` that only some examples take (argparse dest → flag). Their defaults are None, so a
#: value means the user gave the option; each example resolves its own defaults.
_SPECIFIC_OPTIONS = {
    "num_drones": "--num-drones",
    "ground_effect": "--ground-effect",
    "downwash": "--downwash",
    "feedforward": "--feedforward/--no-feedforward",
    "settle": "--settle",
    "obstacles": "--obstacles",
    "video": "--video",
    "no_video": "--no-video",
    "video_size": "--video-size",
    "fps": "--fps",
    "gui": "--gui",
}
_CIRCLE_DEFAULT_NUM_DRONES = 4
_CIRCLE_DEFAULT_DURATION_S = 12.0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``fly`` subcommand (the paper's control examples) to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "fly",
        help="fly one of the paper's control examples (circle, velocity, ground effect, downwash) and plot it",
        description="Fly one of the paper's control examples with the DSL PID controller, save a plot, "
        "metrics.json and flight.npz in a new run folder, and print a summary. circle: N Crazyflies "
        "track a circle (RMS tracking errors); velocity: 4 Crazyflies follow step-wise velocity "
        "commands (RMS velocity errors); ground-effect: one Crazyflie takes off with and without "
        "ground effect (height at 0.5 s); downwash: two Crazyflies cross 0.5 m apart with and without "
        "downwash (the lower one's dips).",
    )
    parser.add_argument("--example", choices=tuple(EXAMPLES), default="circle", help="which example (default circle)")
    parser.add_argument("--num-drones", type=int, default=None, help="circle: number of drones (default 4)")
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        help="flight time in s (default: circle 12, velocity 5, ground-effect 0.5, downwash 12)",
    )
    parser.add_argument("--model", default="cf2x", help=f"airframe: one of {', '.join(MODELS)} or a URDF path")
    parser.add_argument("--drag", action="store_true", help="rotor drag")
    parser.add_argument(
        "--ground-effect",
        action="store_true",
        default=None,
        help="ground effect (circle, velocity, downwash; ground-effect flies with and without)",
    )
    parser.add_argument(
        "--downwash",
        action="store_true",
        default=None,
        help="downwash between drones (circle, velocity; downwash flies with and without)",
    )
    parser.add_argument(
        "--feedforward",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="circle: pass the way-point velocity as the PID's target velocity "
        f"(default {'on' if DEFAULT_FEEDFORWARD else 'off'}; the original passes 0)",
    )
    parser.add_argument(
        "--settle",
        type=float,
        default=None,
        help=f"circle: initial transient excluded from the metrics, s (default "
        f"{DEFAULT_SETTLE_S:g}); velocity: time after each command change excluded (default "
        f"{velocity_example.DEFAULT_SETTLE_S:g})",
    )
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="jax",
        help="physics: jax (default) or pybullet (collisions; circle: obstacles, video, GUI)",
    )
    parser.add_argument(
        "--obstacles",
        action="store_true",
        default=None,
        help="circle, pybullet: fly among the example's obstacles (boxes, a sphere and a duck, "
        "around the circle); contacts are reported in metrics.json",
    )
    video = parser.add_mutually_exclusive_group()
    video.add_argument(
        "--video",
        metavar="PATH",
        default=None,
        help="circle, pybullet: video file, .mp4 or .gif (default flight.mp4; a relative path is "
        "inside the run folder; an existing file is never replaced)",
    )
    video.add_argument(
        "--no-video", action="store_true", default=None, help="circle, pybullet: do not render a video (faster)"
    )
    parser.add_argument(
        "--video-size",
        default=None,
        metavar="WxH",
        help=f"circle: video frame size in pixels (default {'x'.join(map(str, DEFAULT_VIDEO_SIZE))})",
    )
    parser.add_argument(
        "--fps",
        type=float,
        default=None,
        help=f"circle: video frame rate, Hz (default {DEFAULT_VIDEO_FPS:g}; rounded to a whole "
        f"number of control steps per frame)",
    )
    parser.add_argument(
        "--gui",
        action="store_true",
        default=None,
        help="circle, pybullet: show the flight in PyBullet's GUI in real time (needs a display)",
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument(
        "--out",
        default=None,
        help="output folder (default runs/fly for the circle, runs/<example> for the others; a "
        "numbered sibling is used if it exists, unless --overwrite)",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out that jaxdrones wrote (a flight folder), once the new one is complete",
    )
    parser.set_defaults(func=run_cli)


def _video_size(text: str) -> tuple[int, int]:
    """Parse ``WxH`` (pixels)."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--video-size must be WIDTHxHEIGHT in pixels, e.g. 640x480, got {text!r}") from None
    return width, height


def run_cli(args: argparse.Namespace) -> int:
    """Run the ``fly`` subcommand; returns the exit status."""
    if args.example != "circle":
        return _run_example(args)
    from jaxdrones.io.runs import output_folder

    backend, video = args.backend, args.video
    if backend == "pybullet" and video is None and not args.no_video:
        video = "flight.mp4"
    kwargs = dict(
        num_drones=_CIRCLE_DEFAULT_NUM_DRONES if args.num_drones is None else args.num_drones,
        duration_s=_CIRCLE_DEFAULT_DURATION_S if args.duration is None else args.duration,
        model=args.model,
        drag=args.drag,
        ground_effect=bool(args.ground_effect),
        downwash=bool(args.downwash),
        settle_s=DEFAULT_SETTLE_S if args.settle is None else args.settle,
        backend=backend,
        obstacles=True if args.obstacles else None,
        gui=bool(args.gui),
    )
    feedforward = DEFAULT_FEEDFORWARD if args.feedforward is None else args.feedforward
    try:
        if backend == "jax" and video is not None:
            raise ValueError("--video needs --backend pybullet (the jax backend does not render)")
        if video is not None:
            size = "x".join(map(str, DEFAULT_VIDEO_SIZE)) if args.video_size is None else args.video_size
            kwargs.update(video_size=_video_size(size), video_fps=DEFAULT_VIDEO_FPS if args.fps is None else args.fps)
            video_format(video)
        # Validate before creating the run folder (a relative video path is inside the new folder, so it is new).
        check_flight(**kwargs, video=video if video is not None and os.path.isabs(video) else None)
        with output_folder("runs/fly" if args.out is None else args.out, args.overwrite, kind="flight") as folder:
            out = folder.path
            video = None if video is None else os.path.join(out, video)
            result = fly_circle(**kwargs, feedforward=feedforward, video=video, progress=not args.no_progress)
            _write_circle(result, out)
    except (ValueError, RuntimeError, ImportError) as err:
        print(f"jaxdrones fly: error: {err}", file=sys.stderr)
        return 2
    final = folder.final
    m, c = result["metrics"], result["contacts"]
    s = result["settings"]
    print(
        f"{s['num_drones']} × {s['model']}, {s['duration_s']:g} s on {s['backend']}, feed-forward "
        f"{'on' if s['feedforward'] else 'off'}: simulated in {result['wall_s']:.2f} s (compilation included)"
    )
    print(f"RMS tracking error for t ≥ {m['settle_s']:g} s (cm):  to the moving way-point | to the circle path")
    for d, (w, ct) in enumerate(zip(m["waypoint_rms_per_drone_m"], m["cross_track_rms_per_drone_m"], strict=True)):
        print(f"  drone {d}: {100 * w:8.3f} | {100 * ct:8.3f}")
    print(f"  overall: {100 * m['waypoint_rms_m']:8.3f} | {100 * m['cross_track_rms_m']:8.3f}")
    if backend == "pybullet":
        touched = "none" if not c["collided"] else f"first at {c['first_collision_s']:.2f} s"
        print(
            f"contacts with obstacles or other drones: {touched} (steps per drone: obstacle "
            f"{c['obstacle_steps']}, drone {c['drone_steps']}; ground {c['ground_steps']})"
        )
    saved = [os.path.join(final, name) for name in ("flight.png", "metrics.json", "flight.npz")]
    if result["video"] is not None:
        saved.append(f"{os.path.join(final, _inside(result['video'], out))} ({result['video_frames']} frames)")
    print(f"saved {', '.join(saved[:-1])} and {saved[-1]}")
    return 0


def _inside(path: str | None, out: str) -> str | None:
    """``path`` relative to the folder ``out`` where it lies inside it (a video written there), else as it is."""
    return os.path.relpath(path, out) if path and path.startswith(out + os.sep) else path


def _write_circle(result: dict, out: str) -> None:
    """The circle's files in ``out``: ``flight.png``, ``metrics.json`` and ``flight.npz``."""
    plot_flight(result, os.path.join(out, "flight.png"))
    video = _inside(result["video"], out)
    metrics = {key: result[key] for key in ("settings", "metrics", "contacts", "wall_s", "video_frames")}
    write_json(os.path.join(out, "metrics.json"), {**metrics, "video": video})
    np.savez_compressed(
        os.path.join(out, "flight.npz"),
        **{
            k: result[k]
            for k in (
                "times",
                "pos",
                "quat",
                "vel",
                "rpy",
                "ang_vel",
                "rpm",
                "rpm_cmd",
                "contact",
                "target_pos",
                "target_vel",
            )
        },
    )


def _run_example(args: argparse.Namespace) -> int:
    """Run ``jaxdrones fly --example NAME`` for an example other than the circle; returns the exit status.

    Options the example does not take, and invalid values, are reported on stderr with exit status 2 before any
    run folder is created.
    """
    from jaxdrones.io.runs import output_folder

    module = EXAMPLES[args.example]
    given = [
        flag
        for dest, flag in _SPECIFIC_OPTIONS.items()
        if getattr(args, dest) is not None and dest not in module.CLI_OPTIONS
    ]
    if given:
        takes = ", ".join(_SPECIFIC_OPTIONS[d] for d in module.CLI_OPTIONS) or "none"
        return _fail(
            f"{', '.join(given)} {'does' if len(given) == 1 else 'do'} not apply to --example "
            f"{args.example} (of the options that only some examples take, it takes {takes})"
        )
    kwargs = {
        "duration_s": module.DEFAULT_DURATION_S if args.duration is None else args.duration,
        "model": args.model,
        "backend": args.backend,
        "drag": args.drag,
    }
    for dest in ("ground_effect", "downwash"):
        if dest in module.CLI_OPTIONS:
            kwargs[dest] = bool(getattr(args, dest))
    if "settle" in module.CLI_OPTIONS:
        kwargs["settle_s"] = module.DEFAULT_SETTLE_S if args.settle is None else args.settle
    try:
        module.check(**kwargs)
        with output_folder(module.DEFAULT_OUT if args.out is None else args.out, args.overwrite, "flight") as folder:
            result = module.fly(**kwargs)
            module.plot(result, os.path.join(folder.path, "flight.png"))
            metrics = {"settings": result["settings"], "metrics": result["metrics"], "wall_s": result["wall_s"]}
            write_json(os.path.join(folder.path, "metrics.json"), metrics)
            np.savez_compressed(os.path.join(folder.path, "flight.npz"), **module.arrays(result))
    except ValueError as err:
        return _fail(str(err))
    final = folder.final
    print("\n".join(module.summary(result)))
    paths = [os.path.join(final, name) for name in ("flight.png", "metrics.json", "flight.npz")]
    print(f"saved {', '.join(paths[:-1])} and {paths[-1]}")
    return 0


def _fail(message: str) -> int:
    """Print a ``jaxdrones fly`` error on stderr; returns the exit status 2 (argparse's for bad usage)."""
    print(f"jaxdrones fly: error: {message}", file=sys.stderr)
    return 2
