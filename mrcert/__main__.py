"""The one entry point: ``mrcert task=NAME ...`` / ``python -m mrcert task=NAME ...``."""

from __future__ import annotations

import sys

from mrcert.formats.answer import watch_command_line

watch_command_line(sys.argv[1:])  # a verification's time limit counts from here: before the slow imports

import errno
import logging
import os
import shutil
import signal
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from mrcert.errors import MrcertError
from mrcert.infra import config as mrcert_config
from mrcert.infra.checkpoints import check_classes, local_checkpoint, read_checkpoint
from mrcert.infra.identity import RunIdentity
from mrcert.infra.key_migration import migrate_once
from mrcert.infra.locks import key_lock
from mrcert.infra.resolver import LiveRuns, resolve
from mrcert.infra.resumption import log_files_under
from mrcert.infra.run_store import decide
from mrcert.infra.store import is_locked, locked
from mrcert.infra.sweeps import fail_parent
from mrcert.infra.tasks import TASKS
from mrcert.infra.tracking import RunContext, task_run
from mrcert.tasks.inputs import check_inputs

log = logging.getLogger("mrcert")


def task_help() -> str:
    """The tasks with their one line, for ``mrcert --help``; empty in a launch that shows no help
    (Hydra resolves the help text in every launch, and reading every task's summary takes time)."""
    if not any(a in ("--help", "-h") for a in sys.argv[1:]):
        return ""
    return "\n".join(f"  {n:<10} {TASKS.summary(n)}" for n in TASKS)


OmegaConf.register_new_resolver("mrcert_task_help", task_help, replace=True)


def groups_help() -> str:
    """The config groups a user picks, with their options (``group: a, b``): the folders of
    ``conf/`` but Hydra's own, the schemas (``schema/*``) and the blocks options include
    (``task/evaluation``, ``data/camera``)."""
    conf = mrcert_config.CONF_DIR
    return "\n".join(
        f"{g.name}: {', '.join(sorted(p.stem for p in g.glob('*.yaml')))}"
        for g in sorted(conf.iterdir())
        if g.is_dir() and g.name != "hydra"
    )


OmegaConf.register_new_resolver("mrcert_groups_help", groups_help, replace=True)


def bind(cfg: DictConfig) -> tuple[DictConfig, RunIdentity]:
    """``cfg`` bound to its inputs (the one checkpoint an evaluation uses) and its run identity.
    Every file input is checked here, before any data is prepared or any run is created."""
    task = TASKS.of(cfg)
    check_inputs(cfg, task.identity, task.scene_task)
    runs = None
    if cfg.tracking.enabled:
        runs = LiveRuns(cfg.tracking)
        migrate_once(runs.client, cfg.tracking.experiment)  # a store keyed before models were named by content
    cfg, ident = resolve(cfg, runs)
    if ":/" in str(cfg.model.get("checkpoint") or ""):  # a run's model, verified against its seal (a file: above)
        from mrcert.data.sources import load

        path = local_checkpoint(str(cfg.model.checkpoint))
        check_classes(read_checkpoint(path), load(cfg.data).classes, path)
    return cfg, ident


def run_task(cfg: DictConfig, output_dir: Path) -> dict[str, Any]:
    """Validate ``cfg``, bind its inputs, then run its task inside an MLflow run writing to
    ``output_dir`` (or return the FINISHED run of the same run key with ``skip_finished``).

    Any failure of a job in a multirun marks the sweep's parent run FAILED.
    """
    try:
        task = TASKS.of(cfg)
        mrcert_config.validate(cfg, task.scene_task)
        if not task.tracked:  # outside MLflow runs: its launch leaves no folder
            result = task.run(cfg, None)
            discard_launch(output_dir)
            return result
        cfg, ident = bind(cfg)
        with key_lock(cfg, ident):  # lookup and creation of this key's run: one job at a time
            decision = decide(cfg, ident, task.reusable, task.needs)
            if decision.action == "skip":
                done = decision.run
                log.info("skipping task %s: run %s already finished with this config", cfg.task.name, done.info.run_id)
                return dict(done.data.metrics)
            with task_run(cfg, output_dir, ident, decision) as tracker:
                result = task.run(cfg, RunContext(tracker.output_dir, tracker))
    except BaseException:
        fail_parent(cfg)
        raise
    log.info("task %s done: %s", cfg.task.name, result)
    return result


PERMISSION_ERRORS = (errno.EACCES, errno.EPERM)
STORAGE_ERRORS = (errno.EROFS, errno.ENOSPC, errno.EDQUOT)


def _user_error(exc: BaseException, store: str = "") -> str | None:
    """The one-line message for an error the user can fix, else None (a bug: keep the traceback);
    ``store``: the tracking URI in use."""
    if isinstance(exc, MrcertError):
        return str(exc)
    if type(exc).__name__ == "MlflowException" and is_locked(exc):
        return str(locked(store))
    if isinstance(exc, OSError) and exc.errno in PERMISSION_ERRORS:
        where = f" {exc.filename}" if exc.filename else ""
        return f"permission denied on{where} ({exc.strerror}): check its permissions, or point paths.outputs elsewhere"
    if isinstance(exc, OSError) and exc.errno in STORAGE_ERRORS:
        where = f" {exc.filename}" if exc.filename else ""
        return f"cannot write{where}: {exc.strerror}; free some space or point paths.outputs / MRCERT_OUTPUTS elsewhere"
    return None


@hydra.main(version_base="1.3", config_path=str(mrcert_config.CONF_DIR), config_name="config")
def _hydra_main(cfg: DictConfig) -> dict[str, Any]:
    hc = HydraConfig.get()
    try:
        return run_task(cfg, Path(hc.runtime.output_dir))
    except Exception as exc:
        message = _user_error(exc, str(cfg.tracking.uri))
        if message is None or hc.mode == RunMode.MULTIRUN:
            raise  # a bug keeps its traceback; in a multirun Hydra records the job and goes on
        discard_launch(Path(hc.runtime.output_dir))
        print(f"mrcert: error: {message}", file=sys.stderr)
        sys.exit(2)


def discard_launch(folder: Path) -> None:
    """Remove the folder Hydra made for a launch that made no run in it (refused before any run
    existed, or a task outside MLflow runs: only its ``.hydra`` record and log are there), so
    that such a launch leaves nothing behind."""
    if not folder.is_dir() or any(p.name != ".hydra" and p.suffix != ".log" for p in folder.iterdir()):
        return  # a run was created here (resolved_config.yaml, results): keep everything
    for h in log_files_under(folder):
        logging.getLogger().removeHandler(h)
        h.close()
    shutil.rmtree(folder, ignore_errors=True)


def _outputs_root(argv: list[str]) -> Path:
    """Where this launch writes: ``paths.outputs=`` on the command line, MRCERT_OUTPUTS, or outputs/."""
    for arg in argv:
        if arg.startswith("paths.outputs="):
            return Path(arg.split("=", 1)[1])
    return Path(os.environ.get("MRCERT_OUTPUTS", "outputs"))


def check_writable(root: Path) -> str | None:
    """Why ``root`` cannot hold mrcert's outputs, or None."""
    existing = root.resolve()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        return (
            f"the output folder {str(root)!r} is not writable ({existing} is read-only or not a folder); "
            "point paths.outputs=... or MRCERT_OUTPUTS at a writable folder"
        )
    return None


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a scheduler's stop): handled as Ctrl-C is, so that the run is closed
    KILLED with its working time logged, and the same command resumes it."""


def _terminate(signum, frame) -> None:
    raise Terminated()


def main() -> None:
    mrcert_config.new_launch_uid()
    signal.signal(signal.SIGTERM, _terminate)
    if not any(a in ("--help", "-h", "--hydra-help", "--info", "-i") or a.startswith("--cfg") for a in sys.argv[1:]):
        problem = check_writable(_outputs_root(sys.argv[1:]))
        if problem:
            print(f"mrcert: error: {problem}", file=sys.stderr)
            sys.exit(2)
    try:
        _hydra_main()
    except KeyboardInterrupt as exc:  # the run was closed KILLED on the way out (tracking.task_run)
        how = "stopped (SIGTERM)" if isinstance(exc, Terminated) else "interrupted"
        print(f"mrcert: {how}; the run is marked KILLED and the same command resumes it", file=sys.stderr)
        sys.exit(128 + signal.SIGTERM if isinstance(exc, Terminated) else 130)


if __name__ == "__main__":
    main()
