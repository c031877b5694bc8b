"""MLflow tracking: one MLflow run per task run (a child of its sweep's parent in a multirun),
and what a task logs through. The store and experiment: :mod:`mrcert.infra.experiment`; locks:
:mod:`mrcert.infra.locks`; resuming: :mod:`mrcert.infra.resumption`; a sweep's parent run:
:mod:`mrcert.infra.sweeps`.
"""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra import identity
from mrcert.infra.config import plain
from mrcert.infra.experiment import configure, ensure_experiment, run_tags
from mrcert.infra.identity import RunIdentity
from mrcert.infra.locks import run_lock
from mrcert.infra.resumption import adopt, close_stale, timed_segment
from mrcert.infra.run_store import Decision
from mrcert.infra.runtime import code_version, machine
from mrcert.infra.seals import sealed_files, seals
from mrcert.infra.store import uninterrupted
from mrcert.infra.sweeps import parent_info
from mrcert.infra.tasks import TASKS

log = logging.getLogger(__name__)

MAX_PARAM_CHARS = 6000


def interruption(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C (or SIGTERM) behind ``exc``, or None. An interrupt that lands inside compiled
    code (a numba kernel) reaches Python as a ``SystemError`` whose cause is the interrupt."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def flatten(data: Any) -> dict[str, str]:
    """Nested dicts and lists as ``{"a.b.0": "value"}`` strings, for MLflow params."""
    return {k: str(v)[:MAX_PARAM_CHARS] for k, v in identity.flatten(data).items()}


@dataclass(frozen=True)
class RunContext:
    """Where a task writes (its run directory) and what it logs through."""

    output_dir: Path
    tracker: Tracker


@dataclass
class Tracker:
    """What a task logs through (does nothing when tracking is off), and where its files live."""

    output_dir: Path
    run_id: str | None = None
    resumed: bool = False
    key: str | None = None
    """The run key: with the run id, who owns the per-image logs in ``output_dir``."""
    tags: dict[str, str] = field(default_factory=dict)
    """The run's tags when it began here (a resumed run's: the seals it recorded before)."""

    @property
    def owner(self) -> dict[str, str | None]:
        return {"run_key": self.key, "run_id": self.run_id}

    @property
    def enabled(self) -> bool:
        return self.run_id is not None

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        if self.enabled:
            import mlflow

            mlflow.log_metrics({k: float(v) for k, v in metrics.items()}, step=step)

    def set_tags(self, tags: dict[str, str]) -> None:
        if self.enabled:
            import mlflow

            mlflow.set_tags(tags)

    def record(self) -> Callable[[str, str], None] | None:
        """What a per-image log records its seal through (None when tracking is off): a tag
        written whole, never cut by Ctrl-C."""
        if not self.enabled:
            return None
        import mlflow

        def set_tag(key: str, value: str) -> None:
            with uninterrupted():
                mlflow.set_tag(key, value)

        return set_tag

    def log_figure(self, figure, artifact_file: str) -> None:
        """A matplotlib figure, shown by MLflow's UI with the run."""
        if self.enabled:
            import mlflow

            mlflow.log_figure(figure, artifact_file)

    def log_table(self, table, artifact_file: str) -> None:
        """A pandas table (``.json``), shown by MLflow's UI with the run."""
        if self.enabled:
            import mlflow

            mlflow.log_table(table.reset_index() if table.index.names != [None] else table, artifact_file)

    def log_input(self, folder: Path | str, name: str, digest: str, context: str) -> None:
        """The rendered data set a run read (a cache entry: its key is the digest)."""
        if self.enabled:
            import mlflow
            from mlflow.data.dataset_source_registry import resolve_dataset_source
            from mlflow.data.meta_dataset import MetaDataset

            with warnings.catch_warnings():  # a local folder matches two equivalent source kinds
                warnings.simplefilter("ignore", UserWarning)
                source = resolve_dataset_source(Path(folder).resolve().as_uri())
            mlflow.log_input(MetaDataset(source, name=name, digest=digest), context=context)

    def log_artifact(self, path: Path | str, artifact_path: str | None = None) -> None:
        if self.enabled:
            import mlflow

            path = Path(path)
            if path.is_dir():
                mlflow.log_artifacts(str(path), artifact_path=artifact_path or path.name)
            else:
                mlflow.log_artifact(str(path), artifact_path=artifact_path)


@contextmanager
def task_run(cfg: DictConfig, output_dir: Path, ident: RunIdentity, decision: Decision) -> Iterator[Tracker]:
    """An MLflow run around one task: params, tags (the run and cell keys, the model used) and
    the resolved config on entry, status FINISHED, FAILED (an error) or KILLED (interrupted)
    on exit; a child of the sweep's parent run in a multirun.

    ``decision`` (:func:`mrcert.infra.run_store.decide`) says whether it starts a new run or
    resumes an interrupted one (reopened, the task continuing in that run's output directory).
    """
    from mrcert.infra.config import to_yaml

    output_dir.mkdir(parents=True, exist_ok=True)
    resolved = output_dir / "resolved_config.yaml"
    if not cfg.tracking.enabled:
        resolved.write_text(to_yaml(cfg))
        yield Tracker(output_dir, key=ident.key)
        return
    info = parent_info() or {}
    parent_id = info.get("run_id")
    mlflow = configure(cfg.tracking)
    experiment_id = info.get("experiment_id") or ensure_experiment(cfg.tracking)
    previous, lock = decision.run, decision.lock
    close_stale(decision.interrupted, mlflow.MlflowClient(), previous.info.run_id if previous is not None else None)
    if previous is not None:
        resumed = Path(previous.data.tags["mrcert.output_dir"])
        log.info("resuming MLflow run %s from %s", previous.info.run_id, resumed)
        adopt(output_dir, resumed)
        output_dir = resumed
        run_ctx = mlflow.start_run(run_id=previous.info.run_id)
    else:
        resolved.write_text(to_yaml(cfg))
        lock = run_lock(output_dir)
        if not lock.acquire(blocking=False):
            raise MrcertError(f"the run folder {output_dir} is held by another process ({lock.holder()})")
        tags = (
            run_tags(cfg)
            | ident.tags()
            | {
                "mrcert.output_dir": str(output_dir.resolve()),
                "mrcert.machine": machine(),
                "mrcert.code_version": code_version(),
                "mrcert.multirun": "job" if parent_id else "single",  # a sweep's parent: "parent"
            }
        )
        run_ctx = mlflow.start_run(
            experiment_id=experiment_id,
            parent_run_id=parent_id,
            tags=tags,
            run_name=TASKS.of(cfg).title(cfg),
        )
    try:
        with run_ctx as run:
            if previous is None:
                mlflow.log_params(flatten(plain(cfg)) | ident.params())
                mlflow.log_artifact(str(resolved))
            log.info("MLflow run %s in experiment %s at %s", run.info.run_id, experiment_id, cfg.tracking.uri)
            try:
                with timed_segment(mlflow, previous):
                    earlier = dict(previous.data.tags) if previous is not None else {}
                    yield Tracker(output_dir, run.info.run_id, previous is not None, ident.key, earlier)
                task = TASKS.of(cfg)
                with uninterrupted():
                    mlflow.set_tags(seals(output_dir, sealed_files(str(cfg.task.name), task.log)))
            except BaseException as exc:
                stop = interruption(exc)
                if stop is not None:
                    with uninterrupted():
                        mlflow.end_run("KILLED")  # interrupted, not wrong: the next identical command resumes it
                    if stop is exc:
                        raise
                    raise stop from None  # as Ctrl-C, wherever it landed
                with contextlib.suppress(Exception):  # the reason, in the UI (never hiding the error itself)
                    mlflow.set_tag("mrcert.failure", f"{type(exc).__name__}: {exc}"[:5000])
                mlflow.end_run("FAILED")
                raise
    finally:
        lock.release()
