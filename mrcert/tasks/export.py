"""``task=export``: test images' pose intervals as verification instances (ONNX + VNN-LIB).

The base classifier is written once (``model.onnx``, the image as input); for every test image
of the job and every piece of ``[-motion.radius, motion.radius]`` on ``motion.axis`` cut into
``task.pieces``, a VNN-LIB property bounds each input by the lowest and highest value the pixel
and channel take in any image projected from a pose of the piece
(:func:`~mrcert.core.verification.image_bounds.image_boxes`, the bounds ``method=bound_propagation`` uses),
and calls unsafe any other class's logit reaching the label's. ``instances.csv`` lists them as
the competition does (onnx,vnnlib,timeout); an image is robust on its interval when all its
pieces are ``unsat``. ``mrcert task=verify task.instances=.../instances.csv`` checks them.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from mrcert.core.axes import axis_index
from mrcert.core.verification.image_bounds import image_boxes
from mrcert.errors import MrcertError
from mrcert.formats.onnx_model import write_onnx
from mrcert.formats.vnnlib import write_vnnlib
from mrcert.infra.progress import progress
from mrcert.infra.tasks import EVALUATION, Task, model_title
from mrcert.infra.tracking import RunContext
from mrcert.tasks.evaluation import prepare


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    ev = prepare(cfg)
    if not ev.method.single:
        raise MrcertError(f"task=export bounds one axis; motion={ev.method.axes_label} has several")
    if int(t.pieces) < 1:
        raise MrcertError(f"task.pieces={t.pieces} is not allowed: an integer >= 1")
    axis, radius = ev.method.axes[0], float(cfg.motion.radius)
    out = ctx.output_dir
    edges = np.linspace(-radius, radius, int(t.pieces) + 1)
    ends = torch.zeros(2, 6, dtype=torch.float64)
    ends[:, axis_index(axis)] = torch.tensor([-radius, radius], dtype=torch.float64)
    rows = []
    for i in progress(ev.indices, "export"):
        sample = ev.samples[i]
        if not rows:  # the classifier, for images of this data set's size
            write_onnx(ev.model, (sample.colors.shape[1], sample.height, sample.width), out / "model.onnx")
        points, colors, rank = sample.cloud_for(ends)
        low, high = image_boxes(
            points, colors, sample.K, axis, edges[:-1], edges[1:], sample.height, sample.width, sample.background, rank
        )
        for k in range(len(edges) - 1):
            name = f"vnnlib/image_{i}_piece_{k}.vnnlib"
            comment = f"test image {i} (label {sample.label}), {axis} in [{edges[k]!r}, {edges[k + 1]!r}]"
            write_vnnlib(out / name, low[k], high[k], sample.label, len(ev.bundle.classes), comment)
            rows.append(f"model.onnx,{name},{float(t.timeout)!r}")
    (out / "instances.csv").write_text("\n".join(rows) + "\n")
    for path in (out / "model.onnx", out / "instances.csv", out / "vnnlib"):
        ctx.tracker.log_artifact(path)
    return {"instances": float(len(rows)), "images": float(len(ev.indices))}


class Export(Task):
    summary = "write test images' pose intervals as ONNX + VNN-LIB verification instances"
    identity = replace(EVALUATION, ignores=(*EVALUATION.ignores, "task.sequential", "task.look"))  # it samples nothing

    def title(self, cfg: DictConfig) -> str:
        return model_title(cfg)

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
