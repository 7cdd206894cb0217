"""Sequences from config values: one value or many, as a list."""

from __future__ import annotations

from typing import Any

__all__ = ["as_list"]


def as_list(value: Any, *, keep_none: bool = False, atoms: tuple[type, ...] = (str,)) -> list | None:
    """``value`` as a list: the items of a list, a tuple or any other iterable (an omegaconf ``ListConfig``), or
    ``[value]`` for one value. ``atoms``: iterable types that count as one value (strings; add ``tuple`` where a
    tuple is one nested key). None is one value too (``[None]``), or stays None with ``keep_none``."""
    if value is None:
        return None if keep_none else [None]
    if isinstance(value, atoms):
        return [value]
    if isinstance(value, (list, tuple)) or hasattr(value, "__iter__"):
        return list(value)
    return [value]
