"""What the compat classes share: keyword checks with a "did you mean" hint (for their subclasses too), and JAX's
persistent compilation cache turned on at the first aviary or controller."""

from __future__ import annotations

import inspect

from jaxdrones._hints import did_you_mean


class KeywordHints:
    """Mixin: constructing the class with a keyword its ``__init__`` does not take raises a ``TypeError`` naming the
    closest valid keyword (Python's own error names none), for every subclass too; the first construction turns on
    the compilation cache (`use_compilation_cache`)."""

    def __new__(cls, *args, **kwargs):
        params = inspect.signature(cls.__init__).parameters
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            valid = [n for n, p in params.items() if n != "self" and p.kind is not inspect.Parameter.VAR_POSITIONAL]
            for name in kwargs:
                if name not in params:
                    raise TypeError(
                        f"{cls.__name__}() got an unexpected keyword argument {name!r}"
                        f"{did_you_mean(name, valid)}; its keywords are {valid}"
                    )
        use_compilation_cache()
        return super().__new__(cls)


def use_compilation_cache() -> None:
    """Turn on JAX's persistent compilation cache (`jaxdrones.io.runs.enable_compilation_cache`) unless one is set, so
    that a script run again reads its compiled steps from disk rather than compiling them."""
    import jax

    if jax.config.jax_compilation_cache_dir is None:
        from jaxdrones.io.runs import enable_compilation_cache

        enable_compilation_cache()
