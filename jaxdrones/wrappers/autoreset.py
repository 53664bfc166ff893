"""Auto-reset with a fresh key: a finished world starts a new episode with a new start, new task params and new
domain-randomised params, drawn from the world's own key chain (``EnvState.key``).

brax's ``AutoResetWrapper`` restores each world's *first* state instead, so every world would replay one start for
a whole training run; the brax adapter, the vector env and the trainers use these wrappers.

Two forms with the same result:

* `AutoReset` wraps the env of one world (``vmap`` it for many). Under ``vmap`` a reset is computed for every world
  at every step and then discarded where the episode goes on.
* `VmapAutoReset` steps a batch of worlds ``[W]`` itself and resets only the worlds whose episode ended
  (`reset_where`): on CPU, where a reset (mostly its random numbers) costs about as much as a step, this nearly
  halves the cost of a step. A loop of many steps can draw every world's next episode once, before the loop
  (`VmapAutoReset.starts`), and hand them to each step: a world whose episode ends then takes its drawn episode by a
  select, and the step computes no reset at all (the trainers' ``starts_per_window``, on with ``--defaults gpu``:
  `benchmarks/training/train_cost.py`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from jaxdrones.envs.base import Env, EnvState, world_axes

if TYPE_CHECKING:
    from jaxdrones.envs.task import TaskParams

#: What a world's state keeps from the step that ended its episode when it is reset in the same call (brax's
#: convention): the reward, flags and metrics of that step, and the info with its final observation.
ENDING_STEP_FIELDS = ("reward", "terminated", "truncated", "metrics", "info")


def _final_info(state: EnvState) -> EnvState:
    return state.replace(info={**state.info, "final_obs": state.obs, "final_steps": state.steps})


class _Wrapper(Env):
    def __init__(self, env: Env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)

    @property
    def n_drones(self) -> int:
        return self.env.n_drones

    @property
    def observation_size(self) -> int:
        return self.env.observation_size

    @property
    def action_size(self) -> int:
        return self.env.action_size

    @property
    def episode_length(self) -> int:
        return self.env.episode_length

    def close(self) -> None:
        self.env.close()


class AutoReset(_Wrapper):
    """Wrap an env so that ``step`` resets a world whose episode ended, in the same call (brax's convention).

    The returned state of such a world is the new episode's first state, except ``reward``, ``terminated``,
    ``truncated`` and ``metrics``, which report the step that ended the old one; ``info["final_obs"]`` holds that
    step's observation (the new one is in ``obs``) and ``info["final_steps"]`` its length in control steps. The
    new episode is drawn by ``env.reset(state.key, state.task)``: its per-episode task quantities, start and
    params are new, while the task params' ranges and weights carry over.
    """

    def reset(self, key: jax.Array, task: TaskParams | None = None) -> EnvState:
        return _final_info(self.env.reset(key, task))

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        nxt = _final_info(self.env.step(state, action))
        fresh = self.env.reset(nxt.key, nxt.task)
        fresh = fresh.replace(**{k: getattr(nxt, k) for k in ENDING_STEP_FIELDS})
        done = nxt.done
        return jax.tree.map(lambda new, old: jnp.where(done, new, old), fresh, nxt)


class VmapAutoReset(_Wrapper):
    """`AutoReset` over a batch of worlds: ``reset(keys)`` with keys [W], ``step(state, action)`` with a state of
    leading axis [W] and actions f[W, D, n_act]; the same states as ``vmap`` of `AutoReset`, but a reset is
    computed only for the worlds whose episode ended (see `reset_where`).

    When the env does not randomise the drones' params (`Env.shared_params` is not None), the state holds them
    once, with batch shape [D], instead of once per world: ``vmap`` a function of this state with
    ``in_axes=jaxdrones.envs.base.world_axes(wrapper.params_shared)``.

    Args:
        env: the env of one world.
        max_resets: resets computed in the cheap path per step (default: W / 16, at least 1); see `reset_where`.
    """

    def __init__(self, env: Env, max_resets: int | None = None):
        super().__init__(env)
        self.max_resets = max_resets

    @property
    def params_shared(self) -> bool:
        """Whether the state's ``params`` are shared by every world (batch shape [D]) rather than per world."""
        return self.env.shared_params is not None

    def reset(self, key: jax.Array, task: TaskParams | None = None) -> EnvState:
        """Start W episodes from keys [W] (typed or raw uint32 [W, 2]); ``task`` as in the env, with axis [W]."""
        axes = world_axes(self.params_shared)
        if task is None:
            return jax.vmap(lambda k: _final_info(self.env.reset(k)), out_axes=axes)(key)
        return jax.vmap(lambda k, t: _final_info(self.env.reset(k, t)), out_axes=axes)(key, task)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Step every world with ``action`` f[W, D, n_act] and reset the ones whose episode ended."""
        return self.step_ended(state, action)[1]

    def starts(self, state: EnvState) -> EnvState:
        """The episode each world of ``state`` [W] starts when its episode ends (``env.reset(state.key,
        state.task)``, as a reset in `step` would draw it), for `step_ended`'s ``starts``: draw them once before a
        loop of steps (not differentiated: they do not depend on the actions)."""
        axes = world_axes(self.params_shared)
        return jax.lax.stop_gradient(jax.vmap(self.env.reset, out_axes=axes)(state.key, state.task))

    def step_ended(
        self, state: EnvState, action: jax.Array, starts: EnvState | None = None
    ) -> tuple[EnvState, EnvState]:
        """`step`, also returning each world's state right after the step, before any reset (e.g. for a training
        loss of the step that ended an episode): ``(ended [W], state [W])``.

        ``starts``: the worlds' next episodes drawn before (`starts`), which a world whose episode ends takes (a
        select per leaf) instead of a reset computed here. A world whose episode ends twice while the same
        ``starts`` are handed in (an episode shorter than the loop between two draws) starts the same episode again.
        """
        axes = world_axes(self.params_shared)
        ended = _final_info(jax.vmap(self.env.step, in_axes=(axes, 0), out_axes=axes)(state, action))
        return ended, reset_where(
            self.env,
            ended,
            ended.done,
            self.max_resets,
            keep=ENDING_STEP_FIELDS,
            shared_params=self.params_shared,
            starts=starts,
        )


def reset_where(
    env: Env,
    state: EnvState,
    mask: jax.Array,
    max_resets: int | None = None,
    keep: tuple[str, ...] = (),
    shared_params: bool = False,
    starts: EnvState | None = None,
) -> EnvState:
    """Replace the worlds of a batched ``state`` where ``mask`` holds by a new episode, ``env.reset(key, task)`` with
    the world's own key and task params; the other worlds are returned unchanged.

    When at most ``max_resets`` worlds need it (the common case: episodes last many steps), only those are reset:
    their rows are gathered and reset, and each world picks its new row by its rank among the reset worlds (a
    gather fused into the per-world choice, cheaper on CPU than scattering the rows back). Otherwise every world
    is reset and the result chosen per world. Both paths give the same states; the choice is a ``lax.cond``
    (under an outer ``vmap`` both run).

    Args:
        env: the env of one world.
        state: EnvState with leading world axis [W] (``params`` [D] if ``shared_params``).
        mask: bool[W], the worlds to reset.
        max_resets: the most worlds reset by gathering (default: W / 16, at least 1).
        keep: EnvState fields that a reset world keeps from ``state`` (e.g. the reward of the step that ended its
            episode); their structure must match the reset's.
        shared_params: ``state.params`` are shared by every world (see `VmapAutoReset`); the env's ``reset`` must
            then return them unchanged.
        starts: EnvState [W] of new episodes drawn before (`VmapAutoReset.starts`): the worlds of ``mask`` take
            their row, and no reset is computed (no random numbers, no ``lax.cond``).

    Returns:
        EnvState [W].
    """
    n = mask.shape[0]
    k = min(n, max(1, n // 16) if max_resets is None else int(max_resets))
    axes = world_axes(shared_params)
    # Fields taken from `state` as they are: those kept, and the params when shared (None: not a leaf to choose).
    carried = {f: None for f in keep} | ({"params": None} if shared_params else {})

    def fresh(key: jax.Array, task) -> EnvState:
        return jax.vmap(env.reset, out_axes=axes)(key, task).replace(**carried)

    def choose(rows: EnvState, row_of_world) -> EnvState:
        def pick(new, old):
            return jnp.where(mask.reshape(mask.shape + (1,) * (old.ndim - 1)), row_of_world(new), old)

        out = jax.tree.map(pick, rows, state.replace(**carried))
        return out.replace(**{f: getattr(state, f) for f in carried})

    def every() -> EnvState:
        return choose(fresh(state.key, state.task), lambda new: new)

    if starts is not None:
        return choose(starts.replace(**carried), lambda new: new)
    if k >= n:
        return every()
    index = jnp.nonzero(mask, size=k, fill_value=0)[0]  # the worlds to reset, in order (unused slots: world 0)
    rank = jnp.clip(jnp.cumsum(mask) - 1, 0, k - 1)  # each reset world's slot in `index`

    def some() -> EnvState:
        key, task = jax.tree.map(lambda x: x[index], (state.key, state.task))
        return choose(fresh(key, task), lambda new: new[rank])

    return jax.lax.cond(jnp.sum(mask) > k, every, some)
