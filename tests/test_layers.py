"""The package's import contracts (pyproject.toml, ``[tool.importlinter]``): no module imports from a layer above its
own, and no import cycle exists among the modules of any package."""

import pathlib

from importlinter.cli import lint_imports

PYPROJECT = pathlib.Path(__file__).resolve().parents[1] / "pyproject.toml"


def test_import_contracts_hold():
    assert lint_imports(config_filename=str(PYPROJECT), no_cache=True) == 0  # its report, printed, names a breach


def test_every_module_is_in_a_layer():
    """Each module and package at the top of jaxdrones has its place in the layers contract, so that the contract
    governs all of it."""
    import pkgutil
    import tomllib

    import jaxdrones

    config = tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]["contracts"]
    layers = next(c for c in config if c["type"] == "layers")["layers"]
    placed = {name.strip() for layer in layers for name in layer.split("|")}
    modules = {f"jaxdrones.{m.name}" for m in pkgutil.iter_modules(jaxdrones.__path__)}
    assert modules - placed == set()


def test_old_module_paths_still_import():
    """The modules that moved into subpackages keep their old paths (the README's and pickled runs')."""
    import importlib
    import pickle

    import jaxdrones as jd
    from jaxdrones import envs, physics

    for old, new in (
        ("dynamics", physics.dynamics),
        ("params", physics.params),
        ("rotations", physics.rotations),
        ("config", physics.config),
        ("state", physics.state),
        ("realism", envs.realism),
        ("physics.realism", envs.realism),
    ):
        assert importlib.import_module(f"jaxdrones.{old}") is new
        assert getattr(jd, old.replace("physics.", "")) is new
    assert physics.realism is envs.realism
    from jaxdrones.training import export

    assert importlib.import_module("jaxdrones.export") is export
    from jaxdrones.cameras import CameraSpec, make_scene, render  # noqa: F401
    from jaxdrones.plotting import plot_flight  # noqa: F401
    from jaxdrones.sim import JaxStep, make_step, rollout, shard_worlds  # noqa: F401

    # A pickle written before the move names jaxdrones.params.DroneParams (protocol 0 spells names out as text, so the
    # name can be swapped): it loads as today's class.
    old_pickle = pickle.dumps(jd.load_params("cf2x"), protocol=0).replace(
        b"jaxdrones.physics.params", b"jaxdrones.params"
    )
    assert b"jaxdrones.params" in old_pickle
    assert type(pickle.loads(old_pickle)) is physics.params.DroneParams
    # The sim-to-real options moved from physics/ to envs/: a pickle naming the old module loads too.
    realism = envs.realism.resolve("crazyflie")
    old_pickle = pickle.dumps(realism, protocol=0).replace(b"jaxdrones.envs.realism", b"jaxdrones.physics.realism")
    assert b"jaxdrones.physics.realism" in old_pickle
    assert pickle.loads(old_pickle) == realism
