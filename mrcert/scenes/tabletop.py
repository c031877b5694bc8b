"""Synthetic tabletop: the paper's real-robot setting (Section 4.5, Appendix B.4).

One flat shape (1 cm thick, about 9 cm across) at the centre of a 1 m x 1 m table; world z
up with the origin at the shape's centre on the table top. All shapes share one colour, so
they are told apart by their outline. The robot base stands 0.7 m away along -x; the
eye-in-hand camera looks at the shape from that side.
"""

from __future__ import annotations

import numpy as np
from matplotlib.path import Path as PolyPath

from mrcert.scenes.primitives import Surface, rect
from mrcert.scenes.textures import finish, noise, rgb

THICKNESS = 0.01
SHAPE_COLOR = (0.15, 0.35, 0.8)
TABLE = 1.0  # the table's side (m)


def _polar(r_of_theta, n: int = 256) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = r_of_theta(t)
    return np.column_stack([r * np.cos(t), r * np.sin(t)])


OUTLINES: dict[str, np.ndarray] = {
    "diamond": np.array([[0.055, 0], [0, 0.035], [-0.055, 0], [0, -0.035]]),
    "oval": _polar(lambda t: 1 / np.sqrt((np.cos(t) / 0.05) ** 2 + (np.sin(t) / 0.032) ** 2)),
    "quatrefoil": _polar(lambda t: 0.03 + 0.018 * np.abs(np.cos(2 * t))),
    "rectangle": np.array([[0.05, 0.03], [-0.05, 0.03], [-0.05, -0.03], [0.05, -0.03]]),
    "star": np.array(
        [
            [r * np.cos(np.pi / 2 + k * np.pi / 5), r * np.sin(np.pi / 2 + k * np.pi / 5)]
            for k, r in enumerate([0.05, 0.021] * 5)
        ]
    ),
    "trapezoid": np.array([[0.055, -0.03], [0.03, 0.03], [-0.03, 0.03], [-0.055, -0.03]]),
}
CLASSES: tuple[str, ...] = tuple(sorted(OUTLINES))


def _extrude(outline: np.ndarray, density: float) -> Surface:
    """A flat prism: top face (points inside the outline) and side walls along it."""
    lo, hi = outline.min(0), outline.max(0)
    top = rect([lo[0], lo[1], THICKNESS], [hi[0] - lo[0], 0, 0], [0, hi[1] - lo[1], 0], density)
    inside = PolyPath(outline).contains_points(top.points[:, :2])
    parts = [Surface(top.points[inside], top.normals[inside], top.uv[inside])]
    closed = np.vstack([outline, outline[:1]])
    for a, b in zip(closed[:-1], closed[1:], strict=True):
        edge = b - a
        wall = rect([a[0], a[1], 0.0], [edge[0], edge[1], 0.0], [0, 0, THICKNESS], density)
        parts.append(wall)
    return Surface.concat(parts)


TABLE_AMBIENT = 0.6
"""The table's share of ambient light (the rest is Lambert under ``textures.LIGHT``)."""


def table(density: float, ambient: float = TABLE_AMBIENT) -> tuple[np.ndarray, np.ndarray]:
    top = rect([-TABLE / 2, -TABLE / 2, 0.0], [TABLE, 0, 0], [0, TABLE, 0], density)
    grain = 1 + 0.1 * noise(top.points[:, :2] * [1, 6], 0.3, 31)
    return top.points, finish(top, rgb((0.78, 0.66, 0.5), len(grain)) * grain[:, None], ambient)


def shape_cloud(name: str, density: float) -> tuple[np.ndarray, np.ndarray]:
    if name not in OUTLINES:
        raise ValueError(f"unknown tabletop shape {name!r}; allowed: {', '.join(CLASSES)}")
    s = _extrude(OUTLINES[name], density)
    return s.points, finish(s, rgb(SHAPE_COLOR, len(s.points)))
