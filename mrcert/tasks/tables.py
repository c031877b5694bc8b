"""``task=tables``: the paper's tables and figure from the finished runs in MLflow, as
Markdown, LaTeX and CSV under ``task.output_dir`` and as artifacts of the tables run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from mrcert import tables
from mrcert.errors import MrcertError
from mrcert.tasks import RunContext
from mrcert.tracking import configure


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    if not cfg.tracking.enabled:
        raise MrcertError("task=tables reads runs from MLflow: use tracking=sqlite or tracking=server")
    configure(cfg.tracking)
    runs = tables.Runs.gather(t.experiment, t.dataset, t.profile)
    robot = tables.Runs.gather(t.experiment, t.tabletop_dataset, t.profile)
    archs, axes, paper = tuple(t.archs), tuple(t.axes), bool(t.show_paper)
    built = {
        "table3_certified": (
            tables.certified_table(runs, archs, axes, paper),
            "Benign, 5-perturbed empirical robust and certified accuracy of the smoothed models",
        ),
        "table1_augmented": (
            tables.base_vs_smoothed_table(runs, "augmented", archs, axes, 100, paper),
            "Base vs smoothed motion-augmented models: benign and 100-perturbed accuracy",
        ),
        "appendix_vanilla": (
            tables.base_vs_smoothed_table(runs, "vanilla", archs, axes, 100, paper),
            "Base vs smoothed vanilla models: benign and 100-perturbed accuracy",
        ),
        "appendix_5_vs_100": (
            tables.perturbed_5_vs_100_table(runs, archs, axes, paper),
            "Smoothed models: 5- vs 100-perturbed empirical robust accuracy",
        ),
        "tabletop": (
            tables.tabletop_table(robot, t.tabletop_arch, "vanilla", 10, paper),
            "Tabletop: benign and 10-perturbed accuracy, base vs smoothed",
        ),
        "sweep": (tables.sweep_table(runs, t.parent), "Certified accuracy against smoothing sigma and radius"),
    }
    out = Path(t.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics: dict[str, float] = {}
    for name, (df, caption) in built.items():
        for path in tables.write(df, out / name, caption):
            ctx.tracker.log_artifact(path, "tables")
        values = df.to_numpy().ravel() if len(df) else np.array([])
        metrics[f"{name}_filled_cells"] = float(
            sum(1 for v in values if isinstance(v, str) and v.strip() or isinstance(v, float) and not np.isnan(v))
        )
    for path in tables.plot_curves(tables.curves(runs, archs, axes), out / "certified_accuracy_vs_radius"):
        ctx.tracker.log_artifact(path, "tables")
    ctx.tracker.log_metrics(metrics)
    shown = built[t.print][0]
    print(f"\n{built[t.print][1]} ({t.dataset}, profile {t.profile}):\n")
    print(tables.markdown(shown.reset_index().map(tables.format_cell)))
    print(
        f"\nTables and figure: {out.resolve()}\nMLflow: make ui  (or: mlflow ui --backend-store-uri {cfg.tracking.uri})"
    )
    return metrics | {"tables": str(out.resolve())}
