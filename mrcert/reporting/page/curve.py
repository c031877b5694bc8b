"""The learning curve's section: its table recorded with the train runs behind each row, and what it says."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from mrcert.reporting import learning_curve
from mrcert.reporting.cells import compose_config
from mrcert.reporting.experiment_cells import ExperimentCells, sweep_combos
from mrcert.reporting.paper_tables import arch_name
from mrcert.reporting.plots import save
from mrcert.reporting.writers import as_text, markdown


def record_curve(src: ExperimentCells, curve: pd.DataFrame) -> pd.DataFrame:
    """The learning curve's table, each row's test accuracy recorded with the train runs behind it."""
    shown = learning_curve.table(curve)
    for _, row in shown.iterrows():
        keys = [row[k] for k in learning_curve.KEYS]
        runs = curve[(curve[learning_curve.KEYS] == keys).all(axis=1)]["run_id"]
        src.record("learning_curve", tuple(keys), "test accuracy (median)", row["test accuracy (median)"], list(runs))
    return shown


def curve_summary(models: pd.DataFrame, curve: pd.DataFrame) -> dict:
    """What the learning curve says, per architecture: the median test accuracy under `every`
    with the fewest and the most training poses (and under `any` with the most), and the range
    of the evaluated base models' validation and test accuracy."""
    archs = []
    for model, runs in curve.groupby("model", sort=False):
        med = runs.groupby(["separation rule", "training poses per class"])["test accuracy"].median()
        rules = set(med.index.get_level_values(0))
        if "every" not in rules or len(med["every"]) < 2:
            continue
        every = med["every"]
        fewest, most = every.index.min(), every.index.max()
        top = med["any"].index.max() if "any" in rules else None
        archs.append(
            {
                "name": arch_name(model),
                "fewest": int(fewest),
                "most": int(most),
                "fewest_acc": float(every[fewest]),
                "most_acc": float(every[most]),
                "any": None if top is None else {"poses": int(top), "acc": float(med["any"][top])},
            }
        )
    ranges = None
    if len(models):
        val, test = models["validation accuracy"].astype(float), models["test accuracy"].astype(float)
        ranges = {"val": (val.min(), val.max()), "test": (test.min(), test.max())}
    return {"archs": archs, "models": ranges}


def separation(cfg) -> str:
    """The protocol's separation of training from test poses, in words."""
    gaps = cfg.data.protocol.get("separation") or {}
    return ", ".join(f"{quantity} {value:g} degrees" for quantity, value in gaps.items())


def learning_curve_section(src: ExperimentCells, jobs: list, models: pd.DataFrame, page: Path) -> dict | None:
    """The learning curve's section (its figure written beside the page), when its runs exist:
    the experiments, how many of their runs are shown, the protocol's separation, the table and
    what it says beside the evaluated base ``models``."""
    curve = learning_curve.runs(src)
    if not len(curve):
        return None
    plot = page.with_name(f"{page.stem}_learning_curve.png")
    save(learning_curve.figure(curve, learning_curve.histories(curve)), [plot])
    protocol = jobs[0].certify.cfg if jobs else compose_config((f"experiment={learning_curve.EXPERIMENTS[0]}",))
    return {
        "experiments": learning_curve.EXPERIMENTS,
        "shown": len(curve),
        "defined": sum(len(sweep_combos(e)) for e in learning_curve.EXPERIMENTS),
        "separation": separation(protocol),
        "table": markdown(as_text(record_curve(src, curve))),
        "picture": plot.name,
    } | curve_summary(models, curve)
