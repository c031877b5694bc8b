"""The six motion axes by name, in motion-vector order, and their units (plain Python, no torch:
config validation reads them)."""

from __future__ import annotations

AXES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
"""Axis names in motion-vector order."""


def axis_index(axis: str) -> int:
    """Position of ``axis`` in the motion vector; raises ``ValueError`` for unknown names."""
    try:
        return AXES.index(axis)
    except ValueError:
        raise ValueError(f"unknown motion axis {axis!r}; allowed: {', '.join(AXES)}") from None


def is_translation(axis: str) -> bool:
    """True for tx, ty, tz (metres), False for rx, ry, rz (radians); raises for unknown names."""
    return axis_index(axis) < 3


def unit(axis: str) -> str:
    """The unit of a motion along ``axis``: ``"m"`` or ``"rad"``."""
    return "m" if is_translation(axis) else "rad"
