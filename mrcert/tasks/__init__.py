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

    def load(self) -> Callable[[DictConfig, RunContext], dict[str, Any]]:
        module, func = self.target.split(":")
        return getattr(importlib.import_module(module), func)


TASKS: dict[str, Task] = {
    "render": Task("mrcert.tasks.render:run", "render a scene under motions, or a dataset's images into the cache"),
    "train": Task("mrcert.tasks.train:run", "train a vanilla or motion-augmented base classifier"),
}
