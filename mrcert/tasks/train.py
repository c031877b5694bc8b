"""``task=train``: vanilla and augmented base classifiers with the recipe in ``train.*``; an
augmented model trains as its certification method asks (:mod:`mrcert.core.methods.base`: images
rendered under the method's training motions, each batch perturbed by it), and its validation
and test images are perturbed the same way (with noise fixed across epochs) before it sees them.

SGD (momentum, weight decay) with StepLR, seeded model initialisation and a batch order
drawn per epoch from ``(seed, epoch)``. Model selection uses the data source's validation
poses (synthetic MetaRoom: the test ring turned by 30 degrees, as far from the training poses
in pitch and roll as the test poses, docs/method.md §3), or, for a source without them, a held-out share of the training
poses (``train.val_fraction`` per class, :mod:`mrcert.data.holdout`): ``best.pt`` is the epoch
with the highest ``val_acc``, ties going to the lower ``val_loss`` (then the earlier epoch).
The test images never select anything: the test accuracy of ``best.pt`` is measured once, at
the end (``test_acc``; an augmented model's also on the clean test images, ``test_acc_clean``,
which differs from it for a model trained on perturbed images); each epoch's test accuracy is
recorded too (``epoch_test_acc``) for the learning curve, and nothing reads it back. Each epoch
ends with an atomic ``last.pt`` (model, optimiser, scheduler, epoch, best), so a run restarted with
``task.resume=true`` continues in the same MLflow run and ends with the same weights as an
uninterrupted one. ``best.pt`` and ``last.pt`` are logged as artifacts under ``checkpoints/``.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch import nn

from mrcert.core.methods import build_method
from mrcert.core.methods.base import Method
from mrcert.core.models import build_model, non_finite, predicted
from mrcert.core.sampling import image_generator
from mrcert.data.datasets import ImageSet
from mrcert.data.holdout import validation_split
from mrcert.data.sources import load
from mrcert.errors import MrcertError
from mrcert.infra import checkpoints
from mrcert.infra.identity import Identity, file_identity
from mrcert.infra.progress import progress
from mrcert.infra.resolver import DIGEST_TAG
from mrcert.infra.runtime import resolve_device
from mrcert.infra.tasks import DATA_FILES, Task, model_title
from mrcert.infra.tracking import RunContext

log = logging.getLogger(__name__)


def as_tensors(images: ImageSet) -> tuple[torch.Tensor, torch.Tensor]:
    """All images as one uint8 tensor (N, C, H, W) and the labels."""
    return torch.from_numpy(np.array(images.images)).permute(0, 3, 1, 2).contiguous(), torch.from_numpy(images.labels)


def log_inputs(ctx: RunContext, bundle, context: str, logged: set[str]) -> None:
    """The rendered image sets read since ``logged``, as MLflow inputs (their cache key is the digest)."""
    for tag, info in bundle.cache_info.items():
        if tag not in logged:
            logged.add(tag)
            ctx.tracker.log_input(info["folder"], f"{bundle.data.name}-{tag}", info["key"], context)


def to_device(images: torch.Tensor, device: torch.device) -> torch.Tensor:
    """A uint8 image batch as float in [0, 1] on ``device`` (on CUDA: channels-last, and copied
    from pinned memory without blocking unless it is there already)."""
    if device.type != "cuda":
        return images.to(device).float().div_(255)
    if not images.is_cuda:
        images = images.pin_memory().to(device, non_blocking=True)
    return images.float().div_(255).contiguous(memory_format=torch.channels_last)


def resident(images: torch.Tensor, device: torch.device) -> torch.Tensor:
    """Where training batches are cut from: on a GPU, the uint8 images copied there once when they
    take at most a quarter of its free memory (a batch is then an index on the GPU, with no
    host copy per step); otherwise the host tensor."""
    if device.type == "cuda" and images.nbytes <= torch.cuda.mem_get_info(device)[0] // 4:
        return images.to(device)
    return images


@torch.inference_mode()
def evaluate(
    model: nn.Module,
    images: torch.Tensor,
    labels: torch.Tensor,
    device,
    batch: int,
    seen: Method | None = None,
    seed: int = 0,
) -> tuple[float, float]:
    """(accuracy, mean cross-entropy) of ``model`` on the images, each perturbed as ``seen``
    perturbs training batches (a pixel-noise model is only ever used on noisy images); image
    ``i``'s noise comes from its own generator of ``seed``, the same at every call and in any batches."""
    model.eval()
    correct, loss = 0, 0.0
    for s in range(0, len(labels), batch):
        x = to_device(images[s : s + batch], torch.device(device))
        if seen is not None:
            x = torch.cat(
                [seen.perturb(x[j : j + 1], image_generator(seed, "evaluation", s + j)) for j in range(len(x))]
            )
        logits = model(x).float().cpu()
        correct += int((predicted(logits) == labels[s : s + batch]).sum())
        loss += float(nn.functional.cross_entropy(logits, labels[s : s + batch], reduction="sum"))
    return correct / max(len(labels), 1), loss / max(len(labels), 1)


def accuracy(model: nn.Module, images, labels, device, batch: int, seen: Method | None = None, seed: int = 0) -> float:
    return evaluate(model, images, labels, device, batch, seen, seed)[0]


def better(val: tuple[float, float], best: tuple[float, float] | None) -> bool:
    """Whether (accuracy, loss) on the validation images beats ``best``: higher accuracy, or equal
    accuracy and lower loss (a saturated accuracy still ranks epochs)."""
    return best is None or val[0] > best[0] or (val[0] == best[0] and val[1] < best[1])


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t, r = cfg.task, cfg.train
    device = resolve_device(cfg.device)
    bundle = load(cfg.data)
    augment = None
    if cfg.model.variant == "augmented":
        augment = build_method(cfg)
    elif cfg.model.variant != "vanilla":
        raise MrcertError(f"model.variant={cfg.model.variant!r} is not allowed: vanilla or augmented")
    all_x, all_y = as_tensors(bundle.train(augment, int(cfg.seed)))
    inputs: set[str] = set()
    log_inputs(ctx, bundle, "training", inputs)
    validation = bundle.validation()
    if validation is not None:  # the source's validation poses: every training image trains
        train_x, train_y = all_x, all_y
        val_x, val_y = as_tensors(validation)
        log_inputs(ctx, bundle, "validation", inputs)
        selection = {"source": "poses", "images": len(val_y)}
    else:  # a share of the training poses, held out
        keep, held = validation_split(all_y.numpy(), float(r.val_fraction), int(cfg.seed))
        train_x, train_y = all_x[keep], all_y[keep]
        val_x, val_y = all_x[held], all_y[held]
        selection = {"source": "held-out training poses", "fraction": float(r.val_fraction), "indices": held.tolist()}
    test_x, test_y = as_tensors(bundle.test())
    log_inputs(ctx, bundle, "test", inputs)
    ctx.tracker.log_metrics({"train_images": len(train_y), "val_images": len(val_y)})

    torch.manual_seed(int(cfg.seed))
    model = build_model(cfg.model, len(bundle.classes)).to(device)
    amp = bool(r.get("amp", False)) and device.type == "cuda"
    if device.type == "cuda":  # fastest convolution algorithms for these fixed image sizes
        torch.backends.cudnn.benchmark = True
    model = model.to(memory_format=torch.channels_last)  # faster convolutions on CPU and GPU alike
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    optimizer = torch.optim.SGD(model.parameters(), lr=r.lr, momentum=r.momentum, weight_decay=r.weight_decay)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=r.step_size, gamma=r.gamma)
    loss_fn = nn.CrossEntropyLoss()
    last_path, best_path = ctx.output_dir / checkpoints.LAST, ctx.output_dir / checkpoints.BEST
    start, best = 0, None
    if ctx.tracker.resumed and last_path.is_file():
        start, best = checkpoints.resume(last_path, model, optimizer, scheduler, scaler)

    description = checkpoints.describe(cfg, bundle.classes, None if augment is None else cfg.method.name, selection)
    history: dict[str, float] = {}
    batches_x = resident(train_x, device)
    batches_y = train_y.to(batches_x.device)
    for epoch in range(start, int(r.epochs)):
        began = time.perf_counter()
        model.train()
        order = torch.randperm(len(train_y), generator=torch.Generator().manual_seed(int(cfg.seed) * 100_003 + epoch))
        order = order.to(batches_x.device)
        noise = image_generator(int(cfg.seed), epoch, "training noise")  # for a method that perturbs batches
        # Summed on the device and read once per epoch: no host synchronisation per step.
        total_loss = torch.zeros((), dtype=torch.float64, device=device)
        correct = torch.zeros((), dtype=torch.int64, device=device)
        for s in progress(range(0, len(order), r.batch_size), f"epoch {epoch + 1}/{r.epochs}"):
            idx = order[s : s + r.batch_size]
            x = to_device(batches_x[idx], device)
            if augment is not None:
                x = augment.perturb(x, noise)
            y = batches_y[idx].to(device, non_blocking=True)
            optimizer.zero_grad(set_to_none=True)
            with torch.autocast(device.type, dtype=torch.float16, enabled=amp):  # train.amp: training only
                logits = model(x)
                loss = loss_fn(logits, y)
            scaler.scale(loss).backward()
            scaler.step(optimizer)
            scaler.update()
            total_loss += loss.detach().double() * len(idx)
            correct += (logits.argmax(1) == y).sum()
        lr = optimizer.param_groups[0]["lr"]
        diverged = non_finite(model.state_dict()) + ([] if torch.isfinite(total_loss) else ["the training loss"])
        if diverged:  # nothing of this epoch is saved: best.pt and last.pt keep the last finite one
            raise MrcertError(
                f"training diverged in epoch {epoch + 1}: {', '.join(diverged[:3])} stopped being finite "
                f"(train.lr={r.lr}); {checkpoints.BEST} and {checkpoints.LAST} keep the last finite epoch, if any"
            )
        scheduler.step()
        history = {
            "train_loss": float(total_loss) / len(order),
            "train_acc": int(correct) / len(order),
            "lr": lr,
            "epoch_seconds": time.perf_counter() - began,
        }
        # With no validation images (train.val_fraction=0) every epoch replaces best.pt: the last is kept.
        val = evaluate(model, val_x, val_y, device, t.eval_batch_size, augment, int(cfg.seed)) if len(val_y) else None
        if val is not None:
            history["val_acc"], history["val_loss"] = val
        history["epoch_test_acc"] = accuracy(
            model, test_x, test_y, device, t.eval_batch_size, augment, int(cfg.seed)
        )  # recorded only
        ctx.tracker.log_metrics(history, step=epoch)
        if val is None or better(val, best):
            best = val
            checkpoints.save_model(best_path, description, model, epoch, val[0] if val else None)
        checkpoints.save_progress(last_path, description, model, optimizer, scheduler, scaler, epoch, best)
        log.info(
            f"epoch {epoch + 1}/{r.epochs}: loss {history['train_loss']:.4f} "
            f"train acc {history['train_acc']:.3f} val acc {history.get('val_acc', float('nan')):.3f} "
            f"({len(val_y)} validation images)"
        )
    if not last_path.is_file():
        raise MrcertError(f"train.epochs={r.epochs} trained nothing")
    # The test images, once, for the record: the selected model's accuracy on them.
    chosen = checkpoints.selected_epoch(best_path, model)
    test_acc = accuracy(model, test_x, test_y, device, t.eval_batch_size, augment, int(cfg.seed))
    summary = {"test_acc": test_acc, "best_epoch": chosen + 1}
    if augment is not None:  # and on the clean test images (a pixel-noise model's test_acc is on noisy ones)
        summary["test_acc_clean"] = accuracy(model, test_x, test_y, device, t.eval_batch_size)
    summary |= {"best_val_acc": best[0], "best_val_loss": best[1]} if best is not None else {}
    ctx.tracker.log_metrics(summary)
    ctx.tracker.log_artifact(best_path, checkpoints.ARTIFACT_DIR)
    ctx.tracker.log_artifact(last_path, checkpoints.ARTIFACT_DIR)
    ctx.tracker.set_tags({DIGEST_TAG: file_identity(str(best_path))})  # names the model in evaluations' keys
    return summary | history | {"checkpoint": str(best_path)}


class Train(Task):
    summary = "train a vanilla or motion-augmented base classifier"
    identity = Identity(
        defines=("task.name", "data", "model", "train", "motion", "method", "seed", "profile"),
        # A method's certify.* never trains; model.trained_for is refused here (an evaluation's).
        ignores=("task", "model.checkpoint", "model.trained_for", "attack", "method.certify"),
        ignore_when=(  # a vanilla model never sees a motion or a method
            ("model.variant", "vanilla", "motion"),
            ("model.variant", "vanilla", "method"),
        ),
        files=DATA_FILES,
        method="model",
    )
    headline = ("test_acc",)
    needs = checkpoints.BEST_PATH

    def title(self, cfg: DictConfig) -> str:
        return model_title(cfg)

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
