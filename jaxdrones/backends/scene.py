"""What a PyBullet world holds: the ground plane, obstacles and the drone bodies built from `DroneParams`.

The drone bodies are built from the params (not re-read from a URDF), so that both backends use the very same
mass, inertia, propeller and collision geometry, including params batched per world or per drone.
"""

from __future__ import annotations

import os

import numpy as np

from jaxdrones.backends import require_pybullet

# The obstacles are backend-neutral (jaxdrones.scene), re-exported for `from jaxdrones.backends.scene import Obstacle`.
from jaxdrones.scene.obstacles import PAPER_OBSTACLES, Obstacle, resolve_obstacles, urdf_path  # noqa: F401

# The drones' visual shape (a plate and four propeller disks), shared with the JAX cameras.
from jaxdrones.scene.primitives import BODY_RGBA, BODY_SIDE_PER_ARM, BODY_THICKNESS, PROP_RGBA, PROP_THICKNESS, PROP_Z

pybullet = require_pybullet()
import pybullet_data  # noqa: E402  (installed with pybullet)


def load_ground(client: int) -> int:
    """Load ``pybullet_data``'s plane (top at z = 0) and return its body id."""
    return pybullet.loadURDF(os.path.join(pybullet_data.getDataPath(), "plane.urdf"), physicsClientId=client)


def load_obstacle(client: int, obstacle: Obstacle) -> int:
    """Create one fixed obstacle in a Bullet world and return its body id."""
    quat = pybullet.getQuaternionFromEuler(obstacle.rpy)
    if obstacle.shape == "urdf":
        return pybullet.loadURDF(
            urdf_path(obstacle.urdf),
            obstacle.pos,
            quat,
            useFixedBase=True,
            globalScaling=obstacle.scale,
            physicsClientId=client,
        )
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
    col = pybullet.createCollisionShape(
        geom, **kwargs, **({"height": obstacle.size[1]} if axial else {}), physicsClientId=client
    )
    vis = pybullet.createVisualShape(
        geom,
        **kwargs,
        **({"length": obstacle.size[1]} if axial else {}),
        rgbaColor=obstacle.rgba,
        physicsClientId=client,
    )
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
        raise ValueError(
            f"the PyBullet backend needs a diagonal inertia (principal axes along the body axes), "
            f"got {inertia.tolist()}"
        )
    return {
        "mass": float(params["mass"]),
        "inertia": tuple(np.diag(inertia).tolist()),
        "collision_radius": float(params["collision_radius"]),
        "collision_height": float(params["collision_height"]),
        "arm": float(params["arm"]),
        "prop_pos": tuple(map(tuple, np.asarray(params["prop_pos"]).tolist())),
        "prop_radius": float(params["prop_radius"]),
    }


def create_drone(client: int, geometry: dict, damping: bool) -> int:
    """Create a drone body (`drone_geometry`) at the origin and return its id.

    The collision shape is the params' cylinder (centred on the base origin, covering the propellers); the visual
    shape is a plate with four propeller disks. The base's centre of mass is its origin, as in the URDFs. Bullet's
    velocity damping (0.04 linear and angular, docs/physics.md §5.2) is removed unless ``damping``; sleeping is
    disabled, so a drone resting on the ground responds to thrust at once.
    """
    col = pybullet.createCollisionShape(
        pybullet.GEOM_CYLINDER,
        radius=geometry["collision_radius"],
        height=geometry["collision_height"],
        physicsClientId=client,
    )
    side = BODY_SIDE_PER_ARM * geometry["arm"]
    props = [(x, y, z + PROP_Z) for x, y, z in geometry["prop_pos"]]
    vis = pybullet.createVisualShapeArray(
        shapeTypes=[pybullet.GEOM_BOX] + [pybullet.GEOM_CYLINDER] * 4,
        halfExtents=[[side / 2, side / 2, BODY_THICKNESS / 2]] + [[0, 0, 0]] * 4,
        radii=[0.0] + [geometry["prop_radius"]] * 4,
        lengths=[0.0] + [PROP_THICKNESS] * 4,
        rgbaColors=[BODY_RGBA] + [PROP_RGBA] * 4,
        visualFramePositions=[[0.0, 0.0, 0.0]] + props,
        physicsClientId=client,
    )
    body = pybullet.createMultiBody(geometry["mass"], col, vis, physicsClientId=client)
    set_drone_dynamics(client, body, geometry, damping)
    return body


def set_drone_dynamics(client: int, body: int, geometry: dict, damping: bool) -> None:
    """Set a drone body's mass, inertia, damping and sleeping (see `create_drone`)."""
    extra = {} if damping else {"linearDamping": 0.0, "angularDamping": 0.0}
    pybullet.changeDynamics(
        body,
        -1,
        mass=geometry["mass"],
        localInertiaDiagonal=geometry["inertia"],
        activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING,
        **extra,
        physicsClientId=client,
    )
