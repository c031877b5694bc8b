"""A multirun's parent run: created with the experiment before any job starts, its id passed to
the jobs through a file in the sweep directory (never by jobs racing to create it), closed
FINISHED or FAILED when the jobs are done (docs/method.md §6)."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra.experiment import RUNS_VIEW_GROUP, configure, ensure_experiment, run_tags

log = logging.getLogger(__name__)

PARENT_FILE = "mlflow_parent.json"


def parent_info() -> dict[str, str] | None:
    """``{"run_id", "experiment_id"}`` of the sweep's parent run when this job is in a multirun."""
    try:
        hc = HydraConfig.get()
    except ValueError:
        return None
    path = Path(hc.sweep.dir) / PARENT_FILE
    if hc.mode != RunMode.MULTIRUN or not path.exists():
        return None
    return json.loads(path.read_text())


def fail_parent(cfg: DictConfig) -> None:
    """Mark the multirun's parent run FAILED (called when one of its jobs fails)."""
    info = parent_info()
    if cfg.tracking.enabled and info is not None:
        configure(cfg.tracking).MlflowClient().set_terminated(info["run_id"], "FAILED")


def sweep_tasks(config: DictConfig) -> str:
    """The task, or the comma-separated tasks, a multirun's jobs run (``task=certify,smooth``)."""
    swept = [o.split("=", 1)[1] for o in config.hydra.overrides.task if o.split("=", 1)[0].lstrip("+") == "task"]
    return swept[-1] if swept else str(config.task.name)


class MultirunParentCallback(Callback):
    """Creates the experiment and a parent run before a multirun's jobs start, and closes
    it FINISHED (or FAILED when any child failed) when they are done."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        if not config.tracking.enabled:
            return
        try:
            experiment_id = ensure_experiment(config.tracking)
        except MrcertError as exc:  # no store, no sweep: one line, as for a single run
            print(f"mrcert: error: {exc}", file=sys.stderr)
            sys.exit(2)
        client = configure(config.tracking).MlflowClient()
        sweep_dir = Path(config.hydra.sweep.dir)
        tags = {k: v for k, v in run_tags(config).items() if k != RUNS_VIEW_GROUP} | {
            "mrcert.sweep_tasks": sweep_tasks(config),
            "mrcert.multirun": "parent",
            "mrcert.sweep_dir": str(sweep_dir.resolve()),
            "mrcert.overrides": " ".join(config.hydra.overrides.task),
        }
        run = client.create_run(
            experiment_id, tags=tags, run_name=f"sweep {tags['mrcert.sweep_tasks']} {sweep_dir.name}"
        )
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / PARENT_FILE).write_text(json.dumps({"run_id": run.info.run_id, "experiment_id": experiment_id}))
        log.info("MLflow parent run %s for sweep %s", run.info.run_id, sweep_dir)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if not config.tracking.enabled:
            return
        info = json.loads((Path(config.hydra.sweep.dir) / PARENT_FILE).read_text())
        mlflow = configure(config.tracking)
        children = mlflow.search_runs(
            experiment_ids=[info["experiment_id"]],
            filter_string=f"tags.mlflow.parentRunId = '{info['run_id']}'",
            output_format="list",
        )
        failed = any(r.info.status != "FINISHED" for r in children)
        mlflow.MlflowClient().set_terminated(info["run_id"], "FAILED" if failed else "FINISHED")
