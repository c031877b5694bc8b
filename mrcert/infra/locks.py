"""Who may write a run: the lock on a run's output folder, held by the process that writes it,
and the lock on a run key, held from the look-up of its run to the run's end."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra.identity import RunIdentity
from mrcert.infra.store import FileLock


def run_lock(folder: Path) -> FileLock:
    """The lock a process holds on the output folder of the run it writes: a second process
    never resumes (and writes into) a run that a live one still holds; a killed one's is free."""
    return FileLock(Path(folder) / ".mrcert.lock")


@contextmanager
def key_lock(cfg: DictConfig, ident: RunIdentity) -> Iterator[None]:
    """Held from the lookup of a run of this run key to the run's end, so that identical jobs
    started together make one run: the first computes it, the others stop at once naming it
    (they would otherwise each find no run and each create one). The lock lives under
    ``paths.outputs/locks``: it coordinates the jobs that share that folder."""
    if not cfg.tracking.enabled:
        yield
        return
    lock = FileLock(Path(cfg.paths.outputs) / "locks" / f"{ident.key}.lock")
    if not lock.acquire(blocking=False):
        raise MrcertError(
            f"an identical job is computing this config now ({lock.holder()}; run key {ident.key}); "
            "wait for it to finish, then rerun to reuse its result (skip_finished=true) or resume it"
        )
    try:
        yield
    finally:
        lock.release()
