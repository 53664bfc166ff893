"""ROS 2 interfaces (optional extra ``[ros2]``): the paper's node (`jaxdrones.ros2.node`, ``jaxdrones ros2 TASK``)
and a crazyswarm2 physics backend (`jaxdrones.ros2.crazyswarm2`).

The paper (§III-F) ships "a minimalist wrapper ... using a ROS2 Python node" that "continuously steps an environment
while (i) publishing its observations on a topic and (ii) reading actions from a separate topic". The message
conversion (`jaxdrones.ros2.messages`) needs no ROS; the nodes need ``rclpy`` and the message packages, which the
``ros2`` extra installs from the unofficial wheels of ROS 2 Kilted on PyPI
(``pip install "jaxdrones[ros2]"``; ``rclpy`` 9.1.2 with Fast DDS, ``std_msgs``, ``geometry_msgs``, ``nav_msgs``,
``rosgraph_msgs``). Their install adds a ``.pth`` file that runs at every Python start in that environment: keep
them in an environment of their own.
"""

from __future__ import annotations

from types import ModuleType

__all__ = ["require_rclpy"]


def require_rclpy() -> ModuleType:
    """The ``rclpy`` module, or a ModuleNotFoundError naming the extra to install."""
    try:
        import rclpy
    except ModuleNotFoundError as error:
        raise ModuleNotFoundError(
            "the ROS 2 interfaces need rclpy and the ROS 2 message packages, which are not installed: "
            "pip install 'jaxdrones[ros2]' (or source a ROS 2 installation)"
        ) from error
    return rclpy
