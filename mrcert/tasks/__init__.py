"""The tasks: one module per task (``render``, ``train``, ``certify``, ``smooth``, ``attack``,
``viewpoints``, ``tables``, ``import``, ``gather``), each a ``run(cfg, ctx)`` function, plus what
they share (``evaluation``, ``inputs``). What each task is -- its identity, its log -- is declared
in :data:`mrcert.infra.tasks.TASKS`; its computation is here, found by its name. This layer may
import every other one; nothing imports it but the entry point (``mrcert.__main__``)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

MODULES = {"import": "importer"}
"""A task whose module is not named after it (``import`` is a Python keyword)."""


def run_function(name: str) -> Callable[[Any, Any], dict[str, Any]]:
    """Task ``name``'s ``run(cfg, RunContext) -> headline metrics``, its module imported only now
    (so that ``mrcert --help`` and config validation do not import torch)."""
    return importlib.import_module(f"{__name__}.{MODULES.get(name, name)}").run
