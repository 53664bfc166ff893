"""The package's metadata agrees with itself: one version everywhere, the license files it ships."""

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
