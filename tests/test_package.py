"""The package's metadata agrees with itself: one version everywhere, the license files it ships, and the type
hints of its public API (it ships ``py.typed``)."""

import importlib.metadata
import pathlib

import pytest
import yaml

import jaxdrones
from jaxdrones.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_one_version_everywhere(capsys):
    """``jaxdrones --version``, the installed metadata, CITATION.cff and the changelog's latest release all give
    ``jaxdrones.__version__`` (pyproject.toml reads it from there)."""
    version = jaxdrones.__version__
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"jaxdrones {version}"
    assert importlib.metadata.version("jaxdrones") == version
    assert str(yaml.safe_load((ROOT / "CITATION.cff").read_text())["version"]) == version
    releases = [line for line in (ROOT / "CHANGELOG.md").read_text().splitlines() if line.startswith("## ")]
    assert releases[0] == "## Unreleased" and releases[1].startswith(f"## {version} ")


def test_license_carries_the_models_notice():
    """The MIT license, with gym-pybullet-drones' notice for the constants the URDFs carry, is the package's license
    file (pyproject.toml ``license-files``: it ships in the wheel's metadata)."""
    import tomllib

    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and text.count("Permission is hereby granted") == 2
    assert "gym-pybullet-drones" in text and "Copyright (c) 2020 JacopoPan" in text
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]


#: Modules the annotation test leaves out, with the reason: `jaxdrones.compat` mirrors gym-pybullet-drones' own
#: untyped signatures.
UNTYPED_MODULES = ("jaxdrones.compat",)
#: Modules that import an optional package when imported, and that package.
NEEDS = {f"jaxdrones.backends.{name}": "pybullet" for name in ("camera", "pybullet", "scene")}


def _public_modules(package=jaxdrones):
    """The public modules of ``package`` and its subpackages (no name part with a leading underscore), imported, less
    `UNTYPED_MODULES` (not imported at all)."""
    import importlib
    import importlib.util
    import pkgutil

    for info in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
        name = info.name
        if name.rsplit(".", 1)[1].startswith("_") or any(
            name == skip or name.startswith(skip + ".") for skip in UNTYPED_MODULES
        ):
            continue
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError:
            if importlib.util.find_spec(NEEDS.get(name, name)) is None:
                continue  # the PyBullet backend where pybullet is not installed: the lane with pybullet checks it
            raise
        yield module
        if info.ispkg:
            yield from _public_modules(module)


def _public_functions(module):
    """``(qualified name, function)`` of the public functions defined in ``module`` and the public methods (static,
    class, property getters and setters included) of its public classes; decorated ones (``jax.jit``,
    ``functools.cache``) unwrapped. Names imported from elsewhere, and methods that other libraries generate (flax's
    ``replace``), are left to their own module or out."""
    import inspect

    def own(obj):
        obj = inspect.unwrap(obj) if callable(obj) else obj
        return inspect.isfunction(obj) and obj.__module__ == module.__name__

    for name, obj in vars(module).items():
        if name.startswith("_"):
            continue
        if own(obj):
            yield f"{module.__name__}.{name}", inspect.unwrap(obj)
        elif inspect.isclass(obj) and obj.__module__ == module.__name__:
            for attr, member in vars(obj).items():
                if attr.startswith("_"):
                    continue
                if isinstance(member, (staticmethod, classmethod)):
                    member = member.__func__
                parts = (member.fget, member.fset) if isinstance(member, property) else (member,)
                for part in parts:
                    if part is not None and own(part):
                        yield f"{module.__name__}.{name}.{attr}", inspect.unwrap(part)


def _missing_annotations(fn) -> list[str]:
    """The parameters of ``fn`` (``self`` and ``cls`` aside) without an annotation, and ``return`` if it has none."""
    import inspect

    signature = inspect.signature(fn)
    missing = [
        name
        for name, p in signature.parameters.items()
        if p.annotation is inspect.Parameter.empty and name not in ("self", "cls")
    ]
    return missing + (["return"] if signature.return_annotation is inspect.Signature.empty else [])


def test_public_api_is_annotated():
    """Every public function of every public module, and every public method of its public classes, annotates each
    parameter and its return: the package ships ``py.typed`` (PEP 561), so type checkers read these hints as its
    API. Private modules (``_x.py``) and private names are left out, and so are `UNTYPED_MODULES`:
    ``jaxdrones.compat`` (it mirrors gym-pybullet-drones' untyped signatures)."""
    functions = dict(item for module in _public_modules() for item in _public_functions(module))
    assert len(functions) > 300  # the walk found the package (not an empty or broken one)
    assert "jaxdrones.physics.state.init_state" in functions and "jaxdrones.envs.env.TaskEnv.step" in functions
    missing = {name: gaps for name, fn in functions.items() if (gaps := _missing_annotations(fn))}
    assert not missing, f"{len(missing)} public functions lack annotations: {missing}"


@pytest.mark.parametrize("name", ["make", "make_step", "rollout", "load_params", "init_state"])
def test_main_api_hints_resolve(name):
    """The hints of the main API evaluate at run time (``typing.get_type_hints``, as runtime type checkers and
    documentation tools read them), not just as strings: every name they use is bound in its module, and each
    function returns the package's own type."""
    import collections.abc
    import inspect
    import typing

    from jaxdrones.envs.env import TaskEnv

    returns = {
        "make": TaskEnv,
        "make_step": collections.abc.Callable[..., jaxdrones.DroneState],
        "rollout": jaxdrones.DroneState,
        "load_params": jaxdrones.DroneParams,
        "init_state": jaxdrones.DroneState,
    }
    fn = getattr(jaxdrones, name)
    hints = typing.get_type_hints(fn)
    assert set(hints) == set(inspect.signature(fn).parameters) | {"return"}
    assert hints["return"] == returns[name]
