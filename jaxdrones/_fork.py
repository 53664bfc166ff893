"""Fork safety: refuse to run in a process forked from one where JAX had started, instead of hanging.

JAX runs its computations on threads that ``os.fork`` does not copy: in a child forked after the parent started a
JAX backend (ran any computation), the first JAX call waits forever. multiprocessing forks by default on Linux
before Python 3.14, which is how SuperSuit's ``concat_vec_envs_v1(..., num_cpus=2)`` and gymnasium's
``AsyncVectorEnv(context="fork")`` start their workers. At import, jaxdrones registers a hook that records, in each
forked child, whether JAX had started in its parent; `check_not_forked` then raises a `RuntimeError` naming the
fixes before any JAX work (building a `jaxdrones.envs.TaskEnv`, which unpickling one does too, and the adapters'
``reset``/``step``). A child forked before JAX started, or started with ``spawn``/``forkserver``, runs normally.
"""

from __future__ import annotations

import os
import sys

#: What to do instead, in every message that refuses a forked process.
FORK_HELP = (
    "Start worker processes with 'spawn' or keep the envs in this process: "
    "SuperSuit: concat_vec_envs_v1(env, n, num_cpus=0, ...) (every copy in this process), or call "
    "multiprocessing.set_start_method('spawn') first thing under `if __name__ == '__main__':`; "
    "gymnasium: gymnasium.make_vec(id, num_envs=N, vectorization_mode='vector_entry_point') (all worlds in one "
    "jitted call), or vectorization_mode='async' with vector_kwargs={'context': 'spawn'}; "
    "Tianshou: venv_type=VectorEnvType.DUMMY (tianshou.highlevel.env; its examples' env factories fork by default), "
    "or DummyVectorEnv instead of SubprocVectorEnv; "
    "Stable-Baselines3: jaxdrones.adapters.sb3.VecEnv(task, num_envs=N) (all worlds in one jitted call), or "
    "SubprocVecEnv(env_fns, start_method='spawn')"
)

_forked_after_jax = False


def _jax_started() -> bool:
    """Whether a JAX backend has started in this process (read without importing anything new)."""
    bridge = sys.modules.get("jax._src.xla_bridge")
    if bridge is None:
        return False
    started = getattr(bridge, "backends_are_initialized", None)
    return bool(started()) if started is not None else bool(getattr(bridge, "_backends", True))


def _after_fork_in_child() -> None:
    global _forked_after_jax
    _forked_after_jax = _forked_after_jax or _jax_started()


os.register_at_fork(after_in_child=_after_fork_in_child)


def check_not_forked() -> None:
    """Refuse to run jaxdrones in a process forked after JAX started (see the module docstring).

    Raises:
        RuntimeError: in such a process, with `FORK_HELP`.
    """
    if _forked_after_jax:
        raise RuntimeError(
            f"jaxdrones cannot run in this process: it was forked from a process in which JAX had "
            f"already started, and JAX hangs after a fork (multiprocessing forks by default on Linux "
            f"before Python 3.14). {FORK_HELP}"
        )
