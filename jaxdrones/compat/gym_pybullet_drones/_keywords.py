"""Keyword checks with a "did you mean" hint for the compat classes (their own and their subclasses')."""

from __future__ import annotations

import inspect

from jaxdrones._hints import did_you_mean


class KeywordHints:
    """Mixin: constructing the class with a keyword its ``__init__`` does not take raises a ``TypeError`` naming the
    closest valid keyword (Python's own error names none), for every subclass too."""

    def __new__(cls, *args, **kwargs):
        params = inspect.signature(cls.__init__).parameters
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            valid = [n for n, p in params.items() if n != "self" and p.kind is not inspect.Parameter.VAR_POSITIONAL]
            for name in kwargs:
                if name not in params:
                    raise TypeError(f"{cls.__name__}() got an unexpected keyword argument {name!r}"
                                    f"{did_you_mean(name, valid)}; its keywords are {valid}")
        return super().__new__(cls)
