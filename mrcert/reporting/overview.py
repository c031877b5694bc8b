"""The method in one picture: a test view, the views camera motion smoothing draws around it,
and the certified accuracy against radius that CERTIFY's votes over such views give.

``task=tables`` writes it beside the tables (``method_overview.png``) from the first certify
cell it fills; the README's is the one ``make figures`` makes from the demo's runs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from mrcert.core.axes import axis_index, is_translation
from mrcert.core.methods.base import Method
from mrcert.reporting.certify_log import curve
from mrcert.reporting.imaging import pil_array
from mrcert.reporting.plots import save


def motion_text(axes: tuple[str, ...], motion: torch.Tensor) -> str:
    """A motion's values on ``axes``, in centimetres or degrees."""
    return ", ".join(
        f"{a} {float(motion[axis_index(a)]) * 100:+.1f} cm"
        if is_translation(a)
        else f"{a} {np.degrees(float(motion[axis_index(a)])):+.1f} deg"
        for a in axes
    )


def method_figure(
    method: Method, view: torch.Tensor, name: str, views: torch.Tensor, motions: torch.Tensor, log: pd.DataFrame,
    radius: float, path: Path,
) -> Path:  # fmt: skip
    """The picture for a certify run: its test ``view`` (of class ``name``), ``views`` under the
    smoothing ``motions`` that ``method`` drew around it, and the run's per-image ``log`` as
    certified accuracy against radius, with a dashed line at the ``radius`` it certifies."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = -(-len(views) // 2)
    fig = plt.figure(figsize=(3.0 + 1.75 * cols + 3.4, 3.4))
    outer = fig.add_gridspec(1, 3, width_ratios=[3.0, 1.75 * cols, 3.4], wspace=0.22)
    ax = fig.add_subplot(outer[0])
    ax.imshow(pil_array(view), interpolation="nearest")
    ax.set(xticks=[], yticks=[], title=f"a test view ({name})")
    units = method.sigma_unit.split("+")
    noise = ", ".join(f"{a}: sigma {s:g} {u}" for a, s, u in zip(method.axes, method.sigmas, units, strict=True))
    title = fig.add_subplot(outer[1])
    title.axis("off")
    title.set_title(f"views under smoothing motions ({noise})")
    inner = outer[1].subgridspec(2, cols, hspace=0.35, wspace=0.05)
    for k in range(len(views)):
        ax = fig.add_subplot(inner[k // cols, k % cols])
        ax.imshow(pil_array(views[k]), interpolation="nearest")
        ax.set(xticks=[], yticks=[])
        ax.set_xlabel(motion_text(method.axes, motions[k]), fontsize=7)
    ax = fig.add_subplot(outer[2])
    radii, accuracy = curve(log)
    ax.step(np.append(radii, radii[-1] * 1.05 + 1e-12), np.append(accuracy, 0.0), where="pre", lw=1.6)
    ax.axvline(radius, color="grey", ls="--", lw=1, label=f"r = {radius:g}")
    ax.legend(fontsize=8, loc="lower left")
    ax.set(
        xlabel=f"radius ({method.region_unit})",
        ylabel="certified accuracy",
        ylim=(0, 1.02),
        title=f"certified accuracy, {len(log)} test views",
    )
    ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.01, right=0.985, bottom=0.17, top=0.87)
    save(fig, [path])
    return path
