"""The one table from task name to the function that runs it.

Each entry names its module lazily (``"module:function"``) so that ``mrcert --help`` and
config validation do not import torch-heavy code. A task function takes the composed
config and a :class:`RunContext` and returns a dict of headline metrics.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mrcert.tracking import Tracker


@dataclass(frozen=True)
class RunContext:
    """Where a task writes (its run directory) and what it logs through."""

    output_dir: Path
    tracker: Tracker


@dataclass(frozen=True)
class Task:
    target: str
    summary: str
    uses: tuple[str, ...] | None = None
    """Top-level config keys that determine the result (None: all); they make the config key."""

    def load(self) -> Callable[[DictConfig, RunContext], dict[str, Any]]:
        module, func = self.target.split(":")
        return getattr(importlib.import_module(module), func)


EVALUATION = ("task", "data", "model", "motion", "seed", "profile")

TASKS: dict[str, Task] = {
    "render": Task("mrcert.tasks.render:run", "render a scene under motions, or a dataset's images into the cache"),
    "train": Task(
        "mrcert.tasks.train:run",
        "train a vanilla or motion-augmented base classifier",
        ("task", "data", "model", "motion", "seed", "profile"),
    ),
    "certify": Task(
        "mrcert.tasks.certify:run", "CERTIFY each test image of the smoothed classifier (certify.tsv)", EVALUATION
    ),
    "smooth": Task("mrcert.tasks.smooth:run", "smoothed benign accuracy: PREDICT at each test pose", EVALUATION),
    "attack": Task(
        "mrcert.tasks.attack:run", "K-perturbed empirical robust accuracy, base and smoothed", (*EVALUATION, "attack")
    ),
    "tables": Task("mrcert.tasks.tables:run", "the paper's tables and figure from finished MLflow runs"),
    "import": Task(
        "mrcert.tasks.importer:run", "record a certify log computed elsewhere as an MLflow run", ("task", "motion")
    ),
}
