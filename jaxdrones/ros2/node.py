"""The paper's ROS 2 node: a task's simulation stepped at its control rate, publishing each drone's state and reading
its commands (``jaxdrones ros2 TASK``; the ``[ros2]`` extra).

Per drone ``i`` (namespace ``/{namespace}{i}``, default ``/cf0``, ``/cf1``, ...; `jaxdrones.ros2.messages`):

- published after every control step: ``obs`` (``std_msgs/Float32MultiArray``, the paper's 20 floats: pos, quat,
  rpy, vel, ang_vel, last RPM), ``pose`` (``geometry_msgs/PoseStamped``) and ``odom`` (``nav_msgs/Odometry``), in
  frame ``world``;
- subscribed: ``action`` (``Float32MultiArray`` of 4 motor RPM, as the paper's node), ``cmd_vel``
  (``geometry_msgs/Twist``, linear velocity in m/s, world frame) and ``cmd_position`` (``geometry_msgs/PoseStamped``,
  a position and yaw to hold). The last message received sets the drone's command until another arrives: RPM are
  applied as they are (clipped to [0, max_rpm]); velocity and position setpoints go through the DSL PID
  (`jaxdrones.control.pid`) at the control rate. Before any command a drone's motors are off (0 RPM), as in the
  paper's node.

The simulation is the task's (``jaxdrones.make(TASK, ...)``: its drones, physics, rates and start states, drawn by
``reset`` with ``seed``), stepped with the JAX core (`jaxdrones.sim.make_step`) on motor commands, as the paper's
node steps ``CtrlAviary``; rewards and terminations are not computed. ``realtime=True`` steps on a wall-clock timer
at the control rate; ``realtime=False`` steps as fast as it can and publishes the simulated time on ``/clock``
(``rosgraph_msgs/Clock``; run the other nodes with ``use_sim_time``), stamping the messages with it. With
``wait_for_command`` the simulation starts at the first command; with ``sync`` it steps in lockstep with the
controller (a step once every drone has a new command). Ctrl-C (or `EnvNode.close`) shuts the node down
cleanly.
"""

from __future__ import annotations

import re
import signal
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.control.pid import PIDGains, pid_control, pid_init
from jaxdrones.physics.rotations import quat_to_euler
from jaxdrones.ros2 import messages, require_rclpy
from jaxdrones.sim import make_step

__all__ = ["COMMAND_TOPICS", "MODES", "STATE_TOPICS", "EnvNode", "check_namespace"]

#: A drone's command mode: motors off, RPM from ``action``, a velocity, a position.
MODES = ("off", "rpm", "velocity", "position")
_OFF, _RPM, _VELOCITY, _POSITION = range(len(MODES))
#: The topics each drone publishes and subscribes to, under ``/{namespace}{i}``; each command topic's mode.
STATE_TOPICS = ("obs", "pose", "odom")
COMMAND_TOPICS = {"action": "rpm", "cmd_vel": "velocity", "cmd_position": "position"}
_NAMESPACE = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


def check_namespace(namespace: str) -> str:
    """``namespace`` if it makes valid ROS 2 topic names ``/{namespace}{i}/...``: a letter, then letters, digits or
    underscores (not ending in a digit, which would make drone 1's and drone 11's names clash with drones of
    another namespace); else ValueError."""
    if not isinstance(namespace, str) or not _NAMESPACE.fullmatch(namespace) or namespace[-1].isdigit():
        raise ValueError(
            f"namespace must be a letter followed by letters, digits or underscores, not ending in a "
            f"digit (topics /<namespace><i>/obs), got {namespace!r}"
        )
    return namespace


@jax.jit
def _commands(params, pid_state, state, mode, rpm, velocity, position, yaw, ctrl_dt):
    """The RPM f[D, 4] to apply for each drone's mode (`MODES` index i32[D]) and the PID state after it."""
    current_yaw = quat_to_euler(state.quat)[..., 2]
    by_position, by_velocity = (mode == _POSITION)[:, None], (mode == _VELOCITY)[:, None]
    target_pos = jnp.where(by_position, position, state.pos)  # a velocity setpoint holds the current position
    target_vel = jnp.where(by_velocity, velocity, 0.0)
    target_yaw = jnp.where(mode == _POSITION, yaw, current_yaw)
    target_rpy = jnp.stack([jnp.zeros_like(target_yaw), jnp.zeros_like(target_yaw), target_yaw], -1)
    pid_rpm, new_pid = pid_control(
        params,
        PIDGains.dsl(state.pos.dtype),
        pid_state,
        state,
        target_pos,
        target_vel=target_vel,
        target_rpy=target_rpy,
        ctrl_dt=ctrl_dt,
    )
    uses_pid = by_position | by_velocity
    new_pid = jax.tree.map(lambda new, old: jnp.where(uses_pid, new, old), new_pid, pid_state)
    out = jnp.where((mode == _RPM)[:, None], rpm, jnp.where(uses_pid, pid_rpm, 0.0))
    return out.astype(state.rpm.dtype), new_pid


class EnvNode:
    """The node (see the module docstring).

    Args:
        task: a registered task (`jaxdrones.envs.registry.registered`), e.g. ``"hover"``.
        n_drones: the task's drone count (default: the task's).
        namespace: the drones' topic prefix (`check_namespace`).
        realtime: step on a wall-clock timer (True) or as fast as possible with ``/clock`` (False).
        seed: the reset key's seed (start states).
        node_name: the ROS node's name.
        discovery_s: how long to look for another node publishing this namespace's topics at start, s.
        wait_for_command: hold the simulation (publishing the start states at the control rate) until the first
            command of any drone arrives, so that a controller that connects late finds the drones where they
            started.
        sync: lockstep with the controller: step only once every drone has received a command since the last
            step (simulated time then waits for a slow controller instead of running on with old commands).
        **make_options: further options of ``jaxdrones.make`` (e.g. ``drag=True``).

    Raises:
        ValueError: an unknown task or option (``jaxdrones.make``), a bad namespace, or topics of this namespace
            already published by another node (checked at start, after discovery).
        ModuleNotFoundError: rclpy or the message packages are missing (the ``[ros2]`` extra).
    """

    def __init__(
        self,
        task: str = "hover",
        *,
        n_drones: int | None = None,
        namespace: str = "cf",
        realtime: bool = True,
        seed: int = 0,
        node_name: str = "jaxdrones",
        discovery_s: float = 0.5,
        wait_for_command: bool = False,
        sync: bool = False,
        **make_options,
    ):
        rclpy = require_rclpy()
        from geometry_msgs.msg import PoseStamped, Twist
        from nav_msgs.msg import Odometry
        from rosgraph_msgs.msg import Clock
        from std_msgs.msg import Float32MultiArray

        import jaxdrones as jd

        self.namespace = check_namespace(namespace)
        if n_drones is not None:
            make_options["n_drones"] = n_drones
        self.env = jd.make(task, **make_options)
        start = self.env.reset(jax.random.key(seed))
        self.state, self.params = start.sim, start.params
        self.n_drones = self.env.config.n_drones
        self.ctrl_dt = 1.0 / self.env.config.sim.ctrl_freq
        self._step = make_step(self.env.config.sim)
        self._pid = pid_init(self.state)
        n = self.n_drones
        self.mode = np.zeros(n, np.int32)
        self._rpm, self._velocity = np.zeros((n, 4)), np.zeros((n, 3))
        self._position, self._yaw = np.asarray(self.state.pos, np.float64).copy(), np.zeros(n)
        self.time_s, self.steps, self.realtime = 0.0, 0, bool(realtime)
        self.waiting = bool(wait_for_command)
        self.sync = bool(sync)
        self._fresh = np.zeros(n, bool)  # a command arrived since the last step (sync)
        self.errors: list[str] = []  # rejected command messages, newest last
        self._types = {"obs": Float32MultiArray, "pose": PoseStamped, "odom": Odometry, "clock": Clock}
        self._rclpy = rclpy
        self._owns_context = not rclpy.ok()  # shut rclpy down on close only if this node started it
        if self._owns_context:
            # Ctrl-C while starting raises KeyboardInterrupt (Python's own handler), and during `spin` stops its loop,
            # rather than rclpy's handler shutting the context down under a node that is still starting.
            from rclpy.signals import SignalHandlerOptions

            rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(node_name)
        self._publishers = [
            {name: self.node.create_publisher(self._types[name], self.topic(i, name), 10) for name in STATE_TOPICS}
            for i in range(n)
        ]
        self._clock = None if self.realtime else self.node.create_publisher(Clock, "/clock", 10)
        command_types = {"action": Float32MultiArray, "cmd_vel": Twist, "cmd_position": PoseStamped}
        for i in range(n):
            for topic, mode in COMMAND_TOPICS.items():
                self.node.create_subscription(
                    command_types[topic],
                    self.topic(i, topic),
                    lambda msg, i=i, mode=mode: self._on_command(i, mode, msg),
                    10,
                )
        self._check_clash(discovery_s)
        self._timer = self.node.create_timer(self.ctrl_dt, self.tick) if self.realtime else None
        self._start_subscribers = self._obs_subscribers()  # who has the start states (sync mode)
        self.publish()

    def topic(self, drone: int, name: str) -> str:
        """The topic ``/{namespace}{drone}/{name}``."""
        return f"/{self.namespace}{drone}/{name}"

    def _check_clash(self, discovery_s: float) -> None:
        deadline = time.monotonic() + discovery_s
        while True:
            self._rclpy.spin_once(self.node, timeout_sec=0.05)
            taken = [
                self.topic(i, "obs")
                for i in range(self.n_drones)
                if self.node.count_publishers(self.topic(i, "obs")) > 1
            ]
            if taken:
                self.close()
                raise ValueError(
                    f"another node already publishes {taken}: choose another namespace "
                    f"(--namespace) than {self.namespace!r}"
                )
            if time.monotonic() >= deadline:
                return

    def _on_command(self, drone: int, mode: str, msg) -> None:
        """A command message for ``drone``: parsed and held (the drone then flies in ``mode``), or refused and
        logged (the drone keeps its command)."""
        try:
            if mode == "rpm":
                self._rpm[drone] = messages.rpm_command(msg.data)
            elif mode == "velocity":
                self._velocity[drone] = messages.velocity_command(msg.linear)
            else:
                self._position[drone], self._yaw[drone] = messages.position_command(msg.pose)
        except ValueError as error:
            message = f"{self.topic(drone, '')}: {error}"
            self.errors.append(message)
            self.node.get_logger().error(message)
            return
        self.mode[drone] = MODES.index(mode)
        self._fresh[drone] = True

    def tick(self) -> None:
        """One control step: the commands applied, the physics stepped, the states published (while waiting for a
        first command, the start states only; in sync mode, nothing until every drone has a new command)."""
        if self.sync:
            if not self._fresh.all():
                if self.steps == 0:
                    self._publish_start_to_new_subscribers()
                return
            self._fresh[:] = False
        self.waiting = self.waiting and not self.mode.any()
        if self.waiting:
            self.publish()
            return
        dtype = self.state.pos.dtype
        rpm, self._pid = _commands(
            self.params,
            self._pid,
            self.state,
            jnp.asarray(self.mode),
            jnp.asarray(self._rpm, dtype),
            jnp.asarray(self._velocity, dtype),
            jnp.asarray(self._position, dtype),
            jnp.asarray(self._yaw, dtype),
            self.ctrl_dt,
        )
        self.state = self._step(self.params, self.state, rpm)
        self.steps += 1
        self.time_s = self.steps * self.ctrl_dt
        self.publish()

    def _obs_subscribers(self) -> np.ndarray:
        """The number of subscriptions matched to each drone's ``obs`` topic, i64[D]."""
        return np.array([publishers["obs"].get_subscription_count() for publishers in self._publishers])

    def _publish_start_to_new_subscribers(self) -> None:
        """Sync mode, before the first step: the start states again for each drone that has no command yet and
        whose ``obs`` gained a subscriber since they were last published (a controller that connected after them).
        Not on a timer: a controller answers every ``obs`` it receives, and each answer counts as a step's command,
        so a start state it received twice would put its commands one step behind the states for the whole run."""
        count = self._obs_subscribers()
        new = (count > self._start_subscribers) & ~self._fresh
        self._start_subscribers = count
        if new.any():
            self.publish(np.flatnonzero(new))

    def publish(self, drones: np.ndarray | None = None) -> None:
        """Publish the ``obs``, ``pose`` and ``odom`` of every drone (or of the indices ``drones``), and ``/clock``
        when not in real time."""
        fill, t = messages.fill_rclpy, self.time_s
        if self._clock is not None:
            self._clock.publish(fill(self._types["clock"](), messages.clock_fields(t)))
        pos, quat, vel, ang_vel, rpm = (
            np.asarray(getattr(self.state, k), np.float64) for k in ("pos", "quat", "vel", "ang_vel", "rpm")
        )
        rpy = np.asarray(quat_to_euler(self.state.quat), np.float64)
        for i in range(self.n_drones) if drones is None else drones:
            publishers = self._publishers[i]
            obs = messages.obs_vector(pos[i], quat[i], rpy[i], vel[i], ang_vel[i], rpm[i])
            publishers["obs"].publish(fill(self._types["obs"](), messages.float_array_fields(obs)))
            publishers["pose"].publish(fill(self._types["pose"](), messages.pose_fields(pos[i], quat[i], t)))
            publishers["odom"].publish(
                fill(
                    self._types["odom"](),
                    messages.odometry_fields(
                        pos[i], quat[i], vel[i], ang_vel[i], t, child_frame_id=f"{self.namespace}{i}"
                    ),
                )
            )

    def spin(self, duration_s: float | None = None) -> None:
        """Run until ``duration_s`` of simulated time (None: until Ctrl-C), then close the node.

        Called from the main thread, Ctrl-C (SIGINT) sets a flag that the loop reads between two waits of at most one
        control step, rather than raising KeyboardInterrupt wherever the interpreter happens to be (inside an rclpy
        callback, the executor could swallow it and spin on); the previous handler is restored on return."""
        stop = threading.Event()
        previous = None
        if threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
        try:
            while not stop.is_set() and self._rclpy.ok() and (duration_s is None or self.time_s < duration_s - 1e-9):
                if self.realtime:
                    self._rclpy.spin_once(self.node, timeout_sec=self.ctrl_dt)
                else:
                    self._rclpy.spin_once(self.node, timeout_sec=0.01 if self.sync else 0)
                    self.tick()
        except KeyboardInterrupt:  # from another thread's handler, or raised before ours was set
            pass
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)
            self.close()

    def close(self) -> None:
        """Destroy the node, and shut rclpy down if this node started it (idempotent)."""
        if getattr(self, "node", None) is not None:
            self.node.destroy_node()
            self.node = None
        if self._owns_context and self._rclpy.ok():
            self._rclpy.shutdown()
