"""One checkpoint format for every trainer: ``policy.pkl``, a pickle of a dict with the algorithm, the parameters
(NumPy arrays), the task, its config overrides and the trainer's config; `save` writes it, `load_policy` rebuilds
the policy through the trainers' table (`jaxdrones.training.trainers`)."""

from __future__ import annotations

import dataclasses
import os
import pickle
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import jax

from jaxdrones.envs.base import Env
from jaxdrones.training.common import host_array, nonfinite_leaves

if TYPE_CHECKING:
    from jaxdrones.training.brax_ppo import BraxPPOConfig
    from jaxdrones.training.common import Schedule

#: Version of the checkpoint format (files from before it carry ``<algo>_config`` and no version; still loaded).
FORMAT = 1


def save(
    path: str | os.PathLike,
    algo: str,
    params: Any,
    task: str,
    env_overrides: dict,
    config: Schedule | BraxPPOConfig,
) -> str:
    """Write a policy file (see the module doc); returns ``path``. ``params`` may live on any devices."""
    payload = {
        "format": FORMAT,
        "algo": algo,
        "params": jax.tree.map(host_array, params),
        "env_name": task,
        "env_overrides": dict(env_overrides),
        "config": dataclasses.asdict(config),
    }
    path = os.fspath(path)
    with open(path, "wb") as f:
        pickle.dump(payload, f)
    return path


def _config_fields(payload: dict) -> dict:
    """The trainer config's fields of a payload, also of files from before `FORMAT` (``<algo>_config``)."""
    for key in ("config", f"{payload['algo']}_config", "mappo_config", "ppo_config"):
        if key in payload:
            return {k: tuple(v) if isinstance(v, list) else v for k, v in payload[key].items()}
    raise KeyError("config")


def read_payload(path: str | os.PathLike) -> tuple[str, dict]:
    """``(file, payload)`` of a saved policy: ``path`` is a run folder or its ``policy.pkl``; the payload's ``algo``
    is set for the files from before `FORMAT` too.

    Raises:
        ValueError: no policy file there (for a folder of runs, naming them), an empty or damaged one, not
            one of jaxdrones (or of an unknown algorithm), or one with non-finite weights.
    """
    from jaxdrones.training import trainers

    if not isinstance(path, str | os.PathLike):
        raise ValueError(f"path must be a run folder or its policy.pkl (a str or os.PathLike), got {path!r}")
    path = os.fspath(path)
    if os.path.isdir(path):
        runs = _runs_inside(path)
        if runs and not os.path.isfile(os.path.join(path, "policy.pkl")):
            shown = ", ".join(runs[:6]) + (f", ... ({len(runs)} in all)" if len(runs) > 6 else "")
            raise ValueError(f"{path!r} holds no policy of its own but runs in its folders: give one of them ({shown})")
        path = os.path.join(path, "policy.pkl")
    if not os.path.isfile(path):
        raise ValueError(f"no saved policy at {path!r}")
    try:
        with open(path, "rb") as f:
            payload = pickle.load(f)
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError) as err:
        # An empty, cut or overwritten file (or a pickle of something else), whatever pickle's error.
        raise ValueError(
            f"{path!r} cannot be read as a jaxdrones policy file ({type(err).__name__}: {err}); it is empty or "
            f"damaged: train the run again, or load another run's policy.pkl"
        ) from None
    if not isinstance(payload, dict) or not {"params", "env_name"} <= set(payload):
        raise ValueError(f"{path!r} is not a jaxdrones policy file")
    # Files from before FORMAT 1 wrote no "algo" (`jaxdrones.training.trainers.LEGACY_CONFIG_KEYS`).
    legacy = (name for key, name in trainers.LEGACY_CONFIG_KEYS.items() if key in payload)
    algo = payload.get("algo") or next(legacy, None)
    if algo not in trainers.ALGOS:
        raise ValueError(f"{path!r} is not a jaxdrones policy file (algorithm {algo!r})")
    bad = nonfinite_leaves(payload["params"])
    if bad:
        raise ValueError(
            f"{path!r} holds non-finite weights (NaN or infinity in {', '.join(bad[:3])}{', ...' * (len(bad) > 3)}): "
            f"the policy would fly NaN; train it again (jaxdrones train keeps the last finite parameters of a run "
            f"that diverges)"
        )
    return path, {**payload, "algo": algo}


def _runs_inside(path: str) -> list[str]:
    """The run folders inside ``path`` (a run of several seeds or settings: ``seed_<k>/`` or
    ``<setting>/seed_<k>/``) that hold a ``policy.pkl``, as paths relative to it."""
    found = []
    for folder, subfolders, files in os.walk(path):
        subfolders.sort()
        if folder != path and "policy.pkl" in files:
            found.append(os.path.relpath(folder, path))
            subfolders.clear()
    return found


def load_policy(path: str | os.PathLike, deterministic: bool = True, env: Env | None = None) -> tuple[Env, Callable]:
    """Load a policy saved by ``jaxdrones train`` (any algorithm of `jaxdrones.training.trainers`).

    Args:
        path: ``policy.pkl`` of a run folder, or the run folder.
        deterministic: use the distribution's mode (True) or sample (brax's PPO; the other trainers' saved policies
            are deterministic).
        env: the env to fly the policy in (default: the one it was trained on, ``jd.make(name, **overrides)``);
            it may differ in its physics or starts (e.g. with downwash on), not in its task, team size,
            observation or action.

    Returns:
        ``(env, policy)``: the env and ``policy(obs, key) -> (action, extras)``.

    Raises:
        ValueError: ``path`` not a str or path; the file is missing, is not a saved jaxdrones policy or holds
            non-finite weights; a folder of runs (naming them: ``seed_<k>/``, ...); ``env`` not of the
            policy's task, team size, observation size or action size.
    """
    from jaxdrones.envs import make
    from jaxdrones.training import trainers

    path, payload = read_payload(path)
    algo = payload["algo"]
    try:
        fields = _config_fields(payload)
    except KeyError:
        raise ValueError(f"{path!r} is not a jaxdrones policy file (no trainer config)") from None
    trained_on = make(payload["env_name"], **payload["env_overrides"])
    if env is None:
        env = trained_on
    else:
        _check_same_agents(path, payload["env_name"], trained_on, env)
    trainer = trainers.get(algo)
    network = trainer.make_network(trainer.config_cls(**fields), env)
    if trainer.stochastic:
        return env, trainer.make_policy(network, payload["params"], deterministic=deterministic)
    return env, trainer.make_policy(network, payload["params"])


def _check_same_agents(path: str, name: str, trained_on: Env, env: Env) -> None:
    """Raise ValueError unless ``env`` has the task, team size, observation and action sizes of ``trained_on``."""
    have = (getattr(getattr(env, "task", None), "name", None), env.n_drones, env.observation_size, env.action_size)
    want = (name, trained_on.n_drones, trained_on.observation_size, trained_on.action_size)
    if have != want:
        raise ValueError(
            f"the policy in {path!r} was trained on {want[0]!r} with {want[1]} drones, observation "
            f"size {want[2]} and action size {want[3]}; the env given is {have[0]!r} with {have[1]} "
            f"drones, observation size {have[2]} and action size {have[3]}"
        )
