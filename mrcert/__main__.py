"""The one entry point: ``mrcert task=NAME ...`` / ``python -m mrcert task=NAME ...``."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from mrcert import config as mrcert_config
from mrcert.errors import MrcertError
from mrcert.tasks import TASKS, RunContext
from mrcert.tracking import fail_parent, finished_run, task_run

log = logging.getLogger("mrcert")


def run_task(cfg: DictConfig, output_dir: Path) -> dict[str, Any]:
    """Validate ``cfg``, then run its task inside an MLflow run writing to ``output_dir``.

    Any failure of a job in a multirun marks the sweep's parent run FAILED.
    """
    try:
        mrcert_config.validate(cfg)
        done = finished_run(cfg)
        if done is not None:
            log.info("skipping task %s: run %s already finished with this config", cfg.task.name, done.info.run_id)
            return dict(done.data.metrics)
        func = TASKS[cfg.task.name].load()
        with task_run(cfg, output_dir) as tracker:
            result = func(cfg, RunContext(tracker.output_dir, tracker))
    except BaseException:
        fail_parent(cfg)
        raise
    log.info("task %s done: %s", cfg.task.name, result)
    return result


@hydra.main(version_base="1.3", config_path=str(mrcert_config.CONF_DIR), config_name="config")
def _hydra_main(cfg: DictConfig) -> dict[str, Any]:
    hc = HydraConfig.get()
    try:
        return run_task(cfg, Path(hc.runtime.output_dir))
    except MrcertError as exc:
        if hc.mode == RunMode.MULTIRUN:
            raise  # Hydra records the failed job and goes on with the others
        print(f"mrcert: error: {exc}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    mrcert_config.new_launch_uid()
    _hydra_main()


if __name__ == "__main__":
    main()
