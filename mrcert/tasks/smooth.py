"""``task=smooth``: smoothed benign accuracy, PREDICT at each test image's own pose (with
``task.sequential``, sequential PREDICT: the ``n`` column logs the samples each image drew)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from omegaconf import DictConfig

from mrcert.core.methods.base import ABSTAIN
from mrcert.core.sampling import image_generator
from mrcert.infra.tasks import EVALUATION, FIXED_PREDICT, Task, model_title
from mrcert.infra.tracking import RunContext
from mrcert.tasks.evaluation import prepare, run_per_image
from mrcert.tasks.run_log import log_headline, result_log


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    ev = prepare(cfg)
    log = result_log(ctx, "smooth")

    def predict_one(i: int) -> dict[str, Any]:
        sample = ev.samples[i]
        render, generator = ev.render(sample), image_generator(cfg.seed, i)
        if t.sequential:
            pred, votes = ev.smoothed.predict_sequential(render, int(t.n), float(t.alpha), int(t.look), generator)
            drawn = int(votes.sum())
        else:
            pred, drawn = (
                ev.smoothed.predict(render, int(t.n), float(t.alpha), generator, rule=str(t.decision)),
                int(t.n),
            )
        return {
            "label": sample.label,
            "predict": pred,
            "correct": int(pred == sample.label),
            "n": drawn,
            "axis": ev.method.axes_label,
        }

    run_per_image(log, ev, predict_one, "smooth")
    return log_headline(ctx, "smooth", log.path, cfg)


class Smooth(Task):
    summary = "smoothed benign accuracy: PREDICT at each test pose"
    identity = replace(EVALUATION, ignore_when=FIXED_PREDICT)
    log = "smooth.tsv"
    columns = ("idx", "label", "predict", "correct", "n", "axis", "seconds")
    headline = ("smoothed_benign_accuracy",)

    def title(self, cfg: DictConfig) -> str:
        return model_title(cfg)

    def summarize(self, log, cfg: DictConfig) -> dict[str, float]:
        """Smoothed benign accuracy (abstain = wrong)."""
        return {
            "smoothed_benign_accuracy": float(log["correct"].mean()),
            "abstain_rate": float((log["predict"] == ABSTAIN).mean()),
            "num_images": float(len(log)),
            "seconds_per_image": float(log["seconds"].mean()),
        }

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
