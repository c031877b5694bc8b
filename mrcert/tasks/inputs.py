"""Every file a run reads, checked before the run exists.

A missing, unreadable or not regular (a folder, a device) checkpoint, point cloud, poses file
or imported log stops the command in seconds with one line naming the key and the file,
before any data is prepared and before an MLflow run is created (so no FAILED run is left
behind). The keys checked are the ones a task's identity declares as files
(:class:`mrcert.infra.identity.Identity`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mrcert.errors import MrcertError
from mrcert.formats import shipped
from mrcert.infra.identity import Identity


def _checkpoint(path: Path, cfg: DictConfig) -> None:
    """A mrcert checkpoint, trained on the data set's classes."""
    from mrcert.data.sources import load
    from mrcert.infra.checkpoints import check_classes, read_checkpoint

    check_classes(read_checkpoint(path), load(cfg.data).classes, path)


def _cloud(path: Path, cfg: DictConfig) -> None:
    from mrcert.scenes.scene import read_point_cloud

    if path.is_file():
        read_point_cloud(path)


def _poses(path: Path, cfg: DictConfig) -> None:
    from mrcert.data.custom import read_poses

    read_poses(path)


def _log(path: Path, cfg: DictConfig) -> None:
    from mrcert.reporting.certify_log import read_log

    read_log(path)


def _store(path: Path, cfg: DictConfig) -> None:
    from mrcert.tasks.gather import other_store

    other_store(str(path))


def _onnx(path: Path, cfg: DictConfig) -> None:
    from mrcert.formats.onnx_model import read_onnx

    read_onnx(path, int(float(cfg.task.max_model_mb) * 2**20))


CHECKS: dict[str, Callable[[Path, DictConfig], None]] = {
    "model.checkpoint": _checkpoint,
    "data.path": _cloud,  # a cloud file; the released MetaRoom is a folder, checked when opened
    "data.poses": _poses,
    "task.path": _log,
    "task.store": _store,  # task=gather's other store
    "task.onnx": _onnx,  # task=verify's classifier
}


GZIPPED = ("task.onnx", "task.vnnlib")
"""The file inputs that may be given by the name they have once unzipped (``X`` for ``X.gz``)."""

FOLDERS = ("task.store",)
"""The file inputs that are folders (another store's outputs folder, or a tracking URI)."""


def check_classes(data: DictConfig) -> None:
    """Raise a one-line :class:`MrcertError` naming any ``data.classes`` entry a synthetic data
    set does not have (a released or custom data set's classes come from its files, which are
    read when it is opened)."""
    from mrcert.data.synthetic import FAMILIES, SyntheticSource

    if data.get("source") in FAMILIES:
        SyntheticSource(data)  # checks the class names; builds no scene


def check_inputs(cfg: DictConfig, identity: Identity, scene_task: bool = True) -> None:
    """Raise a one-line :class:`MrcertError` for unknown class names, then for the first file
    input of ``cfg`` that is missing or unreadable; a checkpoint file last, once the data's files
    passed, as a mrcert checkpoint of the data set's classes (``runs:/`` URIs are checked against
    the store when bound); the data set's class names only for a task that reads it (``scene_task``)."""
    if scene_task:
        check_classes(cfg.data)
    if OmegaConf.select(cfg, "task.name") == "verify":  # its instances, every file they name
        from mrcert.tasks.verify import instances

        instances(cfg.task)
    for key in sorted(identity.files, key=lambda k: k == "model.checkpoint"):  # its classes: once the data's files pass
        value = OmegaConf.select(cfg, key, default=None)
        if value is None or value == "???" or ":/" in str(value):
            continue
        path = Path(str(value))
        if key in GZIPPED:
            path = shipped(path)
        if not path.exists():
            raise MrcertError(f"{key}={str(value)!r} does not exist")
        folder = key == "data.path" and cfg.data.get("source") == "metaroom"  # the released data set's folder
        if key not in FOLDERS and not (path.is_dir() if folder else path.is_file()):
            kind = "the released data set's folder" if folder else "a regular file"
            raise MrcertError(f"{key}={str(value)!r} is not {kind}: give {kind}")
        if not os.access(path, os.R_OK):
            raise MrcertError(f"{key}={str(value)!r} cannot be read: permission denied (check its permissions)")
        CHECKS.get(key, lambda p, c: None)(path, cfg)
