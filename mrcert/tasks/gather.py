"""``task=gather``: the finished runs of another mrcert store copied into this one, so that its
tables and evidence page read them beside this store's own. For runs made where no tracking
server is shared: a GPU machine, a laptop, a cluster node with its own SQLite store.

Each FINISHED run of the source's experiment is copied once, whole: its name, start and end
time, tags, params, every metric's history, logged data sets and artifacts (checkpoints, logs,
``resolved_config.yaml``). A copy carries ``mrcert.gathered_from`` = the source run's id, so a
second gather copies only what is new; a copy that a kill left unfinished is deleted and made
again. The copies get this store's run ids, and an evaluation names its model by the train
run's id (``runs:/<train run id>/checkpoints/best.pt``, part of its run key): sweep parents and
train runs are copied first, and every reference to a source id is rewritten to its copy's id,
in tags, params and ``resolved_config.yaml``, and the evaluation's run and cell keys are
computed again from the rewritten config -- so a gathered certification fills the same table
cell here as it did there. A run whose keys cannot be recomputed on this machine (its config
names a file that is not here) keeps its keys and is counted in ``kept_keys``.

A store moved after its runs were made (copied off the machine that made them) is read from
its folder: a run's artifacts are taken from ``<source>/mlartifacts/<run id>/artifacts`` when
the path recorded in the store is gone.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from mrcert.errors import MrcertError
from mrcert.infra.experiment import ensure_experiment
from mrcert.infra.identity import identify
from mrcert.infra.tasks import TASKS
from mrcert.infra.tracking import RunContext

GATHERED = "mrcert.gathered_from"
"""Tag of a copy: the id of the run it was copied from."""
CONFIG = "resolved_config.yaml"
BATCH = 100  # MLflow's log_batch takes at most 100 params or tags and 1000 metrics per call


def other_store(value: str) -> tuple[str, Path | None]:
    """The tracking URI of ``task.store`` (an outputs folder holding ``mlflow.db``, or a
    tracking URI) and the folder its artifacts live under, when it is a folder."""
    if value.startswith(("http://", "https://")):
        return value, None
    db = Path(value[len("sqlite:///") :]) if value.startswith("sqlite:///") else Path(value).expanduser() / "mlflow.db"
    if not db.is_file():
        raise MrcertError(
            f"task.store={value!r} is not an mrcert store: {db} does not exist; give an outputs folder "
            "(the one holding mlflow.db), a sqlite:/// URI or a tracking server's http(s):// URI"
        )
    return f"sqlite:///{db.resolve()}", db.resolve().parent


def _runs(client, experiment_id: str, where: str = "") -> list:
    """Every run of the experiment matching ``where``, page by page."""
    runs, token = [], None
    while True:
        page = client.search_runs([experiment_id], where, max_results=1000, page_token=token)
        runs += list(page)
        token = page.token
        if not token:
            return runs


def _finished_runs(client, experiment_id: str) -> list:
    """Every FINISHED run: sweep parents first, then train runs (the runs others refer to), then
    the rest, each group by start time."""
    runs = _runs(client, experiment_id, "attributes.status = 'FINISHED'")

    def order(r) -> tuple[int, int]:
        tags = r.data.tags
        rank = 0 if tags.get("mrcert.multirun") == "parent" else 1 if tags.get("mrcert.task") == "train" else 2
        return rank, r.info.start_time

    return sorted(runs, key=order)


RUN_ID = re.compile(r"(?<![0-9a-f])[0-9a-f]{32}(?![0-9a-f])")
"""An MLflow run id (32 hex digits), bare or inside ``runs:/<id>/...``."""


def _rewrite(text: str, ids: dict[str, str]) -> str:
    """``text`` with every source run id of a copied run replaced by its copy's: one pass over
    the text, however many runs were copied."""
    return RUN_ID.sub(lambda m: ids.get(m[0], m[0]), text)


def _artifacts(client, run, folder: Path | None, into: Path) -> bool:
    """Copy a source run's artifacts into ``into``; False when they are gone."""
    uri = run.info.artifact_uri
    recorded = Path(uri[len("file://") :]) if uri.startswith("file://") else Path(uri)
    moved = folder / "mlartifacts" / run.info.run_id / "artifacts" if folder is not None else None
    for local in (recorded, moved):
        if local is not None and local.is_dir():
            shutil.copytree(local, into, dirs_exist_ok=True)
            return True
    if folder is not None:
        return False
    try:  # a tracking server serves its runs' artifacts
        client.download_artifacts(run.info.run_id, "", str(into))
        return True
    except Exception:  # noqa: BLE001 - a run whose artifacts are gone
        return False


def _rekey(tags: dict[str, str], old_train: str, files: Path, ids: dict[str, str]) -> bool:
    """Recompute an evaluation's run and cell keys (in ``tags``) from its ``resolved_config.yaml``
    with its model's reference rewritten; False (keys kept) when its original config does not
    give its original key on this machine."""
    task = TASKS.get(tags.get("mrcert.task", ""))
    config = files / CONFIG
    if task is None or not task.identity.needs_model or not config.is_file():
        return False
    before = OmegaConf.load(config)
    try:
        same = identify(before, task.identity, old_train).key == tags.get("mrcert.key")
    except Exception:  # noqa: BLE001 - a config this version cannot read
        same = False
    if not same:
        return False
    after = OmegaConf.create(_rewrite(config.read_text(), ids))
    ident = identify(after, task.identity, ids[old_train])
    config.write_text(OmegaConf.to_yaml(after))
    tags["mrcert.key"], tags["mrcert.cell"] = ident.key, ident.cell
    return True


def _copy(src, dst, run, experiment_id: str, folder: Path | None, ids: dict[str, str]) -> dict[str, int]:
    """One run copied into ``dst``, FINISHED last; its new id recorded in ``ids``."""
    from mlflow.entities import Metric, Param, RunTag

    source_id = run.info.run_id
    tags = {k: _rewrite(v, ids) for k, v in run.data.tags.items() if k != "mrcert.output_dir"}
    tags[GATHERED] = source_id
    # Made with no key: until its end a half-made copy is nothing a task could resume or a table read.
    new = dst.create_run(
        experiment_id, start_time=run.info.start_time, tags={GATHERED: source_id}, run_name=run.info.run_name
    )
    new_id = new.info.run_id
    counts = {"without_artifacts": 0, "kept_keys": 0}
    with tempfile.TemporaryDirectory() as tmp:
        files = Path(tmp)
        if not _artifacts(src, run, folder, files) and "mrcert.task" in tags:  # a task run logs its config
            counts["without_artifacts"] = 1
        old_train = run.data.tags.get("mrcert.train_run")
        if old_train and ids.get(old_train, old_train) != old_train and not _rekey(tags, old_train, files, ids):
            counts["kept_keys"] = 1
        params = [Param(k, _rewrite(v, ids)) for k, v in run.data.params.items()]
        new_tags = [RunTag(k, v) for k, v in tags.items() if v != new.data.tags.get(k)]
        metrics = [
            Metric(m.key, m.value, m.timestamp, m.step)
            for key in run.data.metrics
            for m in src.get_metric_history(source_id, key)
        ]
        for i in range(0, len(params), BATCH):
            dst.log_batch(new_id, params=params[i : i + BATCH])
        for i in range(0, len(new_tags), BATCH):
            dst.log_batch(new_id, tags=new_tags[i : i + BATCH])
        for i in range(0, len(metrics), 10 * BATCH):
            dst.log_batch(new_id, metrics=metrics[i : i + 10 * BATCH])
        if run.inputs and run.inputs.dataset_inputs:
            dst.log_inputs(new_id, datasets=list(run.inputs.dataset_inputs))
        if any(files.iterdir()):
            dst.log_artifacts(new_id, str(files))
    dst.set_terminated(new_id, "FINISHED", end_time=run.info.end_time)
    ids[source_id] = new_id
    return counts


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    import mlflow

    uri, folder = other_store(str(cfg.task.store))
    if uri == str(cfg.tracking.uri):
        raise MrcertError(f"task.store={cfg.task.store!r} is this store itself; give another store's folder or URI")
    experiment_id = ensure_experiment(cfg.tracking)
    src, dst = mlflow.MlflowClient(tracking_uri=uri), mlflow.MlflowClient()
    exp = src.get_experiment_by_name(cfg.tracking.experiment)
    if exp is None:
        raise MrcertError(f"task.store={cfg.task.store!r} holds no experiment {cfg.tracking.experiment!r}")
    here = {r.info.run_id: r for r in _runs(dst, experiment_id)}
    ids: dict[str, str] = {}
    for r in here.values():
        origin = r.data.tags.get(GATHERED)
        if origin and r.info.status == "FINISHED":
            ids[origin] = r.info.run_id
        elif origin:  # a copy a kill left unfinished: made again below
            dst.delete_run(r.info.run_id)
    totals = {"gathered": 0, "already_here": 0, "without_artifacts": 0, "kept_keys": 0}
    for r in _finished_runs(src, exp.experiment_id):
        if r.info.run_id in ids or r.info.run_id in here:
            ids.setdefault(r.info.run_id, r.info.run_id)
            totals["already_here"] += 1
            continue
        for k, v in _copy(src, dst, r, experiment_id, folder, ids).items():
            totals[k] += v
        totals["gathered"] += 1
    print(
        f"Gathered {totals['gathered']} runs from {uri} ({totals['already_here']} already here"
        + (f"; {totals['without_artifacts']} without artifacts" if totals["without_artifacts"] else "")
        + (f"; {totals['kept_keys']} kept their keys" if totals["kept_keys"] else "")
        + ")"
    )
    return {k: float(v) for k, v in totals.items()}
