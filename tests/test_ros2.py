"""jaxdrones.ros2: message conversion (through rosbags' CDR, no ROS needed), the crazyswarm2 backend against its
interface with a stand-in node, and, where rclpy is installed (the ros2 extra, its own venv in .ci/run), the node
over real topics: a second process closes the loop with the DSL PID."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.ros2 import messages
from jaxdrones.ros2.crazyswarm2 import Backend
from jaxdrones.ros2.node import check_namespace
from jaxdrones.rotations import quat_to_euler

try:
    import rclpy  # noqa: F401

    HAVE_RCLPY = True
except ModuleNotFoundError:
    HAVE_RCLPY = False
needs_rclpy = pytest.mark.skipif(not HAVE_RCLPY, reason="rclpy is not installed (the ros2 extra, its own venv)")


@pytest.fixture(scope="module")
def typestore():
    typesys = pytest.importorskip("rosbags.typesys", reason="rosbags is not installed (the test extra)")
    return typesys.get_typestore(typesys.Stores.ROS2_KILTED)


def cdr_round_trip(typestore, msgtype, fields):
    msg = messages.build_rosbags(typestore, msgtype, fields)
    raw = typestore.serialize_cdr(msg, msgtype)
    return typestore.deserialize_cdr(raw, msgtype), bytes(raw)


def a_drone(rng):
    quat = rng.normal(size=4)
    quat /= np.linalg.norm(quat)
    return rng.normal(size=3), quat, rng.normal(size=3), rng.normal(size=3), rng.uniform(0, 20000, 4)


def test_obs_through_cdr(typestore, rng):
    pos, quat, vel, ang_vel, rpm = a_drone(rng)
    rpy = np.asarray(quat_to_euler(jnp.asarray(quat)))
    obs = messages.obs_vector(pos, quat, rpy, vel, ang_vel, rpm)
    msg, _ = cdr_round_trip(typestore, "std_msgs/msg/Float32MultiArray", messages.float_array_fields(obs))
    assert msg.data.dtype == np.float32 and msg.data.shape == (20,) and len(messages.OBS_NAMES) == 20
    expected = np.r_[pos, quat, rpy, vel, ang_vel, rpm]
    np.testing.assert_allclose(msg.data, expected.astype(np.float32), rtol=1e-6, atol=1e-6)


def test_pose_odometry_clock_through_cdr(typestore, rng):
    pos, quat, vel, ang_vel, _ = a_drone(rng)
    t = 12.345678901
    pose, _ = cdr_round_trip(typestore, "geometry_msgs/msg/PoseStamped", messages.pose_fields(pos, quat, t))
    assert (pose.header.stamp.sec, pose.header.stamp.nanosec, pose.header.frame_id) == (12, 345678901, "world")
    p, q = pose.pose.position, pose.pose.orientation
    np.testing.assert_array_equal([p.x, p.y, p.z, q.x, q.y, q.z, q.w], np.r_[pos, quat])
    odom, _ = cdr_round_trip(
        typestore, "nav_msgs/msg/Odometry", messages.odometry_fields(pos, quat, vel, ang_vel, t, child_frame_id="cf3")
    )
    assert odom.child_frame_id == "cf3" and odom.pose.covariance.shape == (36,)
    rot = np.asarray(jd.rotations.quat_to_rotmat(jnp.asarray(quat, jnp.float32)), np.float64)
    linear = odom.twist.twist.linear  # body frame: R v_body = v_world
    np.testing.assert_allclose(rot @ [linear.x, linear.y, linear.z], vel, atol=1e-5)
    angular = odom.twist.twist.angular
    np.testing.assert_array_equal([angular.x, angular.y, angular.z], ang_vel)
    clock, _ = cdr_round_trip(typestore, "rosgraph_msgs/msg/Clock", messages.clock_fields(0.5))
    assert (clock.clock.sec, clock.clock.nanosec) == (0, 500_000_000)


def test_commands_are_checked():
    np.testing.assert_array_equal(messages.rpm_command([1.0, 2.0, 3.0, 4.0]), [1, 2, 3, 4])
    with pytest.raises(ValueError, match=r"action message \(4 motor RPM\) must have 4 entries, got 3"):
        messages.rpm_command([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="non-finite"):
        messages.rpm_command([1.0, np.nan, 3.0, 4.0])
    with pytest.raises(ValueError, match="velocity setpoint"):
        messages.velocity_command([0.1, 0.2])
    pose = dataclasses.make_dataclass("Pose", ["position", "orientation"])
    point = dataclasses.make_dataclass("P", ["x", "y", "z"])
    orientation = dataclasses.make_dataclass("Q", ["x", "y", "z", "w"])
    half = np.sqrt(0.5)
    position, yaw = messages.position_command(pose(point(1, 2, 3), orientation(0, 0, half, half)))
    np.testing.assert_array_equal(position, [1, 2, 3])
    assert yaw == pytest.approx(np.pi / 2)
    with pytest.raises(ValueError, match="position setpoint"):
        messages.position_command(pose(point(1, np.inf, 3), orientation(0, 0, 0, 1)))


def test_namespace_is_checked():
    assert check_namespace("cf") == "cf" and check_namespace("team_a") == "team_a"
    for bad in ("", "2cf", "cf/x", "cf-1", "cf1", None):
        with pytest.raises(ValueError, match="namespace"):
            check_namespace(bad)


# crazyswarm2's interface, stood in for: its State (pos, vel, quat w-x-y-z, omega), Action (rpm), the node's
# create_publisher and the Clock message.
@dataclasses.dataclass
class State:
    pos: np.ndarray
    vel: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    quat: np.ndarray = dataclasses.field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    omega: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))


@dataclasses.dataclass
class Action:
    rpm: list


class Time:
    def __init__(self):
        self.sec, self.nanosec = 0, 0


class Clock:
    def __init__(self):
        self.clock = Time()


class StandInNode:
    def __init__(self):
        self.published = []

    def create_publisher(self, msg_type, topic, depth):
        assert (msg_type, topic) == (Clock, "clock")
        return self

    def publish(self, msg):
        self.published.append((msg.clock.sec, msg.clock.nanosec))


def test_crazyswarm2_backend_against_its_interface():
    node, params = StandInNode(), jd.load_params("cf2x")
    yaw90 = np.array([np.sqrt(0.5), 0, 0, np.sqrt(0.5)])  # w, x, y, z
    backend = Backend(
        node, ["cf1", "cf2"], [State(np.array([0.0, 0.0, 1.0]), quat=yaw90), State([1.0, 0.0, 0.0])], clock_type=Clock
    )
    hover = float(params.hover_rpm)
    for _ in range(250):  # 0.5 s at 500 Hz: the first hovers at 1 m, the second rests on the ground with motors off
        states = backend.step([None, None], [Action([hover] * 4), Action([0.0] * 4)])
    assert backend.time() == pytest.approx(0.5) and node.published[-1] == (0, 500_000_000)
    assert all(isinstance(s, State) for s in states)
    np.testing.assert_allclose(states[0].pos, [0, 0, 1], atol=1e-3)  # ground effect lifts it 0.5 mm at 1 m
    np.testing.assert_allclose(states[0].quat, yaw90, atol=1e-6)  # w, x, y, z kept
    assert states[1].pos[2] == pytest.approx(0.5 * float(params.collision_height))
    # Equal and opposite: more thrust on motors 2, 3 (the left side, +y) rolls the drone about +x.
    for _ in range(10):
        states = backend.step([None, None], [Action([hover, hover, hover * 1.01, hover * 1.01]), Action([0.0] * 4)])
    assert states[0].omega[0] > 0
    with pytest.raises(ValueError, match="one action of 4 RPM per drone"):
        backend.step([None], [Action([hover] * 4)])
    with pytest.raises(ValueError, match="one initial state per drone name"):
        Backend(node, ["cf1"], [], clock_type=Clock)
    with pytest.raises(ValueError, match="pos must be 3 finite numbers"):
        Backend(node, ["cf1"], [State(np.array([0.0, np.nan, 1.0]))], clock_type=Clock)
    backend.shutdown()


def test_ros2_command_without_rclpy_names_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rclpy", None)
    from jaxdrones.cli import main

    assert main(["ros2", "hover", "--duration", "0.1"]) == 2
    assert "pip install 'jaxdrones[ros2]'" in capsys.readouterr().err


ROS_ENV = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(40 + os.getpid() % 100)}


@pytest.fixture
def ros_env(monkeypatch):
    for name, value in ROS_ENV.items():
        monkeypatch.setenv(name, value)


@pytest.mark.ros2
@needs_rclpy
def test_rclpy_messages_equal_rosbags(typestore, rng):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float32MultiArray

    pos, quat, vel, ang_vel, rpm = a_drone(rng)
    for cls, msgtype, fields in (
        (
            Float32MultiArray,
            "std_msgs/msg/Float32MultiArray",
            messages.float_array_fields(messages.obs_vector(pos, quat, np.zeros(3), vel, ang_vel, rpm)),
        ),
        (PoseStamped, "geometry_msgs/msg/PoseStamped", messages.pose_fields(pos, quat, 3.25)),
        (Odometry, "nav_msgs/msg/Odometry", messages.odometry_fields(pos, quat, vel, ang_vel, 3.25)),
    ):
        _, raw = cdr_round_trip(typestore, msgtype, fields)
        # rclpy's bytes, read by rosbags and written again (CDR's alignment padding zeroed), are rosbags' own.
        from_rclpy = typestore.deserialize_cdr(serialize_message(messages.fill_rclpy(cls(), fields)), msgtype)
        assert bytes(typestore.serialize_cdr(from_rclpy, msgtype)) == raw


@pytest.mark.ros2
@needs_rclpy
def test_node_rejects_bad_input(ros_env):
    import rclpy
    from std_msgs.msg import Float32MultiArray

    from jaxdrones.ros2.node import EnvNode

    with pytest.raises(ValueError, match="unknown task"):
        EnvNode("no_such_task")
    rclpy.init()
    try:
        first = EnvNode("hover", realtime=False, namespace="clash", node_name="first")
        with pytest.raises(ValueError, match=r"another node already publishes \['/clash0/obs'\]"):
            EnvNode("hover", realtime=False, namespace="clash", node_name="second")
        sender = rclpy.create_node("sender")
        publisher = sender.create_publisher(Float32MultiArray, "/clash0/action", 10)
        deadline = time.monotonic() + 5
        while not first.errors and time.monotonic() < deadline:
            msg = Float32MultiArray()
            msg.data = [14000.0, 14000.0, 14000.0]
            publisher.publish(msg)
            rclpy.spin_once(first.node, timeout_sec=0.05)
        assert first.errors and "must have 4 entries, got 3" in first.errors[-1]
        assert first.mode[0] == 0  # the drone's motors stay off
        sender.destroy_node()
        first.close()
    finally:
        rclpy.shutdown()


@pytest.mark.ros2
@needs_rclpy
def test_velocity_and_position_setpoints_fly_the_pid(ros_env):
    """cmd_position and cmd_vel over topics (in one process): the drone climbs 0.3 m to the position setpoint and
    holds it, then moves along +x at the commanded 0.2 m/s (within 5 cm/s on average)."""
    import rclpy
    from geometry_msgs.msg import PoseStamped, Twist

    from jaxdrones.ros2.node import EnvNode

    rclpy.init()
    try:
        env_node = EnvNode("hover", realtime=False, namespace="setpoint", node_name="env", ctrl_freq=48)
        start = np.asarray(env_node.state.pos[0], np.float64)
        sender = rclpy.create_node("sender")

        def send(topic, msg, mode):
            publisher = sender.create_publisher(type(msg), topic, 10)
            deadline = time.monotonic() + 10
            while env_node.mode[0] != mode and time.monotonic() < deadline:
                publisher.publish(msg)
                rclpy.spin_once(env_node.node, timeout_sec=0.05)
            assert env_node.mode[0] == mode

        goal = PoseStamped()
        goal.pose.position.x, goal.pose.position.y, goal.pose.position.z = start + [0.0, 0.0, 0.3]
        goal.pose.orientation.w = 1.0
        send("/setpoint0/cmd_position", goal, 3)
        for _ in range(4 * 48):
            env_node.tick()
        np.testing.assert_allclose(np.asarray(env_node.state.pos[0]), start + [0, 0, 0.3], atol=0.02)
        command = Twist()
        command.linear.x = 0.2
        send("/setpoint0/cmd_vel", command, 2)
        velocities = []
        for _ in range(3 * 48):
            env_node.tick()
            velocities.append(np.asarray(env_node.state.vel[0]))
        # the PID's velocity loop (the paper's VEL action) over the last 2 s: within 5 cm/s, on average
        np.testing.assert_allclose(np.mean(velocities[48:], axis=0), [0.2, 0.0, 0.0], atol=0.05)
        assert not env_node.errors
        sender.destroy_node()
        env_node.close()
    finally:
        rclpy.shutdown()


@pytest.mark.ros2
@needs_rclpy
def test_sync_node_publishes_the_start_once_to_a_late_controller(ros_env):
    """A sync node started before its controller: the start states reach the controller once, however long it takes
    to answer (a second copy would be answered too, each answer counting as a step's command, and put the
    controller's commands a step behind for the rest of the run); its one answer makes one step."""
    import rclpy
    from std_msgs.msg import Float32MultiArray

    from jaxdrones.ros2.node import EnvNode

    rclpy.init()
    try:
        env_node = EnvNode("hover", realtime=False, sync=True, namespace="late", node_name="env", discovery_s=0.1)
        controller = rclpy.create_node("controller")
        received = []
        controller.create_subscription(Float32MultiArray, "/late0/obs", lambda msg: received.append(msg.data), 10)
        publisher = controller.create_publisher(Float32MultiArray, "/late0/action", 10)
        deadline = time.monotonic() + 10
        while not received and time.monotonic() < deadline:  # discovery, then the start states again
            env_node.tick()
            rclpy.spin_once(controller, timeout_sec=0.01)
        assert len(received) == 1 and env_node.steps == 0
        for _ in range(100):  # a slow controller: 1 s or more without an answer
            env_node.tick()
            rclpy.spin_once(controller, timeout_sec=0.01)
        assert len(received) == 1 and env_node.steps == 0
        command = Float32MultiArray()
        command.data = [14000.0] * 4
        publisher.publish(command)
        deadline = time.monotonic() + 10
        while len(received) < 2 and time.monotonic() < deadline:
            rclpy.spin_once(env_node.node, timeout_sec=0.01)
            env_node.tick()
            rclpy.spin_once(controller, timeout_sec=0.01)
        for _ in range(20):
            env_node.tick()
            rclpy.spin_once(controller, timeout_sec=0.01)
        assert env_node.steps == 1 and len(received) == 2
        np.testing.assert_array_equal(received[1][16:20], [14000.0] * 4)  # the step applied the answer
        controller.destroy_node()
        env_node.close()
    finally:
        rclpy.shutdown()


def serve_while(node, arguments: list[str], timeout_s: float = 120.0) -> str:
    """Run ``jaxdrones ros2 ARGUMENTS`` in its own process while spinning ``node`` (an rclpy node of this process)
    until it exits; then destroy the node and shut rclpy down. Returns the process's output; fails on an error."""
    import rclpy

    server = subprocess.Popen(
        [sys.executable, "-m", "jaxdrones.cli", "ros2", *arguments],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + timeout_s
        while server.poll() is None and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.01)
    finally:
        node.destroy_node()
        rclpy.shutdown()
        if server.poll() is None:
            server.kill()
    output = server.communicate()[0]
    assert server.returncode == 0, output
    return output


@pytest.mark.ros2
@needs_rclpy
def test_two_processes_close_the_loop_with_the_pid(ros_env):
    """The env node in its own process (``jaxdrones ros2 hover --ctrl-freq 48 --fast --sync``: as fast as the loop
    goes, in lockstep with the controller, the simulated time on /clock); this process subscribes to /cf0/obs,
    computes the DSL PID's RPM (the paper's examples run it at 48 Hz) for a hover at the drone's start position,
    and publishes them on /cf0/action. Without the commands the motors are off and the drone falls."""
    import rclpy
    from std_msgs.msg import Float32MultiArray

    from jaxdrones.control.pid import PIDGains, pid_control, pid_init

    freq, duration_s = 48, 8.0
    params = jd.make("hover").params
    start = jd.make("hover").reset(jax.random.key(0)).sim
    pid_control(params, PIDGains.dsl(), pid_init(start), start, start.pos, ctrl_dt=1 / freq)  # compiled first
    rclpy.init()
    node = rclpy.create_node("pid_client")
    publisher = node.create_publisher(Float32MultiArray, "/cf0/action", 10)
    received, sent, pid_state, target = [], [], None, None

    def on_obs(msg):
        nonlocal pid_state, target
        obs = np.asarray(msg.data, np.float64)
        received.append(obs)
        state = jd.DroneState(
            pos=jnp.asarray(obs[None, 0:3]),
            quat=jnp.asarray(obs[None, 3:7]),
            vel=jnp.asarray(obs[None, 10:13]),
            ang_vel=jnp.asarray(obs[None, 13:16]),
            rpm=jnp.asarray(obs[None, 16:20]),
            contact=jnp.zeros(1, jnp.int32),
        )
        if pid_state is None:
            pid_state, target = pid_init(state), obs[0:3].copy()
        rpm, pid_state = pid_control(params, PIDGains.dsl(), pid_state, state, target[None], ctrl_dt=1 / freq)
        out = Float32MultiArray()
        out.data = np.asarray(rpm[0], np.float64).tolist()
        sent.append(np.asarray(out.data, np.float32))
        publisher.publish(out)

    node.create_subscription(Float32MultiArray, "/cf0/obs", on_obs, 10)
    output = serve_while(node, ["hover", "--ctrl-freq", str(freq), "--duration", str(duration_s), "--fast", "--sync"])
    assert f"stopped after {int(duration_s * freq)} steps" in output
    positions = np.array([obs[0:3] for obs in received])
    assert len(positions) == int(duration_s * freq) + 1  # the start's and every step's observation, each once
    # lockstep: each step applied the command computed from the observation before it (the obs' last RPM)
    np.testing.assert_array_equal(np.array([obs[16:20] for obs in received[1:]], np.float32), np.array(sent[:-1]))
    np.testing.assert_allclose(target, np.asarray(start.pos[0]), atol=1e-6)  # the task's start, seed 0
    error = np.linalg.norm(positions[-freq:] - target, axis=-1)  # the last second
    print(f"two-process PID hover: largest distance to the target over the last second {100 * error.max():.2f} cm")
    assert error.max() < 0.05, (error.max(), positions[-1])


@pytest.mark.ros2
@needs_rclpy
def test_real_time_node_publishes_at_its_rate(ros_env):
    """``jaxdrones ros2 hover --ctrl-freq 48 --duration 4`` in real time, no commands: an observation every 1/48 s of
    wall time, and the drone, its motors off, falls from its start (1.08 m up) to rest on the ground."""
    import rclpy
    from std_msgs.msg import Float32MultiArray

    rclpy.init()
    node = rclpy.create_node("listener")
    arrivals = []
    node.create_subscription(
        Float32MultiArray, "/cf0/obs", lambda msg: arrivals.append((time.monotonic(), float(msg.data[2]))), 10
    )
    output = serve_while(node, ["hover", "--ctrl-freq", "48", "--duration", "4"])
    assert "stopped after 192 steps" in output, output
    times, heights = np.array(arrivals).T
    assert len(times) >= 96  # the last 2 s at least (the first messages may precede discovery)
    period = np.median(np.diff(times))
    assert period == pytest.approx(1 / 48, rel=0.2), period
    assert heights[-1] == pytest.approx(0.5 * float(jd.load_params("cf2x").collision_height))


@pytest.mark.ros2
@needs_rclpy
def test_ctrl_c_stops_the_node_cleanly(ros_env):
    """SIGINT (Ctrl-C) while the node steps: exit status 0, no traceback, a last line saying how far it got."""
    import signal

    server = subprocess.Popen(
        [sys.executable, "-m", "jaxdrones.cli", "ros2", "hover"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert "Ctrl-C stops" in server.stdout.readline()  # started: the node steps on its timer
    time.sleep(1.0)
    server.send_signal(signal.SIGINT)
    output = server.communicate(timeout=60)[0]
    assert server.returncode == 0, output
    assert "Traceback" not in output and "jaxdrones ros2: stopped after" in output, output
