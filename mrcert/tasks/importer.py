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
from mrcert.infra.tasks import TASKS
from mrcert.infra.tracking import RunContext
from mrcert.reporting.certify_log import read_log
from mrcert.tasks.certify import report
from mrcert.tasks.evaluation import summarize


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    df = read_log(t.path)
    kept = ctx.output_dir / TASKS["import"].log
    shutil.copyfile(t.path, kept)
    # What its radii mean: the composed method's certificate on the log's own axis and sigma.
    method = build_method(OmegaConf.merge(cfg, {"motion": {"axis": str(t.axis), "sigma": float(t.sigma)}}))
    title = f"imported {t.dataset} {t.arch} {t.variant}, smoothing {t.axis}"
    report(df, float(t.radius), float(t.radius_step), ctx, title, method.region())
    return summarize(ctx, "import", kept, cfg)
