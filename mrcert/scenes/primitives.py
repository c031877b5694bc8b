"""Dense surface sampling of simple shapes, for building scenes from primitives."""

from __future__ import annotations

import numpy as np


def grid_rect(origin, u, v, density: float) -> np.ndarray:
    """Points on the parallelogram ``origin + a u + b v`` (a, b in [0, 1]) spaced ``density``.

    Returns (M, 3) float64, with at least two samples along each edge.
    """
    origin, u, v = (np.asarray(x, dtype=np.float64) for x in (origin, u, v))
    nu = max(2, int(np.ceil(np.linalg.norm(u) / density)) + 1)
    nv = max(2, int(np.ceil(np.linalg.norm(v) / density)) + 1)
    a, b = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    return origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v


def box_faces(center, size, density: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The six faces of an axis-aligned box as (points, outward normal) pairs."""
    c = np.asarray(center, dtype=np.float64)
    s = np.asarray(size, dtype=np.float64) / 2
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            o = c.copy()
            o[axis] += sign * s[axis]
            a, b = [i for i in range(3) if i != axis]
            u = np.zeros(3)
            v = np.zeros(3)
            u[a], v[b] = 2 * s[a], 2 * s[b]
            o[a] -= s[a]
            o[b] -= s[b]
            normal = np.zeros(3)
            normal[axis] = sign
            faces.append((grid_rect(o, u, v, density), normal))
    return faces
