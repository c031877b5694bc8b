"""The built-in test scene: three coloured boxes in front of a textured wall.

Coordinates are in the reference camera frame (OpenCV axes: x right, y down, z forward), so
the scene renders directly at the paper's 160 x 90 intrinsics.
"""

from __future__ import annotations

import numpy as np

from mrcert.scenes.primitives import box_faces, grid_rect

LIGHT = np.array([-0.4, -0.6, -0.7]) / np.linalg.norm([-0.4, -0.6, -0.7])  # towards the light

BOXES = (  # centre (m), size (m), colour (RGB in [0, 1])
    ((-0.35, 0.10, 2.2), (0.35, 0.35, 0.35), (0.85, 0.15, 0.12)),
    ((0.30, 0.05, 2.6), (0.30, 0.50, 0.30), (0.15, 0.65, 0.20)),
    ((0.02, 0.20, 1.7), (0.18, 0.18, 0.18), (0.15, 0.25, 0.85)),
)


def shade(color, normal) -> np.ndarray:
    """Lambert shading with an ambient term, so that box faces are told apart."""
    return np.clip(np.asarray(color) * (0.55 + 0.45 * max(0.0, float(np.dot(normal, LIGHT)))), 0, 1)


def build(density: float = 0.0025) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) float64 and colours (N, 3) float32 of the scene."""
    wall = grid_rect((-2.0, -1.2, 3.2), (4.0, 0, 0), (0, 2.4, 0), density)
    checker = (np.floor(wall[:, 0] / 0.25) + np.floor(wall[:, 1] / 0.25)) % 2
    stripe = 0.08 * np.sin(wall[:, 0] * 40.0)
    base = np.where(checker[:, None] > 0, [0.80, 0.76, 0.62], [0.45, 0.42, 0.55])
    pts, cols = [wall], [np.clip(base + stripe[:, None], 0, 1)]
    for center, size, color in BOXES:
        for face, normal in box_faces(center, size, density):
            pts.append(face)
            cols.append(np.broadcast_to(shade(color, normal), face.shape))
    return np.concatenate(pts), np.concatenate(cols).astype(np.float32)
