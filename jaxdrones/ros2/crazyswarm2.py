"""A physics backend of crazyswarm2's simulator (``crazyflie_sim``) on the JAX core, so that a crazyswarm2 stack
(its server, the firmware's controllers in the loop, its ``takeoff``/``go_to`` services) flies on jaxdrones' physics.

crazyflie_sim loads a backend by name from its own package (``crazyflie_sim/crazyflie_server.py``:
``importlib.import_module('.backend.' + name, package='crazyflie_sim')``, then ``Backend(node, names, states)``), and
at every tick calls ``step(states_desired, actions) -> list[State]`` with one ``Action`` (``rpm``, 4 motor RPM in the
firmware's motor order, which is the cf2x order of docs/physics.md §2) per drone; ``time()`` is the simulated time;
``shutdown()`` releases the backend. Its ``State`` holds ``pos`` and ``vel`` (m, m/s, world), ``quat`` (w, x, y, z,
rowan's order) and ``omega`` (rad/s, body).

To use it, put a one-line module in crazyflie_sim's backend folder and select it in ``crazyflies.yaml``::

    # <crazyswarm2>/crazyflie_sim/crazyflie_sim/backend/jaxdrones.py
    from jaxdrones.ros2.crazyswarm2 import Backend  # noqa: F401

    # crazyflie/config/crazyflies.yaml:  sim: {backend: jaxdrones, ...}
    ros2 launch crazyflie launch.py backend:=sim

Each ``step`` advances one physics step of ``1 / sim_freq`` s (default 500 Hz, the firmware's control rate) for all
drones in one jitted call, and publishes the simulated time on ``/clock`` as crazyflie_sim's own backends do. The
drones are cf2x (gym-pybullet-drones' Crazyflie 2.x, 27 g); crazyflie_sim's own ``np`` backend models a 34 g
Crazyflie 2.0. Not integration-tested here (crazyswarm2 is not on PyPI): tests/test_ros2.py checks it against the
interface above with a stand-in node, and, where rclpy is installed, with a real node.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxdrones.physics.params import load_params
from jaxdrones.physics.state import init_state
from jaxdrones.ros2 import messages
from jaxdrones.sim import SimConfig, make_step

__all__ = ["Backend"]


def _wxyz_to_xyzw(q) -> np.ndarray:
    q = np.asarray(q, np.float64)
    return np.array([q[1], q[2], q[3], q[0]])


class Backend:
    """crazyflie_sim's backend interface on the JAX core (see the module docstring).

    Args:
        node: the crazyflie_sim server's ``rclpy`` node (``create_publisher`` is used for ``/clock``).
        names: the drones' names.
        states: their initial ``State`` (crazyflie_sim's ``sim_data_types.State``; ``pos``, and ``vel``, ``quat``,
            ``omega`` where given).
        model: the airframe (`jaxdrones.physics.params.load_params`), default ``"cf2x"``.
        sim_freq: physics rate, Hz (one ``step`` is one physics step).
        drag, ground_effect, downwash: the aerodynamic effects (`jaxdrones.sim.SimConfig`); ground effect on by
            default (crazyflies take off from the ground).
        clock_type: the ``Clock`` message class (default ``rosgraph_msgs.msg.Clock``).

    Raises:
        ValueError: ``names`` and ``states`` of different lengths or empty, a state without a finite 3-vector
            position, or a bad rate or model.
    """

    def __init__(
        self,
        node: Any,
        names: Sequence[str],
        states: Sequence[Any],
        *,
        model: str = "cf2x",
        sim_freq: int = 500,
        drag: bool = False,
        ground_effect: bool = True,
        downwash: bool | str = False,
        clock_type: Any = None,
    ):
        if len(names) != len(states) or not names:
            raise ValueError(
                f"expected one initial state per drone name, got {len(names)} names and {len(states)} states"
            )
        self.node, self.names = node, list(names)
        self._state_type = type(states[0])
        self.config = SimConfig(
            n_drones=len(names),
            sim_freq=sim_freq,
            ctrl_freq=sim_freq,
            drag=drag,
            ground_effect=ground_effect,
            downwash=downwash,
        )
        self.dt = 1.0 / sim_freq
        self.params = load_params(model)
        self._step = make_step(self.config)
        pos = np.stack([self._vector(s, "pos", 3) for s in states])
        vel = np.stack([self._vector(s, "vel", 3, np.zeros(3)) for s in states])
        quat = np.stack([_wxyz_to_xyzw(self._vector(s, "quat", 4, np.array([1.0, 0, 0, 0]))) for s in states])
        omega = np.stack([self._vector(s, "omega", 3, np.zeros(3)) for s in states])
        self.state = init_state(self.config, pos=pos, quat=quat, vel=vel, ang_vel=omega)
        self.t = 0.0
        if clock_type is None:
            from rosgraph_msgs.msg import Clock as clock_type
        self._clock_type = clock_type
        self.clock_publisher = node.create_publisher(clock_type, "clock", 10)

    @staticmethod
    def _vector(state, name: str, size: int, default=None) -> np.ndarray:
        value = getattr(state, name, None)
        if value is None:
            if default is None:
                raise ValueError(f"an initial state needs {name!r}")
            return default
        value = np.asarray(value, np.float64).ravel()
        if value.shape != (size,) or not np.all(np.isfinite(value)):
            raise ValueError(f"an initial state's {name} must be {size} finite numbers, got {value}")
        return value

    def time(self) -> float:
        """The simulated time, s."""
        return self.t

    def step(self, states_desired: Sequence[Any], actions: Sequence[Any]) -> list:
        """Advance one physics step with each drone's ``action.rpm`` (4 RPM, clipped to [0, max_rpm]); returns the
        drones' new ``State`` (of the type given at construction) and publishes ``/clock``."""
        rpm = np.asarray([np.asarray(a.rpm, np.float64).ravel() for a in actions])
        if rpm.shape != (len(self.names), 4):
            raise ValueError(f"expected one action of 4 RPM per drone ({len(self.names)}), got shape {rpm.shape}")
        self.state = self._step(self.params, self.state, jnp.asarray(rpm, self.state.pos.dtype))
        self.t += self.dt
        self.clock_publisher.publish(messages.fill_rclpy(self._clock_type(), messages.clock_fields(self.t)))
        pos, vel, quat, omega = (
            np.asarray(getattr(self.state, k), np.float64) for k in ("pos", "vel", "quat", "ang_vel")
        )
        return [
            self._state_type(pos=pos[i], vel=vel[i], quat=np.r_[quat[i, 3], quat[i, :3]], omega=omega[i])
            for i in range(len(self.names))
        ]

    def shutdown(self) -> None:
        """Nothing to release (the JAX core holds no resources)."""
