"""Env → env wrappers: `AutoReset` and its batched form `VmapAutoReset` (a fresh episode, drawn from the world's own
key, when one ends), `reset_where`, and `NormalizeObservation` (observations standardised by running statistics
per world)."""

from jaxdrones.wrappers.autoreset import AutoReset, VmapAutoReset, reset_where
from jaxdrones.wrappers.normalize import NormalizeObservation

__all__ = ["AutoReset", "NormalizeObservation", "VmapAutoReset", "reset_where"]
