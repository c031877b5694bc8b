"""Resuming an interrupted run: finding it, moving what the new process wrote into its folder,
and counting the time each process worked on it."""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra.locks import run_lock
from mrcert.infra.store import uninterrupted


def resumable(cfg: DictConfig, interrupted: list):
    """The newest of this run key's ``interrupted`` runs (newest first) with its lock taken, or None.

    A run whose lock a live process holds is refused with an error naming it."""
    if not cfg.task.get("resume"):
        return None, None
    for run in interrupted[:1]:
        folder = Path(run.data.tags["mrcert.output_dir"])
        lock = run_lock(folder)
        if not lock.acquire(blocking=False):
            raise MrcertError(
                f"run {run.info.run_id} with this config is still being written by a live process "
                f"({lock.holder()}, {folder}); wait for it to finish, or stop it and rerun to resume it"
            )
        return run, lock
    return None, None


def close_stale(interrupted: list, client, keep: str | None) -> int:
    """Mark KILLED every RUNNING run of a run key's ``interrupted`` ones (but ``keep``, the run
    being resumed) that no live process holds: a process killed outright (SIGKILL, a lost
    machine) never closed it. The number closed."""
    closed = 0
    for run in interrupted:
        if run.info.status != "RUNNING" or run.info.run_id == keep:
            continue
        folder = Path(run.data.tags.get("mrcert.output_dir", ""))
        lock = run_lock(folder)
        if not folder.is_dir():  # its folder is gone: nothing can be working on it
            client.set_terminated(run.info.run_id, "KILLED")
            closed += 1
        elif lock.acquire(blocking=False):
            try:
                client.set_terminated(run.info.run_id, "KILLED")
                closed += 1
            finally:
                lock.release()
    return closed


def log_files_under(folder: Path) -> list[logging.FileHandler]:
    """The root logger's file handlers that write inside ``folder``."""
    folder = folder.resolve()
    return [
        h
        for h in logging.getLogger().handlers
        if isinstance(h, logging.FileHandler) and Path(h.baseFilename).resolve().is_relative_to(folder)
    ]


def adopt(launch_dir: Path, run_dir: Path) -> None:
    """Move what this launch wrote so far (Hydra's log and ``.hydra`` folder) from its own
    folder into ``run_dir/resumed/<time>/``, point the open log files there, and remove the
    launch folder: a resumed run keeps every process's log, and leaves no orphan folder."""
    launch_dir, run_dir = launch_dir.resolve(), run_dir.resolve()
    if launch_dir == run_dir or not launch_dir.is_dir():
        return
    target = run_dir / "resumed" / f"{time.strftime('%Y-%m-%d_%H-%M-%S')}_{os.getpid()}"
    target.mkdir(parents=True, exist_ok=True)
    handlers = log_files_under(launch_dir)
    for h in handlers:
        h.acquire()
        h.close()
    for item in launch_dir.iterdir():
        shutil.move(str(item), str(target / item.name))
    for h in handlers:
        h.baseFilename = str(target / Path(h.baseFilename).resolve().relative_to(launch_dir))
        h.mode = "a"
        h.stream = h._open()
        h.release()
    launch_dir.rmdir()


@contextmanager
def timed_segment(mlflow, previous) -> Iterator[None]:
    """Count the wall-clock this process works on the active run (``previous``: the interrupted
    run it resumes, or None), apart from the time the run was down between an interruption and
    its resumption: metrics ``segments`` (processes that worked on the run, logged on entry),
    ``timed_segments`` (those that logged their time on exit, whatever the exit) and
    ``active_seconds`` (their time, summed). A process killed outright logs no time, and a run
    begun before this count existed had at least one untimed process, so
    ``timed_segments < segments`` says the sum is short."""
    t0 = time.monotonic()
    before = previous.data.metrics if previous is not None else {}
    mlflow.log_metric("segments", before.get("segments", 0 if previous is None else 1) + 1)
    try:
        yield
    finally:
        with uninterrupted():
            mlflow.log_metrics(
                {
                    "active_seconds": before.get("active_seconds", 0.0) + time.monotonic() - t0,
                    "timed_segments": before.get("timed_segments", 0) + 1,
                }
            )
