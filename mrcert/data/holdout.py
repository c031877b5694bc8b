"""The validation split: training poses held out for model selection.

The test poses are for evaluation only; choosing ``best.pt`` on them would bias every number
computed on them afterwards. So a seeded share of each class's *training* poses is held out:
``round(fraction * n_c)`` poses of class ``c`` (at least one when ``fraction > 0`` and the
class has two or more), drawn by a generator seeded with ``(seed, c)``. The split depends only
on the labels, the fraction and the seed, never on the images.
"""

from __future__ import annotations

import numpy as np


def validation_split(labels: np.ndarray, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(train, validation)`` into ``labels``, both sorted; disjoint, covering all."""
    labels = np.asarray(labels)
    if not 0 <= fraction < 1:
        raise ValueError(f"validation fraction {fraction} is not in [0, 1)")
    held: list[np.ndarray] = []
    for label in np.unique(labels):
        idx = np.flatnonzero(labels == label)
        count = int(round(fraction * len(idx)))
        if fraction > 0 and len(idx) > 1:
            count = min(max(count, 1), len(idx) - 1)
        rng = np.random.default_rng([int(seed), int(label), 0x7A1])
        held.append(rng.choice(idx, size=count, replace=False))
    val = np.sort(np.concatenate(held)) if held else np.zeros(0, np.int64)
    train = np.setdiff1d(np.arange(len(labels)), val)
    return train, val
