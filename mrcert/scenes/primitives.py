"""Dense surface sampling of simple shapes, for building scenes from primitives.

Every sampler returns a :class:`Surface`: points (M, 3) float64 spaced about ``density``
apart, their outward unit normals, and surface coordinates ``uv`` (M, 2) in metres for
procedural textures. Samples are on regular grids, so a scene is a deterministic function of
its parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from mrcert.core.geometry import rotvec_to_matrix


@dataclass
class Surface:
    points: np.ndarray
    normals: np.ndarray
    uv: np.ndarray

    def moved(self, R: np.ndarray | None = None, t=(0.0, 0.0, 0.0)) -> Surface:
        """The surface rotated by ``R`` then translated by ``t``."""
        R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
        return Surface(self.points @ R.T + np.asarray(t, dtype=np.float64), self.normals @ R.T, self.uv)

    @staticmethod
    def concat(parts: list[Surface]) -> Surface:
        return Surface(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("points", "normals", "uv")))


def _steps(length: float, density: float) -> np.ndarray:
    return np.linspace(0.0, 1.0, max(2, int(np.ceil(length / density)) + 1))


def grid_rect(origin, u, v, density: float) -> np.ndarray:
    """Points on the parallelogram ``origin + a u + b v`` (a, b in [0, 1]) spaced ``density``.

    Returns (M, 3) float64, with at least two samples along each edge.
    """
    return rect(origin, u, v, density).points


def rect(origin, u, v, density: float) -> Surface:
    """The parallelogram ``origin + a u + b v``; its normal is ``u x v`` normalised."""
    origin, u, v = (np.asarray(x, dtype=np.float64) for x in (origin, u, v))
    a, b = np.meshgrid(_steps(np.linalg.norm(u), density), _steps(np.linalg.norm(v), density), indexing="ij")
    a, b = a.reshape(-1, 1), b.reshape(-1, 1)
    n = np.cross(u, v)
    n = n / np.linalg.norm(n)
    uv = np.hstack([a * np.linalg.norm(u), b * np.linalg.norm(v)])
    return Surface(origin + a * u + b * v, np.broadcast_to(n, (len(a), 3)).copy(), uv)


def box(center, size, density: float) -> Surface:
    """The six faces of an axis-aligned box with outward normals."""
    return Surface.concat(
        [Surface(p, np.broadcast_to(n, p.shape).copy(), p[:, :2].copy()) for p, n in box_faces(center, size, density)]
    )


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


def revolution(profile: np.ndarray, density: float, arc: tuple[float, float] = (0.0, 2 * np.pi)) -> Surface:
    """Surface of revolution about +z of a polyline ``profile`` of (radius, height) vertices.

    The polyline is resampled every ``density`` along its length; each ring has
    ``ceil(arc length / density)`` points. Normals point away from the axis for a profile
    drawn bottom to top on the outside (cylinders, spheres, bottles, vases...).
    """
    profile = np.asarray(profile, dtype=np.float64)
    seg = np.diff(profile, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    s = np.linspace(0.0, cum[-1], max(2, int(np.ceil(cum[-1] / density)) + 1))
    r = np.interp(s, cum, profile[:, 0])
    z = np.interp(s, cum, profile[:, 1])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    dr, dz = seg[k, 0] / np.maximum(seg_len[k], 1e-12), seg[k, 1] / np.maximum(seg_len[k], 1e-12)
    pts, nrm, uv = [], [], []
    for ri, zi, dri, dzi, si in zip(r, z, dr, dz, s, strict=True):
        span = (arc[1] - arc[0]) * max(ri, 0.0)
        n = max(1, int(np.ceil(span / density))) if ri > 1e-9 else 1
        phi = arc[0] + (arc[1] - arc[0]) * (np.arange(n) + 0.5) / n
        c, sn = np.cos(phi), np.sin(phi)
        pts.append(np.column_stack([ri * c, ri * sn, np.full(n, zi)]))
        nrm.append(np.column_stack([dzi * c, dzi * sn, np.full(n, -dri)]))
        uv.append(np.column_stack([phi * max(ri, 1e-3), np.full(n, si)]))
    return Surface(np.concatenate(pts), np.concatenate(nrm), np.concatenate(uv))


def cylinder(radius: float, height: float, density: float, caps: bool = True) -> Surface:
    """Closed cylinder on z in [0, height]."""
    profile = [(radius, 0.0), (radius, height)]
    if caps:
        profile = [(0.0, 0.0), *profile, (0.0, height)]
    return revolution(np.array(profile), density)


def sphere(radius: float, density: float, center=(0.0, 0.0, 0.0), squash: float = 1.0) -> Surface:
    """Sphere (or spheroid with vertical semi-axis ``radius * squash``)."""
    t = np.linspace(-np.pi / 2, np.pi / 2, 64)
    profile = np.column_stack([radius * np.cos(t), radius * squash * np.sin(t)])
    return revolution(profile, density).moved(t=center)


def torus(major: float, minor: float, density: float, arc: tuple[float, float] = (0.0, 2 * np.pi)) -> Surface:
    """Torus about +z (a handle when rotated and cut with ``arc``)."""
    t = np.linspace(-np.pi, np.pi, 48)
    profile = np.column_stack([major + minor * np.cos(t), minor * np.sin(t)])
    return revolution(profile, density, arc)


def rotation(axis: str, angle: float) -> np.ndarray:
    """Rotation matrix about world axis ``"x"``, ``"y"`` or ``"z"`` (docs/method.md §1)."""
    rotvec = torch.zeros(3, dtype=torch.float64)
    rotvec["xyz".index(axis)] = angle
    return rotvec_to_matrix(rotvec).numpy()
