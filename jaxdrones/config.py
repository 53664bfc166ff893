"""The static simulation config `SimConfig` (hashable; a change recompiles)."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxdrones import dynamics
from jaxdrones.kinks import Kinks


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static simulation settings (hashable; changing one recompiles).

    Attributes:
        n_drones: drones per world, D ≥ 1.
        sim_freq: physics rate, Hz (the paper's ``pyb_freq``, default 240).
        ctrl_freq: control rate, Hz; one `step` call runs ``sim_freq // ctrl_freq`` physics substeps with the
            same RPM command. ``sim_freq`` must be a multiple of ``ctrl_freq`` (as in the paper's code).
        drag: rotor drag, paper eq. (drag).
        ground_effect: per-propeller ground effect, paper eq. (ground).
        downwash: downwash between the drones of a world, paper eq. (down).
        integrator: ``"euler"`` (the paper code's semi-implicit Euler with exact quaternion exponential map) or
            ``"rk4"``.
        kinks: how the JAX core treats the kinks of the physics (RPM clip, ground contact, ground effect's height
            clip and attitude condition, downwash's onset and cut-off) for gradients: a `jaxdrones.kinks.Kinks`, or
            its mode ``"exact"`` (the original's physics, default), ``"smooth"`` (C¹ within small bands, so that
            gradients agree with finite differences across each kink) or ``"straight_through"`` (the original's
            forward pass, identity gradients through the clips and the contact). Stored as a `Kinks`.
        max_neighbors: downwash: None (every drone above a drone acts on it, the original; D² pairs per substep) or
            K ≥ 1: only the K drones horizontally nearest to each drone act on it (D·K pairs; the drones beyond are
            ones whose downwash has decayed, see `jaxdrones.aerodynamics.downwash_force`). The K are chosen at the
            start of each control step and held over its substeps, as a neighbour list is. K ≥ D - 1 is the
            original. The JAX core only.

    Raises:
        ValueError: on a non-positive count or rate, ``sim_freq`` not a multiple of ``ctrl_freq``, an unknown
            integrator or kink treatment, or ``max_neighbors`` neither None nor a positive integer.
    """

    n_drones: int = 1
    sim_freq: int = 240
    ctrl_freq: int = 240
    drag: bool = False
    ground_effect: bool = False
    downwash: bool = False
    integrator: str = "euler"
    kinks: Kinks | str = "exact"
    max_neighbors: int | None = None

    def __post_init__(self):
        if isinstance(self.kinks, str):
            object.__setattr__(self, "kinks", Kinks(self.kinks))
        elif not isinstance(self.kinks, Kinks):
            raise ValueError(f"SimConfig.kinks must be a jaxdrones.kinks.Kinks or one of its modes, got {self.kinks!r}")
        for name in ("n_drones", "sim_freq", "ctrl_freq"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise ValueError(f"SimConfig.{name} must be a positive integer, got {value!r}")
        if self.sim_freq % self.ctrl_freq:
            raise ValueError(f"SimConfig: sim_freq ({self.sim_freq} Hz) must be a multiple of ctrl_freq "
                             f"({self.ctrl_freq} Hz), e.g. sim_freq=240 with ctrl_freq in 240, 120, 80, 48, 30, ...")
        k = self.max_neighbors
        if k is not None and (not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1):
            raise ValueError(f"SimConfig.max_neighbors must be None (every drone) or a positive integer, got {k!r}")
        if self.integrator not in dynamics.INTEGRATORS:
            raise ValueError(f"SimConfig.integrator must be one of {tuple(dynamics.INTEGRATORS)}, "
                             f"got {self.integrator!r}")

    @property
    def n_substeps(self) -> int:
        """Physics substeps per control step."""
        return self.sim_freq // self.ctrl_freq

    @property
    def dt(self) -> float:
        """Physics timestep, s."""
        return 1.0 / self.sim_freq

    @property
    def ctrl_dt(self) -> float:
        """Control period, s."""
        return 1.0 / self.ctrl_freq

    @property
    def effects(self) -> dynamics.Effects:
        return dynamics.Effects(self.drag, self.ground_effect, self.downwash, self.kinks, self.max_neighbors)
