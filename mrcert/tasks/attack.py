"""``task=attack``: K-perturbed empirical robust accuracy of the base and the smoothed model.

``attack=uniform`` draws K motions uniformly in [-r, r] on the run's axis (from a generator
seeded per test image); ``attack=grid`` takes K evenly spaced motions in [-r, r]. An image
counts as robust only if the prediction is right at all K motions (smoothed: PREDICT at the
perturbed pose, abstain = wrong). Per image: the base model's benign prediction and the
worst motion found (base: smallest margin; smoothed: the first failing motion, else the one
with the fewest votes for the label), and how the smoothed model failed there (``abstain``:
PREDICT could not decide; ``wrong``: it decided another class; ``-``: it did not fail). With
``task.sequential`` each PREDICT is sequential (:class:`~mrcert.core.sequential.PredictDesign`),
and the smoothed worst motion is the one with the smallest share of votes for the label.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

from mrcert.core.attacks import Attack as MotionAttack
from mrcert.core.axes import axis_index, unit
from mrcert.core.methods.base import ABSTAIN
from mrcert.core.models import predicted
from mrcert.core.sampling import image_generator
from mrcert.errors import MrcertError
from mrcert.infra.tasks import EVALUATION, FIXED_PREDICT, Task, model_title
from mrcert.infra.tracking import RunContext
from mrcert.tasks.evaluation import prepare, run_per_image
from mrcert.tasks.run_log import log_headline, result_log


def build_attack(attack: DictConfig) -> MotionAttack:
    """The attack ``attack`` names by its ``_target_``."""
    built = instantiate(attack)
    if not isinstance(built, MotionAttack):
        raise MrcertError(f"attack._target_={attack._target_!r} is not an attack (mrcert.core.attacks.Attack)")
    return built


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    ev = prepare(cfg)
    if not ev.method.single:
        raise MrcertError(f"task=attack perturbs one axis; motion={ev.method.axes_label} smooths several")
    axis = ev.method.axes[0]
    attack = build_attack(cfg.attack)
    log = result_log(ctx, "attack")

    @torch.inference_mode()
    def attack_one(i: int) -> dict[str, Any]:
        sample = ev.samples[i]
        motions = attack.motions(axis, int(cfg.seed), i)
        zero = torch.zeros(1, 6, dtype=torch.float64)
        render = ev.render(sample)
        images = render(torch.cat([zero, motions]))
        logits = ev.model(images.to(ev.device)).cpu()
        preds = predicted(logits)
        others = logits.clone()
        others[:, sample.label] = -torch.inf
        margin = logits[1:, sample.label] - others[1:].max(1).values
        row = {
            "label": sample.label,
            "axis": axis,
            "k": len(motions),
            "base_benign": int(preds[0] == sample.label),
            "base_robust": int((preds[1:] == sample.label).all()),
            "base_worst": float(motions[int(margin.argmin()), axis_index(axis)]),
            "smoothed_robust": -1,
            "smoothed_worst": float("nan"),
            "smoothed_failure": "-",
            "motion_unit": unit(axis),
        }
        if t.smoothed:
            votes = []
            for k, m in enumerate(motions):
                generator = image_generator(cfg.seed, i, "predict", k)
                if t.sequential:  # the label's share of the votes drawn names the worst motion
                    n, alpha, look = int(t.n), float(t.alpha), int(t.look)
                    decision, counts = ev.smoothed.predict_sequential(render, n, alpha, look, generator, m)
                    votes.append(counts[sample.label] / counts.sum())
                else:
                    counts = ev.smoothed.sample_counts(render, int(t.n), generator, m)
                    votes.append(counts[sample.label])
                    decision = ev.smoothed.decide(counts, float(t.alpha), str(t.decision))
                if decision != sample.label:
                    failure = "abstain" if decision == ABSTAIN else "wrong"
                    row |= {
                        "smoothed_robust": 0,
                        "smoothed_worst": float(m[axis_index(axis)]),
                        "smoothed_failure": failure,
                    }
                    break
            else:
                row |= {"smoothed_robust": 1, "smoothed_worst": float(motions[int(np.argmin(votes)), axis_index(axis)])}
        return row

    run_per_image(log, ev, attack_one, f"attack {cfg.attack.name} k={cfg.attack.k}")
    return log_headline(ctx, "attack", log.path, cfg)


class Attack(Task):
    summary = "K-perturbed empirical robust accuracy, base and smoothed"
    identity = replace(
        EVALUATION,
        defines=(*EVALUATION.defines, "attack"),
        ignores=tuple(i for i in EVALUATION.ignores if i != "attack"),
        ignore_when=FIXED_PREDICT,
    )
    log = "attack.tsv"
    columns = (
        "idx",
        "label",
        "axis",
        "k",
        "base_benign",
        "base_robust",
        "base_worst",
        "smoothed_robust",
        "smoothed_worst",
        "smoothed_failure",
        "motion_unit",
        "seconds",
    )
    headline = ("smoothed_robust_accuracy", "base_benign_accuracy")

    def title(self, cfg: DictConfig) -> str:
        return model_title(cfg)

    def summarize(self, log, cfg: DictConfig) -> dict[str, float]:
        """Benign and K-perturbed accuracies, base and (with ``task.smoothed``) smoothed."""
        metrics = {
            "base_benign_accuracy": float(log["base_benign"].mean()),
            "base_robust_accuracy": float(log["base_robust"].mean()),
            "k": float(cfg.attack.k),
            "attack_radius": float(cfg.attack.radius),
            "num_images": float(len(log)),
            "seconds_per_image": float(log["seconds"].mean()),
        }
        if cfg.task.smoothed:
            metrics["smoothed_robust_accuracy"] = float((log["smoothed_robust"] == 1).mean())
        return metrics

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
