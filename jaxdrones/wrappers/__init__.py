"""Env → env wrappers: `AutoReset` and its batched form `VmapAutoReset` (a fresh episode, drawn from the world's own
key, when one ends), and `reset_where`."""

from jaxdrones.wrappers.autoreset import AutoReset, VmapAutoReset, reset_where

__all__ = ["AutoReset", "VmapAutoReset", "reset_where"]
