"""Table cells: each cell is a composed config, and its value comes from exactly the runs of
that config's cell key (:mod:`mrcert.infra.identity`), or from none.

:class:`RunIndex` holds the FINISHED runs of the store (one MLflow query). A composed config is
resolved as a launch resolves it (:func:`mrcert.infra.resolver.resolve`: the model is the
FINISHED train run of the derived train key, named in the key by content), and the cell keeps
the runs that make one complete result: one run, or every shard ``0..N-1`` of one sharded job.
Runs with other settings (a ``task.max=2`` smoke run, another alpha, another model) have other
keys and are never mixed in; an incomplete sharded job leaves the cell empty and says which
shards are missing. The cell's metrics are recomputed from its (merged) per-image logs by the
task's own :meth:`~mrcert.infra.tasks.Task.summarize`.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

from mrcert.core.methods import build_method
from mrcert.errors import MrcertError
from mrcert.infra import seals
from mrcert.infra.config import CONF_DIR
from mrcert.infra.experiment import artifact, read_run_config, run_file
from mrcert.infra.resolver import resolve
from mrcert.infra.run_store import CELL_COLUMN, KEY_COLUMN, finished_table, newest_train_run_in
from mrcert.infra.schema import SCHEMAS
from mrcert.infra.tasks import TASKS
from mrcert.reporting import certify_log

KEY, CELL = KEY_COLUMN, CELL_COLUMN


def compose_config(overrides: Iterable[str]) -> DictConfig:
    """The config that ``mrcert OVERRIDES`` would run (with its ``hydra`` node); a copy of the
    one composed the first time, since the tables compose the same cells over and over. An
    override of a ``task.*`` key that the cell's task does not have (``task.n`` given for every
    cell of a table, composed for a train run) applies only to the tasks that have it."""
    return copy.deepcopy(_composed(own_task_keys(tuple(overrides))))


def own_task_keys(overrides: tuple[str, ...]) -> tuple[str, ...]:
    """``overrides`` without the ``task.<key>=...`` ones whose key the named task's schema lacks."""
    names = [o.split("=", 1)[1] for o in overrides if o.startswith("task=")]
    schema = SCHEMAS["task"].get(names[-1]) if names else None
    if schema is None:
        return overrides
    keys = {f.name for f in dataclasses.fields(schema)}
    return tuple(o for o in overrides if not o.startswith("task.") or o[5:].split("=", 1)[0].split(".")[0] in keys)


@functools.cache
def _composed(overrides: tuple[str, ...]) -> DictConfig:
    if GlobalHydra.instance().is_initialized():  # inside a launch
        return compose("config", overrides=list(overrides), return_hydra_config=True)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=True)


@dataclass
class Cell:
    """A composed config and the runs that hold its result (empty with a ``note`` when none do)."""

    cfg: DictConfig
    runs: list[pd.Series] = field(default_factory=list)
    note: str = ""
    train_run: str | None = None
    """The train run in this store of the model its config evaluates (None for a task that
    evaluates none, or a model given as a file)."""

    @property
    def filled(self) -> bool:
        return bool(self.runs)

    @property
    def run_ids(self) -> list[str]:
        return [str(r["run_id"]) for r in self.runs]


def _shards(run: pd.Series) -> tuple[int, int]:
    """``(shard, num_shards)`` of a run (``(0, 1)`` when it was not sharded)."""
    num = pd.to_numeric(run.get("params.task.num_shards"), errors="coerce")
    shard = pd.to_numeric(run.get("params.task.shard"), errors="coerce")
    return (0, 1) if pd.isna(num) else (int(shard), int(num))


def complete(runs: pd.DataFrame) -> tuple[list[pd.Series], str]:
    """The runs (of one cell key, newest first) that make one complete result, or a note why none do.

    Identical run keys are the same computation: the newest counts. One unsharded run is a
    result; two with different run keys (two imported logs for one cell) are ambiguous. Else
    the newest sharded job whose shards ``0..N-1`` all finished is the result."""
    if not len(runs):
        return [], "no finished run"
    newest = runs.drop_duplicates(KEY)
    whole = [r for _, r in newest.iterrows() if _shards(r)[1] == 1]
    if len(whole) == 1:
        return whole, ""
    if len(whole) > 1:
        ids = ", ".join(str(r["run_id"]) for r in whole)
        return [], f"ambiguous: {len(whole)} different finished runs ({ids})"
    notes = []
    by_size: dict[int, dict[int, pd.Series]] = {}
    for _, r in newest.iterrows():
        shard, num = _shards(r)
        by_size.setdefault(num, {}).setdefault(shard, r)
    for num, shards in by_size.items():
        if set(shards) == set(range(num)):
            return [shards[i] for i in range(num)], ""
        missing = sorted(set(range(num)) - set(shards))
        notes.append(f"shards {missing} of task.num_shards={num} not finished")
    return [], "; ".join(notes)


Images = Callable[[DictConfig], Mapping[int, int] | None]
"""The test images a config's run covers (all its shards together), each with its label (None
when its task does not choose them)."""


class RunIndex:
    """The FINISHED runs of one MLflow experiment, indexed by run and cell key.

    A cell's per-image logs are read as their runs sealed them (:mod:`mrcert.infra.seals`) and
    checked for sense: its images those of its config (``images``, when given), with their
    labels, and no radius beyond what the method can certify with the samples a row drew. A
    log that fails leaves the cell empty, with the reason as its note."""

    def __init__(self, df: pd.DataFrame, images: Images | None = None):
        self.df = df
        self.images = images
        self._cache: dict[tuple[str, ...], Cell] = {}
        self._logs: dict[tuple[str, ...], pd.DataFrame | str] = {}

    @classmethod
    def load(cls, experiment: str, images: Images | None = None) -> RunIndex:
        """The index of ``experiment``'s FINISHED runs in the current store (read only)."""
        return cls(finished_table(experiment), images)

    # --- what the resolver reads (mrcert.infra.resolver.TrainRuns) ------------------------------
    def newest_train_run(self, key: str) -> str | None:
        """The newest FINISHED train run with run key ``key``."""
        return newest_train_run_in(self.df, key)

    def run_tags(self, run_id: str) -> dict[str, str] | None:
        fields = self._fields(run_id, "tags.")
        return None if fields is None else {k: str(v) for k, v in fields.items()}

    def metrics(self, run_id: str) -> dict[str, float] | None:
        """A run's metrics by name (None when the index holds no such run)."""
        fields = self._fields(run_id, "metrics.")
        return None if fields is None else {k: float(v) for k, v in fields.items()}

    def _fields(self, run_id: str, prefix: str) -> dict | None:
        """A run's recorded values under ``prefix`` (``tags.``, ``metrics.``), by name."""
        hits = self.df[self.df["run_id"] == run_id]
        if hits.empty:
            return None
        row = hits.iloc[0]
        return {c[len(prefix) :]: row[c] for c in hits.columns if c.startswith(prefix) and pd.notna(row[c])}

    def artifact(self, run_id: str, path: str) -> Path:
        import mlflow

        return artifact(mlflow.MlflowClient(), run_id, path)  # gone: the cell stays empty with a note

    def cell(self, overrides: Iterable[str]) -> Cell:
        """The cell of the config ``overrides`` compose to (cached per override list)."""
        overrides = tuple(overrides)
        if overrides not in self._cache:
            self._cache[overrides] = self.resolve(compose_config(overrides))
        return self._cache[overrides]

    def resolve(self, cfg: DictConfig) -> Cell:
        try:
            cfg, ident = resolve(cfg, self)
        except MrcertError:
            return Cell(cfg, note="no finished train run for its model")
        runs, note = complete(self.df[self.df[CELL] == ident.cell])
        return Cell(cfg, runs, note, ident.train_run)

    def children(self, parent: str) -> list[Cell]:
        """The cells of a sweep's children (by parent run id), one per cell key."""
        kids = self.df[self.df.get("tags.mlflow.parentRunId") == parent]
        cells = []
        for _, group in kids.groupby(CELL, sort=False):
            runs, note = complete(group)
            if runs:
                cells.append(Cell(_run_config(runs[0]), runs, note))
        return cells

    # --- values ---------------------------------------------------------------------------
    def log(self, cell: Cell) -> pd.DataFrame | None:
        """The per-image log of a filled cell (its shards' logs merged), or None (then the
        cell's note says why: a log gone, changed since its run sealed it, or without sense)."""
        if not cell.filled:
            return None
        ids = tuple(cell.run_ids)
        if ids not in self._logs:
            task = TASKS[str(cell.runs[0]["tags.mrcert.task"])]
            try:
                merged = certify_log.concat_logs([_run_log(r, task.log) for r in cell.runs])
                self._check(merged, cell.cfg)
            except MrcertError as exc:
                merged = str(exc)
            self._logs[ids] = merged
        found = self._logs[ids]
        if isinstance(found, str):
            cell.note = found
            return None
        return found

    def _check(self, log: pd.DataFrame, cfg: DictConfig) -> None:
        """Raise when ``log`` cannot be the result of ``cfg``'s run (:func:`problems`)."""
        expected = self.images(cfg) if self.images is not None else None
        found = problems(log, cfg, expected)
        if found:
            raise MrcertError(f"its log does not fit its config: {found}")

    def metric(self, cell: Cell, name: str) -> float:
        """Metric ``name`` of a cell, recomputed from its merged log (NaN when empty)."""
        log = self.log(cell)
        if log is None:
            return float("nan")
        return float(TASKS.of(cell.cfg).summarize(log, cell.cfg).get(name, float("nan")))


def _run_config(run: pd.Series) -> DictConfig:
    """A run's resolved config (its ``resolved_config.yaml``)."""
    path = _run_file(run, "resolved_config.yaml")
    if path is None:
        raise MrcertError(f"run {run['run_id']} has no resolved_config.yaml")
    return read_run_config(path)


def _run_file(run: pd.Series, name: str) -> Path | None:
    """A file of a run: from its output folder, else downloaded from its artifacts (None if gone)."""
    import mlflow

    folder = run.get("tags.mrcert.output_dir")
    return run_file(mlflow.MlflowClient(), str(run["run_id"]), folder if isinstance(folder, str) else None, name)


def _run_log(run: pd.Series, name: str) -> pd.DataFrame:
    """A run's per-image log, as the run sealed it; a one-line error when it is gone or changed."""
    path = _run_file(run, name)
    if path is None:
        raise MrcertError(f"run {run['run_id']}'s {name} is gone")
    tags = {c[len("tags.") :]: str(v) for c, v in run.items() if c.startswith("tags.") and pd.notna(v)}
    seals.verify(str(run["run_id"]), tags, path, name)
    return certify_log.read_log(path, ["idx"])


def problems(log: pd.DataFrame, cfg: DictConfig, expected: Mapping[int, int] | None) -> str:
    """What in a per-image log cannot come from a run of ``cfg`` ('' when nothing): an image
    that is not one of the run's (``expected``: each with its label), a label that is not the
    image's, a radius beyond the most the method certifies with the samples the row drew."""
    if expected is not None:
        idx = log["idx"].to_numpy()
        strange = sorted(set(idx.tolist()) - set(expected))
        if strange:
            return f"images {strange[:5]} are not among the {len(expected)} its config covers"
        if "label" in log.columns:
            wrong = [int(i) for i, y in zip(idx, log["label"], strict=True) if int(y) != expected[int(i)]]
            if wrong:
                return f"images {wrong[:5]} are logged with labels that the data set does not give them"
    if {"radius", "n"} <= set(log.columns) and "alpha" in cfg.task:
        method = build_method(cfg)
        alpha = float(cfg.task.alpha)
        rows = log[pd.to_numeric(log["n"], errors="coerce").notna()]
        limit = {n: method.largest_radius(int(n), alpha) for n in rows["n"].unique()}
        beyond = rows[rows["radius"] > rows["n"].map(limit) * (1 + 1e-9) + 1e-12]
        if len(beyond):
            row = beyond.iloc[0]
            return (
                f"image {int(row['idx'])} has radius {row['radius']!r}, beyond the {limit[row['n']]!r} "
                f"that n = {int(row['n'])} samples allow at alpha = {alpha}"
            )
    return ""
