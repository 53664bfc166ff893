"""XLA flags: ``import jaxdrones`` sets none; the command line's are asked of the installed XLA itself, cached, and
never set over the user's own; and the rest of the command line's own process settings (JAX options, environment
variables, the garbage collector)."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import jaxlib
import numpy as np
import pytest

from jaxdrones import _xla

UNKNOWN = "--xla_jaxdrones_no_such_flag=1"
FUSION = "--xla_cpu_use_fusion_emitters=false"


def run_python(code: str, **env) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
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


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path


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


def test_accepted_asks_xla_and_caches_the_answer(cache_dir, monkeypatch):
    flags = (_xla.CLI_FLAGS[0], UNKNOWN, FUSION)
    accepted = _xla.accepted(flags)
    assert accepted == (_xla.CLI_FLAGS[0],) + ((FUSION,) if has_fusion_flag() else ())
    with open(_xla.cache_file()) as f:
        answers = json.load(f)
    assert list(answers.values()) == [{_xla.CLI_FLAGS[0]: True, UNKNOWN: False, FUSION: has_fusion_flag()}]
    monkeypatch.setattr(_xla, "_probe", lambda *flag_sets: pytest.fail("asked XLA again"))
    assert _xla.accepted(flags) == accepted


def test_every_cli_flag_starts_xla():
    """What the command line sets (where XLA accepts it) lets JAX start and compute."""
    added = run_python("""
        from jaxdrones import _xla
        print(" ".join(_xla.add_flags(_xla.CLI_FLAGS)))
        import jax.numpy as jnp
        print(float(jnp.ones(3).sum()))
    """)
    assert added.returncode == 0, added.stderr
    flags, total = added.stdout.split("\n")[:2]
    assert set(flags.split()) <= set(_xla.CLI_FLAGS) and "--xla_backend_optimization_level=1" in flags
    assert total == "3.0"


def test_every_gpu_flag_is_known_to_xla(cache_dir):
    """XLA parses every backend's flags wherever it starts: the installed XLA knows the GPU's, even on a CPU."""
    assert _xla.accepted(_xla.GPU_FLAGS) == _xla.GPU_FLAGS


def test_add_flags_never_overrides_the_user(cache_dir, monkeypatch):
    jax.numpy.zeros(1).block_until_ready()  # JAX has started: flags set now come too late, and add_flags says so
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=3")
    with pytest.warns(RuntimeWarning, match="before jaxdrones set the XLA flags"):
        added = _xla.add_flags(_xla.CLI_FLAGS)
    assert "--xla_backend_optimization_level=1" not in added and "--xla_llvm_disable_expensive_passes=true" in added
    assert (FUSION in added) == has_fusion_flag()
    assert os.environ["XLA_FLAGS"].split()[0] == "--xla_backend_optimization_level=3"
    assert os.environ["XLA_FLAGS"].count("optimization_level") == 1
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setenv(_xla.OPT_OUT_VAR, "0")
    assert _xla.add_flags(_xla.CLI_FLAGS) == [] and os.environ["XLA_FLAGS"] == ""


def test_nothing_is_cached_where_jax_does_not_start_at_all(cache_dir, monkeypatch):
    """A probe that fails even without flags (say, a broken GPU driver) says nothing of the flags: asked again."""
    monkeypatch.setattr(_xla, "_probe", lambda *flag_sets: [False] * len(flag_sets))
    assert _xla.accepted(_xla.CLI_FLAGS) == ()
    assert not os.path.exists(_xla.cache_file())


def test_each_device_gets_its_flags(tmp_path, monkeypatch):
    """The XLA:CPU flags are added where the CPU is asked for (``--device`` or ``JAX_PLATFORMS``), or where no
    accelerator's plugin is installed; an installed CUDA plugin, or a GPU asked for, gets the XLA:GPU flags."""
    import importlib.util
    import types

    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    assert _xla.compiles_for_cpu("cpu") and not _xla.compiles_for_cpu("gpu") and not _xla.compiles_for_cpu("tpu")
    assert _xla.compiles_for_gpu("gpu") and _xla.compiles_for_gpu("rocm") and not _xla.compiles_for_gpu("tpu")
    monkeypatch.setenv("JAX_PLATFORMS", "cuda,cpu")
    assert not _xla.compiles_for_cpu() and _xla.compiles_for_cpu("cpu") and _xla.compiles_for_gpu()
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert _xla.compiles_for_cpu() and not _xla.compiles_for_cpu("gpu")
    monkeypatch.delenv("JAX_PLATFORMS")
    jaxlib_library = os.path.join(os.path.dirname(jaxlib.__file__), "libjax_common.so")
    plugins = tmp_path / "jax_plugins"
    find_spec = importlib.util.find_spec

    def with_plugins(name, *args):
        if name == "jax_plugins":
            return types.SimpleNamespace(submodule_search_locations=[str(plugins)])
        return None if name == "libtpu" else find_spec(name, *args)

    monkeypatch.setattr(importlib.util, "find_spec", with_plugins)
    monkeypatch.setattr(_xla, "xla_libraries", lambda: (jaxlib_library,))
    assert _xla.compiles_for_cpu()  # jaxlib's own library compiles for the CPU
    assert not _xla.compiles_for_gpu() and _xla.flags_for() == _xla.CLI_FLAGS
    cuda = str(plugins / "xla_cuda13" / "xla_cuda_plugin.so")
    monkeypatch.setattr(_xla, "xla_libraries", lambda: (jaxlib_library, cuda))
    assert not _xla.compiles_for_cpu() and _xla.compiles_for_cpu("cpu")
    assert _xla.compiles_for_gpu() and _xla.flags_for() == _xla.GPU_FLAGS and _xla.flags_for("cpu") == _xla.CLI_FLAGS
    assert _xla.flags_for("tpu") == ()  # measured on CPUs and GPUs only
    assert _xla.jax_options_for() == _xla.GPU_JAX_OPTIONS and _xla.jax_options_for("gpu") == _xla.GPU_JAX_OPTIONS
    assert _xla.jax_options_for("cpu") == {} and _xla.jax_options_for("tpu") == {}
    assert _xla.environment_for() == _xla.GPU_ENV and _xla.environment_for("cpu") == _xla.environment_for("tpu") == {}
    monkeypatch.setattr(_xla, "xla_libraries", lambda: (jaxlib_library,))
    assert _xla.jax_options_for() == {}  # the CPU's programs lower jax.random as they always did
    assert _xla.environment_for() == {}


def test_set_environment_never_overrides_the_user(monkeypatch):
    name = "JAXDRONES_TEST_VARIABLE"
    monkeypatch.delenv(name, raising=False)
    assert _xla.set_environment({name: "ours"}) == [name] and os.environ[name] == "ours"
    monkeypatch.setenv(name, "theirs")
    assert _xla.set_environment({name: "ours"}) == [] and os.environ[name] == "theirs"
    monkeypatch.delenv(name)
    monkeypatch.setenv(_xla.OPT_OUT_VAR, "0")
    assert _xla.set_environment({name: "ours"}) == [] and name not in os.environ


def test_set_jax_options_sets_the_known_ones_and_never_the_users():
    """Set in a fresh process: the option takes effect; a user's own environment variable, an option this JAX lacks
    and the opt-out each leave JAX as it was."""
    code = """
        import jax
        from jaxdrones import _xla
        print(_xla.set_jax_options({**_xla.GPU_JAX_OPTIONS, "jax_jaxdrones_no_such_option": True}),
              jax.config.jax_threefry_gpu_kernel_lowering)
    """
    ours = run_python(code)
    assert ours.returncode == 0, ours.stderr
    assert ours.stdout.split() == ["['jax_threefry_gpu_kernel_lowering']", "True"]
    for env in ({"JAX_THREEFRY_GPU_KERNEL_LOWERING": "0"}, {_xla.OPT_OUT_VAR: "0"}):
        kept = run_python(code, **env)
        assert kept.returncode == 0, kept.stderr
        assert kept.stdout.split() == ["[]", "False"], env


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


def test_command_line_freezes_the_collector_only_as_the_process_command(monkeypatch):
    """As the process's command (no ``argv``), `jaxdrones.cli.main` moves the objects made so far out of the cyclic
    collector's sight before the command runs and again after it (what the command made); called from Python with
    ``argv``, it leaves the collector as it was."""
    import argparse
    import gc

    from jaxdrones import cli

    frozen_while_running, made = [], []

    def parser():
        command = argparse.ArgumentParser()
        command.set_defaults(
            func=lambda args: frozen_while_running.append(gc.get_freeze_count()) or made.append([object()]) or 0
        )
        return command

    def collected(x) -> bool:  # in the generations the collector walks (a frozen object is in none)
        return any(y is x for y in gc.get_objects())

    monkeypatch.setattr(cli, "build_parser", parser)
    monkeypatch.setattr(sys, "argv", ["jaxdrones"])
    monkeypatch.setenv(_xla.OPT_OUT_VAR, "0")  # no flag, option or variable set in this process
    gc.unfreeze()
    try:
        assert cli.main([]) == 0 and frozen_while_running == [0] and gc.get_freeze_count() == 0
        assert collected(made[0])
        assert cli.main() == 0
        assert frozen_while_running[1] > 0  # the imports' objects, before the command ran
        assert not collected(made[1])  # and, after it, what it made
    finally:
        gc.unfreeze()
