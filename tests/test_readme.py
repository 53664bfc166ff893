"""The README's Python examples run as written."""

import os
import re

import pytest

README = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "README.md")


def python_blocks() -> list[str]:
    with open(README) as f:
        return re.findall(r"```python\n(.*?)```", f.read(), flags=re.S)


def test_readme_has_examples():
    assert len(python_blocks()) >= 2


def markers(code: str) -> list:
    """The markers of the optional packages that a README example uses."""
    return [pytest.mark.pybullet] * ('backend="pybullet"' in code) + [pytest.mark.torch] * ("stable_baselines3" in code)


@pytest.mark.parametrize("index", [pytest.param(i, marks=markers(code)) for i, code in enumerate(python_blocks())])
def test_readme_example_runs(index, capsys, users_rank_promotion):
    code = python_blocks()[index]
    exec(compile(code, f"README.md python block {index}", "exec"), {})
    if "print(touched)" in code:  # the PyBullet example's collision report
        assert capsys.readouterr().out.strip() == "[2 0]"
