"""``task=certify``: CERTIFY every test image of this job; one row of ``certify.tsv`` each.

Resumes from its TSV when restarted with the same config (``task.resume``, on by default),
and splits the test set across jobs with ``task.shard`` / ``task.num_shards``.
"""

from __future__ import annotations

import textwrap
from dataclasses import replace
from typing import Any

from omegaconf import DictConfig

from mrcert.core.methods import build_method
from mrcert.core.methods.base import CertifyRequest
from mrcert.core.sampling import image_generator
from mrcert.infra.tasks import EVALUATION, Task, model_title
from mrcert.infra.tracking import RunContext
from mrcert.reporting import certify_log
from mrcert.reporting.plots import curve_figure, save
from mrcert.tasks.evaluation import prepare, run_per_image
from mrcert.tasks.run_log import log_headline, result_log


def report(df, cfg_radius: float, step: float, ctx: RunContext, title: str, region: str) -> None:
    """The radius-grid table and the curve of a certify log, and what its radius means, logged to the run."""
    max_radius = max(float(df["radius"].max()) if len(df) else 0.0, cfg_radius)
    grid = certify_log.grid(df, step, max_radius)
    grid_path = ctx.output_dir / "certified_accuracy.csv"
    grid.to_csv(grid_path, index=False)
    for k, acc in enumerate(grid["certified_accuracy"]):
        ctx.tracker.log_metrics({"certified_accuracy_at_step": acc}, step=k)
    fig = curve_figure({title: {"": certify_log.curve(df)}}, textwrap.fill(region, 70), marks={title: cfg_radius})
    ctx.tracker.log_figure(fig, "certified_accuracy.png")
    save(fig, [ctx.output_dir / "certified_accuracy.png"])
    (ctx.output_dir / "region.txt").write_text(region + "\n")
    for path in (grid_path, ctx.output_dir / "region.txt"):
        ctx.tracker.log_artifact(path)


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    ev = prepare(cfg)
    dist = ev.method
    log = result_log(ctx, "certify", dist.log_columns)
    request = CertifyRequest(
        int(t.n0), int(t.n), float(t.alpha), float(cfg.motion.radius), bool(t.sequential), int(t.look)
    )

    def certify_one(i: int) -> dict[str, Any]:
        sample = ev.samples[i]
        render = ev.render(sample)
        cert = ev.certifier.certify_sample(render, request, image_generator(cfg.seed, i))
        return {
            "label": sample.label,
            "predict": cert.prediction,
            "radius": float(cert.radius),
            "correct": int(cert.prediction == sample.label),
            "count_a": cert.count_a,
            "n0": cert.n0,
            "n": cert.n,
            "projected": render.projected,  # camera poses rendered for this certificate
            "margin": float(cert.margin),
            "p_a_lower": float(cert.p_a_lower),
            "sigma": "+".join(map(repr, dist.noise_scales)),
            "axis": dist.axes_label,
            "radius_unit": cert.unit,
            "sigma_unit": dist.sigma_unit,
        } | cert.details

    run_per_image(log, ev, certify_one, f"certify {dist.axes_label}")
    title = f"{cfg.data.name} {cfg.model.arch} {cfg.model.variant}, {cfg.method.name} {dist.axes_label}"
    report(
        certify_log.read_log(log.path),
        dist.judged_at(float(cfg.motion.radius)),
        float(cfg.motion.radius_step),
        ctx,
        title,
        dist.region(),
    )
    return log_headline(ctx, "certify", log.path, cfg)


class Certify(Task):
    summary = "CERTIFY each test image of the smoothed classifier (certify.tsv)"
    identity = replace(EVALUATION, ignore_when=(("task.sequential", False, "task.look"),))  # fixed n: no looks
    log = "certify.tsv"
    columns = tuple(certify_log.COLUMNS)
    headline = ("certified_accuracy", "clean_accuracy", "mean_samples")

    def title(self, cfg: DictConfig) -> str:
        return model_title(cfg)

    def summarize(self, log, cfg: DictConfig) -> dict[str, float]:
        """Certified accuracy at ``motion.radius`` (or the region the method certifies, e.g.
        pixel-wise smoothing's interval) and the rest of :func:`certify_log.metrics`."""
        radius = build_method(cfg).judged_at(float(cfg.motion.radius))
        metrics = certify_log.metrics(log, radius, float(cfg.motion.radius_step), radius)[0]
        if "n" in log.columns:  # every sample classified: the class guesses' n0 and the n after them
            metrics["mean_samples"] = float(certify_log.samples(log, int(cfg.task.n)).mean())
        return metrics

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
