"""XLA flags: ``import jaxdrones`` sets none; the command line's follow jaxlib's version and the device, start XLA,
and never replace the user's own; and the rest of its process settings on a GPU (JAX options, environment
variables)."""

import os
import subprocess
import sys
import textwrap

import jax
import jaxlib
import numpy as np
import pytest

from jaxdrones.cli import xla

FUSION = "--xla_cpu_use_fusion_emitters=false"


def run_python(code: str, **env) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "XLA_PYTHON_CLIENT_PREALLOCATE")}
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env={**environ, **env},
        capture_output=True,
        text=True,
        timeout=300,
    )


def has_fusion_flag() -> bool:
    """jaxlib 0.11 removed the classic emitters and their flag (its name stays in the library, as a reserved field)."""
    return tuple(map(int, jaxlib.__version__.split(".")[:2])) < (0, 11)


def test_import_sets_no_flag_and_keeps_the_users():
    """A user's own XLA_FLAGS (here an unrelated one) are all XLA sees, and every computation runs."""
    code = """
        import os, jax, jax.numpy as jnp
        import jaxdrones as jd
        env = jd.make("hover")
        state = jax.jit(env.reset)(jax.random.key(0))  # jitted: one compilation each, not one per operation
        grad = jax.jit(jax.grad(lambda a: env.step(state, a).reward.sum()))(jnp.zeros((1, env.action_size)))
        print(repr(os.environ.get("XLA_FLAGS")), len(jax.devices("cpu")), bool(jnp.isfinite(grad).all()))
    """
    default = run_python(code)
    assert default.returncode == 0, default.stderr
    assert default.stdout.split() == ["None", "1", "True"]
    user = run_python(code, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    assert user.returncode == 0, user.stderr
    assert user.stdout.split() == ["'--xla_force_host_platform_device_count=2'", "2", "True"]


def test_cpu_flags_start_xla_and_follow_jaxlib():
    """The command line's XLA:CPU flags (the classic emitters' only up to jaxlib 0.10, which has them) let JAX start
    and compute; so do the GPU's, which XLA parses wherever it starts."""
    assert (FUSION in xla.cpu_flags()) == has_fusion_flag()
    assert xla.cpu_flags(0)[0] == "--xla_backend_optimization_level=0"
    for device in ("cpu", "gpu"):
        run = run_python(
            f"""
            import os
            from jaxdrones.cli import xla
            added = xla.configure({device!r})
            import jax, jax.numpy as jnp
            print(" ".join(added), "|", os.environ["XLA_FLAGS"], "|", float(jax.jit(jnp.sum)(jnp.ones(3))))
        """,
            JAX_PLATFORMS="cpu",
        )
        assert run.returncode == 0, run.stderr
        added, flags, total = (part.strip() for part in run.stdout.split("|"))
        assert added.split() == list(xla.cpu_flags() if device == "cpu" else xla.GPU_FLAGS) == flags.split()
        assert total == "3.0"


def test_configure_never_overrides_the_user(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=3")
    added = xla.configure("cpu")
    assert "--xla_backend_optimization_level=1" not in added and "--xla_llvm_disable_expensive_passes=true" in added
    assert os.environ["XLA_FLAGS"].split()[0] == "--xla_backend_optimization_level=3"
    assert os.environ["XLA_FLAGS"].count("optimization_level") == 1
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setenv(xla.OPT_OUT_VAR, "0")
    assert xla.configure("cpu") == [] and os.environ["XLA_FLAGS"] == ""


def test_each_device_gets_its_settings(tmp_path, monkeypatch):
    """The platform asked for (``--device``, else ``JAX_PLATFORMS``), else an installed CUDA plugin, chooses."""
    import importlib.util
    import types

    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    assert xla.platform("cpu") == "cpu" and xla.platform("cuda") == xla.platform("rocm") == "gpu"
    assert xla.platform("tpu") == "tpu"
    monkeypatch.setenv("JAX_PLATFORMS", "cuda,cpu")
    assert xla.platform() == "gpu" and xla.platform("cpu") == "cpu"
    monkeypatch.delenv("JAX_PLATFORMS")
    plugins = tmp_path / "jax_plugins"
    plugins.mkdir()
    find_spec = importlib.util.find_spec

    def with_plugins(name, *args):
        if name == "jax_plugins":
            return types.SimpleNamespace(submodule_search_locations=[str(plugins)])
        return None if name == "libtpu" else find_spec(name, *args)

    monkeypatch.setattr(importlib.util, "find_spec", with_plugins)
    assert xla.platform() == "cpu"
    (plugins / "xla_cuda13").mkdir()
    assert xla.platform() == "gpu" and xla.platform("cpu") == "cpu"


def test_gpu_settings_are_set_unless_the_user_set_them():
    """On a GPU: the JAX option and the environment variable, each unless the user set its variable or opted out."""
    code = """
        import os
        from jaxdrones.cli import xla
        xla.configure("gpu")
        import jax
        print(jax.config.jax_threefry_gpu_kernel_lowering, os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE"))
    """
    ours = run_python(code, JAX_PLATFORMS="cpu")
    assert ours.returncode == 0, ours.stderr
    assert ours.stdout.split() == ["True", "false"]
    theirs = run_python(
        code, JAX_PLATFORMS="cpu", JAX_THREEFRY_GPU_KERNEL_LOWERING="0", XLA_PYTHON_CLIENT_PREALLOCATE="true"
    )
    assert theirs.returncode == 0, theirs.stderr
    assert theirs.stdout.split() == ["False", "true"]
    off = run_python(code, JAX_PLATFORMS="cpu", **{xla.OPT_OUT_VAR: "0"})
    assert off.returncode == 0, off.stderr
    assert off.stdout.split() == ["False", "None"]


def test_threefry_kernel_option_lowers_each_hash_to_one_kernel_call():
    """With `GPU_JAX_OPTIONS` a program's draws, lowered for a GPU, call the CUDA threefry kernel instead of writing
    the hash out in XLA operations, and the exported program (what `jaxdrones.training.programs` stores) is
    serialised as before."""
    key = jax.random.key(0)

    def draw(k):
        return jax.random.uniform(k, (64,)) + jax.random.normal(jax.random.split(k)[1], (64,))

    lowered, previous = {}, jax.config.jax_threefry_gpu_kernel_lowering
    for on in (False, True):
        jax.config.update("jax_threefry_gpu_kernel_lowering", on)
        try:
            exported = jax.export.export(jax.jit(draw), platforms=["cuda"])(key)
        finally:
            jax.config.update("jax_threefry_gpu_kernel_lowering", previous)
        assert exported.serialize()
        lowered[on] = exported.mlir_module()
    assert "threefry2x32_ffi" not in lowered[False] and "threefry2x32_ffi" in lowered[True]
    assert len(lowered[True]) < len(lowered[False])


@pytest.mark.skipif(jax.default_backend() != "gpu", reason="the CUDA threefry kernel runs on a GPU only")
def test_threefry_kernel_draws_the_same_numbers():
    """On a GPU the kernel and XLA's written-out hash draw the same bits (the same Threefry-2x32)."""
    keys = jax.random.split(jax.random.key(3), 8)

    def draw(k):
        return jax.random.bits(k, (1000,)), jax.random.normal(k, (17, 3))

    draws, previous = {}, jax.config.jax_threefry_gpu_kernel_lowering
    for on in (False, True):
        jax.config.update("jax_threefry_gpu_kernel_lowering", on)
        try:
            draws[on] = jax.jit(jax.vmap(draw))(keys)
        finally:
            jax.config.update("jax_threefry_gpu_kernel_lowering", previous)
    for a, b in zip(jax.tree.leaves(draws[False]), jax.tree.leaves(draws[True]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
