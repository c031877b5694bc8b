"""``task=gather``: the finished runs of another mrcert store copied into this one, so that its
tables and evidence page read them beside this store's own. For runs made where no tracking
server is shared: a GPU machine, a laptop, a cluster node with its own SQLite store.

Each FINISHED run of the source's experiment is copied once, whole and as it is: its name,
start and end time, tags, params, every metric's history, logged data sets and artifacts
(checkpoints, logs, ``resolved_config.yaml``). Its run and cell keys name its model by content
(:mod:`mrcert.infra.resolver`), not by a run id, so a copied certification fills the same table
cell here as there without any change. A copy carries ``mrcert.gathered_from`` = the source
run's id, so a second gather copies only what is new; a copy that a kill left unfinished is
deleted and made again. The one id a copy does not keep as it is, is MLflow's own link to a sweep's
parent run (``mlflow.parentRunId``), pointed at the parent's copy so that the sweep nests as it
did there. Runs from a store written before models were named by content are migrated once
copied (:mod:`mrcert.infra.key_migration`); one whose keys cannot be recomputed keeps them and
is counted in ``kept_keys``. A run whose sealed files (:mod:`mrcert.infra.seals`) are not what it
sealed is not copied at all: one line names it and the file, and it is counted in ``refused``. A
sealed file that is absent (a store brought home without its resume checkpoints, ``last.pt``:
90 MB for each ResNet-18) is no such file: the run is copied with what it has, one line names
what it lacks, and it is counted in ``without_artifacts``, as a run whose artifacts are all gone.
``task.without`` leaves files of those names behind on purpose (``[last.pt]``: a store packed for
another machine with its models but not their resume state), with the same line and count.

A store whose runs are sealed vouches for nothing it holds unsealed: a task run there whose
files carry no seal (its seals deleted, say) is copied as it is, tagged ``mrcert.unsealed``, named
in one line and counted in ``unsealed``, and never sealed here; no table reads it and no task
loads its checkpoint, as in its own store. Only runs of a store made before runs sealed their
files (one never tagged as sealed) are sealed once copied, as their files then are, which is
what opening that store would do.

A run gathered back into the store it came from is already there: a source run whose
``mrcert.gathered_from`` names a run here is not copied, so that two stores gathered into each
other in turn (a store carried between machines) hold each run once.

A store moved after its runs were made (copied off the machine that made them) is read from
its folder: a run's artifacts are taken from ``<source>/mlartifacts/<run id>/artifacts`` when
the path recorded in the store is gone.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra import seals
from mrcert.infra.experiment import ensure_experiment
from mrcert.infra.identity import Identity
from mrcert.infra.key_migration import GATHERED, SEAL_SCHEME, UNSEALED, migrate, seal_finished
from mrcert.infra.run_store import FINISHED, all_runs
from mrcert.infra.store import run_artifacts
from mrcert.infra.tasks import HELPER_IGNORES, TASKS, Task
from mrcert.infra.tracking import RunContext

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


def _finished_runs(client, experiment_id: str) -> list:
    """Every FINISHED run: sweep parents first (their children link to their copies), then the
    rest, each group by start time."""
    runs = all_runs(client, experiment_id, FINISHED)

    def order(r) -> tuple[int, int]:
        return (0 if r.data.tags.get("mrcert.multirun") == "parent" else 1), r.info.start_time

    return sorted(runs, key=order)


def _artifacts(client, run, folder: Path | None, into: Path) -> bool:
    """Copy a source run's artifacts into ``into``; False when they are gone."""
    uri = run.info.artifact_uri
    recorded = Path(uri[len("file://") :]) if uri.startswith("file://") else Path(uri)
    moved = run_artifacts(folder, run.info.run_id) if folder is not None else None
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


def _checked(run, files: Path) -> tuple[str | None, list[str]]:
    """Why a source run's artifacts (copied into ``files``) are not what the run sealed (or None),
    and the sealed files it lacks. Every copy of a sealed file's name in the run is checked."""
    absent = []
    for name in (k[len(seals.PREFIX) :] for k in run.data.tags if k.startswith(seals.PREFIX)):
        found = sorted(files.rglob(name))
        if not found:
            absent.append(name)
        try:
            for path in found:
                seals.verify(run.info.run_id, run.data.tags, path)
        except MrcertError as exc:
            return str(exc), absent
    return None, absent


def _unsealed(run, files: Path) -> list[str]:
    """The files a task run seals that it holds without any seal (a source that cannot vouch for them)."""
    tags = run.data.tags
    task = TASKS.get(tags.get("mrcert.task", ""))
    if task is None or any(k.startswith(seals.PREFIX) for k in tags):
        return []
    return [n for n in seals.sealed_files(tags["mrcert.task"], task.log) if any(files.rglob(n))]


def _copy(
    src, dst, run, experiment_id: str, folder: Path | None, ids: dict[str, str], without: tuple[str, ...], vouched: bool
) -> str:
    """One run copied into ``dst``, FINISHED last; its new id recorded in ``ids``. Returns
    ``copied``, ``without_artifacts`` (all of them or some sealed ones are gone: each named),
    ``unsealed`` (files the run should have sealed and did not, in a store whose runs are sealed:
    ``vouched``; copied as they are, tagged ``mrcert.unsealed``, never sealed here), or why it was
    refused (a sealed file that is not what its run sealed: nothing of it is copied)."""
    from mlflow.entities import Metric, Param, RunTag

    source_id = run.info.run_id
    tags = {k: v for k, v in run.data.tags.items() if k != "mrcert.output_dir"}
    tags[GATHERED] = source_id
    parent = tags.get("mlflow.parentRunId")
    if parent in ids:
        tags["mlflow.parentRunId"] = ids[parent]
    with tempfile.TemporaryDirectory() as tmp:
        files = Path(tmp)
        lost = not _artifacts(src, run, folder, files) and "mrcert.task" in tags  # a task run logs its config
        for left in (f for name in without for f in files.rglob(name)):
            left.unlink()
        refused, absent = (None, []) if lost else _checked(run, files)
        if refused:
            return refused
        if absent:
            print(f"gathered without its {', '.join(absent)}: run {source_id}")
        unsealed = _unsealed(run, files) if vouched else []
        if unsealed:
            tags[UNSEALED] = "true"
            print(
                f"gathered unsealed: run {source_id}'s {', '.join(unsealed)} carry no seal in a store whose runs "
                "are sealed; no table reads them and no task loads them"
            )
        # Made with no key: until its end a half-made copy is nothing a task could resume or a table read.
        new = dst.create_run(
            experiment_id, start_time=run.info.start_time, tags={GATHERED: source_id}, run_name=run.info.run_name
        )
        new_id = new.info.run_id
        params = [Param(k, v) for k, v in run.data.params.items()]
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
    return "without_artifacts" if lost or absent else "unsealed" if unsealed else "copied"


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
    here = {r.info.run_id: r for r in all_runs(dst, experiment_id)}
    ids: dict[str, str] = {}
    for r in here.values():
        origin = r.data.tags.get(GATHERED)
        if origin and r.info.status == "FINISHED":
            ids[origin] = r.info.run_id
        elif origin:  # a copy a kill left unfinished: made again below
            dst.delete_run(r.info.run_id)
    totals = {"gathered": 0, "already_here": 0, "without_artifacts": 0, "unsealed": 0, "kept_keys": 0, "refused": 0}
    without = tuple(str(name) for name in cfg.task.without)
    vouched = exp.tags.get(SEAL_SCHEME[0]) == SEAL_SCHEME[1]  # its runs sealed: an unsealed one is not vouched for
    for r in _finished_runs(src, exp.experiment_id):
        back = r.data.tags.get(GATHERED)  # a copy of a run of this store's: the run itself is here
        if r.info.run_id in ids or r.info.run_id in here or back in here:
            ids.setdefault(r.info.run_id, back if back in here else r.info.run_id)
            totals["already_here"] += 1
            continue
        outcome = _copy(src, dst, r, experiment_id, folder, ids, without, vouched)
        if outcome in ("copied", "without_artifacts", "unsealed"):
            totals["gathered"] += 1
            totals["without_artifacts"] += outcome == "without_artifacts"
            totals["unsealed"] += outcome == "unsealed"
        else:
            totals["refused"] += 1
            print(f"not gathered: {outcome}")
    if totals["gathered"]:  # copies from a store written before models were named by content, or sealed
        totals["kept_keys"] = migrate(dst, experiment_id)["kept"]
        seal_finished(dst, experiment_id)
    print(
        f"Gathered {totals['gathered']} runs from {uri} ({totals['already_here']} already here"
        + (
            f"; {totals['without_artifacts']} without some or all of their artifacts"
            if totals["without_artifacts"]
            else ""
        )
        + (f"; {totals['unsealed']} unsealed" if totals["unsealed"] else "")
        + (f"; {totals['kept_keys']} kept their keys" if totals["kept_keys"] else "")
        + (f"; {totals['refused']} refused: their files are not what they sealed" if totals["refused"] else "")
        + ")"
    )
    return {k: float(v) for k, v in totals.items()}


class Gather(Task):
    summary = "copy the finished runs of another store into this one"
    # What it copies depends on the other store's runs, not only on its config.
    identity = Identity(
        defines=("task",),
        ignores=HELPER_IGNORES,
        files=("task.store",),  # checked before any run starts (mrcert.tasks.inputs)
    )
    reusable = False

    def title(self, cfg: DictConfig) -> str:
        return f"gather {cfg.task.store}"

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
