"""``task=smooth``: smoothed benign accuracy, PREDICT at each test image's own pose."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from mrcert.core.sampling import image_generator
from mrcert.infra.tracking import RunContext
from mrcert.tasks.evaluation import prepare, result_log, run_per_image, summarize


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    ev = prepare(cfg)
    log = result_log(ctx, "smooth")

    def predict_one(i: int) -> dict[str, Any]:
        sample = ev.samples[i]
        pred = ev.smoothed.predict(
            ev.render(sample), int(t.n), float(t.alpha), image_generator(cfg.seed, i), rule=str(t.decision)
        )
        return {
            "label": sample.label,
            "predict": pred,
            "correct": int(pred == sample.label),
            "n": int(t.n),
            "axis": ev.method.axes_label,
        }

    run_per_image(log, ev, predict_one, "smooth")
    return summarize(ctx, "smooth", log.path, cfg)
