"""``task=tables``: the paper's tables and figure from the finished runs in MLflow, as
Markdown, LaTeX and CSV under ``task.output_dir`` and as artifacts of the tables run; beside
each table, ``<table>_sources.csv`` / ``.md`` name the run behind every cell."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from mrcert.core.methods import build_method
from mrcert.core.sampling import image_generator
from mrcert.data.protocols import differences
from mrcert.data.sources import load
from mrcert.data.synthetic import SyntheticData
from mrcert.errors import MrcertError
from mrcert.infra.experiment import configure, ensure_experiment
from mrcert.infra.identity import Identity
from mrcert.infra.runtime import launch_command
from mrcert.infra.tasks import Task
from mrcert.infra.tracking import RunContext
from mrcert.reporting import paper_tables
from mrcert.reporting.cells import RunIndex
from mrcert.reporting.experiment_cells import ExperimentCells
from mrcert.reporting.imaging import contact_sheet
from mrcert.reporting.overview import method_figure
from mrcert.reporting.page.jobs import PAPER_ARCH, TRAIN_RUN, base_models, jobs_of
from mrcert.reporting.plots import save
from mrcert.reporting.results_page import write_page
from mrcert.reporting.writers import as_text, markdown, write
from mrcert.tasks.evaluation import run_images

CERTIFY_TASKS = ("certify", "import")


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    if not cfg.tracking.enabled:
        raise MrcertError("task=tables reads runs from MLflow: use tracking=sqlite or tracking=server")
    if t.certify_task not in CERTIFY_TASKS:
        raise MrcertError(f"task.certify_task={t.certify_task!r} is not allowed: {' or '.join(CERTIFY_TASKS)}")
    configure(cfg.tracking)
    experiment_id = ensure_experiment(cfg.tracking)
    named = named_data()
    outputs = Path(cfg.paths.outputs).resolve()  # the cells' data is cached where this run writes
    src = ExperimentCells(
        RunIndex.load(cfg.tracking.experiment, run_images),
        profile=str(t.profile),
        experiment=t.experiment,
        overrides=(*t.overrides, *((f"data={named}",) if named else ()), f"paths.outputs={outputs}"),
        archs=tuple(t.archs) if t.archs else None,
        axes=tuple(t.axes) if t.axes else None,
        certify_task=str(t.certify_task),
        parent=t.parent,
        link=f"{str(t.ui_url).rstrip('/')}/#/experiments/{experiment_id}/runs/{{run_id}}",
    )
    paper = bool(t.show_paper)
    built = {table.name: (table.build(src, paper), table.caption) for table in paper_tables.tables_for(src)}
    if t.print not in {table.name for table in paper_tables.TABLES}:
        names = ", ".join(table.name for table in paper_tables.TABLES)
        raise MrcertError(f"task.print={t.print!r} is not allowed: one of {names}")
    out = Path(t.output_dir)
    page = Path(t.page) if t.page else None
    with staged([out, *([page.parent] if page else [])]) as stages:
        metrics = write_all(ctx, src, built, stages[0], stages[-1] / page.name if page else None, t)
    if page:
        print(f"\nEvidence page: {page.resolve()}")
    report(cfg, src, built, out)
    return metrics | {"tables": str(out.resolve())}


def write_all(ctx: RunContext, src: ExperimentCells, built: dict, out: Path, page: Path | None, t) -> dict[str, float]:
    """Every table, its sources, the figures and the page (when ``page``) written into ``out``;
    the tables' filled cells, for the run's metrics."""
    metrics: dict[str, float] = {}
    for name, (df, caption) in built.items():
        paths = write(df, out / name, caption)
        paths += write(src.sources(name), out / f"{name}_sources", f"{caption}: the runs behind each cell")
        for path in paths:
            ctx.tracker.log_artifact(path, "tables")
        if len(df):
            ctx.tracker.log_table(as_text(df), f"tables/{name}.json")
        values = df.to_numpy().ravel() if len(df) else np.array([])
        metrics[f"{name}_filled_cells"] = float(
            sum(1 for v in values if isinstance(v, str) and v.strip() or isinstance(v, float) and not np.isnan(v))
        )
    fig = paper_tables.curves_figure(*paper_tables.curves(src))
    ctx.tracker.log_figure(fig, "tables/certified_accuracy_vs_radius.png")
    stem = out / "certified_accuracy_vs_radius"
    figure, _ = save(fig, [stem.with_suffix(".png"), stem.with_suffix(".pdf")])
    overview = method_overview(src, out / "method_overview.png")
    if overview is not None:
        ctx.tracker.log_artifact(overview, "tables")
    if page is not None:
        table = paper_tables.TABLE3_SEQUENTIAL.build(src, show_paper=True, name="page", paper_arch=PAPER_ARCH)
        chosen = f" task.experiment={t.experiment}" if t.experiment else ""
        command = launch_command() or f"mrcert task=tables profile={t.profile}{chosen} task.page={t.page}"
        experiment = src.experiment_for(paper_tables.REPRODUCTION)
        cells = [c for _, c in src.rows(experiment, paper_tables.SMOOTHED_BENIGN)]
        views = nearest_views(cells[0].cfg.data, page.with_name(f"{page.stem}_views.png")) if cells else None
        ctx.tracker.log_artifact(write_page(src, experiment, table, figure, page, command, views), "tables")
    ctx.tracker.log_metrics(metrics)
    return metrics


def report(cfg: DictConfig, src: ExperimentCells, built: dict, out: Path) -> None:
    """What the tables run prints: the table asked for, its base classifiers, why cells are empty."""
    t = cfg.task
    if t.print in built:
        print(f"\n{built[t.print][1]} (profile {t.profile}):\n")
        print(markdown(as_text(built[t.print][0])))
    else:
        own = next(table for table in paper_tables.TABLES if table.name == t.print)
        print(f"\n{t.print}: not written: it is about {', '.join(own.data)}, not {src.data_of(own.experiment)}")
    models = base_models(src, jobs_of(src, src.experiment_for(paper_tables.REPRODUCTION)))
    models = models.drop(columns=TRAIN_RUN, errors="ignore")
    if len(models):
        print("\nTheir base classifiers (validation accuracy selected best.pt; test accuracy measured once):\n")
        print(markdown(as_text(models)))
    sources = src.sources(t.print)
    gaps = sources[sources["note"] != ""] if len(sources) else sources
    if len(gaps):
        print(f"\n{len(gaps)} empty cells; why:")
        for _, g in gaps.drop_duplicates(["row", "note"]).head(12).iterrows():
            print(f"  {g['row']}, {g['column']}: {g['note']}")
    print(
        f"\nTables, figure and the runs behind each cell: {out.resolve()}\n"
        f"MLflow: make ui  (or: mlflow ui --backend-store-uri {cfg.tracking.uri})"
    )


@contextmanager
def staged(folders: list[Path]) -> Iterator[list[Path]]:
    """A temporary folder beside each of ``folders``; once the body has written every file, the
    files are moved into their folders (each move atomic), so that a run killed while writing
    leaves the last complete tables and page as they were, never a table half written."""
    stages = []
    try:
        for folder in folders:
            folder.mkdir(parents=True, exist_ok=True)
            stages.append(Path(tempfile.mkdtemp(prefix=f".{folder.name}-writing-", dir=folder.parent)))
        yield stages
        for stage, folder in zip(stages, folders, strict=True):
            for path in sorted(stage.iterdir(), key=lambda p: p.suffix == ".md"):  # a page after its pictures
                os.replace(path, folder / path.name)
    finally:
        for stage in stages:
            shutil.rmtree(stage, ignore_errors=True)


def method_overview(src: ExperimentCells, path: Path) -> Path | None:
    """The method in one picture (:func:`mrcert.reporting.overview.method_figure`) from the
    first filled certify cell of Table 3's rows (a run of ours: an imported log comes without
    its scene), on its first correctly classified test image; None when no such cell is filled."""
    for _, cell in src.rows(src.experiment_for(paper_tables.REPRODUCTION), paper_tables.CERTIFIED):
        log = src.index.log(cell) if cell.cfg.task.name == "certify" else None  # an imported log has no scene
        if log is not None and len(log):
            right = log[log["correct"] == 1]
            index = int((right if len(right) else log)["idx"].iloc[0])
            cfg = cell.cfg
            method = build_method(cfg)
            bundle = load(cfg.data)
            sample = bundle.samples(crop=method.crop_bound(float(cfg.task.crop_sigmas)))[index]
            # The run's own first selection samples of that image: its generator, its method.
            render, motions = method.views(sample.renderer(), 8, image_generator(int(cfg.seed), index), None)
            view = render(torch.zeros(1, 6, dtype=torch.float64))[0]
            name = bundle.classes[int(sample.label)]
            return method_figure(method, view, name, render(motions), motions, log, float(cfg.motion.radius), path)
    return None


def named_data() -> str | None:
    """The data set named on the command line (``data=metaroom``), if any: the tables are then
    built for it instead of each experiment's own (e.g. Table 3 of the released MetaRoom from
    imported logs)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    named = [o.split("=", 1)[1] for o in HydraConfig.get().overrides.task if o.split("=", 1)[0] in ("data", "+data")]
    return named[-1] if named else None


def nearest_views(data: DictConfig, path: Path, classes: tuple[int, ...] = (0, 5, 10)) -> tuple[Path, str] | None:
    """For a few classes, the first test view beside the three training views nearest to it in
    angle (the largest of the yaw, pitch and roll differences): what a classifier must
    generalise across. Returns the contact sheet and one sentence on the pitches and rolls the
    training views have, measured from the poses; None for data other than synthetic scenes."""
    bundle = load(data)
    if not isinstance(bundle, SyntheticData):
        return None
    test, train = bundle.split("test"), bundle.split("train")
    test_images, train_images = bundle.test().images, bundle.train().images

    def image(a: np.ndarray) -> torch.Tensor:
        return torch.tensor(a).permute(2, 0, 1).float() / 255

    def angles(p: np.ndarray) -> str:
        return f"yaw {p[0]:.0f}, pitch {p[1]:.0f}, roll {p[2]:.0f}"

    rows, names, captions = [], [], []
    for c in (c for c in classes if c < len(bundle.classes)):
        i = int(np.flatnonzero(test.labels == c)[0])
        own = np.flatnonzero(train.labels == c)
        nearest = differences(train.params[own], test.params[i : i + 1])[:, 0, :3].max(axis=1)
        near = own[np.argsort(nearest, kind="stable")[:3]]
        rows.append([image(test_images[i]), *(image(train_images[k]) for k in near)])
        names.append(bundle.classes[c])
        captions.append([f"test: {angles(test.params[i])}", *(f"train: {angles(train.params[k])}" for k in near)])
    title = "a test view (left) and the 3 training views nearest to it in angle"
    contact_sheet(rows, names, captions, path, title=title)
    closest = differences(train.params, test.params)[..., :3].min(axis=(0, 1))  # yaw, pitch, roll
    sentence = (
        f"Test views: pitch {', '.join(f'{v:g}' for v in np.unique(test.params[:, 1]))} and roll "
        f"{', '.join(f'{v:g}' for v in np.unique(test.params[:, 2]))} degrees; training views: pitch "
        f"{train.params[:, 1].min():.0f} to {train.params[:, 1].max():.0f}, roll {train.params[:, 2].min():.0f} to "
        f"{train.params[:, 2].max():.0f}. No training view comes closer to a test view than {closest[0]:.1f} degrees "
        f"in yaw, {closest[1]:.1f} in pitch and {closest[2]:.1f} in roll (separation rule "
        f"`{data.protocol.get('separation_rule', 'every')}`)."
    )
    return path, sentence


class Tables(Task):
    summary = "the paper's tables and figure from finished MLflow runs"
    identity = Identity(
        defines=("task", "profile"), ignores=("data", "model", "motion", "method", "seed", "attack", "train")
    )
    reusable = False  # its result depends on the store's runs, not only on its config

    def title(self, cfg: DictConfig) -> str:
        return f"tables {cfg.task.experiment or 'paper'}"

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
