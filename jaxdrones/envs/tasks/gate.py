"""``fly_thru_gate`` with ``gate_pose="random"``: fly through the paper's gate, drawn per episode ahead of the drone
and seen only through its camera.

The paper's FlyThruGateAviary puts its gate at a fixed place and rewards following a reference through it, so a
policy needs no camera. Here the gate's pose (distance, offset across and yaw) is drawn per episode and is in no
part of the observation, which is the drone's kinematic state alone: the policy finds the gate in its images.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs import terminations
from jaxdrones.envs.tasks.avoid import GoalTask, collided, progress
from jaxdrones.envs.tasks.single import GATE_OPENING_HALF_X, GATE_OPENING_TOP, GATE_PARTS, GateConfig
from jaxdrones.physics.state import DroneState

#: The start's height, m: the opening's mid height (the drone starts at the origin facing +x, towards the gate).
START_Z = 0.25
#: Where the progress reward pulls, in the gate's frame: 0.5 m beyond the opening's centre, at its mid height.
AIM = (0.0, -0.5, 0.25)


class GatePass(GoalTask):
    """Fly through the paper's gate (its two columns and architrave, `GATE_PARTS`), drawn per episode: its centre
    ``gate_distance`` m ahead along +x, within ±``gate_offset`` m across (y), facing the start (its frame's −y
    along +x) yawed within ±``gate_yaw`` rad.

    Starts at (0, 0, 0.25) m within ±0.1 m across, level, facing +x. The observation is the kinematic state only
    (``obs_size`` 0): the gate is in `TaskParams.scene` (the cameras draw it) and nowhere else. The episode ends at
    its goal (`reached`) when the drone crosses the gate's plane inside the opening (|x| < 0.275 m, z < 0.525 m in
    the gate's frame) without touching it; it terminates on a collision with the gate (the drone's centre within its
    collision radius of a box, `jaxdrones.cameras.distance`), on crossing the plane outside the opening (missed),
    touching the ground or leaving the arena.

    Reward (both ``reward`` settings): ``progress``, the velocity towards a point 0.5 m beyond the opening's centre
    (m/s), weight 1; ``reached``, 1 on passing, weight 10; ``crash``, 1 on any termination but passing, weight −50.
    Success metric: ``failure``, 0 when the episode ends through the opening, else 1; solved when at most 10 % of the
    evaluation episodes fail (``success_rate`` ≥ 0.9).
    """

    name = "fly_thru_gate"
    config_cls = GateConfig
    obs_size = 0

    def check(self, config):
        super().check(config)
        if not config.vision:
            raise ValueError("fly_thru_gate with gate_pose='random' sees the gate only through its camera: set "
                             "vision, e.g. vision=('depth',)")

    def obs_bound(self, config):
        return np.zeros(0, np.float32)

    def start_defaults(self, config):
        return dict(pos=[[0.0, 0.0, START_Z]], pos_range=(0.0, 0.1, 0.0), tilt=0.0, yaw=0.0, vel=0.0, ang_vel=0.0)

    def target(self, config):
        return np.array([[config.gate_distance[0] - AIM[1], AIM[0], AIM[2]]])

    def data(self, config):
        return {**super().data(config), "gate_pos": np.zeros(3), "gate_rot": np.eye(3)}

    def scene(self, config):
        from jaxdrones.cameras import make_scene

        return make_scene((), capacity={"box": len(GATE_PARTS)})

    def sample(self, config, task, key):
        u = jax.random.uniform(key, (3,), task.target.dtype)
        lo, hi = config.gate_distance
        centre = jnp.stack([lo + (hi - lo) * u[1], config.gate_offset * (2 * u[0] - 1), jnp.zeros_like(u[0])])
        yaw = math.pi / 2 + config.gate_yaw * (2 * u[2] - 1)  # the gate's −y along +x: it faces the start
        c, s, zero, one = jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw), jnp.ones_like(yaw)
        rot = jnp.stack([jnp.stack([c, -s, zero]), jnp.stack([s, c, zero]), jnp.stack([zero, zero, one])])
        local = jnp.asarray([p for p, _ in GATE_PARTS], centre.dtype)
        half = jnp.asarray([size for _, size in GATE_PARTS], centre.dtype) / 2
        box = task.scene.box.replace(
            pos=centre + local @ rot.T, rot=jnp.broadcast_to(rot, (len(GATE_PARTS), 3, 3)), size=half,
            seg=1 + jnp.arange(len(GATE_PARTS), dtype=jnp.int32), valid=jnp.ones(len(GATE_PARTS), bool),
            rgb=jnp.full((len(GATE_PARTS), 3), 0.6, centre.dtype))
        aim = centre + rot @ jnp.asarray(AIM, centre.dtype)
        return task.replace(target=jnp.broadcast_to(aim, task.target.shape), scene=task.scene.replace(box=box),
                            data={**task.data, "gate_pos": centre, "gate_rot": rot})

    def observe(self, config, task, sim, steps):
        return jnp.zeros(sim.pos.shape[:-1] + (0,), sim.pos.dtype)

    def reward_terms(self, config, task, sim, action, steps):
        dtype = sim.pos.dtype
        return {"progress": progress(sim, task.target), "reached": _through(task, sim).astype(dtype),
                "crash": self._failed(config, task, sim).astype(dtype)}

    def terminated(self, config, task, sim):
        return jnp.any(self._failed(config, task, sim))

    def reached(self, config, task, sim):
        return jnp.all(_through(task, sim)) & ~self.terminated(config, task, sim)

    def metrics(self, config, task, sim, steps):
        hit = jnp.any(collided(task, sim))
        passed = self.reached(config, task, sim)
        dtype = sim.pos.dtype
        return {"collision": hit.astype(dtype), "missed": jnp.any(_missed(task, sim)).astype(dtype),
                "failure": (~passed).astype(dtype)}

    @staticmethod
    def _failed(config, task, sim: DroneState) -> jax.Array:
        """bool[D]: a collision with the gate, a miss, the ground (whatever ``terminate_on_ground``: the opening is
        0.5 m tall) or out of the arena."""
        lost = terminations.crashed(sim, task.bounds, True)
        return collided(task, sim) | _missed(task, sim) | lost


def _in_gate_frame(task, sim: DroneState) -> jax.Array:
    """f[D, 3]: the drones' positions in the gate's frame (x along the architrave, y across, z up)."""
    return (sim.pos - task.data["gate_pos"]) @ task.data["gate_rot"]


def _crossed(task, sim: DroneState) -> tuple[jax.Array, jax.Array]:
    """bool[D] twice: beyond the gate's plane (the start is on its +y side), and within the opening."""
    local = _in_gate_frame(task, sim)
    inside = (jnp.abs(local[..., 0]) < GATE_OPENING_HALF_X) & (local[..., 2] < GATE_OPENING_TOP)
    return local[..., 1] < 0, inside


def _through(task, sim: DroneState) -> jax.Array:
    beyond, inside = _crossed(task, sim)
    return beyond & inside


def _missed(task, sim: DroneState) -> jax.Array:
    beyond, inside = _crossed(task, sim)
    return beyond & ~inside


GATE_PASS = GatePass()
