"""What the host-side adapters (gymnasium, PettingZoo, SB3's VecEnv) share: the frames of ``render_mode``, the window
of ``"human"``, and the warning where torch's threads would contend with JAX's for the CPU."""

from __future__ import annotations

import functools
import sys
import warnings

import jax
import numpy as np

from jaxdrones.envs.base import Env, EnvState

#: ``"human"``: a window shows every step (`HumanView`); ``"rgb_array"``: ``render()`` returns the frame.
RENDER_MODES = ("human", "rgb_array")
#: The env's metrics that count something (action entries): the adapters hand them out as integers.
COUNTS = ("clipped_actions",)


class TorchThreadsWarning(UserWarning):
    """torch computes with several threads in a process where JAX computes on the CPU (`check_torch_threads`)."""


def check_torch_threads() -> None:
    """Warn (`TorchThreadsWarning`, once per process) where torch has been imported with more than one intra-op
    thread and JAX's default backend is the CPU.

    Both libraries then run a thread per core and take the cores from each other at every step, and torch's updates
    run several times slower (measured in docs/adapters.md, "torch beside JAX"). The message gives the fix,
    ``torch.set_num_threads(1)``. The adapters warn rather than set it: torch's threads are the user's, and other
    torch code in the process (a large network, an evaluation) may want them.
    """
    torch = sys.modules.get("torch")
    if torch is None or not hasattr(torch, "get_num_threads"):
        return
    threads = torch.get_num_threads()
    if threads > 1 and jax.default_backend() == "cpu":
        _warn_torch_threads(threads)


@functools.cache  # once per process (Python's own once-per-place registry resets whenever any code sets a filter)
def _warn_torch_threads(threads: int) -> None:
    warnings.warn(
        f"torch computes with {threads} threads in this process, beside JAX on the CPU: the two contend for the "
        f"cores and torch's updates can run several times slower. Call torch.set_num_threads(1) after importing "
        f"torch (docs/adapters.md, 'torch beside JAX'); silence this with warnings.filterwarnings('ignore', "
        f"category=jaxdrones.adapters.TorchThreadsWarning)",
        TorchThreadsWarning,
        stacklevel=4,  # the adapter's caller: the user's reset
    )


def host_metrics(metrics: dict) -> dict:
    """The env's metrics as the host adapters report them: NumPy arrays (of a batch of worlds) or, for one world,
    Python numbers; the counts (`COUNTS`) as integers (i64), the rest as the env's floats."""
    out = {}
    for name, value in metrics.items():
        value = np.asarray(value).astype(np.int64) if name in COUNTS else np.asarray(value)
        out[name] = value.item() if value.ndim == 0 else value
    return out


def render_frame(env: Env, state: EnvState, world: int = 0, shared_params: bool = False) -> np.ndarray:
    """An RGB frame u8[H, W, 3] of one world of ``state``: PyBullet's renderer on that backend, else matplotlib.
    ``shared_params``: ``state.params`` are those of every world (batch shape [D]), not per world."""
    lead = np.shape(state.sim.pos)[:-2]

    def one(x):
        x = np.asarray(x)
        return x.reshape((-1,) + x.shape[len(lead) :])[world] if lead else x

    sim = jax.tree.map(one, state.sim)
    params = jax.tree.map(np.asarray, state.params) if shared_params else jax.tree.map(one, state.params)
    frame = env.render_world(params, sim)
    if frame is not None:
        return frame
    return _plotting().render_state(sim.pos, sim.quat, targets=one(state.task.target), title=env.task.name)


def _plotting():
    from jaxdrones.io import plotting

    return plotting


class HumanView:
    """The window of ``render_mode="human"``: each frame (`render_frame`) drawn with matplotlib's ``imshow`` and
    shown for ``1 / fps`` s (``plt.pause``).

    It needs an interactive matplotlib backend (a display). With a non-interactive one (Agg, e.g. on a headless
    machine or after `jaxdrones.io.plotting` has written files) matplotlib warns that the figure cannot be shown, and
    the env runs on, paced at ``fps``.
    """

    def __init__(self, title: str, fps: float):
        self.title, self.fps = title, fps
        self._figure = self._image = None

    @classmethod
    def for_mode(cls, env: Env, render_mode: str | None) -> HumanView | None:
        """The window of ``env`` (titled by its task, paced at its control rate) for ``render_mode="human"``, else
        None."""
        return cls(env.task.name, env.config.sim.ctrl_freq) if render_mode == "human" else None

    def show(self, frame: np.ndarray) -> None:
        """Draw ``frame`` u8[H, W, 3] in the window (opened, or reopened if the user closed it)."""
        import matplotlib.pyplot as plt

        if self._figure is None or not plt.fignum_exists(self._figure.number):
            self._figure, ax = plt.subplots(num=f"jaxdrones {self.title}")
            ax.set_axis_off()
            self._image = ax.imshow(frame)
            plt.show(block=False)
        else:
            self._image.set_data(frame)
        plt.pause(1.0 / self.fps)

    def close(self) -> None:
        """Close the window."""
        if self._figure is not None:
            import matplotlib.pyplot as plt

            plt.close(self._figure)
            self._figure = None


class OneWorldRendering:
    """``render``, ``close`` and the ``"human"`` window's update of an adapter of one world: it holds ``env``, its
    ``render_mode``, the current ``_state`` (None before the first reset) and ``_view`` (`HumanView.for_mode`)."""

    def render(self) -> np.ndarray | None:
        """An RGB frame u8[H, W, 3] of the current state with ``render_mode="rgb_array"``; None otherwise (with
        ``"human"``, ``reset`` and ``step`` show each frame)."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return render_frame(self.env, self._state)

    def close(self) -> None:
        """Release the env's backend (PyBullet worlds) and close the window of ``render_mode="human"``."""
        if self._view is not None:
            self._view.close()
        self.env.close()

    def _show(self) -> None:
        if self._view is not None:
            self._view.show(render_frame(self.env, self._state))
