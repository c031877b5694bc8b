"""The experiment's jobs (axis, variant) and what the page says of them: its settings as the runs'
composed configs have them, the paper's three findings counted over our rows, and each evaluated
base model's training record."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from mrcert.core.sequential import TOLERANCE
from mrcert.reporting import certify_log
from mrcert.reporting.cells import Cell
from mrcert.reporting.experiment_cells import ExperimentCells
from mrcert.reporting.paper_tables import AXIS_NAMES, CERTIFIED, SMOOTHED_BENIGN, robust


@dataclass
class Job:
    """One job of the experiment (axis, variant) and its cells."""

    axis: str
    variant: str
    arch: str
    certify: Cell
    smooth: Cell
    attack: Cell


def jobs_of(src: ExperimentCells, experiment: str) -> list[Job]:
    """The experiment's jobs with their certify, smooth and attack cells (the attack at the
    experiment's own ``attack.k``)."""
    jobs = []
    for combo, first in src.rows(experiment, SMOOTHED_BENIGN):
        cfg = first.cfg
        jobs.append(
            Job(
                str(cfg.motion.axis),
                str(cfg.model.variant),
                str(cfg.model.arch),
                src.cell(experiment, combo, CERTIFIED),
                first,
                src.cell(experiment, combo, robust("smoothed", int(cfg.attack.k))),
            )
        )
    return jobs


def findings(src: ExperimentCells, jobs: list[Job]) -> dict:
    """The paper's three qualitative findings, each counted over our rows: for each, how many
    rows hold, of how many, and each row's two numbers; the attack's K and n and CERTIFY's alpha
    come from the runs' configs."""
    by = {(j.axis, j.variant): j for j in jobs}
    axes = [a for a in AXIS_NAMES if (a, "vanilla") in by and (a, "augmented") in by]
    # 1. Augmented models certify more than vanilla ones, per axis.
    pairs = [
        (a, src.index.metric(by[(a, "augmented")].certify, "certified_accuracy"),
         src.index.metric(by[(a, "vanilla")].certify, "certified_accuracy"))
        for a in axes
    ]  # fmt: skip
    done = [(a, aug, van) for a, aug, van in pairs if not (np.isnan(aug) or np.isnan(van))]
    augmented = _counted(
        [aug > van for _, aug, van in done], [f"{AXIS_NAMES[a]} {aug:.3f} vs {van:.3f}" for a, aug, van in done]
    )
    # 2. The smoothed model's K-perturbed accuracy is at least the base model's.
    rows = []
    for j in jobs:
        base = src.index.metric(j.attack, "base_robust_accuracy")
        smoothed = src.index.metric(j.attack, "smoothed_robust_accuracy")
        if not (np.isnan(base) or np.isnan(smoothed)):
            rows.append((j, base, smoothed))
    smoothed = _counted(
        [s >= b for _, b, s in rows], [f"{AXIS_NAMES[j.axis]} {j.variant} {s:.3f} vs {b:.3f}" for j, b, s in rows]
    )
    # 3. Certified accuracy is at most the smoothed model's empirical robust accuracy.
    rows, abstained, wrong, certified_broken = [], 0, 0, 0
    for j in jobs:
        clog, alog = src.index.log(j.certify), src.index.log(j.attack)
        if clog is None or alog is None:
            continue
        images = set(alog["idx"].tolist())
        radius = float(j.certify.cfg.motion.radius)
        cert = certify_log.certified_accuracy(clog[clog["idx"].isin(images)], radius)
        emp = float((alog["smoothed_robust"] == 1).mean())
        rows.append((j, cert, emp))
        ok = clog[certify_log.certified(clog, radius)]["idx"]
        broken = alog[alog["idx"].isin(set(ok.tolist())) & (alog["smoothed_robust"] != 1)]
        certified_broken += len(broken)
        if "smoothed_failure" in broken:
            abstained += int((broken["smoothed_failure"] == "abstain").sum())
            wrong += int((broken["smoothed_failure"] == "wrong").sum())
    certified = _counted(
        [c <= e for _, c, e in rows], [f"{AXIS_NAMES[j.axis]} {j.variant} {c:.3f} vs {e:.3f}" for j, c, e in rows]
    )
    attack = jobs[0].attack.cfg if jobs else None
    return {
        "augmented": augmented,
        "smoothed": smoothed,
        "certified": certified,
        "broken": certified_broken,
        "abstained": abstained,
        "wrong": wrong,
        "k": int(attack.attack.k) if attack is not None else None,
        "attack_n": int(attack.task.n) if attack is not None else None,
        "alpha": float(jobs[0].certify.cfg.task.alpha) if jobs else None,
    }


def _counted(holds: list[bool], rows: list[str]) -> dict:
    return {"holds": sum(holds), "total": len(holds), "rows": rows}


def base_models(src: ExperimentCells, jobs: list[Job]) -> pd.DataFrame:
    """Each evaluated model's training record: accuracy on its validation poses (what selected
    ``best.pt``) and on the test images (measured once, after training), and its train run."""
    rows = {}
    for j in jobs:
        run = j.certify.train_run if j.certify.filled else None  # None: an import
        key = j.variant + (j.axis if j.variant == "augmented" else "")
        metrics = src.index.metrics(run) if isinstance(run, str) else None
        if metrics is None or key in rows:
            continue
        label = "vanilla (every axis)" if j.variant == "vanilla" else f"augmented on {j.axis}"
        rows[key] = {
            "model": f"{j.arch} {label}",
            "validation accuracy": metrics.get("best_val_acc", np.nan),
            "test accuracy": metrics.get("test_acc", np.nan),
            TRAIN_RUN: run,
        }
    return pd.DataFrame(list(rows.values()))


TRAIN_RUN = "train run"
"""The column of :func:`base_models` that names each model's train run (recorded, not shown)."""


def record_models(src: ExperimentCells, models: pd.DataFrame) -> pd.DataFrame:
    """Record each base model's accuracies with its train run; the table as the page shows it."""
    for _, m in models.iterrows():
        for column in ("validation accuracy", "test accuracy"):
            src.record("base_models", m["model"], column, m[column], [m[TRAIN_RUN]])
    return models.drop(columns=TRAIN_RUN, errors="ignore")


# The paper's model whose Table 3 values stand beside ours on the page, whatever our architecture.
PAPER_ARCH = "resnet18"


def _validation(cfg) -> str:
    spec = cfg.data.protocol.get("validation")
    if spec is None:
        return f"{int(cfg.train.val_fraction * 100)}% of the training poses held out"
    return f"{spec.per_class} validation poses per class (docs/method.md §3)"


def images_of(src: ExperimentCells, cell: Cell) -> int | str:
    """The number of test images in a cell's per-image log ("its" before it has one)."""
    log = src.index.log(cell)
    return "its" if log is None else len(log)


def share_of(skip: int) -> str:
    """Which test images a task's ``skip`` covers, in words."""
    return "every test image" if skip == 1 else f"one test image in {skip}"


def verdict(counted: dict) -> str:
    """A finding's count (:func:`findings`) in words, as the page's template prints it."""
    holds, total = counted["holds"], counted["total"]
    if total == 0:
        return "not checked (no filled cells)"
    return f"holds in {holds} of {total}" if holds < total else f"holds in all {total}"


ATTACK_WORDS = {"uniform": "uniform", "grid": "evenly spaced"}
"""How the page names an attack's motions (``attack.name``)."""


def setup(src: ExperimentCells, jobs: list[Job]) -> dict | None:
    """The experiment's settings as its runs' composed configs have them."""
    if not jobs:
        return None
    c, s, a = jobs[0].certify.cfg, jobs[0].smooth.cfg, jobs[0].attack.cfg
    classes = len(c.data.classes) if c.data.get("classes") else int(c.data.num_classes)
    return {
        "data": c.data.name,
        "profile": c.profile.name,
        "classes": classes,
        "train_poses": c.data.protocol.train.per_class,
        "validation": _validation(c),
        "test_images": c.data.protocol.test.per_class * classes,
        "arch": c.model.arch,
        "epochs": c.train.epochs,
        "lr": c.train.lr,
        "n0": c.task.n0,
        "n": c.task.n,
        "alpha": c.task.alpha,
        "look": c.task.look,
        "tolerance": TOLERANCE,
        "predict_n": s.task.n,
        "k": a.attack.k,
        "attack": ATTACK_WORDS.get(str(a.attack.name), str(a.attack.name)),
        "attack_n": a.task.n,
        "share": columns_share({"certify": c, "smooth": s, "attack": a}),
    }


def columns_share(configs: dict) -> str:
    """Which test images each task's columns cover: one phrase when all cover the same."""
    shares = {task: share_of(int(cfg.task.skip)) for task, cfg in configs.items()}
    if len(set(shares.values())) == 1:
        return f"Every column covers {next(iter(shares.values()))}, the same images in each."
    return "Columns cover " + "; ".join(f"{task}: {share}" for task, share in shares.items()) + "."
