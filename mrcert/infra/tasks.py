"""The one table of tasks: name -> the function that runs it, what defines its result (its
:class:`~mrcert.infra.identity.Identity`) and the per-image log it writes.

Each entry names its function lazily (``"module:function"``) so that ``mrcert --help`` and
config validation do not import torch-heavy code. A task function takes the composed config
and a :class:`RunContext` and returns a dict of headline metrics.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mrcert.infra.identity import PARTITION, Identity
from mrcert.infra.tracking import Tracker


@dataclass(frozen=True)
class RunContext:
    """Where a task writes (its run directory) and what it logs through."""

    output_dir: Path
    tracker: Tracker


@dataclass(frozen=True)
class Task:
    target: str
    summary: str
    identity: Identity
    """Which config keys define the task's result (see :mod:`mrcert.infra.identity`)."""
    reusable: bool = True
    """Whether a FINISHED run of the same run key may stand in for a new one (``skip_finished``)."""
    log: str | None = None
    """The per-image log the task writes (in its run folder and artifacts), for tables and shards."""

    def load(self) -> Callable[[DictConfig, RunContext], dict[str, Any]]:
        module, func = self.target.split(":")
        return getattr(importlib.import_module(module), func)


DATA_FILES = ("data.path", "data.poses")
MOTION_SMOOTHING = ("method.name", "motion", "method")
"""``method=motion`` adds nothing to a run key: camera motion smoothing's parameters are all in
``motion.*``, and the runs made before mrcert had methods keep their keys."""
EVALUATION = Identity(
    defines=("task", "data", "model", "motion", "method", "seed", "profile"),
    # The recipe in train.* is named by the checkpoint's identity; the crop is exact.
    ignores=("train", "attack", "task.batch_size", "task.backend", "task.resume", "task.crop_sigmas"),
    files=("model.checkpoint", *DATA_FILES),
    ignore_when=(MOTION_SMOOTHING,),
    partition=PARTITION,
    needs_model=True,
)

TASKS: dict[str, Task] = {
    "render": Task(
        "mrcert.tasks.render:run",
        "render a scene under motions, or a dataset's images into the cache",
        Identity(
            defines=("task", "data", "motion", "method", "seed", "profile"),
            ignores=("model", "train", "attack", "task.backend"),
            ignore_when=(MOTION_SMOOTHING,),
            files=DATA_FILES,
        ),
    ),
    "train": Task(
        "mrcert.tasks.train:run",
        "train a vanilla or motion-augmented base classifier",
        Identity(
            defines=("task.name", "data", "model", "train", "motion", "method", "seed", "profile"),
            ignores=("task", "model.checkpoint", "attack", "method.certify"),  # a method's certify.* never trains
            ignore_when=(  # a vanilla model never sees a motion or a method
                ("model.variant", "vanilla", "motion"),
                ("model.variant", "vanilla", "method"),
                MOTION_SMOOTHING,
                ("method.name", "pixelwise", "motion"),  # pixel noise: one model serves every axis
            ),
            files=DATA_FILES,
        ),
    ),
    "certify": Task(
        "mrcert.tasks.certify:run",
        "CERTIFY each test image of the smoothed classifier (certify.tsv)",
        replace(
            EVALUATION, ignore_when=(MOTION_SMOOTHING, ("task.sequential", False, "task.look"))
        ),  # fixed n: no looks
        log="certify.tsv",
    ),
    "smooth": Task(
        "mrcert.tasks.smooth:run", "smoothed benign accuracy: PREDICT at each test pose", EVALUATION, log="smooth.tsv"
    ),
    "attack": Task(
        "mrcert.tasks.attack:run",
        "K-perturbed empirical robust accuracy, base and smoothed",
        replace(
            EVALUATION,
            defines=(*EVALUATION.defines, "attack"),
            ignores=tuple(i for i in EVALUATION.ignores if i != "attack"),
        ),
        log="attack.tsv",
    ),
    "tables": Task(
        "mrcert.tasks.tables:run",
        "the paper's tables and figure from finished MLflow runs",
        Identity(defines=("task", "profile"), ignores=("data", "model", "motion", "method", "seed", "attack", "train")),
        reusable=False,  # its result depends on the store's runs, not only on its config
    ),
    "import": Task(
        "mrcert.tasks.importer:run",
        "record a certify log computed elsewhere as an MLflow run",
        # The log's metadata (task.dataset, task.arch, ...) is all it is; one cell may hold one log.
        Identity(
            defines=("task",),
            ignores=("data", "model", "motion", "method", "seed", "profile", "train", "attack"),
            files=("task.path",),
            partition=("task.path",),
        ),
        log="certify.tsv",
    ),
}
