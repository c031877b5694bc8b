"""What ``certify``, ``smooth`` and ``attack`` share: the test images a job handles, the
trained classifier, the certification method bound to it, and a resumable per-image loop."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from mrcert.core.methods import build_method
from mrcert.core.methods.base import BaseClassifier, Certifier, Method, Render
from mrcert.core.sampling import SmoothedClassifier
from mrcert.data.datasets import DataBundle, SampleSet
from mrcert.data.samples import TestSample
from mrcert.data.sources import load
from mrcert.errors import MrcertError
from mrcert.infra.checkpoints import load_classifier
from mrcert.infra.progress import progress
from mrcert.infra.runtime import batch_size, render_batch, resolve_device
from mrcert.reporting.certify_log import ResultLog


def job_indices(total: int, skip: int, limit: int | None, shard: int, num_shards: int) -> list[int]:
    """Every ``skip``-th test image, at most ``limit`` of them, then this shard's share."""
    if not 0 <= shard < num_shards:
        raise MrcertError(f"task.shard={shard} is not allowed: an integer in [0, task.num_shards={num_shards})")
    chosen = list(range(0, total, skip))[: limit if limit is not None else None]
    return chosen[shard::num_shards]


def run_images(cfg: DictConfig) -> dict[int, int] | None:
    """The test images a run of ``cfg`` covers (all its shards together), each with its label
    in the data set: what a table checks a run's log against (None for a task that does not
    choose its images: an imported log)."""
    if "skip" not in cfg.task:
        return None
    labels = _test_labels(OmegaConf.to_yaml(cfg.data))
    t = cfg.task
    return {i: int(labels[i]) for i in job_indices(len(labels), int(t.get("skip", 1)), t.get("max"), 0, 1)}


@functools.cache
def _test_labels(data: str) -> np.ndarray:
    return np.asarray(load(OmegaConf.create(data)).samples().labels)


@dataclass
class Evaluation:
    """A job's test images, its trained base classifier, and the method's certifier bound to it."""

    bundle: DataBundle
    samples: SampleSet
    model: torch.nn.Module
    method: Method
    certifier: Certifier
    indices: list[int]
    device: torch.device
    backend: str

    @property
    def smoothed(self) -> SmoothedClassifier:
        """The certifier as ``smooth`` and ``attack`` use it: a smoothed classifier (config
        validation refuses those tasks for a method that does not serve them)."""
        if not isinstance(self.certifier, SmoothedClassifier):
            raise MrcertError(f"method={type(self.method).__name__} has no smoothed classifier")
        return self.certifier

    def render(self, sample: TestSample) -> Render:
        """The sample's renderer, on the device of the model unless the numba back end (a CPU
        kernel) is asked for: on a GPU the images are then made where they are classified."""
        return (sample if self.backend == "numba" else sample.to(self.device)).renderer(self.backend)


def prepare(cfg: DictConfig) -> Evaluation:
    t = cfg.task
    bundle = load(cfg.data)
    device = resolve_device(cfg.device)
    model = load_classifier(cfg, bundle.classes, device)  # before the test samples: a bad checkpoint fails fast
    method = build_method(cfg)
    downsampling = None
    if cfg.data.get("downsample"):
        downsampling = (int(cfg.motion.downsample.every_k), float(cfg.motion.downsample.voxel))
    samples = bundle.samples(downsampling=downsampling, crop=method.crop_bound(float(t.crop_sigmas)))
    indices = job_indices(len(samples), int(t.skip), t.get("max"), int(t.shard), int(t.num_shards))
    overlap = device.type == "cuda"  # rendering beside the model pays off when it runs on a GPU
    batch = batch_size(t.batch_size, device)
    renders = render_batch(batch, bundle.height, bundle.width)
    certifier = method.certifier(BaseClassifier(model, len(bundle.classes), batch, device, overlap, renders))
    return Evaluation(bundle, samples, model, method, certifier, indices, device, str(t.get("backend", "auto")))


def run_per_image(log: ResultLog, ev: Evaluation, work: Callable[[int], dict[str, Any]], desc: str) -> int:
    """Run ``work(i)`` for every image of ``ev`` not yet in ``log``, appending each row as it is
    done; a row already there is adopted only when it is valid for that image (its label)."""
    done = log.done({i: int(ev.samples.labels[i]) for i in ev.indices})
    todo = [i for i in ev.indices if i not in done]
    for i in progress(todo, desc):
        start = time.perf_counter()
        row = work(i)
        row["seconds"] = time.perf_counter() - start
        log.append({"idx": i} | row)
    return len(todo)
