"""``task=tables``: the paper's tables and figure from the finished runs in MLflow, as
Markdown, LaTeX and CSV under ``task.output_dir`` and as artifacts of the tables run; beside
each table, ``<table>_sources.csv`` / ``.md`` name the run behind every cell."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra.tasks import RunContext
from mrcert.infra.tracking import configure, ensure_experiment
from mrcert.reporting import tables
from mrcert.reporting.cells import RunIndex
from mrcert.reporting.plots import save
from mrcert.reporting.writers import as_text, markdown, write

SOURCES = {"runs": "certify", "import": "import"}


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    if not cfg.tracking.enabled:
        raise MrcertError("task=tables reads runs from MLflow: use tracking=sqlite or tracking=server")
    if t.source not in SOURCES:
        raise MrcertError(f"task.source={t.source!r} is not allowed: {' or '.join(SOURCES)}")
    configure(cfg.tracking)
    experiment_id = ensure_experiment(cfg.tracking)
    src = tables.Source(
        RunIndex.gather(cfg.tracking.experiment),
        profile=str(t.profile),
        experiment=t.experiment,
        overrides=tuple(t.overrides),
        archs=tuple(t.archs) if t.archs else None,
        axes=tuple(t.axes) if t.axes else None,
        certify_task=SOURCES[t.source],
        link=f"{str(t.ui_url).rstrip('/')}/#/experiments/{experiment_id}/runs/{{run_id}}",
    )
    paper = bool(t.show_paper)
    built = {
        "table3_certified": (
            tables.certified_table(src, paper),
            "Benign, 5-perturbed empirical robust and certified accuracy of the smoothed models",
        ),
        "table1_augmented": (
            tables.base_vs_smoothed_table(src, "augmented", 100, paper),
            "Base vs smoothed motion-augmented models: benign and 100-perturbed accuracy",
        ),
        "appendix_vanilla": (
            tables.base_vs_smoothed_table(src, "vanilla", 100, paper, name="appendix_vanilla"),
            "Base vs smoothed vanilla models: benign and 100-perturbed accuracy",
        ),
        "appendix_5_vs_100": (
            tables.perturbed_5_vs_100_table(src, paper),
            "Smoothed models: 5- vs 100-perturbed empirical robust accuracy",
        ),
        "tabletop": (
            tables.tabletop_table(src, 10, paper),
            "Tabletop: benign and 10-perturbed accuracy, base vs smoothed",
        ),
        "sweep": (tables.sweep_table(src, t.parent), "Certified accuracy against smoothing sigma and radius"),
    }
    if t.print not in built:
        raise MrcertError(f"task.print={t.print!r} is not allowed: one of {', '.join(built)}")
    out = Path(t.output_dir)
    out.mkdir(parents=True, exist_ok=True)
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
    fig = tables.curves_figure(tables.curves(src))
    ctx.tracker.log_figure(fig, "tables/certified_accuracy_vs_radius.png")
    stem = out / "certified_accuracy_vs_radius"
    figure, _ = save(fig, [stem.with_suffix(".png"), stem.with_suffix(".pdf")])
    if t.page:
        from mrcert.reporting.results_page import write_page

        table = tables.certified_table(src, show_paper=True, name="page")
        command = f"mrcert task=tables task.experiment={t.experiment} task.page={t.page}"
        page = write_page(src, str(t.experiment or "table3"), table, figure, Path(t.page), command)
        ctx.tracker.log_artifact(page, "tables")
        print(f"\nEvidence page: {page.resolve()}")
    ctx.tracker.log_metrics(metrics)
    shown = built[t.print][0]
    print(f"\n{built[t.print][1]} (profile {t.profile}):\n")
    print(markdown(as_text(shown)))
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
    return metrics | {"tables": str(out.resolve())}
