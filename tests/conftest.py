"""Shared fixtures: seeded keys and generators, and a scoped float64 switch; the XLA flags the suite compiles with;
the skips of tests whose optional packages are not installed (markers ``pybullet`` and ``torch``); the ``fast``
tier (the tests of the modules marked ``unit``, less those marked slow or needing an optional package); the order
the tests run in (the modules with slow tests first)."""

from __future__ import annotations

import os
import sys

from jaxdrones.cli import xla

# The suite compiles several hundred programs, most of them run for a few steps: it compiles them as the
# ``jaxdrones`` command line does (`jaxdrones.cli.xla.configure`), and on the CPU one step further, at LLVM's
# optimisation level 0 instead of 1 (the command line's programs run thousands of steps, the suite's a few).
# ``JAXDRONES_XLA_FLAGS=0`` runs the suite with XLA's defaults.
# XLA_FLAGS as the user set them, before the suite adds its own: kept in the environment by the first process, so
# that pytest-xdist's workers (which inherit its XLA_FLAGS) know them too.
os.environ.setdefault("JAXDRONES_SUITE_USERS_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
USERS_XLA_FLAGS = os.environ["JAXDRONES_SUITE_USERS_XLA_FLAGS"] or None
xla.configure(cpu=xla.cpu_flags(optimization_level=0))
# Every broadcast between arrays of different ranks is written out (``x[None]``, `jnp.broadcast_to`,
# `jaxdrones.physics.params.align_params`): JAX raises on an implicit one, here and in the suite's subprocesses.
os.environ.setdefault("JAX_NUMPY_RANK_PROMOTION", "raise")
# On a GPU, JAX's client takes 75 % of the device's memory when it starts: pytest-xdist's workers, and the suite's
# subprocesses, would each ask for it and all but the first fail with CUDA_ERROR_OUT_OF_MEMORY. Each takes what it
# uses instead (where the user has not chosen otherwise).
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# pytest-xdist runs one worker per core: torch (the Stable-Baselines3, Tianshou and PettingZoo tests) and OpenBLAS
# would each start a thread per core in every worker and its subprocesses, which then spin against the other
# workers (the docs' SB3 example: 58 s alone, 244 s in the suite). One thread each, where the user has not chosen.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

# Make `tests/reference_dyn.py` importable as `reference_dyn` however pytest is invoked.
sys.path.insert(0, os.path.dirname(__file__))

from optional import MISSING, installed  # noqa: E402

#: Markers that keep a test out of the ``fast`` tier.
NOT_FAST = ("slow", "pybullet", "torch", "tianshou", "ros2", "ray")


def pytest_collection_modifyitems(config, items):
    """Skip the tests marked ``pybullet`` or ``torch`` where that package is missing, with `MISSING`'s reason; mark
    the ``fast`` tier (the tests marked ``unit``, by their module's ``pytestmark``, less `NOT_FAST`); run the
    modules that hold slow tests first, each module's tests together and in their order, so that pytest-xdist's
    workers end on short tests rather than one of them on a minutes-long one (pytest runs ``items`` in this order,
    and xdist hands them out in it)."""
    for name, reason in MISSING.items():
        if not installed(name):
            for item in items:
                if name in item.keywords:
                    item.add_marker(pytest.mark.skip(reason=reason))
    for item in items:
        if item.get_closest_marker("unit") and not any(item.get_closest_marker(m) for m in NOT_FAST):
            item.add_marker(pytest.mark.fast)
    slow_modules = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow_modules)  # stable: each module's order is kept


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


@pytest.fixture
def users_xla_flags(monkeypatch):
    """XLA's flags as the user set them, without the suite's (LLVM at level 0 compiles faster and runs slower, and
    rounds otherwise): for the processes that run a user's whole program, such as a notebook's kernel, which sets the
    command line's flags itself and trains for minutes."""
    if USERS_XLA_FLAGS is None:
        monkeypatch.delenv("XLA_FLAGS", raising=False)
    else:
        monkeypatch.setenv("XLA_FLAGS", USERS_XLA_FLAGS)


@pytest.fixture
def users_rank_promotion(monkeypatch):
    """Run a user's code as users run it, with JAX's default rank promotion (``"allow"``), in this process and in
    the processes it starts (a notebook's kernel): the README's, the docs' and the notebooks' examples write
    ``pos - target`` for f[..., D, 3] and f[3] arrays, as NumPy users do. The library they call is held to
    ``"raise"`` by the rest of the suite."""
    monkeypatch.setenv("JAX_NUMPY_RANK_PROMOTION", "allow")
    with jax.numpy_rank_promotion("allow"):
        yield
