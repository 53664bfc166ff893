"""Static obstacles, as both backends take them: primitive shapes and URDF files (no pybullet import).

The PyBullet backend builds Bullet bodies from them (`jaxdrones.backends.scene.load_obstacle`), the JAX cameras
draw the primitive shapes (`jaxdrones.cameras.make_scene`), and the envs take them as ``obstacles``.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
from collections.abc import Sequence

import numpy as np


@dataclasses.dataclass(frozen=True)
class Obstacle:
    """A static obstacle: a primitive shape, or a URDF file.

    Obstacles are fixed in the world (they do not move when hit), so a world's state is fully carried by the
    drones' `DroneState`.

    Attributes:
        shape: ``"box"``, ``"sphere"``, ``"cylinder"``, ``"capsule"`` or ``"urdf"``.
        size: box: full extents (x, y, z) m; sphere: (radius,); cylinder: (radius, length) m; capsule: (radius,
            length of the axis segment between the centres of its hemispherical ends) m, as Bullet's capsule. The
            cylinder's and capsule's axis is their local z.
        pos: (x, y, z) m, world frame, of the shape's centre (box, sphere, cylinder) or the URDF's base.
        rpy: (roll, pitch, yaw) rad.
        urdf: for ``shape="urdf"``: a file path, or a file name in ``pybullet_data`` (e.g. ``"duck_vhacd.urdf"``).
        scale: uniform scale of a URDF.
        rgba: colour of a primitive shape.

    Raises:
        ValueError: on an unknown shape, a size of the wrong length or not positive, or a URDF not found (a file
            name of ``pybullet_data`` is checked here where pybullet is installed, else when Bullet loads it).
    """

    shape: str = "box"
    size: tuple[float, ...] = (0.2, 0.2, 0.2)
    pos: tuple[float, float, float] = (0.0, 0.0, 0.1)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    urdf: str | None = None
    scale: float = 1.0
    rgba: tuple[float, float, float, float] = (0.8, 0.3, 0.2, 1.0)

    def __post_init__(self):
        n_size = {"box": 3, "sphere": 1, "cylinder": 2, "capsule": 2, "urdf": None}
        if self.shape not in n_size:
            raise ValueError(f"Obstacle.shape must be one of {tuple(n_size)}, got {self.shape!r}")
        if self.shape == "urdf":
            if self.urdf is None:
                raise ValueError("Obstacle(shape='urdf') needs urdf=<path or pybullet_data file name>")
            if _pybullet_data_dir() is not None or os.path.isfile(self.urdf):
                urdf_path(self.urdf)  # without pybullet, a pybullet_data name is checked when Bullet loads it
        elif len(self.size) != n_size[self.shape] or min(self.size) <= 0:
            raise ValueError(
                f"Obstacle {self.shape}: size must be {n_size[self.shape]} positive numbers (m), got {self.size}"
            )
        if len(self.pos) != 3 or len(self.rpy) != 3:
            raise ValueError(f"Obstacle: pos and rpy must have 3 values, got {self.pos} and {self.rpy}")
        if not self.scale > 0:
            raise ValueError(f"Obstacle: scale must be positive, got {self.scale}")


def urdf_path(name: str | os.PathLike) -> str:
    """Resolve an obstacle URDF: an existing path, or a file name in ``pybullet_data`` (installed with pybullet).

    Raises:
        ValueError: if neither exists.
    """
    name = os.fspath(name)
    data = _pybullet_data_dir()
    for candidate in (name, *([os.path.join(data, name)] if data else [])):
        if os.path.isfile(candidate):
            return candidate
    where = "" if data else "; pybullet_data's files need pybullet, which is not installed"
    raise ValueError(
        f"obstacle URDF {name!r} not found (give a path, or a file of pybullet_data such as 'duck_vhacd.urdf'{where})"
    )


def _pybullet_data_dir() -> str | None:
    """The folder of ``pybullet_data`` (installed with pybullet), or None without pybullet."""
    spec = importlib.util.find_spec("pybullet_data")
    return os.path.dirname(spec.origin) if spec is not None and spec.origin else None


#: The obstacle scene of the examples, modelled on the paper's (a few boxes, a sphere and a duck mesh): placed
#: around, not on, the circle flown by `jaxdrones fly` (centre (0, -0.3), radius 0.3 m).
PAPER_OBSTACLES = (
    Obstacle("box", size=(0.15, 0.15, 0.6), pos=(0.7, -0.3, 0.3), rgba=(0.8, 0.3, 0.2, 1.0)),
    Obstacle("box", size=(0.2, 0.2, 0.2), pos=(-0.4, 0.4, 0.1), rgba=(0.2, 0.5, 0.8, 1.0)),
    Obstacle("sphere", size=(0.12,), pos=(-0.75, -0.4, 0.12), rgba=(0.3, 0.7, 0.3, 1.0)),
    Obstacle("urdf", urdf="duck_vhacd.urdf", pos=(0.3, 0.45, 0.0), rpy=(np.pi / 2, 0.0, np.pi), scale=3.0),
)


def resolve_obstacles(
    obstacles: bool | str | os.PathLike | Obstacle | Sequence[Obstacle | str | os.PathLike] | None,
) -> tuple[Obstacle, ...]:
    """Normalise the ``obstacles`` argument of the PyBullet backend.

    Args:
        obstacles: ``None``/``False`` (none), ``True`` or ``"paper"`` (`PAPER_OBSTACLES`), or a sequence of
            `Obstacle`s and URDF paths (a path is loaded at the origin).

    Raises:
        ValueError: on anything else, or a URDF that does not exist.
    """
    if obstacles is None or obstacles is False:
        return ()
    if obstacles is True or (isinstance(obstacles, str) and obstacles == "paper"):
        return PAPER_OBSTACLES
    if isinstance(obstacles, (str, os.PathLike, Obstacle)):
        obstacles = [obstacles]
    out = []
    for item in obstacles:
        if isinstance(item, Obstacle):
            out.append(item)
        elif isinstance(item, (str, os.PathLike)):
            out.append(Obstacle("urdf", urdf=os.fspath(item), pos=(0.0, 0.0, 0.0)))
        else:
            raise ValueError(
                f"obstacles: expected None, True, 'paper', or a sequence of Obstacle or URDF paths; "
                f"got an item {item!r}"
            )
    return tuple(out)
