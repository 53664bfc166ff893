"""``jaxdrones ros2 TASK``: the paper's ROS 2 node (`jaxdrones.ros2.node`; the ``[ros2]`` extra)."""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``ros2`` subcommand to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "ros2",
        help="step a task's drones as a ROS 2 node (publishes obs, pose, odom; reads action, cmd_vel, cmd_position)",
        description="Step a task's simulation at its control rate as a ROS 2 node. Per drone i, under "
        "/<namespace><i>: publishes obs (std_msgs/Float32MultiArray: pos, quat, rpy, vel, ang_vel, "
        "last RPM), pose (geometry_msgs/PoseStamped), odom (nav_msgs/Odometry); subscribes action "
        "(Float32MultiArray, 4 RPM), cmd_vel (geometry_msgs/Twist, m/s) and cmd_position "
        "(geometry_msgs/PoseStamped), the latter two flown by the DSL PID. Ctrl-C stops it. Needs "
        "pip install 'jaxdrones[ros2]'.",
    )
    parser.add_argument("task", help="a registered task, e.g. hover")
    parser.add_argument("--num-drones", type=int, default=None, help="drones (default: the task's)")
    parser.add_argument("--ctrl-freq", type=int, default=None, help="control rate, Hz (default: the task's)")
    parser.add_argument("--namespace", default="cf", help="topic prefix: /<namespace><i>/... (default cf)")
    parser.add_argument(
        "--fast",
        action="store_true",
        help="step as fast as possible and publish the simulated time on /clock (default: real time)",
    )
    parser.add_argument("--duration", type=float, default=None, help="stop after this many simulated seconds")
    parser.add_argument("--seed", type=int, default=0, help="the start states' seed (default 0)")
    parser.add_argument(
        "--wait-for-command",
        action="store_true",
        help="hold the drones at their start states until the first command arrives",
    )
    parser.add_argument(
        "--sync",
        action="store_true",
        help="lockstep: step once every drone has a new command (simulated time waits for the controller)",
    )
    parser.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    """Run ``jaxdrones ros2`` with its parsed arguments; returns the exit status."""
    try:
        from jaxdrones.ros2.node import EnvNode

        options = {} if args.ctrl_freq is None else {"ctrl_freq": args.ctrl_freq}
        node = EnvNode(
            args.task,
            n_drones=args.num_drones,
            namespace=args.namespace,
            realtime=not args.fast,
            seed=args.seed,
            wait_for_command=args.wait_for_command,
            sync=args.sync,
            **options,
        )
    except (ValueError, ModuleNotFoundError) as e:
        print(f"jaxdrones ros2: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C while starting
        print("jaxdrones ros2: stopped before the first step", flush=True)
        return 0
    print(
        f"jaxdrones ros2: {args.task}, {node.n_drones} drone(s) at {1 / node.ctrl_dt:g} Hz on "
        f"{node.topic(0, '{obs,pose,odom}')} ... {node.topic(node.n_drones - 1, '')}; Ctrl-C stops",
        flush=True,
    )
    node.spin(args.duration)
    print(f"jaxdrones ros2: stopped after {node.steps} steps ({node.time_s:.2f} s simulated)", flush=True)
    return 0
