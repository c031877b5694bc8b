"""Tables and figure from a small store of real tiny runs and imported logs."""

from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest

from mrcert import tables
from mrcert.__main__ import run_task
from mrcert.certify_log import read_log
from tests.conftest import TINY, compose_cfg, run_cli

ROOT = Path(__file__).resolve().parent.parent
EVAL = ["task.max=4", "task.batch_size=50"]
# idx label predict radius correct time -- certified accuracy at 0.1: rows 0 and 18 -> 2/5.
COHEN = (
    "idx\tlabel\tpredict\tradius\tcorrect\ttime\n0\t0\t0\t0.5\t1\t0:00:01\n6\t0\t0\t0.05\t1\t0:00:01\n"
    "12\t1\t-1\t0.0\t0\t0:00:01\n18\t1\t1\t0.2\t1\t0:00:01\n24\t2\t0\t0.3\t0\t0:00:01\n"
)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    out = tmp_path_factory.mktemp("tables")
    run = lambda overrides, name: run_task(compose_cfg(overrides, out), out / "runs" / name)  # noqa: E731
    run([*TINY, "task=train", "task.epochs=1", "task.batch_size=8"], "train")
    run([*TINY, "task=certify", "task.n0=8", "task.n=40", *EVAL], "certify")
    run([*TINY, "task=smooth", "task.n=20", *EVAL], "smooth")
    run([*TINY, "task=attack", "attack.k=5", "task.n=20", *EVAL], "attack5")
    run([*TINY, "task=attack", "attack.k=100", "task.smoothed=false", *EVAL], "attack100")
    log = out / "cohen.tsv"
    log.write_text(COHEN)
    for arch, variant in (("resnet18", "vanilla"), ("resnet50", "augmented")):
        run(
            [
                "task=import",
                f"task.path={log}",
                "task.dataset=metaroom_synth",
                f"task.arch={arch}",
                f"task.variant={variant}",
                "task.profile=quick",
                "motion=tz",
            ],
            f"import-{arch}",
        )
    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    return out


def hand(out: Path, name: str, column: str, value=1) -> float:
    df = read_log(next((out / "runs" / name).glob("*.tsv")), ["idx"])
    return float((df[column] == value).mean())


def test_certified_table_cells_match_hand_computation(store):
    runs = tables.Runs.gather("mrcert", "metaroom_synth", "quick")
    df = tables.certified_table(runs, ("small_cnn", "resnet18", "resnet50"), ("tz", "tx"))
    small = df.loc[("Tz", "Smoothed Vanilla SmallCNN")]
    certify = read_log(store / "runs" / "certify" / "certify.tsv")
    assert small["Certified Acc"] == pytest.approx(((certify.correct == 1) & (certify.radius >= 0.1)).mean())
    assert small["Benign Acc"] == pytest.approx(hand(store, "smooth", "correct"))
    assert small["5-pert Emp. Acc"] == pytest.approx(hand(store, "attack5", "smoothed_robust"))
    assert df.loc[("Tz", "Smoothed Vanilla ResNet-18"), "Certified Acc"] == pytest.approx(0.4)
    assert df.loc[("Tz", "Smoothed Augmented ResNet-50"), "Certified Acc"] == pytest.approx(0.4)
    # Missing runs are empty, never zero.
    assert np.isnan(df.loc[("Tz", "Smoothed Augmented SmallCNN"), "Certified Acc"])
    assert df.loc["Tx"].isna().all().all()


def test_base_vs_smoothed_and_5_vs_100_tables(store):
    runs = tables.Runs.gather("mrcert", "metaroom_synth", "quick")
    t1 = tables.base_vs_smoothed_table(runs, "vanilla", ("small_cnn",), ("tz",), k=100)
    assert list(t1.index) == [("Tz", "Benign Accuracy"), ("Tz", "100-perturbed Emp. Robust Acc.")]
    assert t1.loc[("Tz", "Benign Accuracy"), "SmallCNN Base"] == pytest.approx(hand(store, "attack100", "base_benign"))
    assert t1.loc[("Tz", "Benign Accuracy"), "SmallCNN Smoothed"] == pytest.approx(hand(store, "smooth", "correct"))
    assert t1.loc[("Tz", "100-perturbed Emp. Robust Acc."), "SmallCNN Base"] == pytest.approx(
        hand(store, "attack100", "base_robust")
    )
    assert np.isnan(t1.loc[("Tz", "100-perturbed Emp. Robust Acc."), "SmallCNN Smoothed"])  # smoothed=false run
    t5 = tables.perturbed_5_vs_100_table(runs, ("small_cnn",), ("tz",))
    assert t5.loc[("Tz", "5-perturbed"), "SmallCNN Vanilla"] == pytest.approx(hand(store, "attack5", "smoothed_robust"))
    assert np.isnan(t5.loc[("Tz", "100-perturbed"), "SmallCNN Vanilla"])
    robot = tables.tabletop_table(tables.Runs.gather("mrcert", "tabletop_synth", "quick"))
    assert robot.shape == (2, 7) and robot.isna().all().all()


def test_written_files_keep_empty_cells_empty_and_latex_balanced(store, tmp_path):
    runs = tables.Runs.gather("mrcert", "metaroom_synth", "quick")
    df = tables.certified_table(runs, ("resnet18",), ("tz", "tx"))
    md, tex, csv = tables.write(df, tmp_path / "t3", "Table 3")
    back = pd.read_csv(csv, keep_default_na=False)
    assert back.loc[(back.Axis == "Tx"), "Certified Acc"].tolist() == ["", ""]
    assert "0.000" not in md.read_text() and "0.400" in md.read_text()
    lines = [ln for ln in tex.read_text().splitlines() if ln.endswith(r"\\")]
    columns = len(df.reset_index().columns)
    assert len(lines) == 1 + len(df) and all(ln.count("&") - ln.count(r"\&") == columns - 1 for ln in lines)
    assert tex.read_text().count(r"\begin{tabular}{" + "l" * columns + "}") == 1
    shown = tables.certified_table(runs, ("resnet18",), ("tz",), show_paper=True)
    assert shown.loc[("Tz", "Smoothed Vanilla ResNet-18"), "Certified Acc"] == "0.400 (0.792)"
    assert shown.loc[("Tz", "Smoothed Augmented ResNet-18"), "Certified Acc"] == " (0.817)"


def test_figure_uses_the_exact_step_functions(store, tmp_path):
    runs = tables.Runs.gather("mrcert", "metaroom_synth", "quick")
    data = tables.curves(runs, ("resnet18", "resnet50"), ("tz",))
    radii, acc = data["tz"]["Smoothed Vanilla ResNet-18"]
    assert radii.tolist() == [0.0, 0.05, 0.2, 0.5] and acc.tolist() == pytest.approx([0.6, 0.6, 0.4, 0.2])
    png, pdf = tables.plot_curves(data, tmp_path / "fig")
    assert png.stat().st_size > 10_000 and pdf.read_bytes().startswith(b"%PDF")


def test_sweep_table_from_a_parents_children(store):
    proc = run_cli(
        [
            "-m",
            "task=import",
            f"task.path={store / 'cohen.tsv'}",
            "task.dataset=metaroom_synth",
            "task.profile=quick",
            "motion=tz",
            "motion.sigma=0.05,0.1",
        ],
        store,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    mlflow.set_tracking_uri(f"sqlite:///{store / 'mlflow.db'}")
    (parent,) = mlflow.search_runs(
        search_all_experiments=True, filter_string="tags.`mrcert.multirun` = 'parent'", output_format="list"
    )
    runs = tables.Runs.gather("mrcert", "metaroom_synth", "quick")
    sweep = tables.sweep_table(runs, parent.info.run_id)
    assert list(sweep.index) == [("tz", 0.05), ("tz", 0.1)]
    assert sweep.loc[("tz", 0.1), "r=0.2"] == pytest.approx(0.4) and sweep.loc[("tz", 0.1), "r=0"] == pytest.approx(0.6)


def test_tables_task_writes_every_table_and_the_figure(store):
    result = run_task(
        compose_cfg(["task=tables", "task.archs=[small_cnn,resnet18]", "task.axes=[tz]"], store),
        store / "runs" / "tables",
    )
    out = Path(result["tables"])
    for name in ("table3_certified", "table1_augmented", "appendix_vanilla", "appendix_5_vs_100", "tabletop", "sweep"):
        for suffix in (".md", ".tex", ".csv"):
            assert (out / f"{name}{suffix}").is_file()
    assert (out / "certified_accuracy_vs_radius.png").is_file() and (out / "certified_accuracy_vs_radius.pdf").is_file()
    assert result["table3_certified_filled_cells"] == 4  # SmallCNN vanilla: 3 cells; ResNet-18 vanilla: certified
