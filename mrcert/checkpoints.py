"""Checkpoints: saving them atomically, and finding the one a task should use.

``model.checkpoint`` may be a file path or an MLflow artifact URI (``runs:/<run_id>/<path>``);
when it is null, the latest FINISHED train run with the same dataset, profile, architecture,
axis and variant is used, and when there is none the error names the command that makes it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch import nn

from mrcert.errors import MrcertError
from mrcert.models import build_model, for_inference

BEST, LAST = "best.pt", "last.pt"
ARTIFACT_DIR = "checkpoints"


def save(state: dict[str, Any], path: Path) -> None:
    """Write ``state`` so that a crash never leaves a truncated file behind."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def train_command(cfg: DictConfig) -> str:
    """The command that trains the model ``cfg`` asks for."""
    profile = f" profile={cfg.profile.name}" if "profile" in cfg else ""
    return (
        f"mrcert task=train data={cfg.data.name}{profile} model={cfg.model.arch} motion={cfg.motion.axis} "
        f"model.variant={cfg.model.variant}"
    )


def _download(uri: str) -> Path:
    import mlflow

    try:
        return Path(mlflow.artifacts.download_artifacts(artifact_uri=uri))
    except Exception as exc:  # unknown run, missing artifact, unreachable store
        raise MrcertError(f"model.checkpoint={uri!r} cannot be fetched from MLflow: {exc}") from None


def find_checkpoint(cfg: DictConfig) -> Path:
    """The local checkpoint file for ``cfg.model`` (see the module docstring)."""
    ref = cfg.model.get("checkpoint")
    if ref:
        ref = str(ref)
        if ":/" in ref:
            from mrcert.tracking import configure

            configure(cfg.tracking)
            return _download(ref)
        if not Path(ref).is_file():
            raise MrcertError(f"model.checkpoint={ref!r} does not exist; give a file path or runs:/<run_id>/<path>")
        return Path(ref)
    if not cfg.tracking.enabled:
        raise MrcertError(
            "model.checkpoint is not set and tracking is off, so no train run can be looked up; "
            "set model.checkpoint=/path/to/best.pt"
        )
    from mrcert.tracking import configure, run_tags

    mlflow = configure(cfg.tracking)
    wanted = {k: v for k, v in run_tags(cfg).items() if k != "mrcert.task"} | {"mrcert.task": "train"}
    if cfg.model.variant == "vanilla":
        wanted.pop("mrcert.axis", None)  # a vanilla model never saw a motion: any axis's run serves
    exp = mlflow.MlflowClient().get_experiment_by_name(cfg.tracking.experiment)
    runs = (
        []
        if exp is None
        else mlflow.search_runs(
            experiment_ids=[exp.experiment_id],
            filter_string=" and ".join(
                [f"tags.`{k}` = '{v}'" for k, v in wanted.items()] + ["attributes.status = 'FINISHED'"]
            ),
            order_by=["attributes.start_time DESC"],
            max_results=1,
            output_format="list",
        )
    )
    if not runs:
        described = ", ".join(f"{k.split('.', 1)[1]}={v}" for k, v in sorted(wanted.items()))
        raise MrcertError(
            f"no finished train run with {described} in {cfg.tracking.uri}; train one with: {train_command(cfg)}"
        )
    return _download(f"runs:/{runs[0].info.run_id}/{ARTIFACT_DIR}/{BEST}")


def load_classifier(cfg: DictConfig, num_classes: int, device: torch.device) -> nn.Module:
    """The trained base classifier of ``cfg.model`` in eval mode on ``device``."""
    path = find_checkpoint(cfg)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise MrcertError(f"cannot read checkpoint {str(path)!r}: {exc}") from None
    if state.get("arch") != cfg.model.arch or state.get("num_classes") != num_classes:
        raise MrcertError(
            f"checkpoint {str(path)!r} holds a {state.get('arch')} for {state.get('num_classes')} "
            f"classes, but model={cfg.model.arch} with {num_classes} classes was asked for"
        )
    model = build_model(cfg.model, num_classes)
    model.load_state_dict(state["model"])
    return for_inference(model, device)
