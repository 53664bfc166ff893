"""The original gym-pybullet-drones, run beside jaxdrones in the same benchmark run.

The original is not a dependency of jaxdrones. To measure it, clone it and give its folder:

    git clone https://github.com/utiasDSL/gym-pybullet-drones /path/to/gym-pybullet-drones
    pip install "setuptools<81" transforms3d   # the original imports pkg_resources and transforms3d
    python benchmarks/speed/backends.py --original /path/to/gym-pybullet-drones

(or install it with pip, and pass ``--original installed``). Without ``--original`` its rows are left out.
"""

from __future__ import annotations

import os
import sys

import numpy as np


def add_argument(parser) -> None:
    parser.add_argument(
        "--original",
        default=None,
        metavar="DIR",
        help="a checkout of gym-pybullet-drones (or 'installed') to time the original in the same "
        "run; see benchmarks/speed/original.py",
    )


def load(path: str | None):
    """The original's module ``gym_pybullet_drones`` from the checkout ``path`` ('installed': from the
    environment), or None when ``path`` is None.

    Raises:
        SystemExit: the original cannot be imported (with what to install).
    """
    if path is None:
        return None
    if path != "installed":
        if not os.path.isdir(os.path.join(path, "gym_pybullet_drones")):
            raise SystemExit(f"--original {path!r}: no gym_pybullet_drones package in that folder")
        sys.path.insert(0, os.path.abspath(path))
    try:
        import gym_pybullet_drones.envs.CtrlAviary  # noqa: F401
        from gym_pybullet_drones.control.DSLPIDControl import DSLPIDControl  # noqa: F401
    except ImportError as e:
        raise SystemExit(
            f"--original: the original does not import ({e}); it needs pybullet, gymnasium, scipy, "
            f"pillow, transforms3d and setuptools<81 (pkg_resources)"
        ) from e
    import gym_pybullet_drones

    return gym_pybullet_drones


def ctrl_aviary(n_drones: int, ctrl_freq: int, obstacles: bool = False, sim_freq: int = 240):
    """The original's ``CtrlAviary`` (PYB physics, no GUI, no recording), reset, in the paper's formation."""
    import contextlib
    import io

    from gym_pybullet_drones.envs.CtrlAviary import CtrlAviary

    with contextlib.redirect_stdout(io.StringIO()):  # it prints its URDF's parameters
        env = CtrlAviary(
            num_drones=n_drones,
            pyb_freq=sim_freq,
            ctrl_freq=ctrl_freq,
            gui=False,
            obstacles=obstacles,
            user_debug_gui=False,
        )
        env.reset()
    return env


def hover_action(env) -> np.ndarray:
    """f[D, 4] RPM: every motor at the original's hover RPM."""
    return np.full((env.NUM_DRONES, 4), env.HOVER_RPM)
