"""``task=import``: a certify log computed elsewhere (Cohen / paper-authors format, with or
without our extra columns) recorded as an MLflow run with the same metrics as ``certify``."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from mrcert.certify_log import read_log
from mrcert.smoothing import SmoothingDistribution
from mrcert.tasks import RunContext
from mrcert.tasks.certify import report


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    df = read_log(t.path)
    ctx.tracker.log_artifact(t.path)
    dist = SmoothingDistribution((str(t.axis),), (float(t.sigma),))
    title = f"imported {t.dataset} {t.arch} {t.variant}, smoothing {t.axis}"
    return report(df, float(t.radius), float(t.radius_step), ctx, title, dist.region())
