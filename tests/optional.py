"""Optional packages of the suite: pybullet, torch and Tianshou, which the test extra installs on Python 3.11 only,
and ray (RLlib), which the rllib extra installs in an environment of its own.

Tests that need one are marked ``pybullet``, ``torch``, ``tianshou`` or ``ray`` (skipped by ``conftest.py`` where it is
missing); a test module that imports one at its top calls `needs` first.
"""

from __future__ import annotations

import importlib.util

import pytest

from jaxdrones.backends import PYBULLET_INSTALL

#: Why a test marked ``pybullet`` or ``torch`` is skipped where that package is missing: the test extra installs
#: both on Python 3.11 only, where PyPI has wheels that fit (pyproject.toml, the test extra).
MISSING = {
    "pybullet": "pybullet is not installed: PyPI has no pybullet wheel for Python >= 3.12, so the test extra installs "
    f"it on 3.11 only; {PYBULLET_INSTALL}",
    "torch": "torch is not installed: PyPI's torch for Python >= 3.12 on Linux is a CUDA build of several GB, so "
    "the test extra installs torch and stable-baselines3 on 3.11 only (the CPU build)",
    "tianshou": "tianshou is not installed: it needs torch, which the test extra installs on Python 3.11 only",
    "ray": "ray is not installed: RLlib pins an older gymnasium than the suite's, so it has an environment of its own, "
    'the rllib extra: pip install -c constraints-rllib.txt -e ".[rllib]" (the rllib lane of .ci/run)',
}


def installed(name: str) -> bool:
    """Whether the package ``name`` can be imported (without importing it)."""
    return importlib.util.find_spec(name) is not None


def needs(name: str):
    """Skip the calling test module (at its top) where ``name`` (a key of `MISSING`) is not installed."""
    if not installed(name):
        pytest.skip(MISSING[name], allow_module_level=True)
