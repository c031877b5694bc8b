"""Which run: the one module that asks an MLflow store which of its runs serves a job.

* :func:`decide` -- what a job does about its run key, decided once: skip it (a FINISHED run
  serves it, with ``skip_finished``, while it holds the artifact its task ``needs``:
  :func:`holding`), resume an interrupted run of it, or start a new one;
* :func:`finished` -- the FINISHED runs of a run key, newest first (a job's result, which
  ``skip_finished`` reuses; a model's train run: :func:`newest_train_run`, or
  :func:`newest_train_run_in` the tables' index);
* :func:`interrupted` -- a run key's RUNNING or KILLED runs, newest first (what a resumed job
  continues, :mod:`mrcert.infra.resumption`);
* :func:`finished_table` -- every FINISHED run of an experiment as one table (what the tables
  index: :class:`mrcert.reporting.cells.RunIndex`; what ``task=gather`` copies: :func:`all_runs`).

Reading never writes: migrating a store keyed by an older scheme happens once when a launch
opens it (:func:`mrcert.infra.key_migration.migrate_once`, from the entry point), never as a side
effect of a look-up.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig

from mrcert.infra.checkpoints import BEST_PATH
from mrcert.infra.experiment import configure
from mrcert.infra.identity import RunIdentity
from mrcert.infra.resumption import resumable
from mrcert.infra.store import moved_artifact

if TYPE_CHECKING:
    import pandas as pd

log = logging.getLogger("mrcert")

KEY_TAG, CELL_TAG = "mrcert.key", "mrcert.cell"
FINISHED = "attributes.status = 'FINISHED'"
NOT_FINISHED = "attributes.status != 'FINISHED'"
KEY_COLUMN, CELL_COLUMN = f"tags.{KEY_TAG}", f"tags.{CELL_TAG}"


def _key_query(tracking: DictConfig, key: str, status: str, task: str | None) -> list:
    """Runs of run key ``key`` whose status meets ``status`` (a filter clause), newest first."""
    mlflow = configure(tracking)
    exp = mlflow.MlflowClient().get_experiment_by_name(tracking.experiment)
    if exp is None:
        return []
    where = [f"tags.`{KEY_TAG}` = '{key}'", status]
    if task is not None:
        where.append(f"tags.`mrcert.task` = '{task}'")
    return mlflow.search_runs(
        experiment_ids=[exp.experiment_id],
        filter_string=" and ".join(where),
        order_by=["attributes.start_time DESC"],
        output_format="list",
    )


def finished(tracking: DictConfig, key: str, task: str | None = None) -> list:
    """The FINISHED runs whose run key is ``key`` (of task ``task``, when given), newest first."""
    return _key_query(tracking, key, FINISHED, task)


def interrupted(tracking: DictConfig, key: str) -> list:
    """The runs of run key ``key`` that were interrupted (RUNNING or KILLED; never FAILED, which
    ended on an error), newest first."""
    runs = _key_query(tracking, key, NOT_FINISHED, None)
    return [r for r in runs if r.info.status in ("RUNNING", "KILLED")]


@dataclass
class Decision:
    """What a job does about its run key: ``"skip"`` (the FINISHED ``run`` serves it),
    ``"resume"`` (it continues the interrupted ``run``, whose ``lock`` it now holds) or
    ``"new"``. ``interrupted``: the key's RUNNING or KILLED runs, newest first (those a dead
    process left RUNNING are closed before the job starts)."""

    action: str
    run: Any = None
    lock: Any = None
    interrupted: list = field(default_factory=list)


def holding(tracking: DictConfig, runs: list, path: str | None) -> list:
    """Those of ``runs`` that hold the artifact ``path`` (all of them when ``path`` is None): in
    the location each recorded or, for a store folder moved since, in its own ``mlartifacts``."""
    if path is None:
        return runs
    client = configure(tracking).MlflowClient()
    folder = path.rpartition("/")[0] or None
    kept = []
    for run in runs:
        try:
            listed = {f.path for f in client.list_artifacts(run.info.run_id, folder)}
        except Exception:  # noqa: BLE001 - a recorded location that is gone
            listed = set()
        if path in listed or moved_artifact(run.info.run_id, path) is not None:
            kept.append(run)
        else:
            log.info("run %s finished but its %s is gone: it serves no job", run.info.run_id, path)
    return kept


def decide(cfg: DictConfig, ident: RunIdentity, reusable: bool, needs: str | None = None) -> Decision:
    """Skip when ``skip_finished`` is on, the task's results can be reused (``reusable``) and a
    FINISHED run has this run key (and still holds the artifact ``needs``, when given); else
    resume the newest interrupted run (``task.resume``; one a live process holds is refused);
    else new. Untracked jobs are always new."""
    if not cfg.tracking.enabled:
        return Decision("new")
    if reusable and cfg.get("skip_finished"):
        runs = holding(cfg.tracking, finished(cfg.tracking, ident.key), needs)
        if runs:
            return Decision("skip", runs[0])
    waiting = interrupted(cfg.tracking, ident.key)
    run, lock = resumable(cfg, waiting)
    return Decision("new" if run is None else "resume", run, lock, waiting)


def newest_train_run(tracking: DictConfig, key: str) -> str | None:
    """The id of the newest FINISHED train run with run key ``key`` that still holds its
    checkpoint, or None (the model an evaluation loads)."""
    runs = holding(tracking, finished(tracking, key, task="train"), BEST_PATH)
    return runs[0].info.run_id if runs else None


def newest_train_run_in(table: pd.DataFrame, key: str) -> str | None:
    """:func:`newest_train_run` among the rows of a :func:`finished_table`."""
    hits = table[(table[KEY_COLUMN] == key) & (table.get("tags.mrcert.task") == "train")]
    return None if hits.empty else str(hits.iloc[0]["run_id"])


def all_runs(client, experiment_id: str, where: str = "") -> list:
    """Every run of the experiment matching ``where``, page by page."""
    runs, token = [], None
    while True:
        page = client.search_runs([experiment_id], where, max_results=1000, page_token=token)
        runs += list(page)
        token = page.token
        if not token:
            return runs


def finished_table(experiment: str) -> pd.DataFrame:
    """Every FINISHED run of ``experiment`` that has a cell key, newest first, as MLflow's runs
    table (``run_id``, ``start_time``, ``tags.*``, ``metrics.*``, ...); empty when there is none."""
    import mlflow

    exp = mlflow.MlflowClient().get_experiment_by_name(experiment)
    if exp is None:
        import pandas as pd  # on demand: a launch that finds no runs to read never imports it

        return pd.DataFrame(columns=["run_id", "start_time", KEY_COLUMN, CELL_COLUMN])
    df = mlflow.search_runs([exp.experiment_id], filter_string=FINISHED)
    for col in (KEY_COLUMN, CELL_COLUMN):
        if col not in df:
            df[col] = None
    df = df[df[CELL_COLUMN].notna()] if len(df) else df
    return df.sort_values("start_time", ascending=False).reset_index(drop=True)
