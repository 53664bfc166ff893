"""The checks of settings (`jaxdrones._validate`): what each accepts, returns and says."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxdrones import _validate as v

pytestmark = pytest.mark.unit


def test_integers_and_reals_exclude_bool():
    assert v.is_integer(3) and v.is_integer(np.int32(3)) and not v.is_integer(True) and not v.is_integer(3.0)
    assert v.is_real(0.5) and v.is_real(np.float32(0.5)) and v.is_real(2) and not v.is_real(np.bool_(True))
    assert not v.is_real("1")


def test_check_int():
    assert v.check_int("n", np.int64(4)) == 4 and type(v.check_int("n", np.int64(4))) is int
    with pytest.raises(ValueError, match=r"^n must be a positive integer, got 0$"):
        v.check_int("n", 0)
    with pytest.raises(ValueError, match=r"^n must be a positive integer \(drones\), got True$"):
        v.check_int("n", True, what="drones")
    with pytest.raises(ValueError, match=r"^width must be an integer in \[1, 8192\], got 8193$"):
        v.check_int("width", 8193, 1, 8192)
    with pytest.raises(ValueError, match=r"^k must be an integer >= 0, got -1$"):
        v.check_int("k", -1, low=0)


def test_check_real():
    assert v.check_real("x", np.float32(0.25), 0, 1) == 0.25
    assert v.check_real("r", math.inf, 0, low_open=True, finite=False) == math.inf
    with pytest.raises(ValueError, match=r"^dt must be a time in s > 0, got 0.0$"):
        v.check_real("dt", 0.0, 0, low_open=True, what="a time in s")
    with pytest.raises(ValueError, match=r"must be a number in \(0, 0.3\], got 0.31"):
        v.check_real("pid_scale", 0.31, 0, 0.3, low_open=True)
    with pytest.raises(ValueError, match=r"fov must be a number in \(0, 180\), got 180"):
        v.check_real("fov", 180, 0, 180, low_open=True, high_open=True)
    for bad in (math.nan, math.inf, True, "1", None):
        with pytest.raises(ValueError, match="x must be a number >= 0"):
            v.check_real("x", bad, 0)


def test_check_bool_choice_reals():
    assert v.check_bool("flag", np.bool_(True)) is True
    with pytest.raises(ValueError, match="flag must be True or False, got 1"):
        v.check_bool("flag", 1)
    assert v.check_choice("mode", "b", ("a", "b")) == "b"
    with pytest.raises(ValueError, match=r"unknown mode 'hovr' \(did you mean 'hover'\?\): expected one of"):
        v.check_choice("mode", "hovr", ("hover", "velocity"))
    assert v.check_reals("p", [1, 2, 3], 3, nonneg=True) == (1.0, 2.0, 3.0)
    with pytest.raises(ValueError, match="p must be 3 finite numbers >= 0"):
        v.check_reals("p", [1, -2, 3], 3, nonneg=True)
    with pytest.raises(ValueError, match="p must be 3 numbers"):
        v.check_reals("p", "abc", 3)


def test_check_fields_names_the_config():
    class Config:
        n = 0
        lr = 1e-3
        gamma = 1.0
        flag = "yes"

    with pytest.raises(ValueError, match=r"^Config: n must be an integer >= 1, got 0$"):
        v.check_fields(Config(), integers={"n": 1})
    with pytest.raises(ValueError, match=r"^Config: gamma must be a finite number in \[0, 1\), got 1.0$"):
        v.check_fields(Config(), positive=("lr",), open_fractions=("gamma",))
    with pytest.raises(ValueError, match="Config: flag must be True or False"):
        v.check_fields(Config(), booleans=("flag",))
    v.check_fields(Config(), positive=("lr",), fractions=("gamma",))
