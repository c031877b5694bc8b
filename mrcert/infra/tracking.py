"""MLflow tracking: one MLflow run per task run, children of one parent per multirun.

The parent run, the experiment and (for SQLite) the schema are created once, by
:class:`MultirunParentCallback` before any job starts, and the ids reach the jobs through a
file in the sweep directory -- never by jobs racing to create them (docs/method.md §6).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from mrcert.errors import MrcertError
from mrcert.infra import identity
from mrcert.infra.config import plain
from mrcert.infra.identity import RunIdentity
from mrcert.infra.runtime import code_version, machine
from mrcert.infra.store import FileLock, ensure_sqlite_store, probe_server
from mrcert.infra.tasks import TASKS

log = logging.getLogger(__name__)

PARENT_FILE = "mlflow_parent.json"
MAX_PARAM_CHARS = 6000


def flatten(data: Any) -> dict[str, str]:
    """Nested dicts and lists as ``{"a.b.0": "value"}`` strings, for MLflow params."""
    return {k: str(v)[:MAX_PARAM_CHARS] for k, v in identity.flatten(data).items()}


def configure(tracking: DictConfig):
    """The mlflow module pointed at the configured store: a SQLite store is created atomically
    and checked, a server is probed (see :mod:`mrcert.infra.store`)."""
    import mlflow

    uri = str(tracking.uri)
    if uri.startswith("sqlite:///"):
        db = sqlite_path(uri)
        try:
            db.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise MrcertError(f"cannot create the MLflow store folder {db.parent}: {exc}") from None
        if not os.access(db.parent, os.W_OK):
            raise MrcertError(f"the MLflow store folder {db.parent} is not writable; set tracking.uri elsewhere")
        ensure_sqlite_store(db)
    elif uri.startswith(("http://", "https://")):
        probe_server(uri)
    mlflow.set_tracking_uri(uri)
    return mlflow


def sqlite_path(uri: str) -> Path:
    return Path(uri[len("sqlite:///") :])


def ensure_experiment(tracking: DictConfig) -> str:
    """Id of the configured experiment, created (with its artifact location) if missing."""
    mlflow = configure(tracking)
    client = mlflow.MlflowClient()
    try:
        exp = client.get_experiment_by_name(tracking.experiment)
    except Exception as exc:  # unreachable server, corrupt store
        raise MrcertError(f"cannot reach the MLflow store at {tracking.uri}: {exc}") from None
    if exp is not None:
        stale = {k: v for k, v in EXPERIMENT_TAGS.items() if exp.tags.get(k) != v}
        if stale:  # a store an older mrcert wrote: its sweep parents carry the task tag the view groups by
            _untag_parents(mlflow, exp.experiment_id)
        for k, v in stale.items():
            client.set_experiment_tag(exp.experiment_id, k, v)
        return exp.experiment_id
    location = tracking.artifact_location
    if location:
        Path(location).mkdir(parents=True, exist_ok=True)
        location = Path(location).as_uri()
    uri = str(tracking.uri)
    if uri.startswith("sqlite:///"):  # one creator at a time; the others find it made
        db = sqlite_path(uri)
        with FileLock(db.with_name(f".{db.name}.lock")):
            exp = client.get_experiment_by_name(tracking.experiment)
            if exp is not None:
                return exp.experiment_id
            return client.create_experiment(tracking.experiment, location, EXPERIMENT_TAGS)
    try:
        return client.create_experiment(tracking.experiment, artifact_location=location, tags=EXPERIMENT_TAGS)
    except Exception:  # another job created it in between (a server serialises creations)
        exp = client.get_experiment_by_name(tracking.experiment)
        if exp is None:
            raise
        return exp.experiment_id


RUNS_VIEW_METRICS = tuple(
    dict.fromkeys(m for task in sorted(TASKS.values(), key=lambda t: t.log is None) for m in task.headline)
)
"""The tasks' headline metrics, in the order the runs page shows them: those of the tasks with a
per-image log (certify first) before a train run's."""

RUNS_VIEW = "mrcert"
"""Name of the runs page's view that :func:`ui_link` opens (MLflow's shared view state)."""

_NAME_COLUMN = "attributes.`Run Name`"
_VIEW_COLUMNS = [f"metrics.`{name}`" for name in RUNS_VIEW_METRICS]
RUNS_VIEW_GROUP = "mrcert.task"
"""The tag the runs page groups by: every task run carries it, a sweep's parent does not (its
tasks are ``mrcert.sweep_tasks``), so parents gather in MLflow's collapsed "Additional runs"."""
EXPERIMENT_TAGS = {
    # MLflow's UI then opens the experiment on its runs, not on GenAI traces.
    "mlflow.experimentKind": "custom_model_development",
    # A view of the runs page (MLflow's "share view" mechanism: an experiment tag named by the
    # view's key, opened with ``?viewStateShareKey=<key>``): runs grouped by task, each group
    # open and its runs listed (a sweep's jobs are otherwise hidden under their collapsed
    # parent), certify runs first, the run name wide enough for task, axis, variant and model,
    # then the headline metrics, with no horizontal scrolling.
    f"mlflow.sharedViewState.{RUNS_VIEW}": json.dumps(
        {
            "selectedColumns": _VIEW_COLUMNS,
            "columnOrder": [_NAME_COLUMN, *_VIEW_COLUMNS],
            "columnWidths": {_NAME_COLUMN: 320} | {f"metrics.`{m}`": 7 * len(m) + 24 for m in RUNS_VIEW_METRICS},
            "groupBy": {
                "aggregateFunction": "average",
                "groupByKeys": [{"mode": "tag", "groupByData": RUNS_VIEW_GROUP}],
            },
            "orderByKey": _VIEW_COLUMNS[0],
            "orderByAsc": False,
        }
    ),
}
"""Tags every mrcert experiment carries (set on creation, restored when missing or changed)."""


def _untag_parents(mlflow, experiment_id: str) -> None:
    """Move a sweep parent's :data:`RUNS_VIEW_GROUP` tag to ``mrcert.sweep_tasks`` (what parents
    carry now), so that the runs page's groups hold task runs only."""
    parents = mlflow.search_runs(
        experiment_ids=[experiment_id],
        filter_string=f"tags.`mrcert.multirun` = 'parent' and tags.`{RUNS_VIEW_GROUP}` != ''",
        output_format="list",
    )
    client = mlflow.MlflowClient()
    for run in parents:
        client.set_tag(run.info.run_id, "mrcert.sweep_tasks", run.data.tags[RUNS_VIEW_GROUP])
        client.delete_tag(run.info.run_id, RUNS_VIEW_GROUP)


UI_WORKFLOW = "machine_learning"
"""MLflow 3's UI shows an experiment as GenAI work (traces, judges, prompts in its sidebar) unless
the page is asked for its model-training view (``workflowType``): the link asks for it."""


def ui_link(tracking: DictConfig, base: str) -> str:
    """The MLflow UI page of the experiment's runs, in its model-training view and mrcert's view
    of the runs (``base``: where the UI is served)."""
    query = f"workflowType={UI_WORKFLOW}&viewStateShareKey={RUNS_VIEW}"
    return f"{base.rstrip('/')}/#/experiments/{ensure_experiment(tracking)}/runs?{query}"


def ui_link_for(outputs: str, base: str, experiment: str = "mrcert") -> str:
    """:func:`ui_link` for the default SQLite store under ``outputs`` (what ``make ui`` serves)."""
    uri = f"sqlite:///{Path(outputs).resolve() / 'mlflow.db'}"
    location = str(Path(outputs).resolve() / "mlartifacts")
    tracking = OmegaConf.create({"enabled": True, "uri": uri, "artifact_location": location, "experiment": experiment})
    return ui_link(tracking, base)


def run_tags(cfg: DictConfig) -> dict[str, str]:
    """Tags that tables and look-ups filter on."""
    select = lambda key: OmegaConf.select(cfg, key, default=None)  # noqa: E731
    tags = {
        "mrcert.task": select("task.name"),
        "mrcert.axis": select("motion.axis"),
        "mrcert.model": select("model.arch"),
        "mrcert.dataset": select("data.name"),
        "mrcert.variant": select("model.variant"),
        "mrcert.profile": select("profile.name"),
        "mrcert.method": select("method.name"),
    }
    overrides = OmegaConf.select(cfg, "task.tags", default=None)  # e.g. an imported log's metadata
    if overrides:
        tags.update(OmegaConf.to_container(overrides, resolve=True))
    return {k: str(v) for k, v in tags.items() if v is not None}


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


def _parent_info() -> dict[str, str] | None:
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
    info = _parent_info()
    if cfg.tracking.enabled and info is not None:
        configure(cfg.tracking).MlflowClient().set_terminated(info["run_id"], "FAILED")


def find_runs(tracking: DictConfig, key: str, finished: bool, task: str | None = None) -> list:
    """Runs whose run key is ``key``, newest first: FINISHED ones, or (``finished=False``)
    interrupted ones (RUNNING or KILLED; never FAILED, which ended on an error)."""
    mlflow = configure(tracking)
    exp = mlflow.MlflowClient().get_experiment_by_name(tracking.experiment)
    if exp is None:
        return []
    status = "= 'FINISHED'" if finished else "!= 'FINISHED'"
    where = [f"tags.`mrcert.key` = '{key}'", f"attributes.status {status}"]
    if task is not None:
        where.append(f"tags.`mrcert.task` = '{task}'")
    runs = mlflow.search_runs(
        experiment_ids=[exp.experiment_id],
        filter_string=" and ".join(where),
        order_by=["attributes.start_time DESC"],
        output_format="list",
    )
    return runs if finished else [r for r in runs if r.info.status in ("RUNNING", "KILLED")]


def finished_run(cfg: DictConfig, ident: RunIdentity):
    """A FINISHED run with this run key, when ``skip_finished`` is on (reproductions), else None."""
    if not (cfg.get("skip_finished") and cfg.tracking.enabled):
        return None
    runs = find_runs(cfg.tracking, ident.key, finished=True)
    return runs[0] if runs else None


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


def _resumable(cfg: DictConfig, ident: RunIdentity):
    """The newest interrupted run of this run key with its lock taken, or None.

    A run whose lock a live process holds is refused with an error naming it."""
    if not cfg.task.get("resume"):
        return None, None
    for run in find_runs(cfg.tracking, ident.key, finished=False)[:1]:
        folder = Path(run.data.tags["mrcert.output_dir"])
        lock = run_lock(folder)
        if not lock.acquire(blocking=False):
            raise MrcertError(
                f"run {run.info.run_id} with this config is still being written by a live process "
                f"({lock.holder()}, {folder}); wait for it to finish, or stop it and rerun to resume it"
            )
        return run, lock
    return None, None


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
        mlflow.log_metrics(
            {
                "active_seconds": before.get("active_seconds", 0.0) + time.monotonic() - t0,
                "timed_segments": before.get("timed_segments", 0) + 1,
            }
        )


@contextmanager
def task_run(cfg: DictConfig, output_dir: Path, ident: RunIdentity) -> Iterator[Tracker]:
    """An MLflow run around one task: params, tags (the run and cell keys, the model used) and
    the resolved config on entry, status FINISHED, FAILED (an error) or KILLED (interrupted)
    on exit; a child of the sweep's parent run in a multirun.

    With ``task.resume=true`` the newest interrupted run (RUNNING or KILLED, and no live
    process holding it) of the same run key is reopened and the task continues in that run's
    output directory.
    """
    from mrcert.infra.config import to_yaml

    output_dir.mkdir(parents=True, exist_ok=True)
    resolved = output_dir / "resolved_config.yaml"
    if not cfg.tracking.enabled:
        resolved.write_text(to_yaml(cfg))
        yield Tracker(output_dir, key=ident.key)
        return
    info = _parent_info() or {}
    parent_id = info.get("run_id")
    mlflow = configure(cfg.tracking)
    experiment_id = info.get("experiment_id") or ensure_experiment(cfg.tracking)
    previous, lock = _resumable(cfg, ident)
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
            run_name=TASKS[str(cfg.task.name)].title(cfg),
        )
    try:
        with run_ctx as run:
            if previous is None:
                mlflow.log_params(flatten(plain(cfg)) | ident.params())
                mlflow.log_artifact(str(resolved))
            log.info("MLflow run %s in experiment %s at %s", run.info.run_id, experiment_id, cfg.tracking.uri)
            try:
                with timed_segment(mlflow, previous):
                    yield Tracker(output_dir, run.info.run_id, resumed=previous is not None, key=ident.key)
            except KeyboardInterrupt:
                mlflow.end_run("KILLED")  # interrupted, not wrong: the next identical command resumes it
                raise
            except BaseException as exc:
                with contextlib.suppress(Exception):  # the reason, in the UI (never hiding the error itself)
                    mlflow.set_tag("mrcert.failure", f"{type(exc).__name__}: {exc}"[:5000])
                mlflow.end_run("FAILED")
                raise
    finally:
        lock.release()


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
