"""Seconds of deterministic certification (``method=bound_propagation``) beside CERTIFY's.

On one test sample of the quick synthetic MetaRoom (160x90, cropped for the interval), for each
architecture (random weights: the work does not depend on them): the seconds to bound every
image of a piece of tz (``--width`` m) pixel by pixel, to push that box through the classifier by
interval bounds, and by the backward relaxation for every margin (19 rows; the method runs it
only for the margins interval bounds leave undecided, so this is its most); the reference is
camera motion smoothing's CERTIFY of the same sample (n0 + n = 100 + 1000 samples), measured in
the same run. Medians over repeats.
Usage: python benchmarks/verify.py [--device cpu|cuda] [--threads 2] [--arch small_cnn,resnet18] [--width 1e-4]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--arch", default="small_cnn,resnet18")
    ap.add_argument("--width", type=float, default=1e-4, help="the piece is [-width, width] on tz (m)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = os.environ["NUMBA_NUM_THREADS"] = str(args.threads)

    import torch

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device here")
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    print(
        f"device {args.device} ({torch.cuda.get_device_name() if device.type == 'cuda' else f'{args.threads} threads'})"
    )
    for arch in args.arch.split(","):
        measure(arch, args, device, sync)


def measure(arch: str, args, device, sync) -> None:
    import numpy as np
    import torch
    from hydra import compose, initialize_config_dir

    from mrcert.core.methods.bound_propagation import BoundPropagation
    from mrcert.core.methods.camera_motion import CameraMotionSmoothing
    from mrcert.core.models import build_model, for_inference
    from mrcert.core.sampling import SmoothedClassifier, image_generator
    from mrcert.core.verification.image_bounds import image_boxes
    from mrcert.core.verification.network import BoundNetwork
    from mrcert.data.sources import load
    from mrcert.infra.config import CONF_DIR
    from mrcert.infra.runtime import batch_size, render_batch

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "task=certify", "data=metaroom_synth", "motion=tz", f"model={arch}", "data.classes=[mug]",
                f"paths.outputs={tempfile.mkdtemp()}",
            ],
        )  # fmt: skip
    method = BoundPropagation("tz", args.width)
    sample = load(cfg.data).samples(crop=method.crop_bound(1.0))[0]
    model = for_inference(build_model(cfg.model, 20), device)
    network = BoundNetwork(model)
    ends = torch.zeros(2, 6, dtype=torch.float64)
    ends[:, 2] = torch.tensor([-args.width, args.width], dtype=torch.float64)
    points, colors, rank = sample.cloud_for(ends)
    spans = ([-args.width], [args.width], sample.height, sample.width, sample.background, rank)

    def box():
        low, high = image_boxes(points, colors, sample.K, "tz", *spans)
        return torch.from_numpy(low).to(device), torch.from_numpy(high).to(device)

    low, high = box()
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    smoothed = SmoothedClassifier(
        model, dist, 20, batch_size(cfg.task.batch_size, device), device, device.type == "cuda",
        render_batch(batch_size(cfg.task.batch_size, device), sample.height, sample.width),
    )  # fmt: skip
    render = sample.to(device).renderer() if device.type == "cuda" else sample.renderer()
    steps = {
        "image box (numba)": box,
        "interval bounds": lambda: network.margins(low, high, 0, "interval"),
        "backward relaxation, 19 margins": lambda: network.margins(low, high, 0, "crown", upto=np.inf),
        "reference: CERTIFY, 1,100 samples": lambda: smoothed.certify(render, 100, 1000, 0.01, image_generator(0, 0)),
    }
    times = {name: [] for name in steps}
    for step in steps.values():  # warm-up: compilation, allocator, cuDNN
        step()
    for _ in range(args.repeats):
        for name, step in steps.items():
            sync()
            start = time.perf_counter()
            step()
            sync()
            times[name].append(time.perf_counter() - start)
    wide = int(((high - low).amax(1) > 0).sum())
    print(f"{arch}: 160x90, piece tz [-{args.width:g}, {args.width:g}] m, {wide} pixels not fixed")
    for name, values in times.items():
        print(f"  {name:38s} {statistics.median(values):8.4f} s")


if __name__ == "__main__":
    main()
