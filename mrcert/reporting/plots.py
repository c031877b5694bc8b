"""Certified accuracy against radius, drawn as the exact step function of a certify log:
``acc[i]`` on ``(r[i-1], r[i]]``, then 0 beyond the largest radius (:func:`certify_log.curve`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

Curve = tuple[np.ndarray, np.ndarray]


def curve_figure(
    panels: dict[str, dict[str, Curve]],
    title: str,
    xlabels: dict[str, str] | None = None,
    marks: dict[str, float] | None = None,
    columns: int = 3,
):
    """A matplotlib figure: one panel per key of ``panels`` (its title), one step curve per
    label, a dashed line at ``marks[panel]`` (e.g. the certified radius)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = -(-len(panels) // columns)
    cols = min(columns, len(panels))
    fig, grid = plt.subplots(rows, cols, figsize=(4 * cols, 3.25 * rows), squeeze=False)
    for ax in grid.ravel()[len(panels) :]:
        ax.set_visible(False)
    for ax, (name, curves) in zip(grid.ravel(), panels.items(), strict=False):
        ax.set(title=name, xlabel=(xlabels or {}).get(name, "radius"), ylabel="certified accuracy", ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        for label, (radii, acc) in curves.items():
            end = radii[-1] * 1.05 + 1e-12
            ax.step(np.append(radii, end), np.append(acc, 0.0), where="pre", label=label or None, lw=1.6)
        if (marks or {}).get(name) is not None:
            ax.axvline(marks[name], color="grey", ls="--", lw=1)
        if any(curves):
            ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def save(fig, paths: list[Path]) -> list[Path]:
    """Write ``fig`` to every path (PNG, PDF) and free it."""
    import matplotlib.pyplot as plt

    for path in paths:
        fig.savefig(path, dpi=130)
    plt.close(fig)
    return paths
