"""Env → env wrappers: `AutoReset` (a fresh episode, drawn from the world's own key, when one ends)."""

from jaxdrones.wrappers.autoreset import AutoReset

__all__ = ["AutoReset"]
