"""``task=render``: pictures of a scene under camera motions, and the datasets' images.

* For a scene (``data=testscene`` or ``data=pointcloud``): the scene under a grid (or list)
  of motions, one PNG each and a contact sheet (rows = axes, columns = motion values).
* For a dataset (``data=metaroom_synth``, ``tabletop_synth``, ``custom``, ``metaroom``): the
  train and test images into the cache under ``data.cache_dir`` (vanilla, and motion
  augmented on ``motion.axis`` with ``motion.sigma`` when ``task.variants`` lists
  ``augmented``), and two contact sheets like the paper's Figure 3: every class at a test
  pose, and one class under each axis's motions.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from mrcert.core.axes import AXES, axis_index, is_translation
from mrcert.core.methods import build_method
from mrcert.data.cache import folder_size
from mrcert.data.sources import is_scene, load, load_scene
from mrcert.data.synthetic import SyntheticData
from mrcert.errors import MrcertError
from mrcert.infra.identity import Identity
from mrcert.infra.runtime import resolve_device
from mrcert.infra.tasks import DATA_FILES, Task
from mrcert.infra.tracking import RunContext
from mrcert.reporting.imaging import contact_sheet, save_png


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


def motion_label(axis: str, value: float) -> str:
    return f"{axis} {value:+.3f} m" if is_translation(axis) else f"{axis} {torch.tensor(value).rad2deg():+.2f} deg"


def _grid_sheet(images: torch.Tensor, axes: list[str], num: int, labels, path, title: str):
    rows = [list(range(i * num, (i + 1) * num)) for i in range(len(axes))]
    return contact_sheet(
        [[images[i] for i in idx] for idx in rows],
        axes,
        [[motion_label(*labels[i]) for i in idx] for idx in rows],
        path,
        title=title,
    )


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    if is_scene(cfg.data):
        return render_scene(cfg, ctx)
    return render_dataset(cfg, ctx)


def render_scene(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    device = resolve_device(cfg.device)
    scene = load_scene(cfg.data, device)
    t = cfg.task
    start = time.perf_counter()
    if t.motions is not None:
        motions = torch.tensor(OmegaConf.to_container(t.motions), dtype=torch.float64).reshape(-1, 6)
        images, _ = scene.render(motions, backend=t.backend)
        seconds = time.perf_counter() - start
        names = [f"{i:03d}.png" for i in range(len(motions))]
        sheet = contact_sheet(
            [list(images)],
            ["motions"],
            [[str([round(v, 4) for v in m.tolist()]) for m in motions]],
            ctx.output_dir / "contact_sheet.png",
        )
    else:
        motions, labels = motion_grid(list(t.axes or AXES), int(t.num), dict(t.extent))
        images, _ = scene.render(motions, backend=t.backend)
        seconds = time.perf_counter() - start
        names = [f"{i:03d}_{axis}_{value:+.5f}.png" for i, (axis, value) in enumerate(labels)]
        sheet = _grid_sheet(
            images,
            list(t.axes or AXES),
            int(t.num),
            labels,
            ctx.output_dir / "contact_sheet.png",
            f"{cfg.data.name}: {scene.points.shape[0]:,} points, {scene.width}x{scene.height}",
        )
    image_dir = ctx.output_dir / "images"
    for name, image in zip(names, images, strict=True):
        save_png(image, image_dir / name)
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


def render_dataset(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    unknown = set(t.variants) - {"vanilla", "augmented"}
    if unknown:
        raise MrcertError(f"task.variants has {sorted(unknown)}; allowed: vanilla, augmented")
    metrics: dict[str, float] = {}
    start = time.perf_counter()
    bundle = load(cfg.data)
    sets = {"test": bundle.test}
    if "vanilla" in t.variants:
        sets["train"] = bundle.train
    if "augmented" in t.variants:
        augment = build_method(cfg)
        sets[f"train-{augment.axes_label}-aug"] = lambda: bundle.train(augment, int(cfg.seed))
    loaded = {}
    for name, make in sets.items():
        began = time.perf_counter()
        loaded[name] = make()
        metrics[f"{name}_images"] = len(loaded[name])
        metrics[f"{name}_seconds"] = time.perf_counter() - began
    for tag, info in bundle.cache_info.items():
        metrics[f"{tag}_cache_hit"] = float(info["hit"])
        metrics[f"{tag}_cache_bytes"] = folder_size(info["folder"])
    metrics["total_seconds"] = time.perf_counter() - start
    if isinstance(bundle, SyntheticData):
        metrics["points_background"] = len(bundle.source.background[0])
        metrics["points_per_scene_mean"] = sum(len(bundle.cloud(c)[0]) for c in range(len(bundle.classes))) / len(
            bundle.classes
        )

    sheets = [_classes_sheet(loaded["test"], ctx, cfg.data.name), _motions_sheet(bundle, cfg, ctx)]
    ctx.tracker.log_metrics(metrics)
    for sheet in sheets:
        ctx.tracker.log_artifact(sheet)
    return metrics | {"contact_sheets": [str(s) for s in sheets], "cache": bundle.cache_info}


def _classes_sheet(test, ctx: RunContext, name: str):
    """Every class at its first test pose (rows of up to five)."""
    first = [int((test.labels == c).nonzero()[0][0]) for c in range(len(test.classes)) if (test.labels == c).any()]
    tiles = [test[i][0] for i in first]
    names = [test.classes[int(test.labels[i])] for i in first]
    cols = 5 if len(tiles) > 6 else len(tiles)
    rows = [tiles[r : r + cols] for r in range(0, len(tiles), cols)]
    labels = [names[r : r + cols] for r in range(0, len(names), cols)]
    return contact_sheet(
        rows,
        [""] * len(rows),
        labels,
        ctx.output_dir / "classes.png",
        title=f"{name}: the {len(tiles)} classes at a test pose",
    )


def _motions_sheet(bundle, cfg: DictConfig, ctx: RunContext):
    """One class at its first test pose under each axis's motions (like the paper's Figure 3)."""
    t = cfg.task
    label = bundle.classes.index(t.showcase) if t.showcase in bundle.classes else 0
    samples = bundle.samples()
    index = int((samples.labels == label).nonzero()[0][0])
    sample = samples[index]
    motions, labels = motion_grid(list(AXES), int(t.num), dict(t.extent))
    images, _ = sample.render(motions)
    return _grid_sheet(
        images,
        list(AXES),
        int(t.num),
        labels,
        ctx.output_dir / "motions.png",
        f"{cfg.data.name}: {bundle.classes[label]} under camera motions",
    )


class Render(Task):
    summary = "render a scene under motions, or a dataset's images into the cache"
    identity = Identity(
        defines=("task", "data", "motion", "method", "seed", "profile"),
        ignores=("model", "train", "attack", "task.backend"),
        files=DATA_FILES,
        method="result",
    )

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
