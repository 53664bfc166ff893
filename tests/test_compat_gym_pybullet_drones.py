"""`jaxdrones.compat.gym_pybullet_drones`: the original's classes, keywords, observation layout, rewards, episode
lengths and info on the jaxdrones physics; its DSL PID equal to `jaxdrones.control.pid`; keyword hints; the
Logger; no PyBullet import on the JAX backend."""

import os
import subprocess
import sys

import numpy as np
import pytest

from jaxdrones.compat.gym_pybullet_drones import (
    ActionType,
    CtrlAviary,
    DroneModel,
    DSLPIDControl,
    HoverAviary,
    Logger,
    MultiHoverAviary,
    ObservationType,
    Physics,
    str2bool,
)
from jaxdrones.control.pid import PIDGains, pid_control, pid_init
from jaxdrones.params import load_params
from jaxdrones.state import DroneState


def test_hover_aviary_layout_reward_and_episode_length():
    """learn.py's env: KIN of 12 + 15 one-dimensional actions, the reward max(0, 2 - d⁴) and, with hover RPM, an
    episode that ends by time after 242 steps (the original truncates once the time *before* a step exceeds 8 s)."""
    env = HoverAviary(obs=ObservationType("kin"), act=ActionType("one_d_rpm"))
    assert env.observation_space.shape == (1, 27) and env.action_space.shape == (1, 1)
    assert (env.CTRL_FREQ, env.EPISODE_LEN_SEC, env.ACTION_BUFFER_SIZE) == (30, 8, 15)
    obs, info = env.reset(seed=0)
    assert info == {"answer": 42} and obs.dtype == np.float32 and env.observation_space.contains(obs)
    np.testing.assert_allclose(obs[0, :3], [0.0, 0.0, 0.1125], atol=1e-7)
    steps, done, actions = 0, False, np.linspace(-0.2, 0.2, 400)
    while not done:
        obs, reward, terminated, truncated, info = env.step(np.array([[actions[steps]]], np.float32))
        steps += 1
        state = env._getDroneStateVector(0)
        assert reward == pytest.approx(max(0.0, 2 - np.linalg.norm(state[:3] - [0, 0, 1]) ** 4))
        # KIN: pos, rpy, vel, world-frame angular velocity, then the last 15 actions, oldest first
        np.testing.assert_allclose(
            obs[0, :12], np.concatenate([state[0:3], state[7:10], state[10:13], state[13:16]]), rtol=1e-6, atol=1e-6
        )
        np.testing.assert_allclose(obs[0, 12:][-min(steps, 15) :], actions[max(0, steps - 15) : steps], atol=1e-7)
        done = terminated or truncated
    assert steps == 242 and truncated and not terminated


def test_hover_aviary_truncates_on_tilt():
    env = HoverAviary(act=ActionType.RPM)
    env.reset()
    steps, truncated = 0, False
    while not truncated:
        _, _, _, truncated, _ = env.step(np.array([[1.0, -1.0, -1.0, 1.0]], np.float32))  # a roll torque
        steps += 1
    assert steps < 60 and abs(env.rpy[0, 0]) > 0.4 or abs(env.rpy[0, 1]) > 0.4


def test_multi_hover_aviary_targets_and_team_reward():
    env = MultiHoverAviary(num_drones=3, act=ActionType.RPM)
    obs, _ = env.reset()
    assert obs.shape == (3, 12 + 15 * 4) and env.action_space.shape == (3, 4)
    np.testing.assert_allclose(env.TARGET_POS - env.INIT_XYZS, [[0, 0, 1], [0, 0, 0.5], [0, 0, 1 / 3]])
    _, reward, _, _, _ = env.step(np.zeros((3, 4), np.float32))
    dist = np.linalg.norm(env.TARGET_POS - env.pos, axis=1)
    assert reward == pytest.approx(np.sum(np.maximum(0, 2 - dist**4)))


def test_pid_action_types_fly_to_their_targets():
    """``ActionType.PID``: the DSL PID to an absolute target; ``VEL``: to a velocity of 0.25 m/s·|a₃|."""
    env = HoverAviary(act=ActionType.PID)
    env.reset()
    for _ in range(90):  # 3 s
        env.step(np.array([[0.2, -0.1, 0.6]], np.float32))
    np.testing.assert_allclose(env.pos[0], [0.2, -0.1, 0.6], atol=0.05)
    env = HoverAviary(act=ActionType.VEL, initial_xyzs=[[0, 0, 0.5]])
    env.reset()
    for _ in range(60):
        env.step(np.array([[1.0, 0.0, 0.0, 1.0]], np.float32))
    assert env.SPEED_LIMIT == pytest.approx(0.25, rel=1e-3)
    assert env.vel[0, 0] == pytest.approx(0.25, abs=0.05)


def test_dsl_pid_control_equals_the_batched_pid():
    """One `computeControl` is `jaxdrones.control.pid.pid_control` on the same state; its memory carries over."""
    ctrl = DSLPIDControl(drone_model=DroneModel.CF2X)
    params = load_params("cf2x")
    pid_state = pid_init((1,))
    rng = np.random.default_rng(0)
    for _ in range(3):
        pos, vel, target = rng.normal(0, 0.3, 3), rng.normal(0, 0.2, 3), rng.normal(0, 0.3, 3) + [0, 0, 1]
        quat = rng.normal(0, 0.1, 4) + [0, 0, 0, 1]
        quat /= np.linalg.norm(quat)
        state20 = np.concatenate([pos, quat, np.zeros(3), vel, np.zeros(3), np.zeros(4)])
        rpm, pos_e, yaw_e = ctrl.computeControlFromState(1 / 48, state20, target, target_rpy=[0, 0, 0.3])
        state = DroneState(
            pos=pos[None],
            quat=quat[None],
            vel=vel[None],
            ang_vel=np.zeros((1, 3)),
            rpm=np.zeros((1, 4)),
            contact=np.zeros(1, np.int32),
        )
        ref, pid_state = pid_control(
            params, PIDGains.dsl(), pid_state, state, target[None], target_rpy=[[0, 0, 0.3]], ctrl_dt=1 / 48
        )
        np.testing.assert_allclose(rpm, np.asarray(ref)[0], rtol=1e-6)
        np.testing.assert_allclose(pos_e, target - pos, rtol=1e-5, atol=1e-6)
    assert ctrl.control_counter == 3 and np.any(ctrl.integral_pos_e != 0)
    ctrl.reset()
    assert ctrl.control_counter == 0 and np.all(ctrl.integral_pos_e == 0)
    np.testing.assert_array_equal(ctrl.MIXER_MATRIX, [[-0.5, -0.5, -1], [-0.5, 0.5, 1], [0.5, 0.5, -1], [0.5, -0.5, 1]])


def test_ctrl_aviary_with_the_pid_flies_a_circle():
    """pid.py's loop, 3 drones for 4 s: each tracks its moving waypoint within a few centimetres."""
    n, r, freq = 3, 0.3, 48
    init = np.array(
        [
            [r * np.cos(i / 6 * 2 * np.pi + np.pi / 2), r * np.sin(i / 6 * 2 * np.pi + np.pi / 2) - r, 0.1 + 0.05 * i]
            for i in range(n)
        ]
    )
    env = CtrlAviary(num_drones=n, initial_xyzs=init, physics=Physics("pyb"), ctrl_freq=freq)
    ctrls = [DSLPIDControl(drone_model=DroneModel.CF2X) for _ in range(n)]
    waypoints = [
        [
            r * np.cos(k / (10 * freq) * 2 * np.pi + np.pi / 2) + init[0, 0],
            r * np.sin(k / (10 * freq) * 2 * np.pi + np.pi / 2) - r + init[0, 1],
        ]
        for k in range(10 * freq)
    ]
    counters = [int(i * 10 * freq / 6) for i in range(n)]
    action, errors = np.zeros((n, 4)), []
    for t in range(4 * freq):
        obs, reward, terminated, truncated, info = env.step(action)
        assert obs.shape == (n, 20) and reward == -1 and not (terminated or truncated) and info == {"answer": 42}
        for j in range(n):
            target = np.hstack([waypoints[counters[j]], init[j, 2]])
            action[j], _, _ = ctrls[j].computeControlFromState(env.CTRL_TIMESTEP, obs[j], target, target_rpy=[0, 0, 0])
            if t > 2 * freq:
                errors.append(np.linalg.norm(obs[j, :3] - target))
            counters[j] = (counters[j] + 1) % (10 * freq)
    assert np.sqrt(np.mean(np.square(errors))) < 0.1
    np.testing.assert_array_equal(env.last_clipped_action, np.clip(env.last_clipped_action, 0, env.MAX_RPM))


def test_physics_members_set_the_aerodynamics():
    for physics, flags in (
        (Physics.PYB, (False, False, False)),
        (Physics.PYB_GND, (False, True, False)),
        (Physics.PYB_GND_DRAG_DW, (True, True, True)),
    ):
        env = CtrlAviary(num_drones=2, physics=physics)
        assert (env._config.drag, env._config.ground_effect, env._config.downwash) == flags


def test_mistyped_keywords_get_a_hint():
    with pytest.raises(
        TypeError,
        match=r"HoverAviary\(\) got an unexpected keyword argument 'ctrl_fre' \(did you "
        r"mean 'ctrl_freq'\?\)",
    ):
        HoverAviary(ctrl_fre=30)
    with pytest.raises(TypeError, match=r"did you mean 'num_drones'"):
        MultiHoverAviary(num_drone=2)
    with pytest.raises(TypeError, match=r"did you mean 'drone_model'"):
        DSLPIDControl(drone_modle=DroneModel.CF2X)
    with pytest.raises(ValueError, match=r"initial_xyzs must be f\[2, 3\]"):
        CtrlAviary(num_drones=2, initial_xyzs=[[0, 0, 1]])
    with pytest.raises(ValueError, match="pyb_freq .* multiple of ctrl_freq"):
        HoverAviary(ctrl_freq=70)
    with pytest.raises(ValueError, match="KIN only"):
        HoverAviary(obs=ObservationType.RGB)
    with pytest.raises(ValueError, match=r"action must be f\[1, 1\]"):
        env = HoverAviary(act=ActionType.ONE_D_RPM)
        env.reset()
        env.step(np.zeros(4))
    assert str2bool("Yes") and not str2bool("0")


def test_logger_saves_without_overwriting(tmp_path):
    logger = Logger(logging_freq_hz=48, output_folder=str(tmp_path), num_drones=2)
    for k in range(5):
        for d in range(2):
            logger.log(drone=d, timestamp=k / 48, state=np.arange(20) + d, control=np.zeros(12))
    assert logger.states.shape == (2, 16, 5) and logger.timestamps.shape == (2, 5)
    np.testing.assert_array_equal(logger.states[1, :, 0], np.r_[0:3, 10:13, 7:10, 13:20] + 1)
    first, second = logger.save(), logger.save()
    assert first != second and os.path.exists(first) and os.path.exists(second)
    with np.load(first) as data:
        np.testing.assert_array_equal(data["states"], logger.states)
    folder = logger.save_as_csv("pid")
    table = np.loadtxt(os.path.join(folder, "drone0.csv"), delimiter=",", skiprows=1)
    assert table.shape == (5, 17)
    assert logger.plot().endswith(".png")  # headless (Agg): saved rather than shown
    with pytest.raises(ValueError, match="Logger.log"):
        logger.log(drone=2, timestamp=0.0, state=np.zeros(20))


def test_jax_backend_prints_no_pybullet_banner():
    """Building and stepping the JAX envs (the functional one and the compat aviaries) imports no PyBullet, so its
    "pybullet build time" banner never shows."""
    code = (
        "import jax, numpy as np, jaxdrones as jd\n"
        "env = jd.make('hover'); s = env.reset(jax.random.key(0)); env.step(s, np.zeros((1, 4)))\n"
        "from jaxdrones.compat.gym_pybullet_drones import HoverAviary, CtrlAviary\n"
        "e = HoverAviary(); e.reset(); e.step(np.zeros((1, 4))); CtrlAviary().step(np.zeros((1, 4)))\n"
        "import sys; print('pybullet' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert out.returncode == 0, out.stderr
    assert "pybullet build time" not in out.stdout + out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False"


def test_gymnasium_ids_of_the_original():
    import gymnasium as gym

    env = gym.make("hover-aviary-v0", act=ActionType.ONE_D_RPM)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (1, 27)
    assert env.step(np.zeros((1, 1), np.float32))[0].shape == (1, 27)


def test_an_aviary_subclassed_as_for_the_original_runs():
    """A user's aviary written against the original's hooks: its reward and truncation read
    `_getDroneStateVector`, as the original's do."""
    from jaxdrones.compat.gym_pybullet_drones.envs.BaseRLAviary import BaseRLAviary

    class LandAviary(BaseRLAviary):
        def __init__(self, **kwargs):
            self.EPISODE_LEN_SEC = 1
            super().__init__(initial_xyzs=np.array([[0.0, 0.0, 0.5]]), ctrl_freq=30, **kwargs)

        def _computeReward(self):
            return -float(self._getDroneStateVector(0)[2])

        def _computeTerminated(self):
            return bool(self._getDroneStateVector(0)[2] < 0.05)

        def _computeTruncated(self):
            return self.step_counter / self.PYB_FREQ > self.EPISODE_LEN_SEC

        def _computeInfo(self):
            return {"z": float(self.pos[0, 2])}

    env = LandAviary(act=ActionType.ONE_D_RPM)
    obs, info = env.reset()
    assert obs.shape == (1, 27) and info == {"z": 0.5}
    _, reward, _, _, info = env.step(np.array([[-1.0]], np.float32))  # 95 % of the hover RPM: it sinks
    assert reward == -info["z"] and info["z"] < 0.5

    class Incomplete(BaseRLAviary):  # no reward, termination, truncation or info
        pass

    with pytest.raises(TypeError, match="abstract method"):
        Incomplete()


def test_float64_with_x64():
    code = (
        "import jax; jax.config.update('jax_enable_x64', True)\n"
        "import numpy as np\n"
        "from jaxdrones.compat.gym_pybullet_drones import CtrlAviary, DSLPIDControl\n"
        "env = CtrlAviary(); obs, _ = env.reset(); ctrl = DSLPIDControl()\n"
        "rpm, _, _ = ctrl.computeControlFromState(env.CTRL_TIMESTEP, obs[0], [0, 0, 0.5])\n"
        "obs, *_ = env.step(rpm[None]); print(env._state.pos.dtype, obs.dtype)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["float64", "float64"]


@pytest.mark.pybullet
def test_pybullet_backend():
    """``backend="pybullet"``: PyBullet's integrator under the same aviary; a PID climb ends where the JAX core's
    does, to a centimetre."""
    finals = {}
    for backend in ("jax", "pybullet"):
        env = CtrlAviary(num_drones=2, ctrl_freq=48, backend=backend)
        obs, _ = env.reset()
        ctrls = [DSLPIDControl() for _ in range(2)]
        action = np.zeros((2, 4))
        for _ in range(96):
            obs, *_ = env.step(action)
            for j in range(2):
                action[j], _, _ = ctrls[j].computeControlFromState(
                    env.CTRL_TIMESTEP, obs[j], env.INIT_XYZS[j] + [0, 0, 0.4]
                )
        finals[backend] = obs[:, :3]
        assert (env.getPyBulletClient() >= 0) == (backend == "pybullet")
        env.close()
    np.testing.assert_allclose(finals["pybullet"], finals["jax"], atol=0.01)
