"""``jaxdrones camera``: the command line of the scripted camera scene (`jaxdrones.examples.camera_scene`)."""

from __future__ import annotations

import argparse
import os
import sys

from jaxdrones.examples.camera_scene import BOX_DISTANCE, camera_scene, save_camera_images


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``camera`` subcommand (the scripted camera scene) to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "camera",
        help="render a drone's onboard camera in a scripted scene (rgb, depth, segmentation)",
        description="Render the onboard camera of a drone hovering 0.5 m above the ground in front of a box "
        "(PyBullet backend) and save rgb.png, depth.png (uint16 mm), seg.png (body id + 1) and "
        "scene.json in a new run folder.",
    )
    parser.add_argument(
        "--out",
        default="runs/camera",
        help="output folder (default runs/camera; a numbered sibling is used if it exists, unless --overwrite)",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out that jaxdrones wrote, once the new one is complete",
    )
    parser.add_argument("--width", type=int, default=320, help="image width, pixels (default 320)")
    parser.add_argument("--height", type=int, default=240, help="image height, pixels (default 240)")
    parser.add_argument("--fov", type=float, default=60.0, help="vertical field of view, degrees (default 60)")
    parser.add_argument(
        "--distance", type=float, default=BOX_DISTANCE, help=f"camera-to-box distance, m (default {BOX_DISTANCE:g})"
    )
    parser.add_argument("--model", default="cf2x", help="airframe: cf2x, cf2p, racer or a URDF path")
    parser.add_argument(
        "--renderer", choices=("tiny", "egl"), default="tiny", help="TinyRenderer (CPU, default) or OpenGL through EGL"
    )
    parser.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    """Run the ``camera`` subcommand; returns the exit status."""
    from jaxdrones.io.runs import output_folder

    try:
        scene = camera_scene(args.model, args.width, args.height, args.fov, args.distance, args.renderer)
        with output_folder(args.out, overwrite=args.overwrite, kind="camera") as folder:
            names = [os.path.basename(p) for p in save_camera_images(scene, folder.path).values()]
        paths = [os.path.join(folder.final, name) for name in names]
    except (ValueError, RuntimeError, OSError, ImportError) as err:
        print(f"jaxdrones camera: error: {err}", file=sys.stderr)
        return 2
    box = scene["seg"] == scene["body_ids"]["obstacles"][0]
    h, w = scene["depth"].shape
    print(
        f"{w} × {h} image, box face {args.distance:g} m ahead: depth at the image centre "
        f"{scene['depth'][h // 2, w // 2]:.4f} m, box covers {int(box.sum())} pixels"
    )
    print("saved " + ", ".join(paths))
    return 0
