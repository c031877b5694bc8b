"""``task=import``: a certify log computed elsewhere (Cohen / paper-authors format, with or
without our extra columns) recorded as an MLflow run with the same metrics as ``certify``.

The run is filed under the log's metadata (``task.dataset``, ``task.arch``, ``task.variant``,
``task.profile``, ``task.axis``, ``task.sigma``; by default those of the composed data, model,
profile and motion), and the log is kept as the run's ``certify.tsv``."""

from __future__ import annotations

import shutil
from typing import Any

from omegaconf import DictConfig, OmegaConf

from mrcert.core.methods import build_method
from mrcert.infra.identity import Identity
from mrcert.infra.tasks import HELPER_IGNORES, Task
from mrcert.infra.tracking import RunContext
from mrcert.reporting import certify_log
from mrcert.reporting.certify_log import read_log
from mrcert.tasks.certify import report
from mrcert.tasks.run_log import log_headline


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    df = read_log(t.path)
    kept = ctx.output_dir / Import.log
    shutil.copyfile(t.path, kept)
    # What its radii mean: the composed method's certificate on the log's own axis and sigma.
    method = build_method(OmegaConf.merge(cfg, {"motion": {"axis": str(t.axis), "sigma": float(t.sigma)}}))
    title = f"imported {t.dataset} {t.arch} {t.variant}, smoothing {t.axis}"
    report(df, float(t.radius), float(t.radius_step), ctx, title, method.region())
    return log_headline(ctx, "import", kept, cfg)


class Import(Task):
    summary = "record a certify log computed elsewhere as an MLflow run"
    # The log's metadata (task.dataset, task.arch, ...) is all it is; one cell may hold one log.
    identity = Identity(defines=("task",), ignores=HELPER_IGNORES, files=("task.path",), partition=("task.path",))
    log = "certify.tsv"
    columns = tuple(certify_log.COHEN_COLUMNS)  # what an imported log needs
    headline = ("certified_accuracy", "clean_accuracy")

    def title(self, cfg: DictConfig) -> str:
        return f"import {cfg.task.axis} {cfg.task.arch} {cfg.task.variant}"

    def summarize(self, log, cfg: DictConfig) -> dict[str, float]:
        """The certify metrics of an imported log, at its own ``task.radius``."""
        radius = float(cfg.task.radius)
        return certify_log.metrics(log, radius, float(cfg.task.radius_step), radius)[0]

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
