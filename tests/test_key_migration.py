"""Run keys name an evaluation's model by content (its train run's key and its checkpoint's
digest), never by a store's run id; a store written before that keeps filling its cells.

The store in ``tests/data/store_before_content_keys.tar.gz`` was made, at ``MADE_AT``, by mrcert
as it was before content keys, with the commands of ``MADE_WITH`` and ``INTERRUPTED`` (stopped
with SIGTERM after 3 of its 18 images): its ``mlflow.db``, ``mlartifacts`` and the interrupted
run's folder. It is unpacked here and its recorded paths pointed at where it now lies, as a
store copied to another machine would be."""

import sqlite3
import tarfile
from pathlib import Path

import mlflow
import pytest
from omegaconf import OmegaConf

from mrcert.__main__ import run_task
from mrcert.infra.identity import KEY_SCHEME
from mrcert.infra.key_migration import migrate, migrate_once
from mrcert.infra.resolver import resolve
from mrcert.reporting.cells import RunIndex
from mrcert.reporting.certify_log import read_log
from tests.conftest import TINY, compose_cfg
from tests.test_gather import gather, runs_of

FIXTURE = Path(__file__).parent / "data" / "store_before_content_keys.tar.gz"
MADE_AT = "/tmp/mrcert-store-v1"
RECIPE = [*TINY, "train.epochs=2", "train.batch_size=8"]
EVAL = [*RECIPE, "task.n=200", "task.skip=3"]
MADE_WITH = [  # each with task.batch_size=64 for the evaluations
    [*RECIPE, "task=train", "model.variant=vanilla"],
    [*RECIPE, "task=train", "model.variant=augmented", "motion=tz"],
    [*EVAL, "task=certify", "model.variant=vanilla"],
    [*EVAL, "task=certify", "model.variant=augmented", "motion=tz"],
    [*EVAL, "task=smooth", "model.variant=augmented", "motion=tz"],
]
CELLS = MADE_WITH[2:]
INTERRUPTED = [*RECIPE, "task=certify", "model.variant=vanilla", "task.n=1000", "task.skip=1"]


def unpack(into: Path) -> Path:
    """The store, at ``into``, with the paths it records pointed there."""
    with tarfile.open(FIXTURE) as tar:
        tar.extractall(into, filter="data")
    with sqlite3.connect(into / "mlflow.db") as db:
        db.execute("update runs set artifact_uri = replace(artifact_uri, ?, ?)", (MADE_AT, str(into)))
        db.execute("update experiments set artifact_location = replace(artifact_location, ?, ?)", (MADE_AT, str(into)))
        db.execute("update tags set value = replace(value, ?, ?) where key = 'mrcert.output_dir'", (MADE_AT, str(into)))
    return into


def index(out: Path) -> RunIndex:
    """The tables' index of the store at ``out``, opened as a launch opens it (migrated once)."""
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    migrate_once(mlflow.MlflowClient(), "mrcert")
    return RunIndex.load("mrcert")


def recorded(out: Path) -> dict[str, dict]:
    """Each evaluation run of the store as recorded before any migration: its name, keys and log."""
    client, runs = runs_of(out)
    return {
        r.info.run_id: {
            "name": r.info.run_name,
            "key": r.data.tags["mrcert.key"],
            "log": read_log(client.download_artifacts(r.info.run_id, r.data.tags["mrcert.task"] + ".tsv"), ["idx"]),
        }
        for r in runs.values()
        if r.data.tags["mrcert.task"] != "train" and r.info.status == "FINISHED"
    }


@pytest.fixture()
def old_store(tmp_path) -> Path:
    return unpack(tmp_path / "old")


def test_a_store_made_before_content_keys_fills_the_same_cells_and_skips_its_finished_runs(old_store):
    before = recorded(old_store)
    assert len(before) == 3
    idx = index(old_store)  # opening it migrates it
    for overrides in CELLS:
        cell = idx.cell(overrides)
        (run,) = cell.runs  # the very run that was made for it, with the same log
        assert before[run["run_id"]]["log"].equals(idx.log(cell)), overrides
        assert run["tags.mrcert.key"] != before[run["run_id"]]["key"]  # re-keyed
    client, runs = runs_of(old_store)
    assert client.get_experiment_by_name("mrcert").tags[KEY_SCHEME[0]] == KEY_SCHEME[1]
    assert migrate(client, client.get_experiment_by_name("mrcert").experiment_id) == {"migrated": 0, "kept": 0}
    # The same command with skip_finished finds its finished run: nothing is computed again.
    cfg = compose_cfg([*CELLS[0], "skip_finished=true", "task.batch_size=64"], old_store)
    done = run_task(cfg, old_store / "runs" / "again")
    assert done["certified_accuracy"] == idx.metric(idx.cell(CELLS[0]), "certified_accuracy")
    assert len(runs_of(old_store)[1]) == len(runs) and not (old_store / "runs" / "again").exists()


def test_reading_a_store_never_writes_it(old_store):
    """The tables' index and the launch's look-ups only read: an old store stays as it was
    (its migration is the launch's, once, when it opens the store)."""
    from mrcert.infra import run_store

    db = old_store / "mlflow.db"
    before = db.read_bytes()
    mlflow.set_tracking_uri(f"sqlite:///{db}")
    idx = RunIndex.load("mrcert")
    assert len(idx.df) and not idx.cell(CELLS[0]).runs  # old keys: found only once migrated
    tracking = OmegaConf.create(
        {"enabled": True, "uri": f"sqlite:///{db}", "experiment": "mrcert", "artifact_location": None}
    )
    assert run_store.finished(tracking, "0" * 32) == [] and run_store.interrupted(tracking, "0" * 32) == []
    assert db.read_bytes() == before


@pytest.mark.slow
def test_a_run_interrupted_before_content_keys_resumes_with_the_rows_it_logged(old_store):
    folder = old_store / "runs" / "interrupted"
    logged = (folder / "certify.tsv").read_text().splitlines()
    assert len(logged) == 1 + 3
    client, runs = runs_of(old_store)
    (killed,) = [r for r in runs.values() if r.info.status == "KILLED"]
    run_task(compose_cfg([*INTERRUPTED, "task.batch_size=64"], old_store), old_store / "runs" / "resumed")
    assert client.get_run(killed.info.run_id).info.status == "FINISHED"  # the same run, resumed
    rows = (folder / "certify.tsv").read_text().splitlines()
    assert len(rows) == 1 + 18 and [r.split("\t")[:6] for r in rows[1:4]] == [r.split("\t")[:6] for r in logged[1:]]
    assert not (folder / "set_aside").exists()  # none of its rows refused


def test_runs_gathered_from_a_store_made_before_content_keys_fill_their_cells(old_store, tmp_path):
    before = recorded(old_store)  # not migrated: the copies are
    assert gather(tmp_path / "new", old_store)["kept_keys"] == 0
    idx = index(tmp_path / "new")
    for overrides in CELLS:
        cell = idx.cell(overrides)
        (run,) = cell.runs
        assert before[run["tags.mrcert.gathered_from"]]["log"].equals(idx.log(cell)), overrides


class Store:
    """A store as the resolver reads it, holding one train run under ``run_id``."""

    def __init__(self, run_id: str, key: str, digest: str):
        self.id, self.tags = run_id, {"mrcert.task": "train", "mrcert.key": key, "mrcert.checkpoint_sha256": digest}

    def newest_train_run(self, key):
        return self.id if key == self.tags["mrcert.key"] else None

    def run_tags(self, run_id):
        return self.tags if run_id == self.id else None

    def artifact(self, run_id, path):
        raise AssertionError("the digest is recorded: no file is read")


def test_an_evaluations_key_depends_on_its_models_content_not_on_its_run_id():
    from mrcert.infra.resolver import train_key

    cfg = compose_cfg(CELLS[0])
    key = train_key(cfg)
    here = resolve(cfg, Store("a" * 32, key, "sha256:1"))
    there = resolve(cfg, Store("b" * 32, key, "sha256:1"))
    retrained = resolve(cfg, Store("a" * 32, key, "sha256:2"))
    assert here[1].key == there[1].key and here[1].cell == there[1].cell
    assert here[0].model.checkpoint != there[0].model.checkpoint  # each loads its own store's file
    assert retrained[1].key != here[1].key  # another model under the same recipe: another result
    assert OmegaConf.select(here[0], "model.checkpoint") == f"runs:/{'a' * 32}/checkpoints/best.pt"
