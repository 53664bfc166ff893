"""Hints for mistyped names at the API boundary ("did you mean ...?"), and the names gym-pybullet-drones uses for
ours."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

#: gym-pybullet-drones' keyword and attribute names with the `jaxdrones.make` option that does the same, for the
#: hint of an unknown option (the compat classes, `jaxdrones.compat.gym_pybullet_drones`, take the original names).
ORIGINAL_NAMES = {
    "obs": "obs_type",
    "act": "action_type",
    "pyb_freq": "sim_freq",
    "initial_xyzs": "init_pos",
    "initial_rpys": "init_rpy",
    "num_drones": "n_drones",
    "drone_model": "model",
    "neighbourhood_radius": "neighbor_radius",
    "EPISODE_LEN_SEC": "episode_len_s",
    "CTRL_FREQ": "ctrl_freq",
    "PYB_FREQ": "sim_freq",
    "physics": "drag, ground_effect, downwash",
}


def did_you_mean(name: str, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the choice closest to ``name`` (case-insensitive, difflib's ratio ≥ 0.6), else
    an empty string."""
    choices = list(choices)
    lower = {c.lower(): c for c in choices}
    match = difflib.get_close_matches(name.lower(), list(lower), n=1)
    return f" (did you mean {lower[match[0]]!r}?)" if match else ""


def unknown_option(owner: str, name: str, valid: Iterable[str]) -> str:
    """The message for an unknown option ``name`` of ``owner``: a close valid name, or for a gym-pybullet-drones
    name ours and the compat classes."""
    valid = sorted(valid)
    if name in ORIGINAL_NAMES:
        hint = (
            f" ({name!r} is gym-pybullet-drones' name: here {ORIGINAL_NAMES[name]}; the original's classes and "
            f"names are in jaxdrones.compat.gym_pybullet_drones)"
        )
    else:
        hint = did_you_mean(name, valid)
    return f"{owner}: unknown option {name!r}{hint}; valid options are {valid}"
