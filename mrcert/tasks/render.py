"""``task=render``: the scene under a grid (or list) of camera motions."""

from __future__ import annotations

import time
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from mrcert.geometry import AXES, axis_index
from mrcert.imaging import contact_sheet, save_png
from mrcert.runtime import resolve_device
from mrcert.scenes import load_scene
from mrcert.tasks import RunContext


def motion_grid(axes: list[str], num: int, extent: dict[str, float]) -> tuple[torch.Tensor, list[tuple[str, float]]]:
    """``num`` evenly spaced motions in ``[-extent, extent]`` per axis, and their (axis, value) labels."""
    motions, labels = [], []
    for axis in axes:
        values = torch.linspace(-float(extent[axis]), float(extent[axis]), num, dtype=torch.float64)
        m = torch.zeros(num, 6, dtype=torch.float64)
        m[:, axis_index(axis)] = values
        motions.append(m)
        labels += [(axis, float(v)) for v in values]
    return torch.cat(motions), labels


def _label(axis: str, value: float) -> str:
    return f"{axis} {value:+.3f} m" if axis.startswith("t") else f"{axis} {torch.tensor(value).rad2deg():+.2f} deg"


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    device = resolve_device(cfg.device)
    scene = load_scene(cfg.data, device)
    t = cfg.task
    if t.motions is not None:
        motions = torch.tensor(OmegaConf.to_container(t.motions), dtype=torch.float64).reshape(-1, 6)
        rows = [("motions", list(range(len(motions))))]
        labels = [(f"#{i}", 0.0) for i in range(len(motions))]
    else:
        motions, labels = motion_grid(list(t.axes), int(t.num), dict(t.extent))
        rows = [(axis, list(range(i * t.num, (i + 1) * t.num))) for i, axis in enumerate(t.axes)]
    start = time.perf_counter()
    images, _ = scene.render(motions, backend=t.backend)
    seconds = time.perf_counter() - start

    image_dir = ctx.output_dir / "images"
    for i, (axis, value) in enumerate(labels):
        name = f"{i:03d}_{axis}_{value:+.5f}.png" if axis in AXES else f"{i:03d}.png"
        save_png(images[i], image_dir / name)
    sheet = contact_sheet(
        [[images[i] for i in idx] for _, idx in rows],
        [axis for axis, _ in rows],
        [[_label(*labels[i]) if labels[i][0] in AXES else str(motions[i].tolist()) for i in idx] for _, idx in rows],
        ctx.output_dir / "contact_sheet.png",
        title=f"{cfg.data.name}: {scene.points.shape[0]:,} points, {scene.width}x{scene.height}",
    )
    metrics = {
        "num_points": scene.points.shape[0],
        "num_images": len(motions),
        "render_seconds": seconds,
        "images_per_second": len(motions) / max(seconds, 1e-9),
    }
    ctx.tracker.log_metrics(metrics)
    ctx.tracker.log_artifact(sheet)
    ctx.tracker.log_artifact(image_dir, "images")
    return metrics | {"contact_sheet": str(sheet)}
