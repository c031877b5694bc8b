"""Writing images: single PNGs and labelled contact sheets."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from mrcert.core.projection import to_uint8


def pil_array(image: torch.Tensor) -> np.ndarray:
    """One (C, H, W) image as PIL wants it: (H, W, C) uint8, or (H, W) for grey."""
    arr = to_uint8(image)
    return arr[..., 0] if arr.shape[2] == 1 else arr


def save_png(image: torch.Tensor, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pil_array(image)).save(path)
    return path


def contact_sheet(
    images: Sequence[Sequence[torch.Tensor]],
    row_labels: Sequence[str],
    col_labels: Sequence[Sequence[str]],
    path: Path,
    title: str = "",
) -> Path:
    """A grid of images (rows x columns) with a label on each row and under each image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = len(images), max(len(r) for r in images)
    h, w = images[0][0].shape[-2:]
    scale = 2.2 / w
    fig, axes = plt.subplots(
        rows, cols, figsize=(cols * w * scale + 0.8, rows * (h * scale + 0.35) + 0.4), squeeze=False
    )
    for r in range(rows):
        for c in range(cols):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if c < len(images[r]):
                ax.imshow(pil_array(images[r][c]), interpolation="nearest")
                ax.set_xlabel(col_labels[r][c], fontsize=7)
            else:
                ax.axis("off")
        axes[r][0].set_ylabel(row_labels[r], fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
