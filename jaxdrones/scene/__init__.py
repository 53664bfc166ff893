"""World geometry shared by both backends, with no pybullet import: the static obstacles (`Obstacle`, `obstacles`) and
the primitives the JAX cameras see (`primitives`)."""

from jaxdrones.scene.obstacles import PAPER_OBSTACLES, Obstacle, resolve_obstacles, urdf_path

__all__ = ["PAPER_OBSTACLES", "Obstacle", "resolve_obstacles", "urdf_path"]
