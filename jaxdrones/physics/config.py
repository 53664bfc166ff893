"""The static simulation config `SimConfig` (hashable; a change recompiles)."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxdrones._hints import did_you_mean
from jaxdrones._validate import check_bool, check_int, check_real
from jaxdrones.physics import dynamics
from jaxdrones.physics.aerodynamics import DOWNWASH_MODELS
from jaxdrones.physics.kinks import Kinks


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
        downwash: downwash between the drones of a world: False (off), ``"paper"`` (paper eq. (down): one force at
            the lower drone's centre of mass, docs/physics.md §6.3; True, as which it is stored),
            ``"per_rotor"`` (the upper drones' jet sampled at each rotor of the lower drone, a thrust change per rotor
            and hence a torque, docs/physics.md §6.4) or ``"bounded"`` (the paper's form, finite as the drones' heights
            meet and scaled by their thrusts, fitted to real Crazyflie flights: docs/physics.md §6.5,
            docs/validation.md §3).
        integrator: ``"euler"`` (the paper code's semi-implicit Euler with exact quaternion exponential map) or
            ``"rk4"``.
        kinks: how the JAX core treats the kinks of the physics (RPM clip, ground contact, ground effect's height
            clip and attitude condition, downwash's onset and cut-off) for gradients: a
            `jaxdrones.physics.kinks.Kinks`, or its mode ``"exact"`` (the original's physics, default), ``"smooth"`` (C¹
            within small bands, so that gradients agree with finite differences across each kink) or
            ``"straight_through"`` (the original's forward pass, identity gradients through the clips and the contact).
            Stored as a `Kinks`.
        downwash_radius: downwash: None (every pair of drones closer than the original's 10 m horizontally; D² pairs
            per substep) or a cut-off r in m, within which a cell list (`jaxdrones.physics.neighbors.cell_candidates`,
            cells of side r, built at the start of each control step and held over its substeps: a drone that comes
            within r during the step may be missed until the next) finds each drone's neighbours: O(D) pairs. Beyond 1 m
            no drone pushes a cf2x with more than 0.41 % of its weight (docs/physics.md §6.3). The JAX core only.
        cell_capacity: with ``downwash_radius``: drones per cell the list holds (a denser cell loses the extra ones).
        adjoint: take reverse-mode derivatives (``jax.grad``, ``jax.vjp``, ``jax.jacrev``) of the Euler integrator
            with exact kinks through the hand-written adjoint of `jaxdrones.physics.adjoint` (default True): a gradient
            then costs 2-3 forward passes however the step is called (`benchmarks/gradients/gradients.py`). Such a step
            has no forward-mode derivative: ``jax.jvp`` and ``jax.jacfwd`` raise JAX's "can't apply forward-mode
            autodiff (jvp) to a custom_vjp function". False gives JAX's derived derivatives in both modes (the
            control step is then rematerialised in the reverse pass). RK4 and the other kink treatments always
            use JAX's.
        unroll_substeps: the control step's physics substeps written out one after the other in the compiled
            program (True), as a loop (False, default), or None: unrolled on a GPU or TPU and a loop on the CPU,
            chosen when the step is traced. Unrolled, XLA fuses the element-wise work of all substeps into a few
            kernels: on a GPU the step runs about twice as fast but compiles longer, worth it for long runs, not for
            the compilation every new setting costs; on the CPU it runs slower (`benchmarks/training/train_cost.py
            --per-step`, docs/benchmarks.md, "Training at a GPU's speed"). The results are the same either way (to
            float rounding: XLA may fuse the arithmetic differently).

    Raises:
        ValueError: on a non-positive count or rate, ``sim_freq`` not a multiple of ``ctrl_freq``, an unknown
            integrator or kink treatment, a ``downwash_radius`` neither None nor > 0, a ``cell_capacity`` below 1,
            a ``drag``, ``ground_effect``, ``adjoint`` or ``motor_dynamics`` that is not a bool (a string or number
            would otherwise be truthy), an ``unroll_substeps`` neither a bool nor None, or a ``downwash`` that is none
            of False, True, ``"paper"``, ``"per_rotor"``, ``"bounded"``.
    """

    n_drones: int = 1
    sim_freq: int = 240
    ctrl_freq: int = 240
    drag: bool = False
    ground_effect: bool = False
    downwash: bool | str = False
    integrator: str = "euler"
    kinks: Kinks | str = "exact"
    downwash_radius: float | None = None
    cell_capacity: int = 8
    adjoint: bool = True
    motor_dynamics: bool = False
    unroll_substeps: bool | None = False

    def __post_init__(self):
        if isinstance(self.kinks, str):
            object.__setattr__(self, "kinks", Kinks(self.kinks))
        elif not isinstance(self.kinks, Kinks):
            raise ValueError(f"SimConfig.kinks must be a jaxdrones.kinks.Kinks or one of its modes, got {self.kinks!r}")
        for name in ("n_drones", "sim_freq", "ctrl_freq"):
            check_int(f"SimConfig.{name}", getattr(self, name))
        if self.sim_freq % self.ctrl_freq:
            raise ValueError(
                f"SimConfig: sim_freq ({self.sim_freq} Hz) must be a multiple of ctrl_freq "
                f"({self.ctrl_freq} Hz), e.g. sim_freq=240 with ctrl_freq in 240, 120, 80, 48, 30, ..."
            )
        if self.downwash_radius is not None:
            what = "None (every drone) or a finite radius in m"
            check_real("SimConfig.downwash_radius", self.downwash_radius, 0, low_open=True, what=what)
        check_int("SimConfig.cell_capacity", self.cell_capacity)
        for name in ("drag", "ground_effect", "adjoint", "motor_dynamics"):
            object.__setattr__(self, name, check_bool(f"SimConfig.{name}", getattr(self, name)))
        unroll = self.unroll_substeps
        if unroll is not None and not isinstance(unroll, (bool, np.bool_)):
            raise ValueError(f"SimConfig.unroll_substeps must be True, False or None (per device), got {unroll!r}")
        object.__setattr__(self, "unroll_substeps", None if unroll is None else bool(unroll))
        object.__setattr__(self, "downwash", downwash_model(self.downwash, "SimConfig.downwash"))
        if self.integrator not in dynamics.INTEGRATORS:
            raise ValueError(
                f"SimConfig.integrator must be one of {tuple(dynamics.INTEGRATORS)}, got {self.integrator!r}"
            )

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
    def substep_unroll(self) -> int:
        """The ``unroll`` of the substeps' ``lax.scan`` (`unroll_substeps`; None decides by
        ``jax.default_backend()``, so call it while tracing)."""
        import jax

        unroll = self.unroll_substeps
        if unroll is None:
            unroll = jax.default_backend() != "cpu"
        return self.n_substeps if unroll else 1

    @property
    def hand_written_adjoint(self) -> bool:
        """Whether the step's reverse-mode derivative is the hand-written adjoint of `jaxdrones.physics.adjoint`:
        ``adjoint=True`` with the Euler integrator and exact kinks (the defaults). Smooth and straight-through
        kinks (`jaxdrones.physics.kinks`) and RK4 keep JAX's derived derivatives."""
        return self.adjoint and self.integrator == "euler" and self.kinks.mode == "exact"

    @property
    def effects(self) -> dynamics.Effects:
        return dynamics.Effects(
            self.drag, self.ground_effect, self.downwash, self.kinks, self.downwash_radius, self.cell_capacity
        )


def downwash_model(value: bool | str, name: str = "downwash") -> bool | str:
    """A downwash setting (`SimConfig.downwash`, `jd.make(..., downwash=...)`) normalised: False
    (off), True (the paper's model, for True or ``"paper"``), ``"per_rotor"`` or ``"bounded"``.

    Raises:
        ValueError: any other value, naming ``name`` and the valid choices (with a close one for a mistyped string).
    """
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, str) and value in DOWNWASH_MODELS:
        return True if value == "paper" else value
    hint = did_you_mean(value, DOWNWASH_MODELS) if isinstance(value, str) else ""
    raise ValueError(
        f"{name} must be False (off), True or 'paper' (the paper's model), 'per_rotor' (thrust "
        f"changes per rotor) or 'bounded' (the paper's form fitted to real flights), got {value!r}{hint}"
    )
