"""``task=viewpoints``: a trained base classifier's accuracy by viewpoint on a synthetic scene.

Every class is rendered at each pitch of ``task.pitches`` and roll of ``task.rolls``, at the
yaws ``task.yaws`` (null: midway between consecutive test yaws, where the validation poses lie,
never a test view) and the distance ``task.distance`` (null: the test poses'), with only the
scene parts ``task.surroundings`` around the object (``[room, table]``: the whole scene; ``[]``:
the object alone on the background colour). At the test poses with the whole scene the images
are the test images, bit for bit, and the accuracy is the train run's ``test_acc``. It shows
where a model stops generalising between its training views and the test views
(docs/studies/resnet18_generalisation.md).

Writes ``viewpoints.tsv`` (one row per image), ``viewpoints.md`` (accuracy by pitch and roll)
and a contact sheet of one class at every pitch and roll; logs the accuracy of each cell as
``accuracy_pitch<P>_roll<R>`` and over all images as ``accuracy``.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig

from mrcert.core.models import predicted
from mrcert.data.datasets import render_poses
from mrcert.data.sources import load
from mrcert.data.synthetic import SyntheticData
from mrcert.errors import MrcertError
from mrcert.infra.checkpoints import load_classifier
from mrcert.infra.identity import Identity
from mrcert.infra.progress import progress
from mrcert.infra.runtime import batch_size, resolve_device
from mrcert.infra.tasks import DATA_FILES, Task
from mrcert.infra.tracking import RunContext
from mrcert.reporting.imaging import contact_sheet
from mrcert.reporting.writers import markdown
from mrcert.tasks.train import to_device


def midway(yaws: np.ndarray) -> list[float]:
    """The yaws halfway between consecutive distinct ``yaws`` on the circle (degrees)."""
    ring = np.unique(np.mod(yaws, 360.0))
    following = np.append(ring[1:], ring[0] + 360.0)
    return sorted(float(v) for v in np.mod((ring + following) / 2, 360.0))


def cell_name(pitch: float, roll: float) -> str:
    return f"accuracy_pitch{pitch:g}_roll{roll:g}"


@torch.inference_mode()
def classify(model: torch.nn.Module, images: np.ndarray, device: torch.device, batch: int) -> np.ndarray:
    """The classes ``model`` predicts for uint8 images (N, H, W, C)."""
    x = torch.from_numpy(images).permute(0, 3, 1, 2)
    return np.concatenate(
        [predicted(model(to_device(x[s : s + batch], device))).cpu().numpy() for s in range(0, len(x), batch)]
    )


@torch.inference_mode()
def occlusion(
    model: torch.nn.Module, image: np.ndarray, label: int, patch: int, device: torch.device, batch: int
) -> np.ndarray:
    """Occlusion sensitivity (Zeiler and Fergus): how much the probability of ``label`` falls when
    a grey ``patch`` x ``patch`` square covers each place of a uint8 image (H, W, C), stepped by
    half a patch; each pixel gets the mean fall of the squares covering it (H, W)."""
    height, width = image.shape[:2]
    step = max(patch // 2, 1)
    rows = sorted({*range(0, height - patch + 1, step), height - patch})
    cols = sorted({*range(0, width - patch + 1, step), width - patch})
    x = torch.tensor(image).permute(2, 0, 1)  # a copy: the image may be a read-only view of the cache
    base = torch.softmax(model(to_device(x[None], device)), 1)[0, label].item()
    places = [(r, c) for r in rows for c in cols]
    falls = []
    for s in range(0, len(places), batch):
        covered = x[None].repeat(len(places[s : s + batch]), 1, 1, 1)
        for k, (r, c) in enumerate(places[s : s + batch]):
            covered[k, :, r : r + patch, c : c + patch] = 128
        falls.append(base - torch.softmax(model(to_device(covered, device)), 1)[:, label].cpu().numpy())
    total, count = np.zeros((height, width)), np.zeros((height, width))
    for (r, c), fall in zip(places, np.concatenate(falls), strict=True):
        total[r : r + patch, c : c + patch] += fall
        count[r : r + patch, c : c + patch] += 1
    return total / count


def object_share(falls: np.ndarray, mask: np.ndarray) -> float:
    """The share of an occlusion map's positive falls (the evidence for the class) that lies on
    the object's pixels ``mask``; nan when nothing covered lowers the probability."""
    evidence = np.clip(falls, 0, None)
    return float((evidence * mask).sum() / evidence.sum()) if evidence.sum() > 0 else float("nan")


def object_mask(bundle: SyntheticData, label: int, poses: np.ndarray) -> np.ndarray:
    """The pixels the object alone covers at each pose (N, H, W): those that do not change with
    the background colour."""
    dark, light = (
        render_poses(bundle.source.object(label), poses, bundle.K, bundle.height, bundle.width, value)
        for value in (0.0, 1.0)
    )
    return (dark == light).all(axis=-1)


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    bundle = load(cfg.data)
    if not isinstance(bundle, SyntheticData):
        raise MrcertError(f"task=viewpoints renders a synthetic scene: data={cfg.data.name} is not one")
    parts = tuple(str(p) for p in t.surroundings)
    bundle.source.only(parts)  # an unknown part stops here, before anything is rendered
    device = resolve_device(cfg.device)
    model = load_classifier(cfg, bundle.classes, device)
    test = bundle.split("test")
    yaws = [float(y) for y in t.yaws] if t.yaws is not None else midway(test.params[:, 0])
    distance = float(t.distance) if t.distance is not None else float(np.median(test.params[:, 3]))
    cells = list(itertools.product([float(p) for p in t.pitches], [float(r) for r in t.rolls]))
    params = np.array([(y, p, r, distance) for p, r in cells for y in yaws], np.float64)
    poses = bundle.source.poses(params)
    firsts = [i * len(yaws) for i in range(len(cells))]  # each cell's first yaw
    batch = batch_size(t.batch_size, device)
    rows, sheet, maps = [], [], []
    for label in progress(range(len(bundle.classes)), "classes"):
        scene = bundle.source.scene(label, parts)
        images = render_poses(scene, poses, bundle.K, bundle.height, bundle.width, bundle.background)
        predicted = classify(model, images, device, batch)
        own = [
            {"label": label, "yaw": y, "pitch": p, "roll": r, "predict": int(c), "correct": int(c == label)}
            for (y, p, r, _), c in zip(params, predicted, strict=True)
        ]
        if label == 0:
            sheet = [images[i] for i in firsts]
        if t.occlusion:
            for i, mask in zip(firsts, object_mask(bundle, label, poses[firsts]), strict=True):
                falls = occlusion(model, images[i], label, int(t.occlusion_patch), device, batch)
                own[i]["object_share"] = object_share(falls, mask)
                maps.append((label, params[i], images[i], falls))
        rows += own
    log = pd.DataFrame(rows)
    log.to_csv(ctx.output_dir / "viewpoints.tsv", sep="\t", index=False)
    grid = log.pivot_table(index="pitch", columns="roll", values="correct", aggfunc="mean")
    grid = grid.map(lambda v: f"{v:.3f}")
    grid.columns = [f"roll {r:g}" for r in grid.columns]
    grid.insert(0, "pitch", [f"{p:g}" for p in grid.index])
    table = ctx.output_dir / "viewpoints.md"
    table.write_text(markdown(grid) + "\n")
    picture = contact_sheet(
        [[torch.from_numpy(im).permute(2, 0, 1).float() / 255 for im in sheet]],
        [bundle.classes[0]],
        [[f"pitch {p:g}, roll {r:g}" for p, r in cells]],
        ctx.output_dir / "viewpoints.png",
        title=f"yaw {yaws[0]:g}, {distance:g} m, around the object: {', '.join(parts) or 'nothing'}",
    )
    metrics = {cell_name(p, r): float(log[(log.pitch == p) & (log.roll == r)].correct.mean()) for p, r in cells}
    metrics |= {"accuracy": float(log.correct.mean()), "num_images": float(len(log))}
    outputs = [ctx.output_dir / "viewpoints.tsv", table, picture]
    if t.occlusion:
        shares = log.dropna(subset=["object_share"]).groupby(["pitch", "roll"]).object_share.mean()
        metrics |= {f"object_share_pitch{p:g}_roll{r:g}": float(v) for (p, r), v in shares.items()}
        outputs.append(occlusion_sheet(maps, bundle.classes, ctx.output_dir / "occlusion.png"))
    ctx.tracker.log_metrics(metrics)
    for path in outputs:
        ctx.tracker.log_artifact(path)
    print(f"\nAccuracy by viewpoint ({len(yaws)} yaws x {len(bundle.classes)} classes per cell):\n")
    print(table.read_text())
    return metrics


def occlusion_sheet(maps: list, classes: list[str], path):
    """Each occlusion map over its image (red: covering it lowers the class's probability), one
    row per class, one column per pitch and roll."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = sorted({m[0] for m in maps})
    cols = len(maps) // len(labels)
    fig, axes = plt.subplots(len(labels), cols, figsize=(2.4 * cols, 1.5 * len(labels) + 0.4), squeeze=False)
    for k, (label, (_, pitch, roll, _), image, falls) in enumerate(maps):
        ax = axes[k // cols][k % cols]
        top = float(np.abs(falls).max()) or 1.0  # each map on its own scale
        ax.imshow(image)
        ax.imshow(falls, cmap="bwr", vmin=-top, vmax=top, alpha=0.55)
        ax.set(xticks=[], yticks=[])
        ax.set_xlabel(f"pitch {pitch:g}, roll {roll:g}", fontsize=7)
        if k % cols == 0:
            ax.set_ylabel(classes[label], fontsize=8)
    title = "occlusion sensitivity: fall of the true class's probability (red), each map on its own scale"
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / fig.get_figheight()))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


class Viewpoints(Task):
    summary = "a base classifier's accuracy by camera pitch and roll (synthetic scenes)"
    # The base classifier alone, identified by its checkpoint's content: no smoothing, no motion.
    identity = Identity(
        defines=("task", "data", "model", "seed", "profile"),
        ignores=("train", "model.trained_for", "attack", "motion", "method", "task.batch_size"),
        files=("model.checkpoint", *DATA_FILES),
        needs_model=True,
    )
    headline = ("accuracy",)

    def title(self, cfg: DictConfig) -> str:
        return f"viewpoints {cfg.model.variant} {cfg.model.arch}"

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
