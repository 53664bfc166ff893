"""skrl's own PPO example (torch) on ``jaxdrones/Hover-v0``: it runs unchanged but for the environment's name, and
learns (the final distance to the target falls over its checkpoints).

skrl's example samples unclipped Gaussian actions (its policy's mean alone spans [-2, 2], Pendulum's torque
range) and passes them to the env; jaxdrones' gymnasium envs clip them to [-1, 1] and count them in
``info["clipped_actions"]`` (README, gymnasium). The example is not part of skrl's wheel: give its file, from a
checkout of skrl (examples/gymnasium/torch_gymnasium_pendulum_ppo.py):

    pip install skrl==2.1.1    # with torch; tested with skrl 2.1.1 and its 2.0.0 example file
    python benchmarks/experiments/skrl_example.py \
        --example /path/to/skrl/examples/gymnasium/torch_gymnasium_pendulum_ppo.py

The port changes two lines (printed): ``task_name = "Pendulum"`` becomes ``"jaxdrones/Hover"``, and
``import jaxdrones`` is added (it registers the id). It runs in a temporary folder with ``--headless --num_envs N
--seed 42`` (default N = 16: ``gymnasium.make_vec(..., vectorization_mode="sync")``, the example's own choice), 100k
timesteps (the example's), writing a checkpoint every 10k. Then each checkpoint's policy (its mean action, the
example's network and observation scaler restated here) flies 64 hover episodes of the env's defaults
(``gymnasium.make_vec("jaxdrones/Hover-v0", 64)``); printed: the mean distance to the target at the episodes'
last step, and the fraction of episodes that crashed. ``--out FILE`` writes them as JSON.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

import numpy as np


def port(source: str, dest: str) -> int:
    text = open(source).read()
    new = re.sub(r'^task_name = "Pendulum"$', 'task_name = "jaxdrones/Hover"', text, count=1, flags=re.M)
    new = re.sub(
        r"^import gymnasium as gym$",
        "import gymnasium as gym\nimport jaxdrones  # registers the ids",
        new,
        count=1,
        flags=re.M,
    )
    if new.count("jaxdrones") != 2:
        raise SystemExit(f"{source}: not skrl's Pendulum PPO example (no task_name or gymnasium import to change)")
    with open(dest, "w") as f:
        f.write(new)
    return 2


def evaluate(checkpoint: str, episodes: int = 64, seed: int = 0) -> dict:
    """Mean final distance (m) and crash fraction of a checkpoint's deterministic policy on Hover-v0."""
    import gymnasium as gym
    import torch

    import jaxdrones  # noqa: F401

    data = torch.load(checkpoint, map_location="cpu", weights_only=False)
    policy, scaler = data["policy"], data["observation_preprocessor"]
    net = torch.nn.Sequential(
        torch.nn.Linear(policy["net.0.weight"].shape[1], 64),
        torch.nn.ReLU(),
        torch.nn.Linear(64, 64),
        torch.nn.ReLU(),
        torch.nn.Linear(64, policy["net.4.weight"].shape[0]),
        torch.nn.Tanh(),
    )
    net.load_state_dict({k.removeprefix("net."): v for k, v in policy.items() if k.startswith("net.")})
    mean, std = scaler["running_mean"].float(), torch.sqrt(scaler["running_variance"].float()) + 1e-8
    env = gym.make_vec("jaxdrones/Hover-v0", episodes, vectorization_mode="vector_entry_point")
    obs, _ = env.reset(seed=seed)
    done = np.zeros(episodes, bool)
    final = np.zeros(episodes)
    crashed = np.zeros(episodes, bool)
    while not done.all():
        with torch.no_grad():
            x = torch.clamp((torch.as_tensor(obs) - mean) / std, -5.0, 5.0)
            action = (2.0 * net(x)).numpy()  # the example's policy: 2·tanh(...), Pendulum's range
        obs, _, terminated, truncated, info = env.step(action)
        ended = (terminated | truncated) & ~done
        final[ended] = info["distance"][ended]
        crashed[ended] = info["crash"][ended] > 0
        done |= ended
    env.close()
    return {"final_distance_m": float(final.mean()), "crashed": float(crashed.mean())}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--example", required=True, help="skrl's examples/gymnasium/torch_gymnasium_pendulum_ppo.py")
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        script = os.path.join(tmp, "hover_ppo.py")
        print(f"{port(args.example, script)} lines changed")
        start = time.perf_counter()
        done = subprocess.run(
            [sys.executable, script, "--headless", "--num_envs", str(args.num_envs), "--seed", "42"],
            cwd=tmp,
            capture_output=True,
            text=True,
        )
        results["train_s"] = time.perf_counter() - start
        if done.returncode:
            raise SystemExit(f"the example failed:\n{done.stderr[-3000:]}")
        print(f"trained: {results['train_s']:.0f} s ({args.num_envs} envs, 100k timesteps)")
        checkpoints = sorted(
            glob.glob(os.path.join(tmp, "runs", "**", "agent_*.pt"), recursive=True),
            key=lambda p: int(re.findall(r"agent_(\d+)\.pt", p)[0]),
        )
        results["checkpoints"] = {}
        for path in checkpoints:
            step = int(re.findall(r"agent_(\d+)\.pt", path)[0])
            r = results["checkpoints"][step] = evaluate(path)
            print(f"timestep {step:>6}: final distance {r['final_distance_m']:.3f} m, crashed {r['crashed']:.0%}")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
