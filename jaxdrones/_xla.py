"""XLA settings that jaxdrones applies when it is imported, before JAX starts its CPU backend.

XLA:CPU's MLIR fusion emitters, the default of jaxlib 0.9, compile the backward pass of a control step with ground
effect at one physics substep per control step into a fused loop that recomputes shared cotangents per element:
measured on 2 cores, the gradient of a 100-step rollout over 1024 worlds with drag and ground effect cost 180 times
its forward pass, against 6 times with XLA's classic emitters, which also run the forward pass, the envs and PPO
training as fast or faster (`jaxdrones.rollout`, which steps the component form of the state, then brought it
under 3 times: `benchmarks/gradients.py`). jaxdrones therefore adds ``--xla_cpu_use_fusion_emitters=false`` to
``XLA_FLAGS`` unless the variable already sets that flag. The flag concerns the CPU backend only.
"""

from __future__ import annotations

import os
import warnings

#: The XLA flag jaxdrones sets, and the one name it looks for in ``XLA_FLAGS`` to leave the user's choice alone.
CPU_FLAG = "--xla_cpu_use_fusion_emitters=false"
_FLAG_NAME = "xla_cpu_use_fusion_emitters"


def configure() -> bool:
    """Add `CPU_FLAG` to ``XLA_FLAGS`` if the user did not set the flag; returns whether it was added.

    XLA reads ``XLA_FLAGS`` when JAX starts a backend. If a backend is already running (JAX computed something
    before ``import jaxdrones``), the flag cannot take effect: a `RuntimeWarning` says so.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if _FLAG_NAME in flags:
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {CPU_FLAG}".strip()
    try:
        from jax._src import xla_bridge

        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):  # a JAX without this check: nothing to warn about
        started = False
    if started:
        warnings.warn(f"jaxdrones was imported after JAX started its backends, so {CPU_FLAG} (which makes gradients "
                      f"through rollouts with ground effect about 30 times faster on CPU) cannot take effect: import "
                      f"jaxdrones before running JAX code, or set XLA_FLAGS={CPU_FLAG}", RuntimeWarning, stacklevel=3)
    return True
