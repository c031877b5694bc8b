"""The paper's tables and figure, each cell from the runs of exactly one composed config.

Each table is declared once (:class:`Table`, ``TABLES``): its experiment, the data sets it is
about, and its entries. The jobs of the experiment's sweep (``hydra.sweeper.params`` of
``conf/experiment/<name>.yaml``: its axes, models and variants) each fill every entry: a
measure (task, metric and the overrides that fix it, e.g. ``attack.k=100``) at the row and
column its labels name. A cell is the config
``experiment=<name> profile=<p> task=<task> <sweep values> <measure overrides>``; its
value comes from the runs of that config's cell key (:mod:`mrcert.reporting.cells`) or it stays empty
(NaN, written as an empty string), never zero. Every table is written with the runs that
filled each cell (``<table>_sources.csv``/``.md``: run ids and MLflow links). With
``show_paper`` a cell reads ``ours (paper)``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from mrcert.core.axes import unit
from mrcert.reporting import certify_log, paper_results
from mrcert.reporting.cells import Cell
from mrcert.reporting.experiment_cells import ExperimentCells, Measure
from mrcert.reporting.plots import Curve, curve_figure

ARCH_NAMES = {"resnet18": "ResNet-18", "resnet50": "ResNet-50", "small_cnn": "SmallCNN"}
AXIS_NAMES = {"tz": "Tz", "tx": "Tx", "ty": "Ty", "rz": "Rz", "rx": "Rx", "ry": "Ry"}
AXES_ORDER = paper_results.AXES_ORDER

REPRODUCTION = "reproduce_{profile}"
"""The experiment that fills the MetaRoom tables: one per profile (``conf/experiment/``)."""


SMOOTHED_BENIGN = Measure("smooth", "smoothed_benign_accuracy")
CERTIFIED = Measure("certify", "certified_accuracy")
# Sequential CERTIFY: an extra column beside the paper's fixed-n one, with its mean samples per image.
SEQUENTIAL = Measure("certify", "certified_accuracy", ("task.sequential=true",))
SEQUENTIAL_SAMPLES = Measure("certify", "mean_samples", ("task.sequential=true",))
CERTIFY_SECONDS = Measure("certify", "seconds_per_image")
SEQUENTIAL_SECONDS = Measure("certify", "seconds_per_image", ("task.sequential=true",))


def base_benign(k: int | str) -> Measure:
    return Measure("attack", "base_benign_accuracy", (f"attack.k={k}",))


def robust(who: str, k: int | str) -> Measure:
    return Measure("attack", f"{who}_robust_accuracy", (f"attack.k={k}",))


def arch_name(arch: str) -> str:
    """The paper's name of an architecture (``ARCH_NAMES``), or its config name for any other."""
    return ARCH_NAMES.get(arch, arch)


def model_label(arch: str, variant: str, smoothed: bool = True) -> str:
    return f"{'Smoothed ' if smoothed else ''}{variant.capitalize()} {arch_name(arch)}"


# The paper's values of each measure (who, quantity, K); benign accuracy and certified accuracy have no K.
PAPER = {
    ("base", "benign", None): paper_results.BASE_BENIGN,
    ("smoothed", "benign", None): paper_results.SMOOTHED_BENIGN,
    ("base", "perturbed", 100): paper_results.BASE_PERTURBED_100,
    ("smoothed", "perturbed", 100): paper_results.SMOOTHED_PERTURBED_100,
    ("smoothed", "perturbed", 5): paper_results.SMOOTHED_PERTURBED_5,
    ("smoothed", "certified", None): paper_results.CERTIFIED,
}
PAPER_ARCHS = frozenset(arch for _, arch, _ in paper_results.CERTIFIED)
"""The architectures the paper evaluated."""


def paper_value(who: str, quantity: str, k: int | None, axis: str, arch: str, variant: str) -> float | None:
    """The paper's value of a measure: ``who`` (base or smoothed) ``quantity`` (benign,
    perturbed with ``k`` motions, or certified) of a model on an axis; None when it has none."""
    table = PAPER.get((who, quantity, k if quantity == "perturbed" else None), {})
    return table.get((axis, arch, variant))


def tabletop_paper(who: str, quantity: str, axis: str) -> float | None:
    """The paper's real-robot values: one benign accuracy for both models, 10-perturbed per axis."""
    if quantity == "benign":
        return paper_results.TABLETOP_BENIGN
    return paper_results.TABLETOP_PERTURBED_10.get(axis, (None, None))[("base", "smoothed").index(who)]


@dataclass(frozen=True)
class Job:
    """One job of an experiment's sweep, as a table names it: ``{Axis}``, ``{Arch}``,
    ``{Model}`` (the smoothed model), ``{Base}`` (the model itself), ``{Variant}``, ``{k}`` (the
    job's own attack.k) in the entries' labels; ``theirs``: the architecture whose paper values
    the row is compared with."""

    axis: str
    arch: str
    variant: str
    k: int
    theirs: str

    @classmethod
    def of(cls, cell: Cell, paper_arch: str | None) -> Job:
        cfg = cell.cfg
        arch, variant = str(cfg.model.arch), str(cfg.model.variant)
        theirs = arch if arch in PAPER_ARCHS else paper_arch or arch
        return cls(str(cfg.motion.axis), arch, variant, int(cfg.attack.k), theirs)

    def labels(self) -> dict[str, object]:
        return {
            "Axis": AXIS_NAMES.get(self.axis, self.axis),
            "Arch": arch_name(self.arch),
            "Model": model_label(self.arch, self.variant),
            "Base": model_label(self.arch, self.variant, smoothed=False),
            "Variant": self.variant.capitalize(),
            "k": self.k,
        }


@dataclass(frozen=True)
class Entry:
    """One number per job: ``measure`` (its overrides may name ``{k}``) at the row and column
    whose labels the templates give; ``paper(job)``: the paper's value beside it, or ``fmt``:
    how to print a column the paper does not have. Entries of several jobs at the same row and
    column are one cell: the mean of their runs (e.g. a benign accuracy over the axes)."""

    row: tuple[str, ...]
    column: str
    measure: Measure
    paper: Callable[[Job], float | None] | None = None
    fmt: str | None = None


@dataclass(frozen=True)
class Table:
    """One of the paper's tables, declared once: its file name, caption, the experiment whose
    runs fill it (``{profile}`` filled in), the data sets it is about (a cell never shows a run of
    another; None: any), the names of its row labels, the jobs it shows (``where``) and the
    entries each job fills. The sigma sweep, whose columns are radii of the certify logs, has
    its own ``custom`` builder instead of entries."""

    name: str
    caption: str
    experiment: str
    data: tuple[str, ...] | None
    index: tuple[str, ...] = ()
    entries: tuple[Entry, ...] = ()
    where: Callable[[Job], bool] = lambda job: True
    custom: Callable[[ExperimentCells, str], pd.DataFrame] | None = None

    def about(self, data: str | None) -> bool:
        """Whether the table is about the data set ``data`` (None: its experiment cannot be
        composed on the data set asked for, so it is about none)."""
        return data is not None and (self.data is None or data in self.data)

    def build(
        self, src: ExperimentCells, show_paper: bool = False, name: str | None = None, paper_arch: str | None = None
    ) -> pd.DataFrame:
        """The table from ``src``'s runs; with ``show_paper`` each cell reads ``ours (paper)``,
        the paper's value of the row's own architecture or, for one the paper did not evaluate
        (the small CNN), of ``paper_arch`` when given. ``name``: the provenance's table name."""
        name = name or self.name
        if self.custom is not None:
            return self.custom(src, name)
        experiment = src.experiment_for(self.experiment)
        cells: dict[tuple, dict[str, tuple[list[Cell], Entry, Job]]] = {}
        for combo, first in src.rows(experiment, SMOOTHED_BENIGN):
            job = Job.of(first, paper_arch)
            if not self.where(job):
                continue
            labels = job.labels()
            for entry in self.entries:
                row = tuple(t.format(**labels) for t in entry.row)
                measure = Measure(
                    entry.measure.task, entry.measure.metric, tuple(o.format(**labels) for o in entry.measure.overrides)
                )
                at = cells.setdefault(row, {}).setdefault(entry.column.format(**labels), ([], entry, job))
                at[0].append(src.cell(experiment, combo, measure))
        rows = {}
        for row, columns in cells.items():
            rows[row] = {}
            for column, (group, entry, job) in columns.items():
                value = src.value(name, row, column, group, entry.measure.metric)
                if entry.fmt is not None:  # a column the paper does not have
                    rows[row][column] = value if not show_paper or np.isnan(value) else format(value, entry.fmt)
                else:
                    rows[row][column] = _cell(value, entry.paper(job) if entry.paper else None, show_paper)
        return _frame(rows, list(self.index)) if rows else pd.DataFrame()


def _paper(who: str, quantity: str, k: int | None = None) -> Callable[[Job], float | None]:
    """The paper's value of a measure for a job (``k=None``: the job's own attack.k)."""
    return lambda job: paper_value(who, quantity, job.k if k is None else k, job.axis, job.theirs, job.variant)


TABLE3_ENTRIES = (
    Entry(("{Axis}", "{Model}"), "Benign Acc", SMOOTHED_BENIGN, _paper("smoothed", "benign")),
    Entry(("{Axis}", "{Model}"), "{k}-pert Emp. Acc", robust("smoothed", "{k}"), _paper("smoothed", "perturbed")),
    Entry(("{Axis}", "{Model}"), "Certified Acc", CERTIFIED, _paper("smoothed", "certified")),
)


def _base_vs_smoothed(variant: str, k: int) -> dict:
    """Table 1 (augmented) / its appendix twin (vanilla): benign and K-perturbed, base vs smoothed."""
    benign, perturbed = ("{Axis}", "Benign Accuracy"), ("{Axis}", f"{k}-perturbed Emp. Robust Acc.")
    return {
        "index": ("Axis", "Metric"),
        "where": lambda job: job.variant == variant,
        "entries": (
            Entry(benign, "{Arch} Base", base_benign(k), _paper("base", "benign")),
            Entry(benign, "{Arch} Smoothed", SMOOTHED_BENIGN, _paper("smoothed", "benign")),
            Entry(perturbed, "{Arch} Base", robust("base", k), _paper("base", "perturbed", k)),
            Entry(perturbed, "{Arch} Smoothed", robust("smoothed", k), _paper("smoothed", "perturbed", k)),
        ),
    }


def _tabletop(who: str, benign: Measure) -> tuple[Entry, ...]:
    """One row of the real-robot table: benign accuracy (the paper reports one, for both
    models; ours is the mean over the model's axes) and the 10-perturbed accuracy per axis."""
    row = (who.capitalize(), "{Base}")
    return (
        Entry(row, "Benign Accuracy", benign, lambda job: tabletop_paper(who, "benign", job.axis)),
        Entry(row, "{Axis}", robust(who, "{k}"), lambda job: tabletop_paper(who, "perturbed", job.axis)),
    )


def sweep_table(src: ExperimentCells, name: str = "sweep") -> pd.DataFrame:
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


METAROOM = ("metaroom_synth", "metaroom")  # the synthetic room and the released one
TABLE3 = Table(
    "table3_certified",
    "Benign, K-perturbed empirical robust and certified accuracy of the smoothed models",
    REPRODUCTION,
    METAROOM,
    ("Axis", "Model"),
    TABLE3_ENTRIES,
)
TABLE3_SEQUENTIAL = dataclasses.replace(
    TABLE3,
    entries=TABLE3_ENTRIES
    + tuple(  # the evidence page's columns the paper does not have, each with its printed format
        Entry(("{Axis}", "{Model}"), label, measure, fmt=fmt)
        for label, measure, fmt in (
            ("Certified Acc, sequential", SEQUENTIAL, ".3f"),
            ("samples per image, sequential", SEQUENTIAL_SAMPLES, ".1f"),
            ("s per image", CERTIFY_SECONDS, ".2f"),
            ("s per image, sequential", SEQUENTIAL_SECONDS, ".2f"),
        )
    ),
)
SWEEP = Table(
    "sweep",
    "Certified accuracy against smoothing sigma and radius",
    "sweep",
    None,
    custom=lambda src, name: sweep_table(src, name),
)
TABLES = (
    TABLE3,
    Table(
        "table1_augmented",
        "Base vs smoothed motion-augmented models: benign and 100-perturbed accuracy",
        REPRODUCTION,
        METAROOM,
        **_base_vs_smoothed("augmented", 100),
    ),
    Table(
        "appendix_vanilla",
        "Base vs smoothed vanilla models: benign and 100-perturbed accuracy",
        REPRODUCTION,
        METAROOM,
        **_base_vs_smoothed("vanilla", 100),
    ),
    Table(
        "appendix_5_vs_100",
        "Smoothed models: 5- vs 100-perturbed empirical robust accuracy",
        REPRODUCTION,
        METAROOM,
        ("Axis", "Metric"),
        tuple(
            Entry(
                ("{Axis}", f"{k}-perturbed"),
                "{Arch} {Variant}",
                robust("smoothed", k),
                _paper("smoothed", "perturbed", k),
            )
            for k in (5, 100)
        ),
    ),
    Table(
        "tabletop",
        "Tabletop: benign and 10-perturbed accuracy, base vs smoothed",
        "tabletop",
        ("tabletop_synth",),
        ("Who", "Model"),
        _tabletop("base", base_benign("{k}")) + _tabletop("smoothed", SMOOTHED_BENIGN),
    ),
    SWEEP,
)


def tables_for(src: ExperimentCells) -> list[Table]:
    """The tables whose cells ``src`` composes on a data set they are about: every table of the
    paper when each reads its own experiment, only those about ``task.experiment``'s data set
    when one experiment fills them all (``make demo``'s MetaRoom fills no tabletop table)."""
    return [t for t in TABLES if t.about(src.data_of(t.experiment))]


def curves_figure(data: dict[str, dict[str, Curve]], units: dict[str, str]):
    """The figure: one panel per axis (the paper's order), one curve per model; ``units``: each
    panel's radius unit, as its certify runs' method states it (an axis with no run: its own)."""
    order = [a for a in AXES_ORDER if a in data] + [a for a in data if a not in AXES_ORDER]
    panels = {AXIS_NAMES.get(a, a): data[a] for a in order} or {AXIS_NAMES[a]: {} for a in AXES_ORDER}
    units = {AXIS_NAMES.get(a, a): f"radius ({units.get(a) or unit(a)})" for a in [*order, *AXES_ORDER]}
    title = "Certified accuracy against radius" + ("" if data else " (no certify runs)")
    return curve_figure(panels, title, units)


def curves(src: ExperimentCells) -> tuple[dict[str, dict[str, Curve]], dict[str, str]]:
    """Per axis, per model: the exact step function (radii, certified accuracy) of its certify
    cell; and per axis, the unit of those radii (the method's region unit)."""
    out: dict[str, dict[str, Curve]] = {}
    units: dict[str, str] = {}
    for _, cell in src.rows(src.experiment_for(REPRODUCTION), CERTIFIED):
        log = src.index.log(cell)
        if log is not None:
            label = model_label(str(cell.cfg.model.arch), str(cell.cfg.model.variant))
            axis = str(cell.cfg.motion.axis)
            out.setdefault(axis, {})[label] = certify_log.curve(log)
            units[axis] = str(log["radius_unit"].iloc[0]) if "radius_unit" in log and len(log) else unit(axis)
    return out, units


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
