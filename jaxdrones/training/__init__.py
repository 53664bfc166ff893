"""Training: batched PPO through brax.training, evaluation, saving and loading policies."""

from jaxdrones.training.ppo import PPOConfig, evaluate, load_policy, rollout_policy, train

__all__ = ["PPOConfig", "evaluate", "load_policy", "rollout_policy", "train"]
