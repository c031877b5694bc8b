"""The MLflow store and its experiment: mlflow pointed at the store (a SQLite store created
atomically, a server probed), the experiment created with the runs page's view of mrcert's
runs, the tags runs are filed under, and the look-up of runs by run key."""

from __future__ import annotations

import functools
import json
import logging
import os
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mrcert.core.methods import current_names
from mrcert.errors import MrcertError
from mrcert.infra.config import CONF_DIR
from mrcert.infra.store import ensure_sqlite_store, moved_artifact, probe_server, relocate_artifacts, store_lock
from mrcert.infra.tasks import TASKS

log = logging.getLogger(__name__)


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
        stale = {k: v for k, v in experiment_tags().items() if exp.tags.get(k) != v}
        if stale:  # a store an older mrcert wrote: its sweep parents carry the task tag the view groups by
            _untag_parents(mlflow, exp.experiment_id)
        for k, v in stale.items():
            client.set_experiment_tag(exp.experiment_id, k, v)
        follow_moved_store(tracking, exp)
        return exp.experiment_id
    location = tracking.artifact_location
    if location:
        Path(location).mkdir(parents=True, exist_ok=True)
        location = Path(location).as_uri()
    uri = str(tracking.uri)
    if uri.startswith("sqlite:///"):  # one creator at a time; the others find it made
        db = sqlite_path(uri)
        with store_lock(db):
            exp = client.get_experiment_by_name(tracking.experiment)
            if exp is not None:
                return exp.experiment_id
            return client.create_experiment(tracking.experiment, location, experiment_tags())
    try:
        return client.create_experiment(tracking.experiment, artifact_location=location, tags=experiment_tags())
    except Exception:  # another job created it in between (a server serialises creations)
        exp = client.get_experiment_by_name(tracking.experiment)
        if exp is None:
            raise
        return exp.experiment_id


def follow_moved_store(tracking: DictConfig, exp) -> None:
    """A SQLite store whose folder moved (copied off the machine that made it, committed and cloned
    elsewhere) still names the old folder as its experiment's artifact location, where MLflow would
    write every new run's files, or fail to: it is set to the configured ``tracking.artifact_location``
    (the store's own ``mlartifacts``). Runs made before the move are read in place
    (:func:`mrcert.infra.store.moved_artifact`)."""
    uri, location = str(tracking.uri), tracking.artifact_location
    if not (uri.startswith("sqlite:///") and location):
        return
    wanted = Path(location).as_uri()
    if exp.artifact_location == wanted:
        return
    Path(location).mkdir(parents=True, exist_ok=True)
    db = sqlite_path(uri)
    with store_lock(db):
        relocate_artifacts(db, exp.experiment_id, wanted)
    log.info("the store's runs kept their files in %s; new runs keep them in %s", exp.artifact_location, wanted)


RUNS_VIEW = "mrcert"
"""Name of the runs page's view that :func:`ui_link` opens (MLflow's shared view state)."""

_NAME_COLUMN = "attributes.`Run Name`"

RUNS_VIEW_GROUP = "mrcert.task"
"""The tag the runs page groups by: every task run carries it, a sweep's parent does not (its
tasks are ``mrcert.sweep_tasks``), so parents gather in MLflow's collapsed "Additional runs"."""


@functools.cache
def runs_view_metrics() -> tuple[str, ...]:
    """The tasks' headline metrics, in the order the runs page shows them: those of the tasks with a
    per-image log (certify first) before a train run's."""
    return tuple(
        dict.fromkeys(m for task in sorted(TASKS.values(), key=lambda t: t.log is None) for m in task.headline)
    )


@functools.cache
def experiment_tags() -> dict[str, str]:
    """Tags every mrcert experiment carries (set on creation, restored when missing or changed)."""
    metrics = runs_view_metrics()
    columns = [f"metrics.`{name}`" for name in metrics]
    return {
        # MLflow's UI then opens the experiment on its runs, not on GenAI traces.
        "mlflow.experimentKind": "custom_model_development",
        # A view of the runs page (MLflow's "share view" mechanism: an experiment tag named by the
        # view's key, opened with ``?viewStateShareKey=<key>``): runs grouped by task, each group
        # open and its runs listed (a sweep's jobs are otherwise hidden under their collapsed
        # parent), certify runs first, the run name wide enough for task, axis, variant and model,
        # then the headline metrics, with no horizontal scrolling.
        f"mlflow.sharedViewState.{RUNS_VIEW}": json.dumps(
            {
                "selectedColumns": columns,
                "columnOrder": [_NAME_COLUMN, *columns],
                "columnWidths": {_NAME_COLUMN: 320} | {f"metrics.`{m}`": 7 * len(m) + 24 for m in metrics},
                "groupBy": {
                    "aggregateFunction": "average",
                    "groupByKeys": [{"mode": "tag", "groupByData": RUNS_VIEW_GROUP}],
                },
                "orderByKey": columns[0],
                "orderByAsc": False,
            }
        ),
    }


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


def artifact(client, run_id: str, path: str) -> Path:
    """A run's artifact as a local file (downloaded when the store is remote; in a store folder
    that was moved, from its own ``mlartifacts``), or a one-line error."""
    try:
        return Path(client.download_artifacts(run_id, path))
    except Exception as exc:  # noqa: BLE001 - a missing artifact, an unreachable store
        moved = moved_artifact(run_id, path)
        if moved is not None:
            return moved
        raise MrcertError(f"runs:/{run_id}/{path} cannot be fetched from MLflow: {exc}") from None


TARGETED = ("task", "data", "attack")
"""The groups whose options name the class that runs or builds them (``_target_``)."""


def read_run_config(path: Path) -> DictConfig:
    """A run's ``resolved_config.yaml`` as this version reads it: former method names renamed, and
    a config written before options named their classes given the ``_target_`` its option's YAML
    names now (by the option's ``name``)."""
    data = current_names(OmegaConf.to_container(OmegaConf.load(path)))
    for group in TARGETED:
        node = data.get(group)
        option = CONF_DIR / group / f"{node.get('name')}.yaml" if isinstance(node, dict) else None
        if option is not None and "_target_" not in node and option.is_file():
            node["_target_"] = OmegaConf.load(option).get("_target_")
    return OmegaConf.create(data)


def run_file(client, run_id: str, output_dir: str | None, name: str) -> Path | None:
    """A file of a run: from its output folder, else from its artifacts (None when it is gone)."""
    local = Path(str(output_dir or "")) / name
    if output_dir and local.is_file():
        return local
    try:
        return artifact(client, run_id, name)
    except MrcertError:
        return None
