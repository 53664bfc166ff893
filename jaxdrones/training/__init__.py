"""Training: the tasks' recipes (`jaxdrones.training.recipes`: how ``jaxdrones train TASK`` trains each), the table
of trainers (`jaxdrones.training.trainers`: our PPO, brax's PPO, APG, SHAC, MAPPO, IPPO),
their shared loop (`common`), evaluation (`evaluation`), progress display (`progress`), checkpoints (`checkpoint`),
the run of ``jaxdrones train`` (`run.train_task`: its plan of seeds and sweeps in `runs`, its files in `writing`).
The paper's two-drone workflow on RLlib is an example: `jaxdrones.examples.rllib_leader_follower`.

The names below are loaded on first use, so that importing ``jaxdrones.training`` imports no trainer.
"""

_EXPORTS = {"evaluate": "evaluation", "rollout_policy": "evaluation", "load_policy": "checkpoint", "train_task": "run"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f"jaxdrones.training.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'jaxdrones.training' has no attribute {name!r}")
