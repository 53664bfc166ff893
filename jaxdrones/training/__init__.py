"""Training: batched PPO through brax.training, evaluation, saving and loading policies.

The names below are loaded on first use, so that importing ``jaxdrones.training.hover`` (e.g. for the command
line's parser) does not import brax.
"""

__all__ = ["PPOConfig", "evaluate", "load_policy", "rollout_policy", "train"]


def __getattr__(name: str):
    if name in __all__:
        from jaxdrones.training import ppo

        return getattr(ppo, name)
    raise AttributeError(f"module 'jaxdrones.training' has no attribute {name!r}")
