"""The entry point end to end: task runs land in MLflow with params, tags and artifacts."""

import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import mlflow
import pytest

from mrcert.reporting.screenshot import BROWSERS
from tests.conftest import TINY, compose_cfg, run_cli

ROOT = Path(__file__).resolve().parent.parent
FAST = ["task=render", "data=testscene", "data.density=0.03", "task.num=2", "task.axes=[tx,rz]"]


def mrcert(args: list[str], outputs: Path, check: bool = True):
    proc = run_cli(args, outputs, timeout=300)
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def store(outputs: Path):
    mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
    return mlflow.MlflowClient()


def runs(outputs: Path) -> list:
    client = store(outputs)
    exp = client.get_experiment_by_name("mrcert")
    return client.search_runs([exp.experiment_id]) if exp else []


def test_render_run_is_tracked_with_params_tags_and_contact_sheet(tmp_path):
    mrcert(FAST, tmp_path)
    (run,) = runs(tmp_path)
    assert run.info.status == "FINISHED"
    assert run.data.params["task.name"] == "render" and run.data.params["data.density"] == "0.03"
    assert run.data.params["motion.sigma"] == "0.1"
    assert run.data.tags["mrcert.task"] == "render" and run.data.tags["mrcert.dataset"] == "testscene"
    assert run.data.tags["mrcert.axis"] == "tz" and run.data.tags["mrcert.model"] == "resnet18"
    assert run.data.metrics["num_images"] == 4
    artifacts = {a.path for a in store(tmp_path).list_artifacts(run.info.run_id)}
    assert {"contact_sheet.png", "resolved_config.yaml", "images"} <= artifacts
    local = Path(run.data.tags["mrcert.output_dir"])
    assert local.is_relative_to(tmp_path / "runs" / "render") and (local / "contact_sheet.png").is_file()
    assert len(list((local / "images").glob("*.png"))) == 4


def test_two_job_multirun_is_two_children_under_one_finished_parent(tmp_path):
    mrcert(["-m", *FAST, "motion=tx,rz"], tmp_path)
    all_runs = runs(tmp_path)
    parents = [r for r in all_runs if r.data.tags.get("mrcert.multirun") == "parent"]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    children = [r for r in all_runs if r.data.tags.get("mlflow.parentRunId") == parents[0].info.run_id]
    assert sorted(r.data.tags["mrcert.axis"] for r in children) == ["rz", "tx"]
    assert all(r.info.status == "FINISHED" and r.data.metrics["num_images"] == 4 for r in children)


@pytest.mark.slow
def test_a_sweep_over_tasks_is_one_parent_holding_every_job(tmp_path):
    """A sweep over tasks (`-m task=render,tables`) is one FINISHED parent, outside the runs page's
    task groups, and every job is its child: no empty parent, no top-level job."""
    mrcert(["-m", "task=render,tables", "data=testscene", "data.density=0.05"], tmp_path)
    all_runs = runs(tmp_path)
    (parent,) = [r for r in all_runs if r.data.tags.get("mrcert.multirun") == "parent"]
    assert parent.data.tags["mrcert.sweep_tasks"] == "render,tables" and parent.info.status == "FINISHED"
    assert "mrcert.task" not in parent.data.tags  # the runs page groups by task: parents stay out of the groups
    children = [r for r in all_runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert sorted(r.data.tags["mrcert.task"] for r in children) == ["render", "tables"]
    assert len(all_runs) == 3
    sweep = Path(parent.data.tags["mrcert.sweep_dir"])
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0_render", "1_tables"]


def make_recipe(target: str, *variables: str) -> list[list[str]]:
    """The mrcert commands of a Makefile target, as ``make -n`` prints them (arguments only)."""
    out = subprocess.run(
        ["make", "-n", target, "MRCERT=:mrcert:", "STAMP=", *variables],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return [shlex.split(line)[1:] for line in out.splitlines() if line.startswith(":mrcert: ")]


def test_make_learning_curve_trains_exactly_the_experiments_the_page_s_curve_reads():
    """The evidence page's curve reads learning_curve.EXPERIMENTS; `make learning-curve` must
    train each of them, in that order, and nothing else, then rewrite the page."""
    from mrcert.reporting.learning_curve import EXPERIMENTS

    *trains, page = make_recipe("learning-curve")
    assert trains == [["-m", f"experiment={e}", "task=train"] for e in EXPERIMENTS]
    assert "task=tables" in page and "task.page=docs/results.md" in page


@pytest.mark.parametrize("profile,archs", [("quick", {"small_cnn"}), ("paper", {"resnet18", "resnet50"})])
def test_make_reproduce_tables_runs_one_experiment_per_profile_that_fills_every_metaroom_table(profile, archs):
    """`make reproduce-tables PROFILE=p`: one MetaRoom experiment (the profile's, on its own
    profile, with the profile's architectures: the small CNN on 2 CPU cores, the paper's ResNets
    for a GPU) trained, certified, smoothed and attacked at K = 5 and 100, the tabletop experiment
    beside it, and the tables and evidence page built from exactly those runs."""
    from mrcert.reporting import paper_tables
    from mrcert.reporting.experiment_cells import sweep_combos

    recipe = make_recipe("reproduce-tables", f"PROFILE={profile}")
    experiments = {a.split("=", 1)[1] for c in recipe for a in c if a.startswith("experiment=")}
    reproduction = paper_tables.REPRODUCTION.format(profile=profile)
    assert experiments == {reproduction, "tabletop"}
    stages = {
        (a, *sorted(x for x in c if x.startswith("attack.k") or x.startswith("task.sequential")))
        for c in recipe
        if f"experiment={reproduction}" in c
        for a in c
        if a.startswith("task=")
    }
    assert stages == {
        ("task=train",),
        ("task=certify,smooth",),
        ("task=attack", "attack.k=5,100"),
        ("task=certify", "task.sequential=true"),
        ("task=attack", "attack.k=5,100", "task.sequential=true"),
    }
    # ATTACKS=sequential: the attacks run sequential PREDICT only, and the tables read those runs.
    sequential = make_recipe("reproduce-tables", f"PROFILE={profile}", "ATTACKS=sequential")
    attacks = [c for c in sequential if "task=attack" in c and f"experiment={reproduction}" in c]
    assert all("++per_task.attack.sequential=true" in c or "task.sequential=true" in c for c in attacks)
    (page,) = [c for c in sequential if "task=tables" in c]
    assert "task.overrides=[++per_task.attack.sequential=true]" in page
    misspelt = ["make", "-n", "reproduce-tables", "ATTACKS=sequntial"]
    wrong = subprocess.run(misspelt, cwd=ROOT, capture_output=True, text=True)
    assert wrong.returncode != 0 and "ATTACKS=sequntial is not allowed: fixed or sequential" in wrong.stderr
    cfg = compose_cfg([f"experiment={reproduction}", "task=attack", "++per_task.attack.sequential=true"])
    assert cfg.task.sequential and not compose_cfg([f"experiment={reproduction}", "task=attack"]).task.sequential
    cfgs = [compose_cfg([f"experiment={reproduction}", "task=train", *combo]) for combo in sweep_combos(reproduction)]
    assert {c.model.arch for c in cfgs} == archs and {c.profile.name for c in cfgs} == {profile}
    assert {c.data.name for c in cfgs} == {"metaroom_synth"} and {str(c.attack.k) for c in cfgs} == {"5"}
    (page,) = [c for c in recipe if "task=tables" in c]
    assert (
        f"profile={profile}" in page
        and "task.page=docs/results.md" in page
        and not any(a.startswith("task.experiment=") for a in page)
    )  # each table from its own experiment: the MetaRoom ones from the reproduction, tabletop from its own
    own = {t.name: t.experiment.format(profile=profile) for t in paper_tables.TABLES if t.data is not None}
    assert set(own.values()) == {reproduction, "tabletop"}


@pytest.mark.slow
def test_after_the_demo_every_run_is_a_sweep_parent_with_jobs_or_one_of_its_jobs(tmp_path):
    """Every step of make demo, its tables included, runs as a sweep: a parent and its jobs. The
    demo's own recipe, on a tiny scene, and the runs page's view names metrics the runs log."""
    from mrcert.infra.experiment import experiment_tags, runs_view_metrics, ui_link

    recipe = make_recipe("demo")
    assert [c for c in recipe if "task=tables" in c], recipe
    for command in recipe:
        mrcert([*command, *([*TINY, "train.epochs=1"] if "task=tables" not in command else [])], tmp_path)
    all_runs = runs(tmp_path)
    parents = {r.info.run_id for r in all_runs if r.data.tags.get("mrcert.multirun") == "parent"}
    children = [r.data.tags.get("mlflow.parentRunId") for r in all_runs if r.info.run_id not in parents]
    assert len(parents) == len(recipe) and all(c in parents for c in children)
    assert set(children) == parents  # no parent is empty
    tasks = sorted(r.data.tags["mrcert.task"] for r in all_runs if r.info.run_id not in parents)
    assert tasks == ["attack"] * 2 + ["certify"] * 2 + ["smooth"] * 2 + ["tables"] + ["train"] * 2
    # Task runs say whether they are a sweep's job (searchable: tags.`mrcert.multirun` = 'job').
    assert {r.data.tags["mrcert.multirun"] for r in all_runs if r.info.run_id not in parents} == {"job"}
    logged = set().union(*(r.data.metrics for r in all_runs))
    assert set(runs_view_metrics()) <= logged, set(runs_view_metrics()) - logged
    # The view groups by a tag every task run carries and no parent does: the page lists every
    # job in its task's group and gathers the parents in MLflow's collapsed "Additional runs".
    (group,) = json.loads(experiment_tags()["mlflow.sharedViewState.mrcert"])["groupBy"]["groupByKeys"]
    assert group["mode"] == "tag"
    assert {r.info.run_id for r in all_runs if group["groupByData"] not in r.data.tags} == parents
    assert ui_link(compose_cfg(["task=ui"], tmp_path).tracking, "http://127.0.0.1:5000").endswith(
        "/runs?workflowType=machine_learning&viewStateShareKey=mrcert"
    )


def test_failing_job_marks_the_parent_failed_and_keeps_the_other_result(tmp_path):
    proc = mrcert(["-m", *FAST, "data.image.height=90,0"], tmp_path, check=False)
    assert proc.returncode != 0
    all_runs = runs(tmp_path)
    (parent,) = [r for r in all_runs if r.data.tags.get("mrcert.multirun") == "parent"]
    assert parent.info.status == "FAILED"
    (child,) = [r for r in all_runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert child.info.status == "FINISHED" and child.data.params["data.image.height"] == "90"


def test_bad_value_stops_with_a_clear_message_and_no_traceback(tmp_path):
    proc = mrcert([*FAST, "motion.sigma=-1"], tmp_path, check=False)
    assert proc.returncode == 2
    assert "motion.sigma=-1" in proc.stderr and "> 0" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert runs(tmp_path) == []


def test_help_lists_the_tasks(tmp_path):
    out = mrcert(["--help"], tmp_path).stdout
    listed = "task: attack, certify, export, gather, import, render, smooth, tables, train, ui, verify, viewpoints"
    assert "Tasks:" in out and listed in out
    tasks = out.split("Tasks:")[1]
    for name in (
        "render",
        "train",
        "certify",
        "smooth",
        "attack",
        "tables",
        "import",
        "gather",
        "verify",
        "export",
        "ui",
    ):
        assert f"\n  {name} " in tasks
    groups = out.split("== Config groups ==")[1].split("== Config ==")[0]  # only what a user picks
    assert "model: resnet18, resnet50, small_cnn" in groups and not any(
        g in groups for g in ("schema/", "/evaluation", "/camera")
    )


def test_help_and_the_config_s_schemas_import_no_torch():
    """``mrcert --help`` lists every task (its summary read from its module's source) and the
    config's schemas and checks load, all without importing torch (seconds of start-up)."""
    code = (
        "import sys; sys.argv = ['mrcert', '--help']\n"
        "import mrcert.infra.config, mrcert.infra.schema, mrcert.__main__ as m\n"
        "try:\n    m.main()\nexcept SystemExit:\n    pass\n"
        "print('torch' in sys.modules, 'torchvision' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert "  certify " in done.stdout and done.stdout.strip().endswith("False False"), done.stdout[-500:]


def test_the_ui_task_refuses_a_tracking_server_and_leaves_no_run_or_folder(tmp_path):
    proc = mrcert(["task=ui", "tracking=server"], tmp_path, check=False)
    assert proc.returncode == 2 and "task=ui serves a SQLite store" in proc.stderr
    assert not any(p.is_file() for p in tmp_path.rglob("*"))


@pytest.mark.slow
@pytest.mark.skipif(
    not any(map(shutil.which, BROWSERS)), reason="no headless browser (Debian: apt-get install chromium)"
)
def test_the_ui_task_pictures_the_runs_page_and_adds_no_run(tmp_path):
    """``make figures``' picture: the UI served on the store, a PNG of its runs page, the UI
    stopped, and the store as it was (no run, no launch folder)."""
    mrcert([*FAST], tmp_path)
    before = {r.info.run_id for r in runs(tmp_path)}
    png = tmp_path / "runs.png"
    mrcert(["task=ui", "task.port=5093", f"task.screenshot={png}"], tmp_path)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert {r.info.run_id for r in runs(tmp_path)} == before
    assert not any(p.is_file() for p in (tmp_path / "runs" / "ui").rglob("*"))


def test_tracking_off_still_writes_outputs(tmp_path):
    mrcert([*FAST, "tracking=off"], tmp_path)
    assert not (tmp_path / "mlflow.db").exists()
    assert len(list((tmp_path / "runs" / "render").glob("*/contact_sheet.png"))) == 1


@pytest.mark.parametrize("suffix", [".ply"])
def test_render_a_point_cloud_file(tmp_path, suffix):
    import numpy as np
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    rng = np.random.default_rng(0)
    pcd.points = o3d.utility.Vector3dVector(
        np.column_stack([rng.uniform(-1, 1, 5000), rng.uniform(-0.5, 0.5, 5000), rng.uniform(1, 3, 5000)])
    )
    pcd.colors = o3d.utility.Vector3dVector(rng.uniform(0, 1, (5000, 3)))
    path = tmp_path / f"scan{suffix}"
    o3d.io.write_point_cloud(str(path), pcd)
    mrcert([*FAST, "data=pointcloud", f"data.path={path}", "tracking=off"], tmp_path)
    missing = mrcert(
        [*FAST, "data=pointcloud", f"data.path={tmp_path / 'nope.ply'}", "tracking=off"], tmp_path, check=False
    )
    assert missing.returncode == 2 and "nope.ply" in missing.stderr and "does not exist" in missing.stderr


def test_a_store_from_before_the_grouped_view_gets_its_parents_out_of_the_task_groups(tmp_path):
    """Sweep parents an older mrcert wrote carry ``mrcert.task``, the tag the runs page groups
    by; the first run against such a store moves it to ``mrcert.sweep_tasks`` and sets the view."""
    from omegaconf import OmegaConf

    from mrcert.infra.experiment import ensure_experiment, experiment_tags

    client = store(tmp_path)
    old_view = {"mlflow.sharedViewState.mrcert": json.dumps({"selectedColumns": []})}
    exp = client.create_experiment("mrcert", tags=old_view)
    parent = client.create_run(exp, tags={"mrcert.task": "certify,smooth", "mrcert.multirun": "parent"})
    job = client.create_run(exp, tags={"mrcert.task": "certify", "mrcert.multirun": "job"})
    tracking = OmegaConf.create(
        {"uri": f"sqlite:///{tmp_path / 'mlflow.db'}", "artifact_location": None, "experiment": "mrcert"}
    )
    assert ensure_experiment(tracking) == exp
    moved = client.get_run(parent.info.run_id).data.tags
    assert "mrcert.task" not in moved and moved["mrcert.sweep_tasks"] == "certify,smooth"
    assert client.get_run(job.info.run_id).data.tags["mrcert.task"] == "certify"
    assert (
        client.get_experiment(exp).tags["mlflow.sharedViewState.mrcert"]
        == experiment_tags()["mlflow.sharedViewState.mrcert"]
    )


TOY_TASK = """
import pandas as pd

from mrcert.infra.identity import Identity
from mrcert.infra.tasks import Task


class Toy(Task):
    summary = "write task.times rows and add them up"
    identity = Identity(defines=("task",))
    log = "toy.tsv"
    columns = ("idx", "value")
    headline = ("total",)

    def title(self, cfg):
        return f"toy x{cfg.task.times}"

    def summarize(self, log, cfg):
        return {"total": float(log["value"].sum())}

    def run(self, cfg, ctx):
        rows = pd.DataFrame({"idx": range(cfg.task.times), "value": range(1, cfg.task.times + 1)})
        rows.to_csv(ctx.output_dir / self.log, sep="\\t", index=False)
        metrics = self.summarize(rows, cfg)
        ctx.tracker.log_metrics(metrics)
        return metrics
"""


def test_a_new_task_is_one_python_file_and_one_yaml(tmp_path):
    """A task defined outside the package -- its class in one module, its config in one YAML on
    Hydra's search path -- runs through the one entry point as a tracked run, named by its class,
    keyed by its config and reused by ``skip_finished``."""
    package, conf = tmp_path / "package", tmp_path / "conf" / "task"
    package.mkdir()
    conf.mkdir(parents=True)
    (package / "toytask.py").write_text(TOY_TASK)
    (conf / "toy.yaml").write_text("_target_: toytask.Toy\nname: toy\ntimes: 3\n")
    env = os.environ | {"MRCERT_OUTPUTS": str(tmp_path / "out"), "PYTHONPATH": str(package)}
    args = [sys.executable, "-m", "mrcert", "task=toy", f"hydra.searchpath=[file://{tmp_path / 'conf'}]"]
    for _ in range(2):
        proc = subprocess.run(
            [*args, "skip_finished=true"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'out' / 'mlflow.db'}")
    (run,) = mlflow.search_runs(search_all_experiments=True, output_format="list")
    assert run.info.status == "FINISHED" and run.info.run_name == "toy x3" and run.data.metrics["total"] == 6.0
    assert run.data.tags["mrcert.task"] == "toy" and "mrcert.sealed.toy.tsv" in run.data.tags
