"""Without pybullet (the `pybullet` extra): the JAX backend, its cameras, the trainers, the command line and every
adapter import and run; ``backend="pybullet"`` says in one line which extra installs it.

Each runs in a fresh interpreter where ``import pybullet`` fails as if it were not installed (on Python 3.11 it is)."""

import subprocess
import sys
import textwrap

BLOCK_PYBULLET = "import sys; sys.modules['pybullet'] = sys.modules['pybullet_data'] = None\n"


def run_without_pybullet(code: str, tmp_path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", BLOCK_PYBULLET + textwrap.dedent(code)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_jax_backend_and_everything_above_it(tmp_path):
    result = run_without_pybullet(
        """
        import importlib
        import jax, jax.numpy as jnp
        import jaxdrones as jd
        modules = ["jaxdrones.cameras", "jaxdrones.training", "jaxdrones.training.apg", "jaxdrones.training.shac",
                   "jaxdrones.training.brax_ppo", "jaxdrones.training.mappo", "jaxdrones.adapters.gymnasium",
                   "jaxdrones.adapters.pettingzoo", "jaxdrones.adapters.jaxmarl", "jaxdrones.adapters.brax",
                   "jaxdrones.cli", "jaxdrones.cli.train", "jaxdrones.cli.fly", "jaxdrones.examples.circle",
                   "jaxdrones.compat.gym_pybullet_drones"]
        for name in modules:
            importlib.import_module(name)
        env = jd.make("avoid")  # the JAX backend's cameras and obstacles
        state = jax.jit(env.step)(jax.jit(env.reset)(jax.random.key(0)), jnp.zeros((1, env.action_size)))
        assert state.obs["depth"].shape == (1, 16, 64)
        from jaxdrones.compat.gym_pybullet_drones import HoverAviary  # the original's scripts, on Python 3.12 too
        assert HoverAviary().reset()[0].shape == (1, 72)
        print("ok")
    """,
        tmp_path,
    )
    assert result.returncode == 0, result.stderr  # any import of pybullet would have raised
    assert result.stdout.split() == ["ok"]


def test_pybullet_backend_names_the_extra(tmp_path):
    result = run_without_pybullet(
        """
        import jaxdrones as jd
        for call in (lambda: jd.make_step(jd.SimConfig(), backend="pybullet"),
                     lambda: jd.make("hover", backend="pybullet")):
            try:
                call()
            except ModuleNotFoundError as e:
                print(e)
    """,
        tmp_path,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().split("\n")
    assert len(lines) == 2 and all(
        "needs pybullet, which is not installed: pip install pybullet" in line for line in lines
    ), lines
    for args in (["fly", "--backend", "pybullet", "--out", "f"], ["camera", "--out", "f"]):
        cli = subprocess.run(
            [
                sys.executable,
                "-c",
                BLOCK_PYBULLET + f"from jaxdrones.cli import main; raise SystemExit(main({args!r}))",
            ],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert cli.returncode == 2 and cli.stderr.count("\n") == 1 and "pip install pybullet" in cli.stderr, cli.stderr
        assert not (tmp_path / "f").exists()
