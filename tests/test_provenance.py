"""Where every number comes from: a run is reused, resumed or looked up only by its run key,
through the command line and the task API against a real SQLite store."""

import contextlib
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest

import mrcert
from mrcert.__main__ import bind, run_task
from mrcert.infra.checkpoints import BEST_PATH
from mrcert.infra.identity import file_identity
from mrcert.infra.runtime import EVIDENCE_STORE, as_typed, checkout_version
from mrcert.infra.store import run_artifacts
from mrcert.reporting.certify_log import read_log
from mrcert.reporting.page.commands import MAKEFILE
from tests.conftest import ROOT, TINY, compose_cfg, run_cli

RECIPE = [*TINY, "train.epochs=2", "train.batch_size=8"]
DEMO = ["experiment=demo", *RECIPE]
CERTIFY = ["task=certify", "task.n0=8", "task.n=40", "task.max=3", "task.skip=1"]


def runs(out: Path, where: str = "") -> list:
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    return mlflow.search_runs(search_all_experiments=True, filter_string=where, output_format="list")


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A store with one tiny train run (vanilla, the recipe above)."""
    out = tmp_path_factory.mktemp("trained")
    run_task(compose_cfg([*RECIPE, "task=train"], out), out / "runs" / "train")
    return out


def checkpoint(out: Path, name: str) -> Path:
    (path,) = out.glob(f"runs/train/{name}")
    return path


@pytest.mark.slow
def test_rerunning_a_sweep_keeps_checkpoint_lookup_on_the_trained_model(tmp_path):
    for _ in range(2):  # `make demo` twice: the second sweep skips its jobs but makes a parent run
        proc = run_cli(["-m", *DEMO, "task=train"], tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
    parents = runs(tmp_path, "tags.`mrcert.multirun` = 'parent'")
    trains = runs(tmp_path, "tags.`mrcert.task` = 'train'")
    assert len(parents) == 2 and len(trains) == 2  # the 2 trained models (parents carry mrcert.sweep_tasks)
    for variant in ("vanilla", "augmented"):
        cfg = compose_cfg([*DEMO, "task=certify", f"model.variant={variant}", "task.max=1", "task.n=20"], tmp_path)
        run_task(cfg, tmp_path / "runs" / f"certify-{variant}")
        (run,) = runs(tmp_path, f"tags.`mrcert.task` = 'certify' and tags.`mrcert.variant` = '{variant}'")
        train = mlflow.get_run(run.data.tags["mrcert.train_run"])
        assert train.data.tags["mrcert.variant"] == variant and train.data.tags["mrcert.multirun"] == "job"
        # The model is named by its train run's key and its checkpoint's content, not by a run id.
        best = Path(train.data.tags["mrcert.output_dir"]) / "best.pt"
        assert run.data.tags["mrcert.checkpoint"] == f"train:{train.data.tags['mrcert.key']} {file_identity(str(best))}"
        assert run.data.params["checkpoint.train_run_id"] == train.info.run_id


def test_skip_finished_reuses_only_a_run_of_the_same_model_and_ignores_batch_size(trained, tmp_path):
    best, last = checkpoint(trained, "best.pt"), checkpoint(trained, "last.pt")
    common = [*TINY, *CERTIFY, "skip_finished=true"]
    run_task(compose_cfg([*common, f"model.checkpoint={best}"], tmp_path), tmp_path / "runs" / "a")
    # Another model: computed, not taken from the first run.
    run_task(compose_cfg([*common, f"model.checkpoint={last}"], tmp_path), tmp_path / "runs" / "b")
    # Another batch size, back end or device: the same result, reused.
    again = [f"model.checkpoint={best}", "task.batch_size=7", "task.backend=torch", "device=cpu"]
    run_task(compose_cfg([*common, *again], tmp_path), tmp_path / "runs" / "c")
    done = runs(tmp_path, "tags.`mrcert.task` = 'certify'")
    assert len(done) == 2 and not (tmp_path / "runs" / "c" / "certify.tsv").exists()
    digests = {r.data.tags["mrcert.checkpoint"] for r in done}
    assert len(digests) == 2 and all(d.startswith("sha256:") for d in digests)
    assert {r.data.params["model.checkpoint"] for r in done} == {str(best), str(last)}
    # Each run records the code that made it: the version and, in a checkout, the commit.
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    recorded = {r.data.tags["mrcert.code_version"] for r in done}
    assert len(recorded) == 1 and recorded.pop().split()[0] == mrcert.__version__
    if head.returncode == 0:
        assert all(f"git:{head.stdout.strip()}" in r.data.tags["mrcert.code_version"] for r in done)


def test_a_train_run_whose_checkpoint_is_gone_is_trained_again_and_not_evaluated(tmp_path):
    train, certify = [*RECIPE, "task=train", "skip_finished=true"], [*RECIPE, *CERTIFY, "task.max=1"]
    run_task(compose_cfg(train, tmp_path), tmp_path / "runs" / "first")
    run_task(compose_cfg(train, tmp_path), tmp_path / "runs" / "again")  # reused while best.pt is there
    (first,) = runs(tmp_path, "tags.`mrcert.task` = 'train'")
    # The store copied without that checkpoint (an evidence store that leaves a large one out).
    (run_artifacts(tmp_path, first.info.run_id) / BEST_PATH).unlink()
    run_task(compose_cfg(train, tmp_path), tmp_path / "runs" / "retrained")
    retrained = [r for r in runs(tmp_path, "tags.`mrcert.task` = 'train'") if r.info.run_id != first.info.run_id]
    assert len(retrained) == 1 and retrained[0].info.status == "FINISHED"
    run_task(compose_cfg(certify, tmp_path), tmp_path / "runs" / "certify")
    (evaluated,) = runs(tmp_path, "tags.`mrcert.task` = 'certify'")
    assert evaluated.data.tags["mrcert.train_run"] == retrained[0].info.run_id


def test_the_code_version_is_dirty_for_a_changed_code_file_but_not_for_the_evidence_store(tmp_path):
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(tmp_path), *args], capture_output=True, text=True, check=True).stdout

    code, record = tmp_path / "mrcert" / "core.py", tmp_path / EVIDENCE_STORE / "mlflow.db"
    for path in (code, record):
        path.parent.mkdir(parents=True)
        path.write_text("one")
    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    clean = f"0.1.0 git:{git('rev-parse', 'HEAD').strip()}"
    assert checkout_version(tmp_path, "0.1.0") == clean
    record.write_text("two")  # runs gathered into the evidence store: still the commit's code
    (tmp_path / "untracked.py").write_text("x")
    assert checkout_version(tmp_path, "0.1.0") == clean
    code.write_text("two")
    assert checkout_version(tmp_path, "0.1.0") == clean + "+dirty"
    assert checkout_version(tmp_path / "mrcert", "0.1.0") == "0.1.0"  # not a checkout's root


def test_the_page_prints_the_makefiles_tables_command_as_its_recipe_writes_it():
    """The evidence page's "Written by" line is the launch's own overrides. Under ``-m`` Hydra's
    sweeper hands its one job the overrides written back from their parsed values (a bool as
    ``True``); ``as_typed`` gives the recipe's text back, and leaves a quoted string quoted."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    recipe = next(line for line in MAKEFILE.read_text().splitlines() if line.startswith("PAGE_TABLES ="))
    typed = recipe.split("$(MRCERT) -m ", 1)[1].rstrip(" \\").replace("$(PROFILE)", "quick")
    typed = typed.replace("$(PAGE)", "docs/results.md").split() + ["tracking.experiment='True'"]
    ((job,),) = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(typed), None)
    assert "task.show_paper=True" in job  # what the sweeper hands the job
    assert as_typed(job) == typed


def row_sealed(out: Path) -> bool:
    """Whether a certify log has a row and its seal is committed to the store (the writer is then
    computing its next image, holding no lock on the store)."""
    logs = list(out.glob("runs/certify/*/certify.tsv"))
    if not logs or len(logs[0].read_text().splitlines()) < 2 or not (out / "mlflow.db").exists():
        return False
    with contextlib.closing(sqlite3.connect(out / "mlflow.db", timeout=1)) as db:
        try:
            found = db.execute("SELECT value FROM tags WHERE key = 'mrcert.sealed.certify.tsv'").fetchall()
        except sqlite3.OperationalError:  # the writer is in a write: look again
            return False
    return any(int(value.split()[0]) == logs[0].stat().st_size for (value,) in found)


@pytest.mark.slow
def test_a_run_held_by_a_live_process_is_never_resumed_and_a_killed_one_is(trained, tmp_path):
    args = [*TINY, "task=certify", "task.n0=8", "task.n=1500", "task.max=2", "task.skip=1",
            f"model.checkpoint={checkpoint(trained, 'best.pt')}"]  # fmt: skip
    env = os.environ | {"MRCERT_OUTPUTS": str(tmp_path)}
    first = subprocess.Popen(
        [sys.executable, "-m", "mrcert", *args], cwd=ROOT, env=env,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.time() + 240
    while time.time() < deadline and not row_sealed(tmp_path):
        time.sleep(0.05)
    first.send_signal(signal.SIGSTOP)  # alive, holding its run, writing nothing (between two images)
    try:
        (log,) = tmp_path.glob("runs/certify/*/certify.tsv")
        rows = log.read_text()
        second = run_cli(args, tmp_path)
        assert second.returncode == 2, second.stderr[-2000:]
        # refused at once, naming the live process (the run key's lock: an identical job is running)
        assert "an identical job is computing this config now" in second.stderr and f"pid {first.pid}" in second.stderr
        assert log.read_text() == rows  # the second process wrote nothing into the live run
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    third = run_cli(args, tmp_path)  # the killed run is resumed
    assert third.returncode == 0, third.stderr[-2000:]
    (run,) = runs(tmp_path, "tags.`mrcert.task` = 'certify'")
    assert run.info.status == "FINISHED" and Path(run.data.tags["mrcert.output_dir"]) == log.parent
    assert read_log(log)["idx"].tolist() == [0, 1]


def test_a_run_that_failed_on_an_error_is_not_resumed(trained, tmp_path):
    cfg = compose_cfg([*TINY, *CERTIFY, f"model.checkpoint={checkpoint(trained, 'best.pt')}"], tmp_path)
    bound, ident = bind(cfg)
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = mlflow.set_experiment("mrcert")
    failed_dir = tmp_path / "failed"
    failed_dir.mkdir()
    (failed_dir / "certify.tsv").write_text("not a certify log\n")
    client = mlflow.MlflowClient()
    failed = client.create_run(exp.experiment_id, tags=ident.tags() | {"mrcert.output_dir": str(failed_dir)})
    client.set_terminated(failed.info.run_id, "FAILED")
    run_task(cfg, tmp_path / "runs" / "new")
    done = runs(tmp_path, "attributes.status = 'FINISHED'")
    assert len(done) == 1 and done[0].info.run_id != failed.info.run_id
    assert len(read_log(tmp_path / "runs" / "new" / "certify.tsv")) == 3
