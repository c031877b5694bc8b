"""``task=gather``: runs made in another store (a GPU machine's) join this one and fill the same
table cells there as here, and the evidence page shows the paper profile's runs with the
machine and time they took.

The source store holds real tiny runs under ``profile=paper`` (the tiny data and a short
recipe, as in tests/test_tables.py)."""

import shutil
from pathlib import Path

import mlflow
import pytest

from mrcert.infra.checkpoints import local_checkpoint, read_checkpoint
from mrcert.infra.runtime import machine
from mrcert.infra.store import run_artifacts
from mrcert.reporting import paper_tables
from mrcert.reporting.cells import RunIndex
from mrcert.reporting.certify_log import read_log
from mrcert.reporting.experiment_cells import ExperimentCells
from mrcert.reporting.page import paper_profile
from mrcert.reporting.page.times import run_seconds
from mrcert.tasks.gather import GATHERED
from tests.conftest import run_cli
from tests.test_tables import SETTINGS, run

PAPER = ["experiment=reproduce_paper", "profile=paper", *SETTINGS, "model.variant=vanilla", "motion=tz"]
CHEAP = ("task.n=200", "task.skip=3")  # a short certification: every cell of the tables gets these too
MOVED = (GATHERED, "mrcert.output_dir", "mlflow.parentRunId")  # what a copy cannot keep as it is


@pytest.fixture(scope="module")
def gpu_store(tmp_path_factory):
    """A GPU machine's store: a paper-profile train run and its certification."""
    out = tmp_path_factory.mktemp("gpu")
    run(out, [*PAPER, "task=train"], "train")
    run(out, [*PAPER, "task=certify", "task.batch_size=64", *CHEAP], "certify")
    return out


def index(out: Path, profile: str = "quick") -> ExperimentCells:
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    return ExperimentCells(RunIndex.load("mrcert"), profile, overrides=(*SETTINGS, *CHEAP))


def gather(into: Path, source: Path) -> dict:
    return run(into, ["task=gather", f"task.store={source}"], f"gather-{source.name}")


def test_the_page_shows_the_paper_profiles_runs_with_their_machine_and_time(gpu_store):
    section = paper_profile.paper_profile_section(index(gpu_store))
    table, times = (" ".join(section[k].split()) for k in ("table", "times"))
    clog = read_log(next((gpu_store / "runs" / "certify").glob("certify.tsv")), ["idx"])
    certified = ((clog.correct == 1) & (clog.radius >= 0.1) & (clog.predict >= 0)).mean()
    # One row per model (the paper has no small CNN, so no value of its own beside it).
    assert table.count("| Tz | Smoothed Vanilla SmallCNN |") == 1
    assert f"| Tz | Smoothed Vanilla SmallCNN | | | {certified:.3f} |" in table
    assert (section["n"], section["alpha"], section["images"]) == (200, 0.01, len(clog))
    assert f"| certify | 1 | {len(clog)} |" in times and f"| {machine()} (1 run) |" in times
    assert "| train | 1 |" in times and "| smooth |" not in times  # stages that did not run are left out
    # The whole profile at these paces: each measured job's time times the profile's jobs of its
    # stage (12 on the small CNN: the ResNets' two rows are one job here) or models (7: one vanilla
    # model for every axis and one augmented per axis).
    df = index(gpu_store).index.df.set_index("run_id")
    seconds = {df.loc[r, "tags.mrcert.task"]: run_seconds(df.loc[r]) for r in df.index}
    estimate = section["estimate"]
    shown = " ".join(estimate["table"].split())
    for stage, jobs in (("train", 7), ("certify", 12)):
        hours = seconds[stage] / 3600
        assert f"| {stage} | small_cnn | 1 | {hours:.3f} | {jobs} | {jobs * hours:.2f} |" in shown
    assert estimate["hours"] == f"{(7 * seconds['train'] + 12 * seconds['certify']) / 3600:.2f}"
    # The profile's other stages are named, not estimated.
    assert estimate["unmeasured"].split("; ") == [
        "certify (task.sequential=true)",
        "smooth",
        "attack (attack.k=5)",
        "attack (attack.k=100)",
        "attack (attack.k=5, task.sequential=true)",
        "attack (attack.k=100, task.sequential=true)",
    ]
    # A store without paper-profile runs gets a section that says how many jobs it lacks.
    empty = paper_profile.paper_profile_section(index(gpu_store.parent / "nothing-here"))
    assert empty == {"profile": "paper", "experiment": "reproduce_paper", "missing": 24}
    assert section["missing"] == 0


def runs_of(out: Path) -> tuple[mlflow.MlflowClient, dict]:
    client = mlflow.MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    exp = client.get_experiment_by_name("mrcert")
    return client, {r.info.run_id: r for r in client.search_runs([exp.experiment_id])}


def test_gathered_runs_fill_the_same_cells_here_as_there(gpu_store, tmp_path):
    # Gathered into a laptop store, which is then moved (as when copied off a GPU machine) and
    # gathered again into a third store: the artifacts come from the moved folder.
    laptop, moved, page_store = tmp_path / "laptop", tmp_path / "moved", tmp_path / "page"
    assert gather(laptop, gpu_store)["gathered"] == 2  # the train and the certify run
    shutil.move(laptop, moved)
    done = gather(page_store, moved)  # those two and the laptop's gather run
    assert (done["gathered"], done["without_artifacts"], done["kept_keys"]) == (3, 0, 0)
    there, here = index(gpu_store, "paper"), index(page_store, "paper")
    ours = paper_tables.TABLE3.build(here, name="t")
    assert ours.equals(paper_tables.TABLE3.build(there, name="t")) and ours.notna().any().any()
    # The cell binds the copied model, which loads here.
    cell = here.cell("reproduce_paper", ("motion=tz", "model.variant=vanilla"), paper_tables.CERTIFIED)
    assert cell.cfg.model.checkpoint == f"runs:/{cell.train_run}/checkpoints/best.pt"
    assert read_checkpoint(local_checkpoint(cell.cfg.model.checkpoint))["arch"] == "small_cnn"
    # Each copy keeps its name, times, params and every metric's history.
    (src, originals), (_, middle), (dst, copies) = runs_of(gpu_store), runs_of(moved), runs_of(page_store)
    checked = 0
    for copy in copies.values():
        origin = middle.get(copy.data.tags.get(GATHERED))
        if origin is None or origin.data.tags.get(GATHERED) not in originals:
            continue
        original = originals[origin.data.tags[GATHERED]]
        assert (copy.info.run_name, copy.info.start_time, copy.info.end_time) == (
            original.info.run_name,
            original.info.start_time,
            original.info.end_time,
        )
        # Copied as it is: no key, param or config rewritten (MLflow's parent link aside).
        assert copy.data.params == original.data.params
        assert {k: v for k, v in copy.data.tags.items() if k not in MOVED} == {
            k: v for k, v in original.data.tags.items() if k not in MOVED
        }
        config = "resolved_config.yaml"
        assert Path(dst.download_artifacts(copy.info.run_id, config)).read_text() == (
            Path(src.download_artifacts(original.info.run_id, config)).read_text()
        )
        for key in original.data.metrics:
            theirs = [(m.step, m.value) for m in src.get_metric_history(original.info.run_id, key)]
            assert [(m.step, m.value) for m in dst.get_metric_history(copy.info.run_id, key)] == theirs
        checked += 1
    assert checked == 2
    # A second gather copies nothing; a copy a kill left unfinished is made again.
    assert gather(page_store, moved)["gathered"] == 0
    dst.set_terminated(cell.runs[0]["run_id"], "KILLED")
    again = gather(page_store, moved)
    assert (again["gathered"], again["already_here"]) == (1, 2)
    assert paper_tables.TABLE3.build(index(page_store, "paper"), name="t").equals(ours)


def test_a_store_that_is_not_one_is_refused_before_any_run(tmp_path):
    proc = run_cli(["task=gather", f"task.store={tmp_path}"], tmp_path / "out")
    assert proc.returncode != 0 and f"task.store='{tmp_path}' is not an mrcert store" in proc.stderr
    assert not (tmp_path / "out" / "mlflow.db").exists()


def test_a_store_brought_home_without_its_resume_checkpoints_fills_the_same_cells(gpu_store, tmp_path):
    # A GPU store packed without last.pt (the resume state, twice best.pt's size): the train run is
    # gathered without it, named in one line; its model loads and the cells are the ones there.
    light = tmp_path / "light"
    gather(light, gpu_store)  # a store of its own whose artifacts are its own files
    (last,) = (light / "mlartifacts").rglob("checkpoints/last.pt")
    last.unlink()
    here = tmp_path / "here"
    proc = run_cli(["task=gather", f"task.store={light}"], here)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (line,) = [s for s in proc.stdout.splitlines() if s.startswith("gathered without")]
    assert line.startswith("gathered without its last.pt: run ") and "not gathered" not in proc.stdout
    _, copies = runs_of(here)
    assert sorted(r.data.tags.get("mrcert.task") for r in copies.values() if GATHERED in r.data.tags) == [
        "certify",
        "gather",
        "train",
    ]
    ours = paper_tables.TABLE3.build(index(here, "paper"), name="t")
    assert ours.equals(paper_tables.TABLE3.build(index(gpu_store, "paper"), name="t")) and ours.notna().any().any()
    cell = index(here, "paper").cell("reproduce_paper", ("motion=tz", "model.variant=vanilla"), paper_tables.CERTIFIED)
    assert read_checkpoint(local_checkpoint(cell.cfg.model.checkpoint))["arch"] == "small_cnn"


def test_a_store_carried_between_machines_holds_each_run_once_and_skips_what_it_holds(gpu_store, tmp_path):
    # Packed without the resume checkpoints, taken to a fresh machine, worked on there, gathered
    # back: each run is in the carried store once, and the fresh machine redoes nothing it holds.
    carried, fresh = tmp_path / "carried", tmp_path / "fresh"
    packed = run(carried, ["task=gather", f"task.store={gpu_store}", "task.without=[last.pt]"], "pack")
    assert (packed["gathered"], packed["without_artifacts"]) == (2, 1)  # the train run lacks last.pt
    assert not list((carried / "mlartifacts").rglob("last.pt")) and list((carried / "mlartifacts").rglob("best.pt"))
    gather(fresh, carried)
    _, before = runs_of(fresh)
    certify = [*PAPER, "task=certify", "task.batch_size=64", *CHEAP, "skip_finished=true"]
    run(fresh, certify, "again")  # held: the gathered run stands in for it
    run(fresh, [*PAPER, "task=certify", "task.batch_size=64", "task.n=200", "task.skip=4"], "new")
    _, after = runs_of(fresh)
    assert len(after) == len(before) + 1
    back = gather(carried, fresh)
    # The new run and the gather that filled fresh are new; the three copies are the carried runs.
    assert (back["gathered"], back["already_here"]) == (2, len(before) - 1)
    _, held = runs_of(carried)
    tasks = sorted(r.data.tags.get("mrcert.task") for r in held.values() if r.data.tags.get("mrcert.task") != "gather")
    assert tasks == ["certify", "certify", "train"]
    ours = paper_tables.TABLE3.build(index(carried, "paper"), name="t")
    assert ours.equals(paper_tables.TABLE3.build(index(gpu_store, "paper"), name="t")) and ours.notna().any().any()


def test_a_store_folder_moved_elsewhere_is_read_in_place(gpu_store, tmp_path):
    # A store committed or copied to another folder (its runs recorded their files under the old
    # one): its tables and models read from its own mlartifacts.
    made, moved = tmp_path / "made", tmp_path / "clone" / "store"
    gather(made, gpu_store)
    shutil.move(made, moved)
    assert not made.exists()
    ours = paper_tables.TABLE3.build(index(moved, "paper"), name="t")
    assert ours.equals(paper_tables.TABLE3.build(index(gpu_store, "paper"), name="t")) and ours.notna().any().any()
    here = index(moved, "paper")
    cell = here.cell("reproduce_paper", ("motion=tz", "model.variant=vanilla"), paper_tables.CERTIFIED)
    log = here.index.log(cell)  # the per-image log, read from the moved folder
    assert log is not None and len(log) > 0, cell.note
    assert local_checkpoint(cell.cfg.model.checkpoint).is_relative_to(moved)
    # A run made in the moved store keeps its files there, not in the folder the store was made in.
    run(moved, [*PAPER, "task=certify", "task.batch_size=64", "task.n=100", "task.skip=3"], "certify-after-move")
    new = mlflow.search_runs(search_all_experiments=True, filter_string="params.`task.n` = '100'", output_format="list")
    assert len(new) == 1 and new[0].info.artifact_uri == run_artifacts(moved, new[0].info.run_id).as_uri()
    assert (run_artifacts(moved, new[0].info.run_id) / "certify.tsv").exists() and not made.exists()
