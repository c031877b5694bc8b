"""Tables and figure: each cell from exactly the runs of its composed config, never another's.

The store holds real tiny runs of the demo experiment (small CNNs, vanilla and augmented on
tz) made with the tiny data settings; the tables are built from the demo experiment with the
same settings as every cell's overrides.
"""

import re
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest

from mrcert.__main__ import run_task
from mrcert.reporting import certify_log, paper_results, paper_tables
from mrcert.reporting.cells import RunIndex
from mrcert.reporting.certify_log import read_log
from mrcert.reporting.experiment_cells import ExperimentCells
from mrcert.reporting.page import times as page_times
from mrcert.reporting.writers import write
from tests.conftest import TINY, compose_cfg, run_cli

# The tiny data and a short recipe; every cell of the tables gets the same overrides.
SETTINGS = [*TINY, "train.epochs=2", "train.batch_size=8"]
TASKS = ("smooth", "attack", "certify")
DEMO = ["experiment=demo", *SETTINGS]
# idx label predict radius correct time -- certified accuracy at 0.1: rows 0 and 18 -> 2/5.
COHEN = (
    "idx\tlabel\tpredict\tradius\tcorrect\ttime\n0\t0\t0\t0.5\t1\t0:00:01\n6\t0\t0\t0.05\t1\t0:00:01\n"
    "12\t1\t-1\t0.0\t0\t0:00:01\n18\t1\t1\t0.2\t1\t0:00:01\n24\t2\t0\t0.3\t0\t0:00:01\n"
)


def run(out: Path, overrides: list[str], name: str) -> dict:
    return run_task(compose_cfg(overrides, out), out / "runs" / name)


def train_overrides(variant: str) -> list[str]:
    return [*DEMO, "task=train", f"model.variant={variant}"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    out = tmp_path_factory.mktemp("tables")
    for variant in ("vanilla", "augmented"):
        run(out, train_overrides(variant), f"train-{variant}")
    for task in ("certify", "smooth", "attack"):
        run(out, [*DEMO, f"task={task}", "model.variant=vanilla", "task.batch_size=64"], task)
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    return out


def source(out: Path, **kw) -> ExperimentCells:
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    return ExperimentCells(RunIndex.load("mrcert"), "quick", experiment="demo", overrides=tuple(SETTINGS), **kw)


def hand(out: Path, name: str, file: str, column: str, value=1) -> float:
    df = read_log(next((out / "runs" / name).glob(file)), ["idx"])
    return float((df[column] == value).mean())


def test_cells_hold_exactly_the_runs_of_their_config(store):
    src = source(store)
    df = paper_tables.TABLE3.build(src)
    vanilla = df.loc[("Tz", "Smoothed Vanilla SmallCNN")]
    certify = read_log(store / "runs" / "certify" / "certify.tsv")
    assert len(certify) == 2  # the demo's every 12th of 18 test images
    assert vanilla["Certified Acc"] == pytest.approx(((certify.correct == 1) & (certify.radius >= 0.1)).mean())
    # The evidence page's version: both procedures' cost per image (no sequential run here: empty).
    page = paper_tables.TABLE3_SEQUENTIAL.build(source(store)).loc[("Tz", "Smoothed Vanilla SmallCNN")]
    assert page["s per image"] == pytest.approx(certify.seconds.mean())
    assert np.isnan(page["s per image, sequential"]) and np.isnan(page["Certified Acc, sequential"])
    assert vanilla["Benign Acc"] == pytest.approx(hand(store, "smooth", "smooth.tsv", "correct"))
    assert vanilla["5-pert Emp. Acc"] == pytest.approx(hand(store, "attack", "attack.tsv", "smoothed_robust"))
    # The augmented model is trained but never evaluated: its cells stay empty, never zero.
    assert df.loc[("Tz", "Smoothed Augmented SmallCNN")].isna().all()
    # Each cell names its run.
    sources = src.sources("table3_certified").set_index(["row", "column"])
    runs = mlflow.search_runs(search_all_experiments=True, filter_string="tags.`mrcert.task` = 'certify'")
    assert sources.loc[("Tz / Smoothed Vanilla SmallCNN", "Certified Acc"), "runs"] == runs.iloc[0]["run_id"]
    assert "no finished run" in sources.loc[("Tz / Smoothed Augmented SmallCNN", "Certified Acc"), "note"]


def test_a_smoke_run_or_other_settings_never_change_a_cell(store):
    before = paper_tables.TABLE3.build(source(store))
    # A smoke run, another alpha and a sequential run of the same model after the full run.
    run(store, [*DEMO, "task=certify", "model.variant=vanilla", "task.max=1"], "smoke")
    run(store, [*DEMO, "task=certify", "model.variant=vanilla", "task.alpha=0.3"], "alpha")
    run(store, [*DEMO, "task=smooth", "model.variant=vanilla", "task.max=1"], "smoke-smooth")
    run(store, [*DEMO, "task=certify", "model.variant=vanilla", "task.sequential=true"], "sequential")
    after_src = source(store)
    after = paper_tables.TABLE3.build(after_src)
    pd.testing.assert_frame_equal(after, before)
    # The page prints the sequential columns beside the fixed-n ones in the same format.
    page = paper_tables.TABLE3_SEQUENTIAL.build(after_src, True, "page").loc[("Tz", "Smoothed Vanilla SmallCNN")]
    sequential = read_log(store / "runs" / "sequential" / "certify.tsv")
    at_radius = ((sequential.correct == 1) & (sequential.radius >= 0.1)).mean()
    assert page["Certified Acc, sequential"] == f"{at_radius:.3f}"
    assert (sequential.n0 == 0).all()  # no separate class guess: every sample classified is in n
    assert page["samples per image, sequential"] == f"{(sequential.n0 + sequential.n).mean():.1f}"
    assert page["Certified Acc"].startswith(f"{before.loc[('Tz', 'Smoothed Vanilla SmallCNN'), 'Certified Acc']:.3f}")
    smoke = read_log(store / "runs" / "smoke" / "certify.tsv")
    assert len(smoke) == 1  # the smoke run exists and differs in size from the full one
    sources = after_src.sources("table3_certified")
    full = mlflow.search_runs(
        search_all_experiments=True, filter_string="tags.`mrcert.task` = 'certify' and params.`task.max` = 'None'"
    )
    certified = sources[sources.column == "Certified Acc"].set_index("row")["runs"]
    assert certified["Tz / Smoothed Vanilla SmallCNN"] == full.sort_values("start_time").iloc[0]["run_id"]


@pytest.mark.slow  # over 20 s: make test-full
def test_a_sharded_cell_is_filled_only_when_every_shard_finished(tmp_path):
    out = tmp_path
    run(out, train_overrides("vanilla"), "train")
    shard = ["model.variant=vanilla", "task.num_shards=2", "task.skip=1", "task.max=4"]
    for task in TASKS:
        run(out, [*DEMO, f"task={task}", *shard, "task.shard=0"], f"{task}-0")
    overrides = tuple([*SETTINGS, "task.skip=1", "task.max=4"])
    src = ExperimentCells(RunIndex.load("mrcert"), "quick", experiment="demo", overrides=overrides)
    early = paper_tables.TABLE3.build(src)
    assert early.loc[("Tz", "Smoothed Vanilla SmallCNN"), ["Benign Acc", "5-pert Emp. Acc"]].isna().all()
    notes = src.sources("table3_certified").set_index(["row", "column"])["note"]
    assert notes[("Tz / Smoothed Vanilla SmallCNN", "Benign Acc")] == "shards [1] of task.num_shards=2 not finished"
    assert notes[("Tz / Smoothed Augmented SmallCNN", "Benign Acc")] == "no finished train run for its model"
    for task in TASKS:
        run(out, [*DEMO, f"task={task}", *shard, "task.shard=1"], f"{task}-1")
    src = ExperimentCells(RunIndex.load("mrcert"), "quick", experiment="demo", overrides=overrides)
    df = paper_tables.TABLE3.build(src)
    smooth, attack, certify = (
        pd.concat([read_log(out / "runs" / f"{task}-{i}" / f"{task}.tsv", ["idx"]) for i in (0, 1)]) for task in TASKS
    )
    assert len(smooth) == len(attack) == len(certify) == 4
    row = df.loc[("Tz", "Smoothed Vanilla SmallCNN")]
    assert row["Benign Acc"] == pytest.approx(smooth.correct.mean())
    assert row["5-pert Emp. Acc"] == pytest.approx((attack.smoothed_robust == 1).mean())
    certified = (certify.correct == 1) & (certify.radius >= 0.1) & (certify.predict >= 0)
    assert row["Certified Acc"] == pytest.approx(certified.mean())
    radii, acc = paper_tables.curves(src)[0]["tz"]["Smoothed Vanilla SmallCNN"]  # the figure's curve: the merged log's
    expected_radii, expected_acc = certify_log.curve(certify)
    assert radii.tolist() == expected_radii.tolist() and acc.tolist() == expected_acc.tolist()
    assert acc[0] == pytest.approx(((certify.correct == 1) & (certify.predict >= 0)).mean())
    runs = src.sources("table3_certified").set_index(["row", "column"])["runs"]
    assert len(runs[("Tz / Smoothed Vanilla SmallCNN", "Benign Acc")].split()) == 2


def test_imported_logs_fill_cells_only_when_asked_and_only_unambiguously(store, tmp_path):
    log = tmp_path / "cohen.tsv"
    log.write_text(COHEN)
    run(store, ["experiment=demo", "task=import", f"task.path={log}", "model.variant=augmented"], "import")
    ours = paper_tables.TABLE3.build(source(store))
    assert np.isnan(ours.loc[("Tz", "Smoothed Augmented SmallCNN"), "Certified Acc"])  # not mixed into ours
    imported = paper_tables.TABLE3.build(source(store, certify_task="import"))
    assert imported.loc[("Tz", "Smoothed Augmented SmallCNN"), "Certified Acc"] == pytest.approx(0.4)
    assert np.isnan(imported.loc[("Tz", "Smoothed Augmented SmallCNN"), "Benign Acc"])
    radii, acc = paper_tables.curves(source(store, certify_task="import"))[0]["tz"]["Smoothed Augmented SmallCNN"]
    assert radii.tolist() == [0.0, 0.05, 0.2, 0.5] and acc.tolist() == pytest.approx([0.6, 0.6, 0.4, 0.2])
    other = tmp_path / "other.tsv"
    other.write_text(COHEN.replace("0.5\t1", "0.05\t1"))
    run(store, ["experiment=demo", "task=import", f"task.path={other}", "model.variant=augmented"], "import2")
    src = source(store, certify_task="import")
    assert np.isnan(paper_tables.TABLE3.build(src).loc[("Tz", "Smoothed Augmented SmallCNN"), "Certified Acc"])
    notes = src.sources("table3_certified").set_index(["row", "column"])["note"]
    assert "ambiguous: 2 different finished runs" in notes[("Tz / Smoothed Augmented SmallCNN", "Certified Acc")]


@pytest.mark.slow  # over 20 s: make test-full
def test_table_3_of_the_released_metaroom_from_imported_logs(tmp_path):
    """The authors' logs, imported under the released data set, fill its Table 3 when the tables
    are built for that data set -- and never the synthetic MetaRoom's."""
    log = tmp_path / "cohen.tsv"
    log.write_text(COHEN)
    released = ["data=metaroom", "profile=paper", "model=resnet18", "motion=tz", "model.variant=augmented"]
    done = run_cli(["task=import", f"task.path={log}", *released], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    for data, expected in (("data=metaroom", "0.400 (0.817)"), (None, "(0.817)")):
        args = ["task=tables", "task.certify_task=import", "profile=paper", "task.show_paper=true"]
        args += [data] if data else []
        built = run_cli(args, tmp_path)
        assert built.returncode == 0, built.stderr[-2000:]
        table = pd.read_csv(tmp_path / "tables" / "table3_certified.csv", keep_default_na=False)
        row = table[(table.Axis == "Tz") & (table.Model == "Smoothed Augmented ResNet-18")]
        assert row["Certified Acc"].str.strip().tolist() == [expected]


def test_written_files_keep_empty_cells_empty_and_latex_balanced(store, tmp_path):
    src = source(store)
    df = paper_tables.TABLE3.build(src)
    md, tex, csv = write(df, tmp_path / "t3", "Table 3: $x$ & y_z ~^")
    back = pd.read_csv(csv, keep_default_na=False)
    assert back.loc[back.Model == "Smoothed Augmented SmallCNN", "Certified Acc"].tolist() == [""]
    assert "nan" not in md.read_text()
    vanilla = df.loc[("Tz", "Smoothed Vanilla SmallCNN"), "Certified Acc"]
    assert f"| {vanilla:.3f} " in md.read_text()  # numbers as written, not re-parsed
    lines = [ln for ln in tex.read_text().splitlines() if ln.endswith(r"\\")]
    columns = len(df.reset_index().columns)
    assert len(lines) == 1 + len(df) and all(ln.count("&") - ln.count(r"\&") == columns - 1 for ln in lines)
    assert r"\caption{Table 3: \$x\$ \& y\_z \textasciitilde{}\textasciicircum{}}" in tex.read_text()
    shown = paper_tables.TABLE3.build(source(store), show_paper=True)
    assert shown.loc[("Tz", "Smoothed Augmented SmallCNN"), "Certified Acc"] == ""  # no paper value for a SmallCNN


def test_sweep_table_from_a_parents_children(store):
    log = store / "cohen-sweep.tsv"
    log.write_text(COHEN)
    proc = run_cli(["-m", "task=import", f"task.path={log}", "motion=tz", "motion.sigma=0.05,0.1"], store)
    assert proc.returncode == 0, proc.stderr[-2000:]
    mlflow.set_tracking_uri(f"sqlite:///{store / 'mlflow.db'}")
    (parent,) = mlflow.search_runs(
        search_all_experiments=True, filter_string="tags.`mrcert.multirun` = 'parent'", output_format="list"
    )
    sweep = paper_tables.SWEEP.build(source(store, parent=parent.info.run_id))
    assert [idx[:2] for idx in sweep.index] == [("tz", 0.05), ("tz", 0.1)]
    assert sweep.loc[("tz", 0.1, "Vanilla ResNet-18"), "r=0.2"] == pytest.approx(0.4)
    assert sweep.loc[("tz", 0.1, "Vanilla ResNet-18"), "r=0"] == pytest.approx(0.6)


class Encoded:
    """A run index whose every cell holds a value that names its own measure: the task's metric,
    the attack's K and the axis (``VALUES``); a measure not in ``VALUES`` has no run."""

    METRICS = ("base_benign_accuracy", "base_robust_accuracy", "smoothed_robust_accuracy", "smoothed_benign_accuracy")

    def cell(self, overrides):
        from mrcert.reporting.cells import Cell, compose_config

        cfg = compose_config(tuple(overrides))
        return Cell(cfg, [pd.Series({"run_id": f"{cfg.task.name}-k{cfg.attack.k}-{cfg.motion.axis}"})])

    def metric(self, cell, name: str) -> float:
        cfg = cell.cfg
        if name not in self.METRICS or int(cfg.attack.k) not in (5, 10, 100):
            return float("nan")
        axis = paper_results.AXES_ORDER.index(str(cfg.motion.axis).removeprefix("tabletop_"))
        k = (5, 10, 100).index(int(cfg.attack.k))
        return round(self.METRICS.index(name) / 10 + k / 100 + axis / 1000, 4)


def test_every_declared_table_takes_each_cell_from_its_own_measure():
    """The declared tables on the reproduction's and the tabletop's own jobs, read through an
    index whose values name their measure (tenths: the metric, hundredths: K = 5, 10, 100,
    thousandths: the axis): Table 1 puts base and smoothed side by side at K = 100, the appendix
    the smoothed 5- and 100-perturbed, the tabletop table the mean benign accuracy over the axes
    beside each axis's 10-perturbed accuracy; each cell names the run it came from."""
    src = ExperimentCells(Encoded(), "quick")
    by_name = {t.name: t for t in paper_tables.TABLES}
    t1 = by_name["table1_augmented"].build(src)
    assert list(t1.columns) == ["SmallCNN Base", "SmallCNN Smoothed"]
    assert [a for a, _ in t1.index[::2]] == ["Tz", "Tx", "Ty", "Rz", "Rx", "Ry"]
    assert t1.loc[("Rx", "Benign Accuracy")].tolist() == [0.024, 0.304]  # PREDICT has no K: the experiment's
    assert t1.loc[("Rx", "100-perturbed Emp. Robust Acc.")].tolist() == [0.124, 0.224]
    assert (
        src.sources("table1_augmented")
        .set_index(["row", "column"])
        .loc[("Rx / 100-perturbed Emp. Robust Acc.", "SmallCNN Base"), "runs"]
        == "attack-k100-rx"
    )
    five = by_name["appendix_5_vs_100"].build(src)
    assert five.loc[("Ty", "5-perturbed")].tolist() == [0.202, 0.202]
    assert five.loc[("Ty", "100-perturbed"), "SmallCNN Augmented"] == 0.222
    robot = by_name["tabletop"].build(src)
    assert list(robot.columns) == ["Benign Accuracy", "Tx", "Ty", "Tz", "Rx", "Ry", "Rz"]
    assert robot.loc[("Base", "Vanilla ResNet-18"), "Benign Accuracy"] == pytest.approx(0.0125)  # over the six axes
    assert (
        by_name["tabletop"].build(src, show_paper=True).loc[("Smoothed", "Vanilla ResNet-18"), "Rz"] == "0.213 (0.833)"
    )
    t3 = by_name["table3_certified"].build(src)
    assert t3.loc[("Tz", "Smoothed Vanilla SmallCNN"), "5-pert Emp. Acc"] == 0.2
    assert np.isnan(t3.loc[("Tz", "Smoothed Vanilla SmallCNN"), "Certified Acc"])


@pytest.fixture(scope="module")
def tables_run(store):
    """The tables task over the store, with the evidence page."""
    quoted = ",".join(f"'{o}'" for o in SETTINGS)
    overrides = [
        "task=tables",
        "task.experiment=demo",
        f"task.overrides=[{quoted}]",
        f"task.page={store}/evidence/r.md",
    ]
    return run_task(compose_cfg(overrides, store), store / "runs" / "tables")


def test_tables_task_writes_every_table_its_sources_and_the_figure(store, tables_run):
    result = tables_run
    out = Path(result["tables"])
    for name in ("table3_certified", "table1_augmented", "appendix_vanilla", "appendix_5_vs_100", "sweep"):
        for suffix in (".md", ".tex", ".csv"):
            assert (out / f"{name}{suffix}").is_file() and (out / f"{name}_sources{suffix}").is_file()
    # The demo's runs are of the MetaRoom: no table about the tabletop is written from them.
    assert not list(out.glob("tabletop*")) and "tabletop_filled_cells" not in result
    assert (out / "certified_accuracy_vs_radius.png").is_file() and (out / "certified_accuracy_vs_radius.pdf").is_file()
    assert (out / "method_overview.png").is_file()  # from the filled certify cell
    assert result["table3_certified_filled_cells"] == 3  # the vanilla model's three cells
    sources = pd.read_csv(out / "table3_certified_sources.csv", keep_default_na=False)
    filled = sources[sources.runs != ""]
    assert len(filled) == 3 and filled.links.str.match(r"http://127\.0\.0\.1:5000/#/experiments/\d+/runs/\w+").all()
    (tables_run,) = mlflow.search_runs(
        search_all_experiments=True, filter_string="tags.`mrcert.task` = 'tables'", output_format="list"
    )
    shown = {a.path for a in mlflow.MlflowClient().list_artifacts(tables_run.info.run_id, "tables")}
    assert {"tables/table3_certified.json", "tables/certified_accuracy_vs_radius.png"} <= shown  # log_table, log_figure


def test_the_evidence_page_states_the_numbers_of_its_runs(store, tables_run):
    """The evidence page (as `make reproduce-tables` writes it): the Table 3 row, the findings and the
    timings, each equal to what the runs' own per-image logs give when recomputed here."""
    page = " ".join((store / "evidence" / "r.md").read_text().split())
    assert (store / "evidence" / "r_certified_accuracy_vs_radius.png").is_file()
    clog = read_log(next((store / "runs" / "certify").glob("certify.tsv")), ["idx"])
    slog = read_log(next((store / "runs" / "smooth").glob("smooth.tsv")), ["idx"])
    alog = read_log(next((store / "runs" / "attack").glob("attack.tsv")), ["idx"])
    radius = float(compose_cfg([*DEMO, "task=certify"], store).motion.radius)
    certified = (clog.correct == 1) & (clog.radius >= radius) & (clog.predict >= 0)
    # Each cell beside the paper's value for its axis and variant, of the paper's ResNet-18.
    paper = [
        paper_tables.paper_value("smoothed", "benign", None, "tz", "resnet18", "vanilla"),
        paper_tables.paper_value("smoothed", "perturbed", 5, "tz", "resnet18", "vanilla"),
        paper_results.CERTIFIED[("tz", "resnet18", "vanilla")],
    ]
    ours = [slog.correct.mean(), alog.smoothed_robust.mean(), certified.mean()]
    row = "| " + " | ".join(f"{o:.3f} ({p:.3f})" for o, p in zip(ours, paper, strict=True)) + " |"
    assert f"| Tz | Smoothed Vanilla SmallCNN {row}" in page
    # Finding 2: smoothed vs base 5-perturbed accuracy on the same images.
    assert f"Tz vanilla {alog.smoothed_robust.mean():.3f} vs {alog.base_robust.mean():.3f}" in page
    # Finding 3: certified accuracy on the attacked images vs the smoothed 5-perturbed accuracy,
    # and every certified image that the attack broke, by how it failed.
    on_attacked = certified[clog.idx.isin(alog.idx)].sum() / len(alog)
    assert f"Tz vanilla {on_attacked:.3f} vs {alog.smoothed_robust.mean():.3f}" in page
    broken = alog[alog.idx.isin(clog.idx[certified]) & (alog.smoothed_robust != 1)]
    abstained = int((broken.smoothed_failure == "abstain").sum())
    assert f"Of the certified images, {len(broken)} failed the attack: {abstained} by a PREDICT abstention" in page
    # Test views beside their nearest training views, with the closest pitch and roll gaps.
    from mrcert.data.sources import load

    bundle = load(compose_cfg([*DEMO, "task=certify"], store).data)
    test, train = bundle.split("test").params, bundle.split("train").params
    pitch = min(abs(a - b) for a in train[:, 1] for b in test[:, 1])
    roll = min(abs(a - b) for a in train[:, 2] for b in test[:, 2])
    assert f"{pitch:.1f} in pitch and {roll:.1f} in roll (separation rule `every`)" in page and pitch >= 15
    assert (store / "evidence" / "r_views.png").is_file()
    # Time per stage: seconds per image from the per-image logs, and the machine the run ran on.
    from mrcert.infra.runtime import machine

    assert f"| certify | 1 | {len(clog)} |" in page and f"| {clog.seconds.mean():.2f} |" in page
    assert f"| {machine()} (1 run) |" in page


def page_table(page: str, heading: str) -> pd.DataFrame:
    """The first Markdown table after ``heading`` on a page, cells as text."""
    lines = page.split(heading, 1)[1].splitlines()
    end = next(i for i, x in enumerate(lines) if x.startswith("## "))
    rows = [line for line in lines[:end] if line.startswith("|")]
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in rows]
    return pd.DataFrame(cells[2:], columns=cells[0])


def page_of(store: Path, name: str, extra: list[str]) -> bytes:
    quoted = ",".join(f"'{o}'" for o in [*SETTINGS, *extra])
    overrides = ["task=tables", "task.experiment=demo", f"task.overrides=[{quoted}]", f"task.page={store}/{name}/r.md"]
    run_task(compose_cfg(overrides, store), store / "runs" / f"tables-{name}")
    return (store / name / "r.md").read_bytes()


def test_the_evidence_page_follows_the_configs_n_and_k_and_regenerates_byte_identical(store):
    """The same runs give the same page, byte for byte; runs made with another n (CERTIFY,
    PREDICT, the attack's PREDICT) and another attack K give a page that states those and no
    other: no setting on it is written into the code."""
    changed = ["task.n=40", "attack.k=3"]
    for task in TASKS:
        run(store, [*DEMO, f"task={task}", "model.variant=vanilla", "task.batch_size=64", *changed], f"{task}-n40")
    first, again = page_of(store, "p1", changed), page_of(store, "p1", changed)  # written again in place
    assert first == again
    page = first.decode()
    alog = read_log(next((store / "runs" / "attack-n40").glob("attack.tsv")), ["idx"])
    table3 = page_table(page, "## Table 3")
    row = table3[table3.Model == "Smoothed Vanilla SmallCNN"].iloc[0]
    assert set(alog.k) == {3} and row["3-pert Emp. Acc"] == f"{alog.smoothed_robust.mean():.3f}"  # paper: no K = 3
    numbers = re.findall(r"\bn = (\d+)", page)
    assert numbers and set(numbers) == {"40"}, numbers  # CERTIFY's n, PREDICT's n, the attack's n
    assert not re.search(r"\b5[- ](pert|uniform)", page) and "3 uniform perturbations" in page
    default = page_of(store, "p3", []).decode()
    assert set(re.findall(r"\bn = (\d+)", default)) == {"1000", "100"} and "| 5-pert Emp. Acc " in default


def test_the_pages_time_per_stage_sums_every_run_behind_its_tables(store):
    """The time table counts every stage the tables read, not only Table 3's: Table 1's
    100-perturbed attack and the page's sequential CERTIFY too, each with its own runs' time,
    and a last row summing them all (the figure the reproduction's time budget is judged by)."""
    extra = ("task.n=60",)  # runs of their own: the module's other pages keep their cells
    made = {  # stage as the page names it: (its overrides, its run folder)
        "certify": (["task=certify"], "stage-certify"),
        "certify (task.sequential=true)": (["task=certify", "task.sequential=true"], "stage-sequential"),
        "attack (attack.k=100)": (["task=attack", "attack.k=100"], "stage-attack100"),
    }
    for overrides, folder in made.values():
        run(store, [*DEMO, *overrides, "model.variant=vanilla", "task.batch_size=64", *extra], folder)
    src = ExperimentCells(RunIndex.load("mrcert"), "quick", experiment="demo", overrides=(*SETTINGS, *extra))
    for table in paper_tables.tables_for(src):  # as task=tables builds them before the page
        table.build(src)
    paper_tables.TABLE3_SEQUENTIAL.build(src)
    times = page_times.stage_times(src).set_index("stage")

    def hours(folder: str) -> float:
        (r,) = mlflow.search_runs(
            search_all_experiments=True,
            filter_string=f"tags.`mrcert.output_dir` = '{store / 'runs' / folder}'",
            output_format="list",
        )
        return r.data.metrics["active_seconds"] / 3600

    spent = {stage: hours(folder) for stage, (_, folder) in made.items()} | {"train": hours("train-vanilla")}
    assert set(times.index) == {*spent, ""}  # the augmented model is never evaluated: not timed
    for stage, h in spent.items():
        assert times.loc[stage, "runs"] == 1 and times.loc[stage, "run time, summed (h)"] == pytest.approx(h)
    total = times.loc[""]
    assert total["experiment"] == "every stage" and total["runs"] == len(spent)
    assert total["run time, summed (h)"] == pytest.approx(sum(spent.values()))
    # The page prints the same rows.
    page = page_table(page_of(store, "stages", list(extra)).decode(), "## Time per stage")
    assert list(page["stage"]) == list(times.index)
    assert list(page["run time, summed (h)"]) == [f"{h:.2f}" for h in times["run time, summed (h)"]]


def test_the_page_puts_the_sequential_attack_beside_fixed_ns_cell_by_cell(store):
    """With both attacks run on a cell, the page shows each one's smoothed K-perturbed accuracy,
    the difference in images and the images whose verdict differs, as their logs hold them;
    the sequential attack's time is a stage of its own, and the profile's hours are summed
    both ways."""
    extra = ["task.n=44"]  # runs of their own: the module's other pages keep their cells
    attack = [*DEMO, "task=attack", "model.variant=vanilla", "task.batch_size=64", *extra]
    run(store, attack, "attack-fixed-44")
    run(store, [*attack, "task.sequential=true"], "attack-sequential-44")
    page = page_of(store, "pseq", extra).decode()
    logs = {n: read_log(store / "runs" / f"attack-{n}-44" / "attack.tsv", ["idx"]) for n in ("fixed", "sequential")}
    robust = {n: (log.set_index("idx").smoothed_robust == 1) for n, log in logs.items()}
    row = page_table(page, "## The attacks with sequential PREDICT").iloc[0]
    assert (row["Axis"], row["Model"], row["K"], row["images"]) == ("Tz", "Smoothed Vanilla SmallCNN", "5", "2")
    for name, column in (("fixed", "fixed n"), ("sequential", "sequential")):
        assert row[column] == f"{robust[name].mean():.3f}"
    assert int(row["difference (images)"]) == robust["sequential"].sum() - robust["fixed"].sum()
    assert int(row["images whose verdict differs"]) == (robust["sequential"] != robust["fixed"]).sum()
    assert row["s per image, sequential"] == f"{logs['sequential'].seconds.mean():.2f}"
    times = page_table(page, "## Time per stage").set_index("stage")
    assert times.loc["attack (attack.k=5, task.sequential=true)", "runs"] == "1"
    assert re.search(r"stages summed: [0-9.]+ h with the fixed-n attacks .* [0-9.]+ h with the sequential ones", page)


def test_the_profiles_hours_put_the_sequential_attacks_in_the_fixed_ones_place():
    times = pd.DataFrame(
        {
            "experiment": ["e", "e", "e", "e", "other", "every stage"],
            "stage": ["train", "attack (attack.k=5)", "certify (task.sequential=true)",
                      "attack (attack.k=5, task.sequential=true)", "attack (attack.k=5)", ""],
            "run time, summed (h)": [1.0, 2.0, 0.25, 0.5, 8.0, 11.75],
        }
    )  # fmt: skip
    assert page_times.profile_hours(times, "e") == {"fixed": 3.25, "sequential": 1.75}
    assert page_times.profile_hours(times.iloc[[0, 1, 2]], "e") is None  # no sequential attack ran


def test_findings_count_what_the_logs_hold():
    """The page's findings on hand-made logs whose answers are known: of 4 test images, 0, 1 and 2
    are certified at r (3 has a larger radius but a wrong prediction); the attack ran on 0, 2 and
    3; the certified image 2 failed it by an abstention, the uncertified 3 by another class."""
    from types import SimpleNamespace

    from mrcert.reporting.cells import Cell
    from mrcert.reporting.page.jobs import Job, findings

    cfg = compose_cfg([*DEMO, "task=certify"], Path("/tmp"))
    r = float(cfg.motion.radius)
    clog = pd.DataFrame({"idx": [0, 1, 2, 3], "predict": [0, 1, 2, 0], "correct": [1, 1, 1, 0],
                         "radius": [2 * r, r, 3 * r, 5 * r]})  # fmt: skip
    alog = pd.DataFrame({"idx": [0, 2, 3], "smoothed_robust": [1, 0, 0], "smoothed_failure": ["-", "abstain", "wrong"]})
    metrics = {("certify", "certified_accuracy"): 0.75, ("attack", "base_robust_accuracy"): 1.0,
               ("attack", "smoothed_robust_accuracy"): 1 / 3}  # fmt: skip
    cells = {name: Cell(cfg, [pd.Series({"run_id": name})]) for name in ("certify", "smooth", "attack")}
    index = SimpleNamespace(
        metric=lambda cell, key: metrics.get((cell.runs[0]["run_id"], key), float("nan")),
        log=lambda cell: {"certify": clog, "attack": alog}.get(cell.runs[0]["run_id"]),
    )
    found = findings(SimpleNamespace(index=index), [Job("tz", "vanilla", "small_cnn", *cells.values())])
    assert found["smoothed"] == {"holds": 0, "total": 1, "rows": ["Tz vanilla 0.333 vs 1.000"]}
    assert found["certified"] == {"holds": 0, "total": 1, "rows": ["Tz vanilla 0.667 vs 0.333"]}
    assert (found["broken"], found["abstained"], found["wrong"]) == (1, 1, 0)
    assert (found["k"], found["attack_n"], found["alpha"]) == (cfg.attack.k, cfg.task.n, cfg.task.alpha)


def test_the_learning_curve_reads_its_experiments_train_runs(tmp_path):
    """Two jobs of the learning-curve sweeps, run for real on tiny data -- the small CNN from
    experiment=learning_curve and the paper's ResNet-18 from its own experiment: one row each,
    with the selected model's accuracies as the runs logged them and each epoch's history, and a
    per-epoch panel for each architecture (both rules in one table: the next test)."""
    from mrcert.reporting import learning_curve

    tiny = [o for o in SETTINGS if not o.startswith(("data.protocol.train.per_class", "model"))]
    jobs = {
        ("small_cnn", "every"): "learning_curve",
        ("resnet18", "every"): "learning_curve_resnet18",
    }
    results = {}
    for (arch, rule), experiment in jobs.items():
        job = [f"experiment={experiment}", "task=train", f"data.protocol.separation_rule={rule}", *tiny]
        results[arch, rule] = run(tmp_path, [*job, "data.protocol.train.per_class=40", "seed=0"], f"lc-{arch}-{rule}")
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    src = ExperimentCells(RunIndex.load("mrcert"), "quick", overrides=tuple(tiny))
    df = learning_curve.runs(src).set_index(["model", "separation rule"])
    assert sorted(df.index) == sorted(jobs) and (df["training poses per class"] == 40).all()
    for key, result in results.items():
        assert df.loc[key, "test accuracy"] == result["test_acc"]
        assert df.loc[key, "validation accuracy"] == result["best_val_acc"]
        hist = learning_curve.histories(df.loc[[key]])[df.loc[key, "run_id"]]
        assert len(hist["epoch_test_acc"]) == len(hist["val_acc"]) == 2  # SETTINGS: two epochs
    table = learning_curve.table(df.reset_index())
    assert table["model"].tolist() == ["small_cnn", "resnet18"]  # the page's model first
    fig = learning_curve.figure(df.reset_index(), learning_curve.histories(df))
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[1:] == ["SmallCNN, separation `every`", "ResNet-18, separation `every`"]
    assert len(fig.axes[0].lines) >= 2 and len(fig.axes[1].lines) == len(fig.axes[2].lines) == 2


def test_the_learning_curve_table_and_its_summary_follow_the_numbers():
    from mrcert.reporting import learning_curve
    from mrcert.reporting.page.curve import curve_summary

    models = pd.DataFrame({"validation accuracy": [1.0, 0.975], "test accuracy": [0.817, 0.867]})
    curve = pd.DataFrame(
        {
            "separation rule": ["every"] * 5 + ["any"] * 2,
            "training poses per class": [40, 40, 40, 500, 500, 40, 500],
            "seed": [0, 1, 2, 0, 1, 0, 0],
            "model": ["small_cnn"] * 7,
            "validation accuracy": [0.5, 0.6, 0.7, 1.0, 1.0, 0.8, 1.0],
            "test accuracy": [0.2, 0.3, 0.25, 0.9, 0.8, 0.6, 0.95],
        }
    )
    table = learning_curve.table(curve).set_index(["separation rule", "training poses per class"])
    assert table.index.tolist() == [("every", 40), ("every", 500), ("any", 40), ("any", 500)]  # every first
    assert table.loc[("every", 40), "seeds"] == 3 and table.loc[("every", 40), "test accuracy (median)"] == 0.25
    assert table.loc[("every", 500), "test accuracy (median)"] == 0.85  # median of two seeds
    assert table.loc[("every", 40), "test accuracy (min-max)"] == "0.200-0.300"
    summary = curve_summary(models, curve)
    assert summary["models"] == {"val": (0.975, 1.0), "test": (0.817, 0.867)}
    assert summary["archs"] == [
        {"name": "SmallCNN", "fewest": 40, "most": 500, "fewest_acc": 0.25, "most_acc": pytest.approx(0.85),
         "any": {"poses": 500, "acc": 0.95}}
    ]  # fmt: skip
    resnet = pd.DataFrame(
        {
            "separation rule": ["every"] * 2,
            "training poses per class": [40, 500],
            "seed": [0, 0],
            "model": ["resnet18"] * 2,
            "validation accuracy": [0.1, 0.5],
            "test accuracy": [0.05, 0.4],
        }
    )
    both = curve_summary(models, pd.concat([curve, resnet], ignore_index=True))  # each architecture's own medians
    assert [(a["name"], a["fewest_acc"], a["most_acc"], a["any"]) for a in both["archs"]] == [
        ("SmallCNN", 0.25, pytest.approx(0.85), {"poses": 500, "acc": 0.95}),
        ("ResNet-18", 0.05, 0.4, None),
    ]


def test_runs_are_named_and_carry_their_figure_tables_and_data_as_mlflow_users_expect(store):
    from mrcert.infra.experiment import ui_link

    mlflow.set_tracking_uri(f"sqlite:///{store / 'mlflow.db'}")
    client = mlflow.MlflowClient()
    runs = {r.data.tags["mrcert.task"] + "/" + r.data.tags.get("mrcert.variant", ""): r
            for r in mlflow.search_runs(search_all_experiments=True, output_format="list")
            if "mrcert.task" in r.data.tags}  # task runs; a sweep's parent has mrcert.sweep_tasks  # fmt: skip
    assert runs["train/vanilla"].info.run_name == "train vanilla small_cnn"
    assert runs["train/augmented"].info.run_name == "train tz augmented small_cnn"
    assert runs["certify/vanilla"].info.run_name == "certify tz vanilla small_cnn"
    assert runs["attack/vanilla"].info.run_name == "attack tz vanilla small_cnn k=5"
    # The rendered data sets a model was trained and tested on, with their cache keys as digests.
    inputs = {(d.dataset.name, [t.value for t in d.tags][0]): d.dataset.digest
              for d in runs["train/vanilla"].inputs.dataset_inputs}  # fmt: skip
    train_folder = next(p for p in (store / "data").glob("metaroom_synth-train-*") if "-aug-" not in p.name)
    assert inputs[("metaroom_synth-train", "training")] == train_folder.name.rsplit("-", 1)[1]
    assert ("metaroom_synth-test", "test") in inputs and ("metaroom_synth-validation", "validation") in inputs
    # The certified-accuracy curve is a figure of the certify run; the experiment opens on its runs.
    certify_files = {a.path for a in client.list_artifacts(runs["certify/vanilla"].info.run_id)}
    assert "certified_accuracy.png" in certify_files
    experiment = client.get_experiment(runs["certify/vanilla"].info.experiment_id)
    assert experiment.tags["mlflow.experimentKind"] == "custom_model_development"
    link = ui_link(compose_cfg(["task=ui"], store).tracking, "http://127.0.0.1:5000")
    assert (
        link
        == f"http://127.0.0.1:5000/#/experiments/{experiment.experiment_id}/runs?workflowType=machine_learning&viewStateShareKey=mrcert"
    )


def test_progress_is_a_log_line_every_few_seconds_when_nobody_watches(caplog):
    from mrcert.infra.progress import progress

    with caplog.at_level("INFO", logger="mrcert.progress"):
        assert list(progress(range(5), "certify tz", interval=0.0)) == [0, 1, 2, 3, 4]
        assert list(progress(range(5), "quiet", interval=3600.0)) == [0, 1, 2, 3, 4]
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 5 and lines[-1].startswith("certify tz: 5/5 done")  # pytest's stderr is no terminal


def test_the_side_by_side_compares_both_methods_on_the_same_images(tmp_path):
    """make side-by-side on tiny data: a motion-augmented model certified by motion smoothing
    (experiment=reproduce_quick) and a pixel-noise model by pixel-wise smoothing (experiment=side_by_side,
    one interval) give a pair of rows whose numbers are those of their per-image logs, on the
    pixel-wise run's images, with each method's cost per image."""
    from mrcert.reporting import side_by_side

    shared = [*SETTINGS, "task.n0=8", "task.n=40"]
    motion = ["experiment=reproduce_quick", "motion=tz", "model.variant=augmented"]
    pixelwise = ["experiment=side_by_side", "method.certify.half_width=0.001", "method.certify.frames=3"]
    cms_train = run(tmp_path, [*motion, *SETTINGS, "task=train"], "cms-train")
    run(tmp_path, [*motion, *shared, "task=certify"], "cms")
    pws_train = run(tmp_path, [*pixelwise, *SETTINGS, "task=train"], "pws-train")
    pws_run = run(tmp_path, [*pixelwise, *shared, "task=certify"], "pws")
    # Motion smoothing on the pixel-noise model: both methods on one base classifier.
    run(tmp_path, [*motion, *shared, "task=certify", "model.trained_for={name:pixelwise,sigma:0.25}"], "cms-noise")
    # The deterministic method on both models, the same interval and images (every 5th).
    bound = [*motion, *shared, "task=certify", "task.skip=5", "method=bound_propagation", "method.half_width=0.001"]
    budget = ["method.max_pieces=2", "method.samples=3"]
    bp_run = run(tmp_path, [*bound, *budget, "model.trained_for={name:camera_motion}"], "bp")
    run(tmp_path, [*bound, *budget, "model.trained_for={name:pixelwise,sigma:0.25}"], "bp-noise")
    exact = [*motion, *shared, "task=certify", "task.skip=5", "method=enumeration", "method.half_width=0.001"]
    run(tmp_path, [*exact, "model.trained_for={name:camera_motion}"], "en")
    run(tmp_path, [*exact, "model.trained_for={name:pixelwise,sigma:0.25}"], "en-noise")
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    src = ExperimentCells(RunIndex.load("mrcert"), "quick", overrides=(*shared, "method.certify.frames=3"))
    methods = (
        (("method=bound_propagation", *budget), side_by_side.DETERMINISTIC[0][1], None),
        side_by_side.DETERMINISTIC[1],
    )
    df = side_by_side.runs(src, deterministic=methods)
    # The deterministic methods' rows: the share verified with the right class, on the same images.
    assert list(df["method"].iloc[3:]) == ["bound propagation (crown)"] * 2 + ["image enumeration (exact)"] * 2
    for row, name in zip(df.iloc[3:].itertuples(), ("bp", "bp-noise", "en", "en-noise"), strict=True):
        log = read_log(tmp_path / "runs" / name / "certify.tsv", ["idx"])
        assert set(log.idx) == set(row.log.idx) and row.kind == "deterministic"
        verified = (log.outcome == "verified") & (log.correct == 1)
        assert df.loc[row.Index, "certified accuracy"] == verified.mean()
        assert df.loc[row.Index, "left by the bound"] == (log.outcome == "unknown").sum()
        assert (log.n0 == 0).all() and (log.n == 0).all()  # it classifies no smoothing samples
    assert bp_run["mean_samples"] == 0
    assert list(df["base model"].iloc[3:]) == ["motion-augmented model", "pixel-noise model (sigma 0.25)"] * 2
    df = df.iloc[:3]
    cms, noise, pws = (
        read_log(tmp_path / "runs" / name / "certify.tsv", ["idx"]) for name in ("cms", "cms-noise", "pws")
    )
    assert len(pws) < len(cms) and set(pws.idx) < set(cms.idx)  # every 10th image
    assert list(df["frames"].isna()) == [True, True, False] and (df["half_width"] == 0.001).all()
    assert list(df["base model"]) == ["motion-augmented model", *["pixel-noise model (sigma 0.25)"] * 2]
    motion, on_noise, pixel = df.iloc[0], df.iloc[1], df.iloc[2]
    for row, whole in ((motion, cms), (on_noise, noise)):
        same = whole[whole.idx.isin(pws.idx)]
        assert row["certified accuracy"] == ((same.correct == 1) & (same.radius >= 0.001) & (same.predict >= 0)).mean()
    assert not noise.equals(cms)  # another base classifier
    assert pixel["certified accuracy"] == ((pws.correct == 1) & (pws.radius >= 0.001) & (pws.predict >= 0)).mean()
    assert motion["images"] == pixel["images"] == len(pws)
    assert (motion["poses projected / image"], motion["forward passes / image"]) == (48, 48)
    # Pixel-wise: 3 frames rendered; each image stops after its first frame here (n = 40 cannot
    # give a radius above the bound), so n0 + n forward passes per frame certified.
    assert (pws.n == 40).all()
    assert (pixel["poses projected / image"], pixel["forward passes / image"]) == (3, 48)
    assert pws_run["mean_samples"] == 48  # the run's own count of its samples is the page's
    # Why each image was left: every margin here is negative, so the bound left them all.
    assert (pws.margin < 0).all() and (pixel["left by the bound"], pixel["left by the classes"]) == (len(pws), 0)
    assert motion[["left by the bound", "left by the classes"]].isna().all()
    assert pixel["seconds / image"] == pws.seconds.mean()
    # The page's tables show each run once. A motion smoothing run serves every interval: with a
    # second, wider interval it is a second column of the comparison, not a second row.
    wider = df.iloc[:2].assign(half_width=0.01, interval="+-0.01 m")
    shown = side_by_side.table(pd.concat([df, wider]))
    assert list(shown["method"].str.split().str[0]) == ["motion", "motion", "pixel-wise"]
    assert list(shown["+-0.01"]) == [
        *(f"{r['certified accuracy']:.3f} ({r.low:.2f}-{r.high:.2f})" for r in (motion, on_noise)),
        "",
    ]
    costs = side_by_side.costs(pd.concat([df, wider]))
    assert list(costs["interval"]) == ["every a", "every a", "+-0.001 m"]
    assert list(costs["seconds / image"]) == [f"{r['seconds / image']:.1f}" for r in (motion, on_noise, pixel)]
    assert "machine" not in costs  # one machine: the page names it once
    # Every cell the page shows names its run and its model's train run in the page's sources.
    from mrcert.infra.runtime import machine
    from mrcert.reporting.page.side_by_side import side_by_side_section

    runs_by_dir = src.index.df.set_index("tags.mrcert.output_dir")["run_id"]
    cms_train_id, pws_train_id = (runs_by_dir[str(tmp_path / "runs" / n)] for n in ("cms-train", "pws-train"))
    assert list(df["train_run"]) == [cms_train_id, pws_train_id, pws_train_id]

    section = side_by_side_section(src, tmp_path / "page.md")
    recorded = [r for r in src.provenance if r["table"] == "side_by_side"]
    paged = side_by_side.runs(src)  # the page's own methods: the enumeration runs beside the smoothing ones
    assert set(df["run_id"]) < set(paged["run_id"])
    assert {r["runs"] for r in recorded} == set(paged["run_id"])
    assert {r["model runs"] for r in recorded} == set(paged["train_run"])
    assert set(src.cited_runs()) == {*paged["run_id"], cms_train_id, pws_train_id}
    assert section["machine"] == machine()
    # The pixel-noise model's caps, as its train run measured them, stated beside the guarantees.
    assert section["caps"] == {"clean": f"{pws_train['test_acc_clean']:.3f}", "noisy": f"{pws_train['test_acc']:.3f}"}
    # Each certified accuracy with its exact 95% interval (statsmodels' Clopper-Pearson as the oracle).
    from statsmodels.stats.proportion import proportion_confint

    for row in (motion, on_noise, pixel):
        k, n = round(row["certified accuracy"] * row["images"]), row["images"]
        assert (row["low"], row["high"]) == pytest.approx(proportion_confint(k, n, alpha=0.05, method="beta"), abs=1e-9)
    # The base classifiers' test accuracy from their train runs: the pixel-noise model's on clean and
    # on noisy images (the images it is used on), the motion-augmented model's on clean ones.
    assert (motion["base clean accuracy"], np.isnan(motion["base noisy accuracy"])) == (cms_train["test_acc"], True)
    for row in (on_noise, pixel):
        assert (row["base clean accuracy"], row["base noisy accuracy"]) == (
            pws_train["test_acc_clean"],
            pws_train["test_acc"],
        )
    assert list(shown["+-0.001"]) == [
        f"{a:.3f} ({b:.2f}-{c:.2f})" for a, b, c in zip(df["certified accuracy"], df["low"], df["high"], strict=True)
    ]
    fig = side_by_side.figure(df)
    assert len(fig.axes[0].lines) == 3  # motion smoothing's curves (two models) and pixel-wise smoothing's point


def test_the_page_states_which_test_images_each_tasks_columns_cover():
    """The quick reproduction attacks every 2nd test image (its 8-hour budget) and certifies and
    smooths them all: the page says so; a demo's columns all cover one image in 12."""
    from mrcert.reporting.cells import compose_config
    from mrcert.reporting.page.jobs import columns_share

    def shares(experiment):
        tasks = ("certify", "smooth", "attack")
        return columns_share({t: compose_config([f"experiment={experiment}", f"task={t}", "motion=tz"]) for t in tasks})

    assert shares("reproduce_quick") == (
        "Columns cover certify: every test image; smooth: every test image; attack: one test image in 2."
    )
    assert shares("demo") == "Every column covers one test image in 12, the same images in each."
