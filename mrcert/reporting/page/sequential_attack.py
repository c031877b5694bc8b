"""The attack under fixed-n PREDICT beside sequential PREDICT, on the same images and motions."""

from __future__ import annotations

import pandas as pd

from mrcert.reporting.experiment_cells import ExperimentCells, Measure
from mrcert.reporting.paper_tables import AXIS_NAMES, SMOOTHED_BENIGN, model_label
from mrcert.reporting.writers import markdown


def sequential_attack_section(src: ExperimentCells, experiment: str) -> dict | None:
    """Per attack cell (axis, model, K) that has both: the smoothed K-perturbed accuracy under
    fixed-n PREDICT and under sequential PREDICT on the same images and motions, the images
    whose verdict differs, and each one's seconds per image; None when no sequential attack has
    run. The sequential runs' time also enters the time table (their own stage)."""
    rows = []
    for combo, first in src.rows(experiment, SMOOTHED_BENIGN):
        cfg = first.cfg
        for k in dict.fromkeys((int(cfg.attack.k), 100)):
            cells = {
                name: src.cell(
                    experiment,
                    combo,
                    Measure("attack", "smoothed_robust_accuracy", (f"attack.k={k}", f"task.sequential={flag}")),
                )
                for name, flag in (("fixed", "false"), ("sequential", "true"))
            }
            fixed, sequential = (src.index.log(cells[name]) for name in ("fixed", "sequential"))
            if fixed is None or sequential is None:
                continue
            n = int(cells["fixed"].cfg.task.n)  # the paper's attack: PREDICT with n samples per pose
            both = fixed.merge(sequential, on="idx", suffixes=("_fixed", "_sequential"))
            robust = {n: (both[f"smoothed_robust_{n}"] == 1) for n in ("fixed", "sequential")}
            seconds = {n: float(both[f"seconds_{n}"].mean()) for n in ("fixed", "sequential")}
            rows.append(
                {
                    "Axis": AXIS_NAMES.get(str(cfg.motion.axis), str(cfg.motion.axis)),
                    "Model": model_label(str(cfg.model.arch), str(cfg.model.variant)),
                    "K": k,
                    "images": len(both),
                    "fixed n": f"{robust['fixed'].mean():.3f}",
                    "sequential": f"{robust['sequential'].mean():.3f}",
                    "difference (images)": int(robust["sequential"].sum() - robust["fixed"].sum()),
                    "images whose verdict differs": int((robust["fixed"] != robust["sequential"]).sum()),
                    "s per image, fixed n": f"{seconds['fixed']:.2f}",
                    "s per image, sequential": f"{seconds['sequential']:.2f}",
                    "time, sequential / fixed": f"{seconds['sequential'] / seconds['fixed']:.2f}",
                }
            )
    if not rows:
        return None
    table = pd.DataFrame(rows)
    return {
        "table": markdown(table),
        "cells": len(table),
        "largest": int(table["difference (images)"].abs().max()),
        "n": n,
    }
