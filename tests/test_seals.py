"""What a table shows is what its run recorded: per-image logs and checkpoints sealed when a run
finishes (and a log as it is written), checked wherever they are read again; the image cache
checked on use; custom poses, inputs and table files that cannot mislead."""

import json
import shutil
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch

from mrcert.__main__ import bind, run_task
from mrcert.data.cache import cached_arrays
from mrcert.data.custom import read_poses
from mrcert.errors import MrcertError
from mrcert.infra.log_keys import check_value, owner_path, read_owner
from mrcert.reporting.cells import RunIndex, problems
from mrcert.reporting.certify_log import read_log
from mrcert.tasks.evaluation import run_images
from mrcert.tasks.tables import staged
from tests.conftest import PER_RUN, TINY, certify_args, certify_logs, compose_cfg, kill_when, run_cli, store_runs

RECIPE = [*TINY, "train.epochs=1", "train.batch_size=8"]
CERTIFY = [*RECIPE, "task=certify", "task.n0=8", "task.n=40", "task.max=3", "task.skip=1"]


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    """A store with a tiny train run and a certify run of its model (looked up in the store)."""
    out = tmp_path_factory.mktemp("sealed")
    run_task(compose_cfg([*RECIPE, "task=train"], out), out / "runs" / "train")
    run_task(compose_cfg(CERTIFY, out), out / "runs" / "certify")
    return out


def copy_of(store: Path, tmp_path: Path) -> Path:
    """The store copied whole, with every path it records rewritten to the copy."""
    out = tmp_path / "store"
    shutil.copytree(store, out)
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    client = mlflow.MlflowClient()
    for run in store_runs(out):
        folder = run.data.tags.get("mrcert.output_dir", "")
        if folder.startswith(str(store)):
            client.set_tag(run.info.run_id, "mrcert.output_dir", folder.replace(str(store), str(out)))
    import sqlite3

    with sqlite3.connect(out / "mlflow.db") as db:  # artifact locations
        db.execute("UPDATE runs SET artifact_uri = replace(artifact_uri, ?, ?)", (str(store), str(out)))
        db.execute(
            "UPDATE experiments SET artifact_location = replace(artifact_location, ?, ?)", (str(store), str(out))
        )
    return out


def certify_cell(out: Path):
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    index = RunIndex.load("mrcert", run_images)
    cell = index.cell(CERTIFY)
    return index, cell


def forge(log: Path) -> None:
    """Every row made a correct prediction certified at radius 0.3 (the label, predict and
    correct columns edited by hand, as a user with an editor could)."""
    df = pd.read_csv(log, sep="\t", dtype=str)
    df["predict"], df["correct"], df["radius"] = df["label"], "1", "0.3"
    df.to_csv(log, sep="\t", index=False)


def test_an_edited_finished_log_leaves_its_cell_empty_and_says_why(store, tmp_path):
    out = copy_of(store, tmp_path)
    index, cell = certify_cell(out)
    honest = index.metric(cell, "certified_accuracy")
    assert not np.isnan(honest) and cell.note == ""
    forge(out / "runs" / "certify" / "certify.tsv")
    index, cell = certify_cell(out)
    assert np.isnan(index.metric(cell, "certified_accuracy"))
    assert "is not the file the run recorded" in cell.note and cell.runs[0]["run_id"] in cell.note


def test_a_gathered_run_whose_log_was_edited_is_not_copied(store, tmp_path):
    out = copy_of(store, tmp_path)
    (artifact,) = (out / "mlartifacts").rglob("certify.tsv")
    forge(artifact)
    here = tmp_path / "here"
    done = run_cli(["task=gather", f"task.store={out}"], here)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "not gathered: run" in done.stdout and "certify.tsv" in done.stdout
    tasks = [r.data.tags.get("mrcert.task") for r in store_runs(here, "attributes.status = 'FINISHED'")]
    assert tasks.count("train") == 1 and "certify" not in tasks


def test_a_swapped_checkpoint_is_refused_before_any_run(store, tmp_path):
    out = copy_of(store, tmp_path)
    (best,) = (out / "mlartifacts").rglob("checkpoints/best.pt")
    state = torch.load(best, weights_only=True)
    state["model"] = {k: v + 1 if v.is_floating_point() else v for k, v in state["model"].items()}
    torch.save(state, best)
    before = len(store_runs(out))
    done = run_cli([*CERTIFY, "task.n=41"], out)
    assert done.returncode == 2 and "best.pt" in done.stderr and "is not the file the run recorded" in done.stderr
    assert len([line for line in done.stderr.splitlines() if line.startswith("mrcert:")]) == 1
    assert len(store_runs(out)) == before


def test_a_model_of_other_classes_is_refused_before_any_run(checkpoints, tmp_path):
    args = [
        a if not a.startswith("data.classes=") else "data.classes=[can,mug,banana]"
        for a in certify_args(checkpoints["a"])
    ]
    done = run_cli(args, tmp_path)
    assert done.returncode == 2 and "was trained on classes apple, can, mug" in done.stderr
    assert "first difference 0: 'apple' vs 'banana'" in done.stderr and store_runs(tmp_path) == []


@pytest.mark.slow
def test_an_interrupted_log_edited_and_checked_anew_is_computed_again(checkpoints, reference, tmp_path):
    """Killed after two rows, the log's second row is made a certified correct one with its check
    value recomputed from the key in the owner file (what a reader of the code could do): the same
    command sets the log aside and gives the uninterrupted run's rows."""
    args = certify_args(checkpoints["a"])
    kill_when(args, tmp_path, lambda: any(len(p.read_text().splitlines()) == 3 for p in certify_logs(tmp_path)))
    (log,) = certify_logs(tmp_path)
    key = read_owner(owner_path(log))["run_key"]
    lines = log.read_text().splitlines()
    cells = lines[2].split("\t")[:-1]
    cells[2], cells[3], cells[4] = cells[1], "5.0", "1"
    lines[2] = "\t".join([*cells, check_value(key, "\t".join(cells))])
    log.write_text("\n".join(lines) + "\n")
    done = run_cli(args, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    pd.testing.assert_frame_equal(read_log(log).drop(columns=PER_RUN, errors="ignore"), reference["a"])
    (aside,) = log.parent.glob("set_aside/rejected_*/certify.rejected.tsv")
    assert "not the log this run recorded" in aside.read_text()


def test_a_log_sealed_row_by_row_is_sealed_as_the_whole_file_is(tmp_path):
    """The seal a log records as it is written (carried on row by row) is the one of the file
    (read whole), and after a resume it goes on from the rows it kept."""
    from mrcert.infra.seals import seal_file, tag
    from mrcert.reporting.certify_log import ResultLog

    recorded = {}
    columns = ["idx", "label", "predict", "radius", "correct", "time", "seconds"]
    owner = {"run_key": "k", "run_id": "r"}
    log = ResultLog(tmp_path / "certify.tsv", columns, owner, recorded.__setitem__)
    row = {"label": 1, "predict": 1, "radius": 0.25, "correct": 1, "seconds": 1.5}
    for i in range(30):
        log.append({"idx": i} | row)
        assert recorded[tag("certify.tsv")] == seal_file(tmp_path / "certify.tsv")
    again = ResultLog(tmp_path / "certify.tsv", columns, owner, recorded.__setitem__, recorded[tag("certify.tsv")])
    assert again.done() == set(range(30))
    again.append({"idx": 30} | row)
    assert recorded[tag("certify.tsv")] == seal_file(tmp_path / "certify.tsv")


def test_rows_that_no_run_of_the_config_could_log_are_found():
    """An index outside the run's images, a label the data set does not give the image, and a
    radius beyond the one n = 40 votes out of 40 give at the config's alpha."""
    from mrcert.core.methods import build_method

    cfg = compose_cfg(CERTIFY)
    images = run_images(cfg)
    assert sorted(images) == [0, 1, 2]
    limit = build_method(cfg).largest_radius(40, float(cfg.task.alpha))
    log = pd.DataFrame({"idx": [0, 1, 2], "label": [images[i] for i in range(3)], "radius": limit, "n": 40})
    assert problems(log, cfg, images) == ""
    assert "beyond" in problems(log.assign(radius=[0.0, limit * 1.001, 0.0]), cfg, images)
    wrong = log.assign(label=[(images[0] + 1) % 3, *log.label[1:]])
    assert "labels that the data set does not give" in problems(wrong, cfg, images)
    assert "not among the 3" in problems(log.assign(idx=[0, 1, 7]), cfg, images)


def test_a_damaged_image_cache_entry_is_rendered_again_never_used(tmp_path, caplog):
    built = []

    def build():
        built.append(1)
        return {"images": np.arange(24, dtype=np.uint8).reshape(2, 3, 4), "labels": np.array([0, 1])}

    arrays, folder, hit = cached_arrays(tmp_path, "set", {"a": 1}, build)
    assert not hit and len(built) == 1
    np.save(folder / "labels.npy", np.array([1, 0]))  # labels flipped
    arrays, folder, hit = cached_arrays(tmp_path, "set", {"a": 1}, build)
    assert not hit and len(built) == 2 and arrays["labels"].tolist() == [0, 1]
    assert "labels.npy is not the array recorded" in caplog.text
    data = (folder / "images.npy").read_bytes()
    (folder / "images.npy").write_bytes(data[: len(data) // 2])  # cut short
    arrays, folder, hit = cached_arrays(tmp_path, "set", {"a": 1}, build)
    assert not hit and len(built) == 3 and arrays["images"].shape == (2, 3, 4)
    arrays, folder, hit = cached_arrays(tmp_path, "set", {"a": 1}, build)
    assert hit and len(built) == 3  # an intact entry is used as it is


def pose(x: float) -> list:
    return [[1, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


@pytest.mark.parametrize(
    "entries, message",
    [
        ([("test", "mug", 0.1), ("test", "mug", 0.1)], "poses[1] and poses[2] are the same pose, twice among the test"),
        (
            [("train", "mug", 0.1), ("test", "can", 0.1)],
            "poses[1] and poses[2] are the same pose, labelled 'mug' and 'can'",
        ),
        ([("train", "mug", 0.1), ("test", "mug", 0.1)], "poses[1] and poses[2] are the same pose, a train and a test"),
    ],
)
def test_custom_poses_that_would_mislead_are_refused_naming_them(entries, message, tmp_path):
    poses = [{"split": "train", "label": "can", "pose": pose(0.0)}]
    poses += [{"split": s, "label": label, "pose": pose(x)} for s, label, x in entries]
    if not any(p["split"] == "test" for p in poses):
        poses.append({"split": "test", "label": "can", "pose": pose(0.5)})
    path = tmp_path / "poses.json"
    path.write_text(json.dumps({"classes": ["mug", "can"], "poses": poses}))
    with pytest.raises(MrcertError, match=message.replace("[", r"\[").replace("]", r"\]")):
        read_poses(path)


def test_a_tables_run_killed_while_writing_leaves_the_last_tables_whole(tmp_path):
    out = tmp_path / "tables"
    out.mkdir()
    (out / "table3.md").write_text("complete\n")
    with pytest.raises(KeyboardInterrupt), staged([out]) as (stage,):
        (stage / "table3.csv").write_text("new\n")
        (stage / "table3.md").write_text("half")
        raise KeyboardInterrupt  # killed while writing
    assert (out / "table3.md").read_text() == "complete\n" and not (out / "table3.csv").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["tables"]  # nothing left behind
    with staged([out]) as (stage,):
        (stage / "table3.md").write_text("new\n")
    assert (out / "table3.md").read_text() == "new\n"


def test_a_run_a_killed_process_left_running_ends_killed_when_its_config_runs_again(store, tmp_path):
    out = copy_of(store, tmp_path)
    cfg, ident = bind(compose_cfg(["task=tables", "task.experiment=demo"], out))
    client = mlflow.MlflowClient()
    experiment = client.get_experiment_by_name("mrcert").experiment_id
    stale = client.create_run(experiment, tags={"mrcert.key": ident.key, "mrcert.output_dir": str(tmp_path / "gone")})
    run_task(cfg, out / "runs" / "tables")
    assert client.get_run(stale.info.run_id).info.status == "KILLED"


@pytest.mark.parametrize("path", ["/dev/zero", "folder"])
def test_an_input_that_is_not_a_regular_file_is_refused_before_any_run(path, tmp_path):
    (tmp_path / "folder").mkdir()
    (tmp_path / "poses.json").write_text("{}")
    value = path if path.startswith("/") else str(tmp_path / path)
    done = run_cli(
        ["task=render", "data=custom", f"data.path={value}", f"data.poses={tmp_path / 'poses.json'}"], tmp_path
    )
    assert done.returncode == 2 and f"data.path={value!r} is not a regular file" in done.stderr
    assert store_runs(tmp_path) == [] if (tmp_path / "mlflow.db").exists() else True


def test_a_run_whose_seals_were_deleted_is_never_sealed_by_a_gather(store, tmp_path):
    """The laundering trial: a train run's seal tags deleted and its best.pt swapped. Its own store
    refuses the model; gathered, it is copied as unsealed, not sealed as it now is, and refused there too."""
    from mrcert.infra.key_migration import SEAL_SCHEME

    out = copy_of(store, tmp_path)
    client = mlflow.MlflowClient()
    assert client.get_experiment_by_name("mrcert").tags.get(SEAL_SCHEME[0]) == SEAL_SCHEME[1]
    (train,) = [r for r in store_runs(out) if r.data.tags.get("mrcert.task") == "train"]
    for key in [k for k in train.data.tags if k.startswith("mrcert.sealed.")]:
        client.delete_tag(train.info.run_id, key)
    (best,) = (out / "mlartifacts").rglob("checkpoints/best.pt")
    state = torch.load(best, weights_only=True)
    state["model"] = {k: v + 1 if v.is_floating_point() else v for k, v in state["model"].items()}
    torch.save(state, best)
    refused = run_cli([*CERTIFY, "task.n=41"], out)
    assert refused.returncode == 2 and "recorded no seal of its best.pt" in refused.stderr
    here = tmp_path / "here"
    done = run_cli(["task=gather", f"task.store={out}"], here)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"gathered unsealed: run {train.info.run_id}'s best.pt, last.pt carry no seal" in done.stdout
    (copy,) = [r for r in store_runs(here) if r.data.tags.get("mrcert.gathered_from") == train.info.run_id]
    assert copy.data.tags.get("mrcert.unsealed") == "true" and "mrcert.sealed_late" not in copy.data.tags
    assert not any(k.startswith("mrcert.sealed.") for k in copy.data.tags)
    again = run_cli([*CERTIFY, "task.n=41"], here)  # a later launch of the new store seals nothing either
    assert again.returncode == 2 and "recorded no seal of its best.pt" in again.stderr


def test_every_copy_of_a_sealed_log_in_a_run_is_checked_by_a_gather(store, tmp_path):
    """A forged log at the run's root with the genuine one moved to a folder that sorts first."""
    out = copy_of(store, tmp_path)
    (artifact,) = (out / "mlartifacts").rglob("certify.tsv")
    (artifact.parent / "a").mkdir()
    shutil.copy(artifact, artifact.parent / "a" / "certify.tsv")
    forge(artifact)
    done = run_cli(["task=gather", f"task.store={out}"], tmp_path / "here")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "not gathered: run" in done.stdout and "certify.tsv" in done.stdout
    tasks = [r.data.tags.get("mrcert.task") for r in store_runs(tmp_path / "here", "attributes.status = 'FINISHED'")]
    assert "certify" not in tasks
