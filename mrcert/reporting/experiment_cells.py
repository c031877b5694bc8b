"""Where tables take their cells from: an experiment's jobs (the sweep of its config), the
measure a column shows (a task's metric with the overrides that define it), and the record of
which runs filled each cell. Generic: the paper's tables (:mod:`mrcert.reporting.paper_tables`), the
evidence page and its sections all read their cells through a :class:`ExperimentCells`.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException

from mrcert.reporting.cells import Cell, RunIndex, compose_config


@dataclass(frozen=True)
class Measure:
    """What a column shows: a metric of a task's runs, with the overrides that define it."""

    task: str
    metric: str
    overrides: tuple[str, ...] = ()


@functools.cache
def sweep_combos(experiment: str) -> list[tuple[str, ...]]:
    """Every job of an experiment's sweep as its overrides, in the sweeper's order."""
    params = compose_config([f"experiment={experiment}"]).hydra.sweeper.params or {}
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()])
    axes = [
        [f"{o.key_or_group}={v}" for v in o.sweep_string_iterator()]
        if o.is_sweep_override()
        else [f"{o.key_or_group}={o.get_value_element_as_str()}"]
        for o in parsed
    ]
    return list(itertools.product(*axes))


SOURCE_COLUMNS = ["table", "row", "column", "value", "runs", "model runs", "links", "note"]
"""What :meth:`ExperimentCells.record` keeps of each cell, in the sources files' order."""


@dataclass
class ExperimentCells:
    """Where the tables take their cells from, and the record of which runs filled them.

    ``experiment``: build every table from this experiment (e.g. ``demo``) instead of each
    table's own; ``overrides``: extra overrides for every cell (e.g. ``seed=1`` when the
    experiment ran with it); ``archs`` / ``axes``: only these rows; ``certify_task``:
    ``import`` to take certification cells from imported logs instead of certify runs."""

    index: RunIndex
    profile: str
    experiment: str | None = None
    overrides: tuple[str, ...] = ()
    archs: tuple[str, ...] | None = None
    axes: tuple[str, ...] | None = None
    certify_task: str = "certify"
    link: str = "{run_id}"
    parent: str | None = None  # the sweep table from one sweep's children (a parent run id)
    provenance: list[dict] = field(default_factory=list)
    read: dict[tuple[str, str], dict[tuple[str, ...], Cell]] = field(default_factory=dict)
    """Every filled cell read so far, each once, by stage: ``(experiment, task)``, the task with
    the overrides of the measure that read it first (``attack (attack.k=100)``). Once the
    tables are built, these are the runs behind them, stage by stage as their experiments ran."""

    def experiment_for(self, own: str) -> str:
        """``experiment`` when set, else ``own`` with its ``{profile}`` filled in."""
        return self.experiment or own.format(profile=self.profile)

    def data_of(self, own: str) -> str | None:
        """The data set the cells of a table whose own experiment is ``own`` are composed on
        (None when that experiment cannot be composed with these overrides: ``data=metaroom``
        given for the released data set, which has none of a synthetic experiment's settings)."""
        cell = (f"experiment={self.experiment_for(own)}", f"profile={self.profile}", "task=certify", *self.overrides)
        try:
            return str(compose_config(cell).data.name)
        except HydraException:
            return None

    def task(self, measure: Measure) -> str:
        """The task whose runs fill ``measure``'s cells (``certify_task`` for certification)."""
        return self.certify_task if measure.task == "certify" else measure.task

    def stage(self, measure: Measure) -> str:
        """The stage whose runs fill ``measure``'s cells: its task, with the overrides that tell
        its runs apart (``attack (attack.k=100)``)."""
        task = self.task(measure)
        return f"{task} ({', '.join(measure.overrides)})" if measure.overrides else task

    def cell(self, experiment: str, combo: tuple[str, ...], measure: Measure) -> Cell:
        task = self.task(measure)
        fixed = {o.split("=", 1)[0] for o in (*measure.overrides, *self.overrides)}
        combo = tuple(c for c in combo if c.split("=", 1)[0] not in fixed)
        cell = self.index.cell(
            (f"experiment={experiment}", f"profile={self.profile}", f"task={task}", *combo, *measure.overrides)
            + self.overrides
        )
        ids = tuple(cell.run_ids)
        if ids and not any(ids in cells for cells in self.read.values()):
            self.read.setdefault((experiment, self.stage(measure)), {})[ids] = cell
        return cell

    def rows(self, experiment: str, measure: Measure):
        """``(combo, cell)`` of the experiment's jobs for ``measure``, filtered by arch and axis."""
        for combo in sweep_combos(experiment):
            cell = self.cell(experiment, combo, measure)
            if self.archs and cell.cfg.model.arch not in self.archs:
                continue
            if self.axes and cell.cfg.motion.axis not in self.axes:
                continue
            yield combo, cell

    def value(self, table: str, row, column: str, cells: list[Cell], metric: str) -> float:
        """The metric of ``cells`` (their mean when several), recorded with the runs behind it."""
        values = [self.index.metric(c, metric) for c in cells]
        ok = [v for v in values if not np.isnan(v)]
        value = float(np.mean(ok)) if ok and len(ok) == len(values) else float("nan")
        note = "; ".join(sorted({c.note for c in cells if c.note}))
        runs = [rid for c in cells for rid in c.run_ids]
        return self.record(table, row, column, value, runs, [c.train_run for c in cells if c.train_run], note)

    def record(self, table: str, row, column: str, value, runs, models=(), note: str = ""):
        """Record that ``runs`` are behind the cell ``(table, row, column)`` showing ``value``,
        with ``models``, the train runs in this store of the models they evaluated (a section of
        the page that reads runs itself records its cells here); returns ``value``."""
        self.provenance.append(
            {
                "table": table,
                "row": " / ".join(map(str, row)) if isinstance(row, tuple) else str(row),
                "column": column,
                "value": value,
                "runs": " ".join(runs),
                "links": " ".join(self.link.format(run_id=r) for r in runs),
                "model runs": " ".join(dict.fromkeys(models)),
                "note": note,
            }
        )
        return value

    def cited_runs(self) -> list[str]:
        """Every run behind a recorded cell and every train run of the models they evaluated,
        each once, in order of first mention."""
        return list(dict.fromkeys(r for p in self.provenance for r in f"{p['runs']} {p['model runs']}".split()))

    def sources(self, table: str) -> pd.DataFrame:
        """Per cell of ``table``: row, column, value, the runs behind it, their links, why it is empty."""
        rows = [{k: v for k, v in p.items() if k != "table"} for p in self.provenance if p["table"] == table]
        return pd.DataFrame(rows, columns=SOURCE_COLUMNS[1:])
