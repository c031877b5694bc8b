"""``task=smooth``: smoothed benign accuracy, PREDICT at each test image's own pose."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from mrcert.certify_log import ResultLog, read_log
from mrcert.smoothing import ABSTAIN, image_generator
from mrcert.tasks import RunContext
from mrcert.tasks.evaluation import log_outputs, prepare, run_per_image

COLUMNS = ["idx", "label", "predict", "correct", "n", "axis", "seconds"]
LOG = "smooth.tsv"


def summarize(df, cfg: DictConfig) -> dict[str, float]:
    """Smoothed benign accuracy (abstain = wrong) of a (possibly merged) smooth log."""
    return {
        "smoothed_benign_accuracy": float(df["correct"].mean()),
        "abstain_rate": float((df["predict"] == ABSTAIN).mean()),
        "num_images": float(len(df)),
        "seconds_per_image": float(df["seconds"].mean()),
    }


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    ev = prepare(cfg)
    log = ResultLog(ctx.output_dir / LOG, COLUMNS)

    def predict_one(i: int) -> dict[str, Any]:
        sample = ev.samples[i]
        pred = ev.smoothed(sample, cfg).predict(int(t.n), float(t.alpha), image_generator(cfg.seed, i))
        return {
            "label": sample.label,
            "predict": pred,
            "correct": int(pred == sample.label),
            "n": int(t.n),
            "axis": ev.distribution.name,
        }

    run_per_image(log, ev.indices, predict_one, "smooth")
    metrics = summarize(read_log(log.path, COLUMNS), cfg)
    log_outputs(ctx, metrics, log.path)
    return metrics
