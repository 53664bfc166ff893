"""Per-drone cameras in pure JAX, under the path they have always had: the camera model and `render`
(`jaxdrones.sensors.camera`), the scene of primitives and the drones' shapes (`jaxdrones.scene.primitives`), and the
ray caster (`jaxdrones.sensors.raycast`)."""

from jaxdrones.scene.primitives import *  # noqa: F403
from jaxdrones.scene.primitives import __all__ as _scene_names
from jaxdrones.sensors.camera import *  # noqa: F403
from jaxdrones.sensors.camera import __all__ as _camera_names
from jaxdrones.sensors.camera import _images  # noqa: F401  (benchmarks/speed/cameras.py times it)
from jaxdrones.sensors.raycast import ROWS_PER_BLOCK, SLOTS_PER_STEP  # noqa: F401

__all__ = [*_scene_names, *_camera_names, "ROWS_PER_BLOCK", "SLOTS_PER_STEP"]
