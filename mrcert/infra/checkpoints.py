"""Checkpoints: their format (the one place that writes and reads them), saving them
atomically, and binding an evaluation to exactly one of them.

``task=train`` writes two files per run. ``best.pt`` (:func:`save_model`) is the selected model
an evaluation loads: its weights, the epoch and validation accuracy that selected it, and the
model's description (:func:`describe`: architecture, classes, variant, method, axis,
``model.net`` config, how it was validated). ``last.pt`` (:func:`save_progress`) is what a
resumed run continues from: the same description, the last epoch's weights, the optimiser,
scheduler and gradient-scaler states, and the best validation result so far.

``model.checkpoint`` may be a file path or an MLflow artifact URI (``runs:/<run_id>/<path>``);
which model an evaluation reads when it is null, and how that model is named in the
evaluation's key, is :mod:`mrcert.infra.resolver`'s.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra import seals
from mrcert.infra.store import moved_artifact

BEST, LAST = "best.pt", "last.pt"
ARTIFACT_DIR = "checkpoints"
BEST_PATH = f"{ARTIFACT_DIR}/{BEST}"
"""Where a train run logs the model an evaluation loads."""


def _save(state: dict[str, Any], path: Path) -> None:
    """Write ``state`` so that a crash never leaves a truncated file behind."""
    import torch

    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def describe(cfg: DictConfig, classes: list[str], method: str | None, validation: dict[str, Any]) -> dict[str, Any]:
    """What every checkpoint of the model ``cfg`` trains says about it (``method``: the
    certification method it was trained for, None for a vanilla model)."""
    from omegaconf import OmegaConf

    return {
        "arch": cfg.model.arch,
        "num_classes": len(classes),
        "classes": list(classes),
        "variant": cfg.model.variant,
        "method": method,
        "axis": cfg.motion.axis,
        "model_config": OmegaConf.to_container(cfg.model.net, resolve=True),
        "validation": validation,
    }


def _weights(module) -> dict[str, Any]:
    return {k: v.cpu() for k, v in module.state_dict().items()}


def save_model(path: Path, description: dict[str, Any], model, epoch: int, val_acc: float | None) -> None:
    """``best.pt``: the selected model (:func:`load_classifier` reads it)."""
    _save(description | {"model": _weights(model), "epoch": epoch, "val_acc": val_acc}, path)


def save_progress(
    path: Path, description: dict[str, Any], model, optimizer, scheduler, scaler, epoch: int, best
) -> None:
    """``last.pt``: where a resumed run continues (:func:`resume`)."""
    parts = {"optimizer": optimizer, "scheduler": scheduler, "scaler": scaler}
    state = {name: part.state_dict() for name, part in parts.items()}
    _save(description | {"model": _weights(model), **state, "epoch": epoch, "best": best}, path)


def resume(path: Path, model, optimizer, scheduler, scaler) -> tuple[int, Any]:
    """Load ``last.pt`` into the training objects; ``(next epoch, best validation result so far)``."""
    import torch

    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    if "scaler" in state:  # written before mixed precision existed
        scaler.load_state_dict(state["scaler"])
    return state["epoch"] + 1, state["best"]


def selected_epoch(path: Path, model) -> int:
    """Load ``best.pt``'s weights into ``model``; the epoch that was selected."""
    state = read_checkpoint(path)
    model.load_state_dict(state["model"])
    return int(state["epoch"])


def local_checkpoint(ref: str) -> Path:
    """The local file of a bound ``model.checkpoint``: for a ``runs:/`` URI downloaded from
    MLflow (in a store folder that moved, from its own artifact root) and verified, byte for
    byte, against the checkpoint its run sealed (a one-line error names the run and the file
    otherwise: a swapped file is never loaded under the run's name)."""
    if ":/" not in ref:
        return Path(ref)
    import mlflow

    run_id, _, name = ref[len("runs:/") :].partition("/")
    failed = f"model.checkpoint={ref!r} cannot be fetched from MLflow"
    try:
        tags = mlflow.MlflowClient().get_run(run_id).data.tags
    except Exception as exc:  # an unknown run, an unreachable store
        raise MrcertError(f"{failed}: {exc}") from None
    try:
        path = Path(mlflow.artifacts.download_artifacts(artifact_uri=ref))
    except Exception as exc:  # a missing artifact, unless the store folder moved
        path = moved_artifact(run_id, name)
        if path is None:
            raise MrcertError(f"{failed}: {exc}") from None
    seals.verify(run_id, tags, path)
    return path


def check_classes(state: dict[str, Any], classes: list[str], path: Path | str) -> None:
    """Refuse a checkpoint whose class names are not the data set's (a model of other objects)."""
    saved = state.get("classes")
    if saved is not None and list(saved) != list(classes):
        differ = [f"{i}: {a!r} vs {b!r}" for i, (a, b) in enumerate(zip(saved, classes, strict=False)) if a != b]
        raise MrcertError(
            f"checkpoint {str(path)!r} was trained on classes {', '.join(map(str, saved[:4]))}... "
            f"({len(saved)}), not this data set's {', '.join(map(str, classes[:4]))}... ({len(classes)})"
            + (f": first difference {differ[0]}" if differ else "")
        )


REQUIRED_KEYS = ("model", "arch", "num_classes")


def read_checkpoint(path: Path | str) -> dict[str, Any]:
    """The state a ``task=train`` checkpoint holds, or a one-line error saying it is not one."""
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # not a torch file, truncated, or holding objects other than tensors
        raise MrcertError(
            f"{str(path)!r} is not a mrcert checkpoint (a file written by task=train): torch cannot read it "
            "as tensors and plain values (not a PyTorch file, truncated, or holding other objects)"
        ) from None
    if not isinstance(state, dict) or any(k not in state for k in REQUIRED_KEYS):
        raise MrcertError(
            f"{str(path)!r} is not a mrcert checkpoint (a file written by task=train): "
            f"it lacks {', '.join(k for k in REQUIRED_KEYS if not isinstance(state, dict) or k not in state)}"
        )
    from mrcert.core.models import non_finite

    bad = non_finite(state["model"]) if isinstance(state["model"], dict) else []
    if bad:
        raise MrcertError(
            f"checkpoint {str(path)!r} holds NaN or infinite weights ({', '.join(bad[:3])}): a model that diverged "
            "in training classifies nothing; train it again (e.g. with a smaller train.lr)"
        )
    return state


def _differences(saved: Any, wanted: Any, prefix: str) -> list[str]:
    """``key=saved`` vs ``key=wanted`` for every leaf where two model configs differ."""
    from mrcert.infra.identity import flatten

    a, b = flatten(saved, prefix), flatten(wanted, prefix)
    return [f"{k}={a.get(k, '(unset)')!r} (checkpoint) vs {b.get(k, '(unset)')!r} (asked for)"
            for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]  # fmt: skip


def load_classifier(cfg: DictConfig, classes: list[str], device):
    """The trained base classifier (``nn.Module``) of the bound ``cfg.model.checkpoint`` in eval
    mode on ``device``. A checkpoint of other classes, another architecture, class count or
    ``model.net`` config is refused with a message naming both values."""
    from omegaconf import OmegaConf

    from mrcert.core.models import build_model, for_inference

    num_classes = len(classes)
    path = local_checkpoint(str(cfg.model.checkpoint))
    state = read_checkpoint(path)
    check_classes(state, classes, path)
    if state.get("arch") != cfg.model.arch or state.get("num_classes") != num_classes:
        raise MrcertError(
            f"checkpoint {str(path)!r} holds a {state.get('arch')} for {state.get('num_classes')} "
            f"classes, but model={cfg.model.arch} with {num_classes} classes was asked for"
        )
    wanted = OmegaConf.to_container(cfg.model.net, resolve=True)
    saved = state.get("model_config")
    if saved is not None and saved != wanted:
        raise MrcertError(
            f"checkpoint {str(path)!r} was trained with another model: "
            + "; ".join(_differences(saved, wanted, "model.net"))
        )
    model = build_model(cfg.model, num_classes)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:  # an older checkpoint without model_config, of another shape
        first = str(exc).strip().splitlines()
        raise MrcertError(
            f"checkpoint {str(path)!r} does not fit model={cfg.model.arch} with model.net={wanted}: "
            f"{first[1].strip() if len(first) > 1 else first[0]}"
        ) from None
    return for_inference(model, device)
