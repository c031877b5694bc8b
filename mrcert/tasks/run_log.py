"""The per-image log a task writes as it goes (``ResultLog``, owned by its run) and the headline
metrics it logs with that log when it is finished: what every evaluating task shares, without
the evaluation's own imports (data, methods, statistics)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from mrcert.infra.seals import tag
from mrcert.infra.tasks import TASKS
from mrcert.infra.tracking import RunContext
from mrcert.reporting.certify_log import ResultLog, read_log


def result_log(ctx: RunContext, task: str, extra: tuple[str, ...] = ()) -> ResultLog:
    """The per-image log of ``task`` (its name and columns from the task table, then ``extra``:
    a method's own columns) in the run's folder, owned by this run (rows of any other run found
    there are set aside, never adopted)."""
    name = TASKS[task].log
    recorded = ctx.tracker.tags.get(tag(name))
    columns = [*TASKS[task].columns, *extra]
    return ResultLog(ctx.output_dir / name, columns, ctx.tracker.owner, ctx.tracker.record(), recorded)


def log_headline(ctx: RunContext, task: str, log: Path, cfg: DictConfig) -> dict[str, float]:
    """The task's headline metrics of its finished per-image log, logged with the log."""
    metrics = TASKS[task].summarize(read_log(log, list(TASKS[task].columns)), cfg)
    log_outputs(ctx, metrics, log)
    return metrics


def log_outputs(ctx: RunContext, metrics: dict[str, float], *paths) -> None:
    ctx.tracker.log_metrics(metrics)
    for p in paths:
        ctx.tracker.log_artifact(p)
