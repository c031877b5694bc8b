"""Seconds of exact enumeration (``method=enumeration``) beside rendering the same images by brute force.

On one test sample of the quick synthetic MetaRoom (160x90, cropped for the interval), for each
half-width on ``--axis``: the seconds to enumerate every image the interval renders (crossings
located in the renderer's arithmetic, images changed pixel by pixel) and to materialise them all,
beside the reference measured in the same run: rendering each of those images by projecting the
whole crop at its first pose (the brute force). Then the seconds per image to classify them with
the small CNN (random weights: the work does not depend on them), each image whole (the
reference) and incrementally, each from the one before it where its pixels changed (what
``method=enumeration`` does; the logits checked to agree). Medians over repeats.
Usage: python benchmarks/enumeration.py [--threads 2] [--axis tz] [--widths 0.001,0.01] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--axis", default="tz", choices=["tx", "ty", "tz"])
    ap.add_argument("--widths", default="0.001,0.01", help="half-widths of the intervals (m)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = os.environ["NUMBA_NUM_THREADS"] = str(args.threads)

    import torch
    from hydra import compose, initialize_config_dir

    from mrcert.core.models import build_model, for_inference
    from mrcert.infra.config import CONF_DIR

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(f"device {args.device} ({args.threads} threads), axis {args.axis}")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=["task=certify", "data=metaroom_synth", f"motion={args.axis}", "model=small_cnn",
                       "data.classes=[mug]", f"paths.outputs={tempfile.mkdtemp()}"],
        )  # fmt: skip
    model = for_inference(build_model(cfg.model, 20), device)
    for width in (float(w) for w in args.widths.split(",")):
        measure(width, args, cfg, model, device)


def measure(width: float, args, cfg, model, device) -> None:
    import torch

    from mrcert.core.axes import axis_index
    from mrcert.core.methods.base import BaseClassifier
    from mrcert.core.methods.enumeration import ImageEnumeration, _Run
    from mrcert.core.projection import project
    from mrcert.core.verification.events import enumerate_images
    from mrcert.data.sources import load

    sample = load(cfg.data).samples(crop=ImageEnumeration(args.axis, width).crop_bound(1.0))[0]
    ends = torch.zeros(2, 6, dtype=torch.float64)
    ends[:, axis_index(args.axis)] = torch.tensor([-width, width], dtype=torch.float64)
    points, colors, rank = sample.cloud_for(ends)
    spans = (sample.K, sample.height, sample.width, sample.background, args.axis, -width, width)

    def enumerate_all():
        e = enumerate_images(points, colors, rank, *spans)
        return e, e.images(0, len(e))

    e, images = enumerate_all()  # warm-up: compilation
    motions = torch.zeros(len(e), 6, dtype=torch.float64)
    motions[:, axis_index(args.axis)] = torch.from_numpy(e.starts)
    size = (sample.height, sample.width, sample.background)

    def brute_force():
        out = [project(points, colors, sample.K, motions[s : s + 256], *size, rank=rank)[0]
               for s in range(0, len(motions), 256)]  # fmt: skip
        return torch.cat(out)

    def classify():
        with torch.inference_mode():
            return torch.cat([model(torch.from_numpy(images[s : s + 256]).to(device)).float().cpu()
                              for s in range(0, len(images), 256)])  # fmt: skip

    method = ImageEnumeration(args.axis, width)
    run = _Run(method.certifier(BaseClassifier(model, 20, device=device)), sample.renderer())

    def incremental():
        return run.lanes(e, [(0, len(e))])[0]

    assert torch.equal(brute_force(), torch.from_numpy(images)), "the enumeration and the renderer differ"
    whole, changed = classify(), incremental()
    scale = float(whole.abs().max())
    assert (whole - changed).abs().max() <= 1e-5 * max(1.0, scale), "incremental logits differ from the forward pass"
    times = {"enumerate and materialise": [], "reference: render each image": [], "reference: classify each image": [],
             "classify incrementally": []}  # fmt: skip
    for _ in range(args.repeats):
        for name, step in zip(times, (enumerate_all, brute_force, classify, incremental), strict=True):
            start = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - start)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"[-{width:g}, {width:g}] m: {e.events} crossings, {len(e)} images")
    for name, value in med.items():
        print(f"  {name:32s} {value:8.3f} s   ({1e3 * value / len(e):.3f} ms per image)")
    ratio = med["reference: render each image"] / med["enumerate and materialise"]
    print(f"  rendering / enumeration: {ratio:.1f}x")
    ratio = med["reference: classify each image"] / med["classify incrementally"]
    print(f"  classifying each image / incrementally: {ratio:.1f}x")


if __name__ == "__main__":
    main()
