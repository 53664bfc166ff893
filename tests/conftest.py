"""Shared fixtures: seeded keys and generators, and a scoped float64 switch; the XLA flags the suite compiles with;
the skips of tests whose optional packages are not installed (markers ``pybullet`` and ``torch``)."""

from __future__ import annotations

import os
import sys

from jaxdrones import _xla

# The suite compiles several hundred programs, most of them run for a few steps: it compiles them as the
# ``jaxdrones`` command line does (`jaxdrones._xla.CLI_FLAGS`, where the installed XLA accepts them: LLVM's cheaper
# passes, and XLA:CPU's classic emitters up to jaxlib 0.10; tests/test_avoid.py and tests/test_gate.py in 45-50 s
# instead of 65-67 s). ``JAXDRONES_XLA_FLAGS=0`` runs it with XLA's defaults.
_xla.add_flags(_xla.CLI_FLAGS)

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

# Make `tests/reference_dyn.py` importable as `reference_dyn` however pytest is invoked.
sys.path.insert(0, os.path.dirname(__file__))

from optional import MISSING, installed  # noqa: E402


def pytest_collection_modifyitems(config, items):
    """Skip the tests marked ``pybullet`` or ``torch`` where that package is missing, with `MISSING`'s reason."""
    for name, reason in MISSING.items():
        if not installed(name):
            for item in items:
                if name in item.keywords:
                    item.add_marker(pytest.mark.skip(reason=reason))


@pytest.fixture(autouse=True, scope="session")
def _compile_cache_in_tmp(tmp_path_factory):
    """``jaxdrones train`` turns JAX's persistent compilation cache on in the user's cache folder: the suite's runs
    use a folder of their own."""
    os.environ["JAXDRONES_CACHE_DIR"] = str(tmp_path_factory.mktemp("jaxdrones_xla_cache"))


@pytest.fixture
def key():
    """A fixed typed PRNG key."""
    return jax.random.key(0)


@pytest.fixture
def rng():
    """A fixed NumPy generator, for host-side test data."""
    return np.random.default_rng(0)


@pytest.fixture
def x64():
    """Run the test with ``jax_enable_x64`` on (float64 default dtype), restoring the previous setting after.

    The setting is global, not the thread-local ``jax.enable_x64`` context: host callbacks (the PyBullet backend
    under ``jit``) run on XLA's threads, where JAX converts their outputs with the global setting.
    """
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)
