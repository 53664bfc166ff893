"""What a PyBullet world holds: the ground plane, obstacles and the drone bodies built from `DroneParams`.

The drone bodies are built from the params (not re-read from a URDF), so that both backends use the very same
mass, inertia, propeller and collision geometry, including params batched per world or per drone.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pybullet
import pybullet_data

# The drones' visual shape (a plate and four propeller disks), shared with the JAX cameras.
from jaxdrones.cameras import BODY_RGBA, BODY_SIDE_PER_ARM, BODY_THICKNESS, PROP_RGBA, PROP_THICKNESS, PROP_Z


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
        ValueError: on an unknown shape, a size of the wrong length or not positive, or a URDF not found.
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
            urdf_path(self.urdf)
        elif len(self.size) != n_size[self.shape] or min(self.size) <= 0:
            raise ValueError(f"Obstacle {self.shape}: size must be {n_size[self.shape]} positive numbers (m), "
                             f"got {self.size}")
        if len(self.pos) != 3 or len(self.rpy) != 3:
            raise ValueError(f"Obstacle: pos and rpy must have 3 values, got {self.pos} and {self.rpy}")
        if not self.scale > 0:
            raise ValueError(f"Obstacle: scale must be positive, got {self.scale}")


def urdf_path(name: str | os.PathLike) -> str:
    """Resolve an obstacle URDF: an existing path, or a file name in ``pybullet_data``.

    Raises:
        ValueError: if neither exists.
    """
    name = os.fspath(name)
    for candidate in (name, os.path.join(pybullet_data.getDataPath(), name)):
        if os.path.isfile(candidate):
            return candidate
    raise ValueError(f"obstacle URDF {name!r} not found (give a path, or a file of pybullet_data such as "
                     f"'duck_vhacd.urdf')")


#: The obstacle scene of the examples, modelled on the paper's (a few boxes, a sphere and a duck mesh): placed
#: around, not on, the circle flown by `jaxdrones fly` (centre (0, -0.3), radius 0.3 m).
PAPER_OBSTACLES = (
    Obstacle("box", size=(0.15, 0.15, 0.6), pos=(0.7, -0.3, 0.3), rgba=(0.8, 0.3, 0.2, 1.0)),
    Obstacle("box", size=(0.2, 0.2, 0.2), pos=(-0.4, 0.4, 0.1), rgba=(0.2, 0.5, 0.8, 1.0)),
    Obstacle("sphere", size=(0.12,), pos=(-0.75, -0.4, 0.12), rgba=(0.3, 0.7, 0.3, 1.0)),
    Obstacle("urdf", urdf="duck_vhacd.urdf", pos=(0.3, 0.45, 0.0), rpy=(np.pi / 2, 0.0, np.pi), scale=3.0),
)


def resolve_obstacles(obstacles) -> tuple[Obstacle, ...]:
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
            raise ValueError(f"obstacles: expected None, True, 'paper', or a sequence of Obstacle or URDF paths; "
                             f"got an item {item!r}")
    return tuple(out)


def load_ground(client: int) -> int:
    """Load ``pybullet_data``'s plane (top at z = 0) and return its body id."""
    return pybullet.loadURDF(os.path.join(pybullet_data.getDataPath(), "plane.urdf"), physicsClientId=client)


def load_obstacle(client: int, obstacle: Obstacle) -> int:
    """Create one fixed obstacle in a Bullet world and return its body id."""
    quat = pybullet.getQuaternionFromEuler(obstacle.rpy)
    if obstacle.shape == "urdf":
        return pybullet.loadURDF(urdf_path(obstacle.urdf), obstacle.pos, quat, useFixedBase=True,
                                 globalScaling=obstacle.scale, physicsClientId=client)
    if obstacle.shape == "box":
        kwargs = {"halfExtents": [s / 2 for s in obstacle.size]}
        geom = pybullet.GEOM_BOX
    elif obstacle.shape == "sphere":
        kwargs = {"radius": obstacle.size[0]}
        geom = pybullet.GEOM_SPHERE
    else:
        kwargs = {"radius": obstacle.size[0]}
        geom = pybullet.GEOM_CYLINDER if obstacle.shape == "cylinder" else pybullet.GEOM_CAPSULE
    axial = geom in (pybullet.GEOM_CYLINDER, pybullet.GEOM_CAPSULE)
    col = pybullet.createCollisionShape(geom, **kwargs, **({"height": obstacle.size[1]} if axial else {}),
                                        physicsClientId=client)
    vis = pybullet.createVisualShape(geom, **kwargs, **({"length": obstacle.size[1]} if axial else {}),
                                     rgbaColor=obstacle.rgba, physicsClientId=client)
    return pybullet.createMultiBody(0.0, col, vis, obstacle.pos, quat, physicsClientId=client)


def drone_geometry(params: dict) -> dict:
    """The Bullet-body description of one drone from its (NumPy, unbatched) params.

    Returns a dict of mass (kg), inertia diagonal (kg·m²), collision radius and length (m), the arm (m), the
    propeller positions and radius (m): everything a body is built from, to compare with a world's bodies.

    Raises:
        ValueError: if the inertia is not diagonal (Bullet takes principal moments along the body axes).
    """
    inertia = np.asarray(params["inertia"], dtype=np.float64)
    if np.any(np.abs(inertia - np.diag(np.diag(inertia))) > 1e-12 * np.max(np.abs(inertia))):
        raise ValueError(f"the PyBullet backend needs a diagonal inertia (principal axes along the body axes), "
                         f"got {inertia.tolist()}")
    return {
        "mass": float(params["mass"]), "inertia": tuple(np.diag(inertia).tolist()),
        "collision_radius": float(params["collision_radius"]), "collision_height": float(params["collision_height"]),
        "arm": float(params["arm"]), "prop_pos": tuple(map(tuple, np.asarray(params["prop_pos"]).tolist())),
        "prop_radius": float(params["prop_radius"]),
    }


def create_drone(client: int, geometry: dict, damping: bool) -> int:
    """Create a drone body (`drone_geometry`) at the origin and return its id.

    The collision shape is the params' cylinder (centred on the base origin, covering the propellers); the visual
    shape is a plate with four propeller disks. The base's centre of mass is its origin, as in the URDFs. Bullet's
    velocity damping (0.04 linear and angular, docs/physics.md §5.2) is removed unless ``damping``; sleeping is
    disabled, so a drone resting on the ground responds to thrust at once.
    """
    col = pybullet.createCollisionShape(pybullet.GEOM_CYLINDER, radius=geometry["collision_radius"],
                                        height=geometry["collision_height"], physicsClientId=client)
    side = BODY_SIDE_PER_ARM * geometry["arm"]
    props = [(x, y, z + PROP_Z) for x, y, z in geometry["prop_pos"]]
    vis = pybullet.createVisualShapeArray(
        shapeTypes=[pybullet.GEOM_BOX] + [pybullet.GEOM_CYLINDER] * 4,
        halfExtents=[[side / 2, side / 2, BODY_THICKNESS / 2]] + [[0, 0, 0]] * 4,
        radii=[0.0] + [geometry["prop_radius"]] * 4,
        lengths=[0.0] + [PROP_THICKNESS] * 4,
        rgbaColors=[BODY_RGBA] + [PROP_RGBA] * 4,
        visualFramePositions=[[0.0, 0.0, 0.0]] + props,
        physicsClientId=client)
    body = pybullet.createMultiBody(geometry["mass"], col, vis, physicsClientId=client)
    set_drone_dynamics(client, body, geometry, damping)
    return body


def set_drone_dynamics(client: int, body: int, geometry: dict, damping: bool) -> None:
    """Set a drone body's mass, inertia, damping and sleeping (see `create_drone`)."""
    extra = {} if damping else {"linearDamping": 0.0, "angularDamping": 0.0}
    pybullet.changeDynamics(body, -1, mass=geometry["mass"], localInertiaDiagonal=geometry["inertia"],
                            activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING, **extra,
                            physicsClientId=client)
