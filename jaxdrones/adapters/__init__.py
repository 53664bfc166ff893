"""Adapters from jaxdrones envs to other APIs: `brax` (brax.training's trainers), `gymnasium` (Env and VectorEnv),
`pettingzoo` (ParallelEnv), `jaxmarl` (JAX multi-agent dicts), `sb3` (Stable-Baselines3's VecEnv).

`TorchThreadsWarning`: the host adapters' warning where torch's threads would contend with JAX's for the CPU
(`jaxdrones.adapters._host.check_torch_threads`)."""

from jaxdrones.adapters._host import TorchThreadsWarning

__all__ = ["TorchThreadsWarning"]
