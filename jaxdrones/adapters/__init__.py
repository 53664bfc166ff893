"""Adapters from jaxdrones envs to other APIs: `brax` (brax.training's trainers), `gymnasium` (Env and VectorEnv),
`pettingzoo` (ParallelEnv), `jaxmarl` (JAX multi-agent dicts)."""
