"""The checks of settings at the API boundary, shared by every config (`jaxdrones.physics.config.SimConfig`,
`jaxdrones.envs.config.TaskConfig` and the tasks' configs, `jaxdrones.envs.realism.Realism`,
`jaxdrones.envs.config.DomainRandomization`, the trainers' configs) and the functions that take settings.

Each check raises ``ValueError`` naming the setting, what it must be (kind, unit, range) and the value given, and
returns the value in a canonical form (a Python ``int``, ``float``, ``bool`` or tuple), so that a frozen config stores
what it checked. A ``bool`` is never taken for a number, nor a number for a ``bool`` (a string or number would
otherwise be truthy).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Collection, Iterable
from typing import Any

import numpy as np

from jaxdrones._hints import did_you_mean


def is_real(value: Any) -> bool:
    """Whether ``value`` is a real number (Python's or NumPy's), not a ``bool``."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def is_integer(value: Any) -> bool:
    """Whether ``value`` is an integer (Python's or NumPy's), not a ``bool``."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def interval(low: float = -math.inf, high: float = math.inf, low_open: bool = False, high_open: bool = False) -> str:
    """The range's words: ``"> 0"``, ``">= 1"``, ``"<= 8192"``, ``"in (0, 0.3]"``; empty where it is unbounded."""
    if low > -math.inf and high < math.inf:
        return f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    if low > -math.inf:
        return f"{'>' if low_open else '>='} {low}"
    if high < math.inf:
        return f"{'<' if high_open else '<='} {high}"
    return ""


def check_int(name: str, value: Any, low: int = 1, high: float = math.inf, what: str = "") -> int:
    """``value`` as an ``int`` in [``low``, ``high``].

    Raises:
        ValueError: not an integer (a ``bool`` is not) or out of the range: "``name`` must be a positive integer"
            (``low`` = 1, no ``high``; ``what`` is said in brackets) or "an integer in [low, high]".
    """
    if not (is_integer(value) and low <= value <= high):
        kind = "a positive integer" if (low, high) == (1, math.inf) else f"an integer {interval(low, high)}"
        raise ValueError(f"{name} must be {kind}{f' ({what})' if what else ''}, got {value!r}")
    return int(value)


def check_real(
    name: str,
    value: Any,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    high_open: bool = False,
    finite: bool = True,
    what: str = "a number",
) -> float:
    """``value`` as a ``float`` in the range (``low``/``high``, each closed unless ``*_open``; finite unless
    ``finite=False``, which lets ``inf`` through where the range does).

    Raises:
        ValueError: "``name`` must be ``what`` ``range``, got ``value``" (``what`` names the kind and unit, e.g. "a
            finite rate in Hz"), for a non-number (a ``bool`` is not one), NaN, an infinity where ``finite``, or a
            value out of the range.
    """
    ok = is_real(value) and not math.isnan(value) and (math.isfinite(value) or not finite)
    if ok:
        ok = (low < value if low_open else low <= value) and (value < high if high_open else value <= high)
    if not ok:
        words = " ".join(w for w in (what, interval(low, high, low_open, high_open)) if w)
        raise ValueError(f"{name} must be {words}, got {value!r}")
    return float(value)


def check_bool(name: str, value: Any) -> bool:
    """``value`` as a ``bool``.

    Raises:
        ValueError: not ``True``/``False`` (NumPy's included): "``name`` must be True or False".
    """
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_choice(name: str, value: Any, choices: Collection) -> Any:
    """``value``, one of ``choices``.

    Raises:
        ValueError: "unknown ``name`` ``value`` (did you mean ...?): expected one of ``choices``".
    """
    if value not in choices:
        hint = did_you_mean(value, [str(c) for c in choices]) if isinstance(value, str) else ""
        raise ValueError(f"unknown {name} {value!r}{hint}: expected one of {tuple(choices)}")
    return value


def check_reals(name: str, value: Any, n: int, nonneg: bool = False) -> tuple[float, ...]:
    """``value`` as ``n`` finite floats (``>= 0`` if ``nonneg``), a hashable tuple.

    Raises:
        ValueError: "``name`` must be ``n`` finite numbers [>= 0]".
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)) or (nonneg and np.any(arr < 0)):
        raise ValueError(f"{name} must be {n} finite numbers{' >= 0' if nonneg else ''}, got {value!r}")
    return tuple(float(v) for v in arr)


def check_fields(
    config: object,
    *,
    integers: dict[str, int] | None = None,
    positive: Iterable[str] = (),
    nonnegative: Iterable[str] = (),
    fractions: Iterable[str] = (),
    open_fractions: Iterable[str] = (),
    booleans: Iterable[str] = (),
) -> None:
    """Check a config's fields by kind, each message naming the config's class and the field
    (``"ApgConfig: num_envs must be an integer >= 1, got 0"``): ``integers`` maps fields to their least value;
    ``positive`` fields must be finite and > 0, ``nonnegative`` finite and >= 0, ``fractions`` in [0, 1] and
    ``open_fractions`` in [0, 1); ``booleans`` True or False. A non-finite setting (an infinite step size or norm)
    trains a NaN policy, so none passes.

    Raises:
        ValueError: the first field out of its range.
    """
    owner = type(config).__name__
    for field in booleans:
        check_bool(f"{owner}: {field}", getattr(config, field))
    for field, low in (integers or {}).items():
        value = getattr(config, field)
        if not (is_integer(value) and value >= low):
            raise ValueError(f"{owner}: {field} must be an integer >= {low}, got {value!r}")
    ranges = (
        (positive, {"low": 0, "low_open": True}),
        (nonnegative, {"low": 0}),
        (fractions, {"low": 0, "high": 1}),
        (open_fractions, {"low": 0, "high": 1, "high_open": True}),
    )
    for fields, bounds in ranges:
        for field in fields:
            check_real(f"{owner}: {field}", getattr(config, field), what="a finite number", **bounds)
