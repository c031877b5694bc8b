"""The paper's tables and figure, each cell from the runs of exactly one composed config.

A table's rows come from an experiment config's sweep (``hydra.sweeper.params`` of
``conf/experiment/<name>.yaml``: its axes, models and variants), its columns from measures
(task, metric and the overrides that fix the measure, e.g. ``attack.k=5``). A cell is the
config ``experiment=<name> profile=<p> task=<task> <sweep values> <measure overrides>``; its
value comes from the runs of that config's cell key (:mod:`mrcert.reporting.cells`) or it stays empty
(NaN, written as an empty string), never zero. Every table is written with the runs that
filled each cell (``<table>_sources.csv``/``.md``: run ids and MLflow links). With
``show_paper`` a cell reads ``ours (paper)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from mrcert.core.geometry import AXES, unit
from mrcert.reporting import certify_log, paper_results
from mrcert.reporting.cells import Cell
from mrcert.reporting.plots import Curve, curve_figure
from mrcert.reporting.source import Measure, Source

ARCH_NAMES = {"resnet18": "ResNet-18", "resnet50": "ResNet-50", "small_cnn": "SmallCNN"}
AXIS_NAMES = {"tz": "Tz", "tx": "Tx", "ty": "Ty", "rz": "Rz", "rx": "Rx", "ry": "Ry"}
AXES_ORDER = paper_results.AXES_ORDER


SMOOTHED_BENIGN = Measure("smooth", "smoothed_benign_accuracy")
CERTIFIED = Measure("certify", "certified_accuracy")
# Sequential CERTIFY: an extra column beside the paper's fixed-n one, with its mean samples per image.
SEQUENTIAL = Measure("certify", "certified_accuracy", ("task.sequential=true",))
SEQUENTIAL_SAMPLES = Measure("certify", "mean_samples", ("task.sequential=true",))
CERTIFY_SECONDS = Measure("certify", "seconds_per_image")
SEQUENTIAL_SECONDS = Measure("certify", "seconds_per_image", ("task.sequential=true",))


def base_benign(k: int) -> Measure:
    return Measure("attack", "base_benign_accuracy", (f"attack.k={k}",))


def robust(who: str, k: int) -> Measure:
    return Measure("attack", f"{who}_robust_accuracy", (f"attack.k={k}",))


def arch_name(arch: str) -> str:
    """The paper's name of an architecture (``ARCH_NAMES``), or its config name for any other."""
    return ARCH_NAMES.get(arch, arch)


def model_label(arch: str, variant: str, smoothed: bool = True) -> str:
    return f"{'Smoothed ' if smoothed else ''}{variant.capitalize()} {arch_name(arch)}"


# The paper's values of each measure (who, quantity, K); benign accuracy has no K.
PAPER = {
    ("base", "benign", None): paper_results.BASE_BENIGN,
    ("smoothed", "benign", None): paper_results.SMOOTHED_BENIGN,
    ("base", "perturbed", 100): paper_results.BASE_PERTURBED_100,
    ("smoothed", "perturbed", 100): paper_results.SMOOTHED_PERTURBED_100,
    ("smoothed", "perturbed", 5): paper_results.SMOOTHED_PERTURBED_5,
}


def paper_value(who: str, quantity: str, k: int | None, axis: str, arch: str, variant: str) -> float | None:
    table = PAPER.get((who, quantity, None if quantity == "benign" else k), {})
    return table.get((axis, arch, variant))


def _axis(cell: Cell) -> str:
    return str(cell.cfg.motion.axis)


def certified_table(
    src: Source,
    show_paper: bool = False,
    name: str = "table3_certified",
    sequential: bool = False,
    paper_arch: str | None = None,
) -> pd.DataFrame:
    """Table 3: benign, 5-perturbed and certified accuracy (fixed-n CERTIFY, the paper's) of the
    smoothed models; with ``sequential``, sequential CERTIFY's certified accuracy and mean samples
    per image as extra columns, and both procedures' seconds per image. With ``show_paper`` a
    cell shows the paper's value of the same axis and variant for ``paper_arch`` (default: the
    row's own architecture; an architecture the paper did not evaluate, e.g. the small CNN, is
    compared with one it did only when asked)."""
    exp = src.experiment_for("table3")
    jobs = list(src.rows(exp, SMOOTHED_BENIGN))
    k = int(jobs[0][1].cfg.attack.k) if jobs else 5  # the experiment's attack: the paper's Table 3 has K = 5
    columns = (
        ("Benign Acc", SMOOTHED_BENIGN, ("smoothed", "benign", None)),
        (f"{k}-pert Emp. Acc", robust("smoothed", k), ("smoothed", "perturbed", k)),
        ("Certified Acc", CERTIFIED, ("certified",)),
    ) + (
        (  # columns the paper does not have, each with its printed format
            ("Certified Acc, sequential", SEQUENTIAL, ".3f"),
            ("samples per image, sequential", SEQUENTIAL_SAMPLES, ".1f"),
            ("s per image", CERTIFY_SECONDS, ".2f"),
            ("s per image, sequential", SEQUENTIAL_SECONDS, ".2f"),
        )
        if sequential
        else ()
    )
    rows = {}
    for combo, first in jobs:
        ax, a, v = _axis(first), first.cfg.model.arch, first.cfg.model.variant
        key = (AXIS_NAMES.get(ax, ax), model_label(a, v))
        theirs = paper_arch or a
        rows[key] = {}
        for label, measure, paper in columns:
            value = src.value(name, key, label, [src.cell(exp, combo, measure)], measure.metric)
            if isinstance(paper, str):  # a column the paper does not have: ``paper`` is its format
                rows[key][label] = value if not show_paper or np.isnan(value) else format(value, paper)
                continue
            reported = (
                paper_results.CERTIFIED.get((ax, theirs, v))
                if paper == ("certified",)
                else paper_value(*paper, ax, theirs, v)
            )
            rows[key][label] = _cell(value, reported, show_paper)
    return _frame(rows, ["Axis", "Model"])


def base_vs_smoothed_table(
    src: Source, variant: str, k: int = 100, show_paper: bool = False, name: str = "table1_augmented"
) -> pd.DataFrame:
    """Table 1 (augmented) / its appendix twin (vanilla): benign and K-perturbed, base vs smoothed."""
    exp = src.experiment_for("table1")
    measures = {
        ("benign", "base"): base_benign(k),
        ("benign", "smoothed"): SMOOTHED_BENIGN,
        ("perturbed", "base"): robust("base", k),
        ("perturbed", "smoothed"): robust("smoothed", k),
    }
    labels = {"benign": "Benign Accuracy", "perturbed": f"{k}-perturbed Emp. Robust Acc."}
    rows: dict = {}
    for combo, first in src.rows(exp, SMOOTHED_BENIGN):
        if first.cfg.model.variant != variant:
            continue
        ax, a = _axis(first), first.cfg.model.arch
        for quantity in ("benign", "perturbed"):
            key = (AXIS_NAMES.get(ax, ax), labels[quantity])
            for who in ("base", "smoothed"):
                column = f"{arch_name(a)} {who.capitalize()}"
                measure = measures[(quantity, who)]
                value = src.value(name, key, column, [src.cell(exp, combo, measure)], measure.metric)
                reported = paper_value(who, quantity, None if quantity == "benign" else k, ax, a, variant)
                rows.setdefault(key, {})[column] = _cell(value, reported, show_paper)
    return _frame(rows, ["Axis", "Metric"])


def perturbed_5_vs_100_table(src: Source, show_paper: bool = False, name: str = "appendix_5_vs_100") -> pd.DataFrame:
    """Appendix: smoothed 5- vs 100-perturbed empirical robust accuracy (K=5 cells from the
    Table 3 experiment, K=100 cells from the Table 1 experiment)."""
    rows: dict = {}
    for k, own in ((5, "table3"), (100, "table1")):
        exp = src.experiment_for(own)
        measure = robust("smoothed", k)
        for combo, first in src.rows(exp, SMOOTHED_BENIGN):
            ax, a, v = _axis(first), first.cfg.model.arch, first.cfg.model.variant
            key = (AXIS_NAMES.get(ax, ax), f"{k}-perturbed")
            column = f"{arch_name(a)} {v.capitalize()}"
            value = src.value(name, key, column, [src.cell(exp, combo, measure)], measure.metric)
            rows.setdefault(key, {})[column] = _cell(
                value, paper_value("smoothed", "perturbed", k, ax, a, v), show_paper
            )
    order = sorted(rows, key=lambda r: list(AXIS_NAMES.values()).index(r[0]) if r[0] in AXIS_NAMES.values() else 99)
    return _frame({r: rows[r] for r in order}, ["Axis", "Metric"])


def tabletop_table(src: Source, k: int = 10, show_paper: bool = False, name: str = "tabletop") -> pd.DataFrame:
    """The real-robot table: benign and K-perturbed accuracy, base vs smoothed, per axis; one
    pair of rows per model of the experiment.

    The paper reports one benign accuracy for both; ours is the mean over the model's axes."""
    exp = src.experiment_for("tabletop")
    by_model: dict[str, list] = {}
    for combo, first in src.rows(exp, SMOOTHED_BENIGN):
        model = model_label(str(first.cfg.model.arch), str(first.cfg.model.variant), smoothed=False)
        by_model.setdefault(model, []).append((combo, first))
    data = {}
    for model, jobs in by_model.items():
        for idx, who in enumerate(("base", "smoothed")):
            benign = base_benign(k) if who == "base" else SMOOTHED_BENIGN
            label = (who.capitalize(), model)
            cells = [src.cell(exp, combo, benign) for combo, _ in jobs]
            row = {
                "Benign Accuracy": _cell(
                    src.value(name, label, "Benign Accuracy", cells, benign.metric),
                    paper_results.TABLETOP_BENIGN,
                    show_paper,
                )
            }
            for combo, first in jobs:
                ax = _axis(first)
                measure = robust(who, k)
                value = src.value(name, label, AXIS_NAMES.get(ax, ax), [src.cell(exp, combo, measure)], measure.metric)
                reported = paper_results.TABLETOP_PERTURBED_10.get(ax, (None, None))[idx]
                row[AXIS_NAMES.get(ax, ax)] = _cell(value, reported, show_paper)
            data[label] = row
    return _frame(data, ["Who", "Model"]) if data else pd.DataFrame()


def sweep_table(src: Source, name: str = "sweep") -> pd.DataFrame:
    """Certified accuracy against sigma (rows) and radius (columns, each axis's grid
    ``k * radius_step``): from the sweep experiment's certify cells, or, with the source's
    ``parent`` (a sweep's parent run id), from that sweep's children."""
    if src.parent:
        cells = src.index.children(src.parent)
    else:
        exp = src.experiment_for("sweep")
        cells = [cell for _, cell in src.rows(exp, CERTIFIED)]
    rows = []
    for cell in cells:
        log = src.index.log(cell)
        cfg = cell.cfg
        sigma = float(cfg.task.sigma if cfg.task.name == "import" else cfg.motion.sigma)
        step = float(cfg.task.radius_step if cfg.task.name == "import" else cfg.motion.radius_step)
        model = model_label(str(cfg.model.arch), str(cfg.model.variant), smoothed=False)
        key = (str(cfg.motion.axis), sigma, model)
        src.value(name, key, "all radii", [cell], "certified_accuracy")
        if log is None:
            continue
        grid = certify_log.radius_grid(step, 4 * sigma)
        for r in grid[:: max(1, len(grid) // 8)]:
            rows.append(
                {
                    "Axis": key[0],
                    "sigma": sigma,
                    "Model": model,
                    "radius": float(r),
                    "Certified Acc": certify_log.certified_accuracy(log, float(r)),
                }
            )
    if not rows:
        return pd.DataFrame()
    wide = pd.DataFrame(rows).pivot_table(index=["Axis", "sigma", "Model"], columns="radius", values="Certified Acc")
    wide.columns = [f"r={c:.4g}" for c in wide.columns]
    return wide


@dataclass(frozen=True)
class Table:
    """One of the paper's tables, declared once: its file name, caption, the experiment whose
    runs fill it by default, the data sets it is about (a cell never shows a run of another),
    and how it is built from a :class:`Source` (``show_paper``: the paper's values beside ours)."""

    name: str
    caption: str
    experiment: str
    data: tuple[str, ...] | None  # None: any data set (the sigma sweep)
    build: Callable[[Source, bool], pd.DataFrame]

    def about(self, data: str) -> bool:
        return self.data is None or data in self.data


METAROOM = ("metaroom_synth", "metaroom")  # the synthetic room and the released one
TABLES = (
    Table(
        "table3_certified",
        "Benign, K-perturbed empirical robust and certified accuracy of the smoothed models",
        "table3",
        METAROOM,
        lambda src, paper: certified_table(src, paper),
    ),
    Table(
        "table1_augmented",
        "Base vs smoothed motion-augmented models: benign and 100-perturbed accuracy",
        "table1",
        METAROOM,
        lambda src, paper: base_vs_smoothed_table(src, "augmented", 100, paper),
    ),
    Table(
        "appendix_vanilla",
        "Base vs smoothed vanilla models: benign and 100-perturbed accuracy",
        "table1",
        METAROOM,
        lambda src, paper: base_vs_smoothed_table(src, "vanilla", 100, paper, name="appendix_vanilla"),
    ),
    Table(
        "appendix_5_vs_100",
        "Smoothed models: 5- vs 100-perturbed empirical robust accuracy",
        "table3",
        METAROOM,
        lambda src, paper: perturbed_5_vs_100_table(src, paper),
    ),
    Table(
        "tabletop",
        "Tabletop: benign and 10-perturbed accuracy, base vs smoothed",
        "tabletop",
        ("tabletop_synth",),
        lambda src, paper: tabletop_table(src, 10, paper),
    ),
    Table(
        "sweep",
        "Certified accuracy against smoothing sigma and radius",
        "sweep",
        None,
        lambda src, paper: sweep_table(src),
    ),
)


def tables_for(src: Source) -> list[Table]:
    """The tables whose cells ``src`` composes on a data set they are about: every table of the
    paper when each reads its own experiment, only those about ``task.experiment``'s data set
    when one experiment fills them all (``make demo``'s MetaRoom fills no tabletop table)."""
    return [t for t in TABLES if t.about(src.data_of(t.experiment))]


def curves_figure(data: dict[str, dict[str, Curve]]):
    """The figure: one panel per axis (the paper's order), one curve per model."""
    order = [a for a in AXES_ORDER if a in data] + [a for a in data if a not in AXES_ORDER]
    panels = {AXIS_NAMES.get(a, a): data[a] for a in order} or {AXIS_NAMES[a]: {} for a in AXES_ORDER}
    # One axis: metres or radians; several axes (Theorem 1's combinations): radii in sigmas.
    units = {AXIS_NAMES.get(a, a): f"radius ({unit(a) if a in AXES else 'sigmas'})" for a in [*order, *AXES_ORDER]}
    title = "Certified accuracy against radius" + ("" if data else " (no certify runs)")
    return curve_figure(panels, title, units)


def curves(src: Source) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Per axis, per model: the exact step function (radii, certified accuracy) of its certify cell."""
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for _, cell in src.rows(src.experiment_for("table3"), CERTIFIED):
        log = src.index.log(cell)
        if log is not None:
            label = model_label(str(cell.cfg.model.arch), str(cell.cfg.model.variant))
            out.setdefault(_axis(cell), {})[label] = certify_log.curve(log)
    return out


def _cell(value: float, paper: float | None, show_paper: bool):
    if not show_paper:
        return value
    ours = "" if np.isnan(value) else f"{value:.3f}"
    return ours if paper is None else f"{ours} ({paper:.3f})"


def _frame(rows: dict[tuple[str, str], dict], index_names: list[str]) -> pd.DataFrame:
    """Rows keyed by (level 0, level 1), in insertion order, as a two-level indexed frame."""
    df = pd.DataFrame.from_dict(rows, orient="index")
    df.index = pd.MultiIndex.from_tuples(df.index, names=index_names)
    return df
