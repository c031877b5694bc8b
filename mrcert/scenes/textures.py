"""Procedural colours for sampled surfaces: solid, noise, stripes, checks, shading.

All colours are RGB in [0, 1]. :func:`finish` shades with a fixed light and quantises to
multiples of 1/255 (capped at 254/255), so rendered images convert to uint8 losslessly and
no surface is ever the pure-white background.
"""

from __future__ import annotations

import numpy as np

from mrcert.scenes.primitives import Surface

LIGHT = np.array([0.3, -0.4, 0.87]) / np.linalg.norm([0.3, -0.4, 0.87])  # from above, slightly aside


def rgb(color, n: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(color, dtype=np.float64), (n, 3)).copy()


def noise(coords: np.ndarray, scale: float, seed: int, octaves: int = 3) -> np.ndarray:
    """Smooth pseudo-random field in [-1, 1] over 2-D or 3-D coordinates (sums of sines)."""
    rng = np.random.default_rng(seed)
    out = np.zeros(len(coords))
    for o in range(octaves):
        freq = (2.0**o) / scale
        for _ in range(3):
            direction = rng.normal(size=coords.shape[1])
            direction /= np.linalg.norm(direction)
            out += np.sin(coords @ direction * freq * 2 * np.pi + rng.uniform(0, 2 * np.pi)) / (2.0**o)
    return np.tanh(out / 2.0)


def mottled(surface: Surface, color, amp: float, scale: float, seed: int) -> np.ndarray:
    """``color`` varied by a noise field on the 3-D points (roughcast, fruit skin, ...)."""
    c = rgb(color, len(surface.points))
    return c * (1 + amp * noise(surface.points, scale, seed)[:, None])


ROUGHCAST = (0.88, 0.87, 0.84)
"""The room's one material: the MetaRoom's walls, floor, ceiling, door and table are all Webots'
Roughcast, a matte white plaster whose relief is a normal map."""


def roughcast(surface: Surface, seed: int) -> np.ndarray:
    """Matte off-white plaster: ``ROUGHCAST`` with a fine grain standing in for its relief."""
    return mottled(surface, ROUGHCAST, 0.06, 0.01, seed)


RUG_PALETTE = np.array(
    [
        (0.62, 0.16, 0.12),  # madder red
        (0.5, 0.33, 0.2),  # walnut
        (0.16, 0.22, 0.45),  # indigo
        (0.78, 0.6, 0.22),  # ochre
        (0.22, 0.42, 0.26),  # green
        (0.86, 0.8, 0.68),  # undyed wool
        (0.5, 0.5, 0.52),  # grey
        (0.3, 0.2, 0.12),  # dark brown
    ]
)


def patchwork_rug(surface: Surface, half: float, seed: int, tile: float = 0.25, border: float = 0.15) -> np.ndarray:
    """A square rug of side ``2 * half`` centred at the origin: ``tile``-sized squares of wool
    colours picked by a hash of the square and ``seed``, inside a madder-red border."""
    xy = surface.points[:, :2]
    cell = np.floor((xy + half) / tile).astype(np.int64)
    pick = (cell[:, 0] * 73856093 ^ cell[:, 1] * 19349663 ^ (seed + 1) * 83492791) % len(RUG_PALETTE)
    colors = RUG_PALETTE[pick]
    colors[np.abs(xy).max(axis=1) > half - border] = (0.45, 0.12, 0.1)
    return colors * (1 + 0.06 * noise(surface.points, 0.01, seed)[:, None])


def stripes(values: np.ndarray, period: float, color_a, color_b, duty: float = 0.5) -> np.ndarray:
    """Two colours alternating along ``values`` with the given period."""
    on = np.mod(values / period, 1.0) < duty
    return np.where(on[:, None], np.asarray(color_a, float), np.asarray(color_b, float))


def checks(u: np.ndarray, v: np.ndarray, period: float, color_a, color_b) -> np.ndarray:
    on = (np.floor(u / period) + np.floor(v / period)) % 2 == 0
    return np.where(on[:, None], np.asarray(color_a, float), np.asarray(color_b, float))


def finish(surface: Surface, colors: np.ndarray, ambient: float = 0.6) -> np.ndarray:
    """Lambert shading with an ambient term, quantised to k/255 (k <= 254), float32."""
    lambert = np.clip(surface.normals @ LIGHT, 0.0, 1.0)
    shaded = np.clip(colors * (ambient + (1 - ambient) * lambert)[:, None], 0.0, 254 / 255)
    return (np.round(shaded * 255) / 255).astype(np.float32)
