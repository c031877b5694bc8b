"""The headline metrics of each task's per-image log (whole, or merged from shards): what a task
logs when it ends and what a table cell shows, computed by the same function
(:func:`summarize`, by the task's name)."""

from __future__ import annotations

import pandas as pd
from omegaconf import DictConfig

from mrcert.core.method import ABSTAIN
from mrcert.core.methods import build_method
from mrcert.reporting import certify_log


def certify(df: pd.DataFrame, cfg: DictConfig) -> dict[str, float]:
    """Certified accuracy at ``motion.radius`` (or the region the method certifies, e.g. pixel-wise
    smoothing's interval) and the rest of :func:`certify_log.metrics`."""
    radius = build_method(cfg).judged_at(float(cfg.motion.radius))
    metrics = certify_log.metrics(df, radius, float(cfg.motion.radius_step), radius)[0]
    if "n" in df.columns:
        metrics["mean_samples"] = float(df["n"].mean())
    return metrics


def imported(df: pd.DataFrame, cfg: DictConfig) -> dict[str, float]:
    """The certify metrics of an imported log, at its own ``task.radius``."""
    radius = float(cfg.task.radius)
    return certify_log.metrics(df, radius, float(cfg.task.radius_step), radius)[0]


def smooth(df: pd.DataFrame, cfg: DictConfig) -> dict[str, float]:
    """Smoothed benign accuracy (abstain = wrong)."""
    return {
        "smoothed_benign_accuracy": float(df["correct"].mean()),
        "abstain_rate": float((df["predict"] == ABSTAIN).mean()),
        "num_images": float(len(df)),
        "seconds_per_image": float(df["seconds"].mean()),
    }


def attack(df: pd.DataFrame, cfg: DictConfig) -> dict[str, float]:
    """Benign and K-perturbed accuracies, base and (with ``task.smoothed``) smoothed."""
    metrics = {
        "base_benign_accuracy": float(df["base_benign"].mean()),
        "base_robust_accuracy": float(df["base_robust"].mean()),
        "k": float(cfg.attack.k),
        "attack_radius": float(cfg.attack.radius),
        "num_images": float(len(df)),
        "seconds_per_image": float(df["seconds"].mean()),
    }
    if cfg.task.smoothed:
        metrics["smoothed_robust_accuracy"] = float((df["smoothed_robust"] == 1).mean())
    return metrics


def verify(df: pd.DataFrame, cfg: DictConfig) -> dict[str, float]:
    """How many instances each answer got, and the seconds they took."""
    counts = {r: float((df["result"] == r).sum()) for r in ("unsat", "sat", "unknown", "timeout")}
    return {
        "verified": counts["unsat"],
        "falsified": counts["sat"],
        "unknown": counts["unknown"],
        "timeout": counts["timeout"],
        "instances": float(len(df)),
        "seconds_total": float(df["seconds"].sum()),
    }


SUMMARIES = {"certify": certify, "import": imported, "smooth": smooth, "attack": attack, "verify": verify}
"""Each task that writes a per-image log (:data:`mrcert.infra.tasks.TASKS`), and its headline metrics."""


def summarize(task: str, log: pd.DataFrame, cfg: DictConfig) -> dict[str, float]:
    """The headline metrics of task ``task``'s per-image ``log``."""
    return SUMMARIES[task](log, cfg)
