"""Seconds per certified image, split into projection, model and overhead, beside the model alone.

ResNet-18 (20 classes; with ``--device cuda`` ResNet-18 and ResNet-50), 160x90, CERTIFY with
n0 + n = 100 + 1000 in batches of 200 on a test sample of the quick synthetic MetaRoom (cropped
for the axis's smoothing, exact), on the given threads or GPU; the reference is the same 1100
forward passes on random images, measured in the same run. On CUDA the rendering of the next
batch overlaps the model (as in the tasks) and the peak GPU memory is printed. Medians over
repeats. Usage: python benchmarks/certify.py [--axis tz] [--threads 2] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--axis", default="tz")
    ap.add_argument("--arch", default=None, help="comma-separated (default: resnet18; on cuda resnet18,resnet50)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--profile", default="quick", choices=["quick", "paper"])
    ap.add_argument("--cprofile", action="store_true", help="print a cProfile of one certified image")
    ap.add_argument("--overlap", action="store_true", help="render the next batch while the model runs")
    args = ap.parse_args()
    archs = (args.arch or ("resnet18,resnet50" if args.device == "cuda" else "resnet18")).split(",")
    for arch in archs:
        run(args, arch)


def run(args, arch: str) -> None:
    os.environ["OMP_NUM_THREADS"] = os.environ["NUMBA_NUM_THREADS"] = str(args.threads)

    import torch
    from hydra import compose, initialize_config_dir

    from mrcert.core.models import build_model, for_inference
    from mrcert.core.smoothing import SmoothedClassifier, SmoothingDistribution, image_generator
    from mrcert.data.sources import load
    from mrcert.infra.config import CONF_DIR

    torch.set_num_threads(args.threads)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "data=metaroom_synth",
                f"profile={args.profile}",
                f"motion={args.axis}",
                f"model={arch}",
                "data.classes=[mug]",
                f"paths.outputs={tempfile.mkdtemp()}",
            ],
        )
    bundle = load(cfg.data)
    dist = SmoothingDistribution.from_config(cfg.motion)
    samples = bundle.samples(crop=dist.crop_bound(6.0))
    sample = samples[0]
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device here")
    overlap = args.overlap or device.type == "cuda"
    model = for_inference(build_model(cfg.model, 20), device)
    batches = [100] + [200] * 5  # n0 = 100, then n = 1000 in batches of 200
    inputs = [torch.rand(b, 3, 90, 160, generator=torch.Generator().manual_seed(b)).to(device) for b in batches]

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    @torch.inference_mode()
    def model_alone():
        for x in inputs:
            model(x).argmax(1)
        sync()

    def certify():
        start = time.perf_counter()
        test_sample = samples[0]  # building the sample (cloud in the camera frame, crop) is per-image work
        built = time.perf_counter() - start
        smoothed = SmoothedClassifier(model, dist, 20, 200, device, overlap=overlap)
        smoothed.certify(test_sample.renderer(), 100, 1000, 0.01, image_generator(0, 0))
        total = time.perf_counter() - start
        return total, built, smoothed.votes.timings["render"], smoothed.votes.timings["model"]

    model_alone()
    certify()  # warm-up: numba compilation, allocator, cuDNN
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    ref = statistics.median(_timed(model_alone) for _ in range(args.repeats))
    if args.cprofile:
        import cProfile
        import pstats

        profiler = cProfile.Profile()
        profiler.runcall(certify)
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(14)
    runs = [certify() for _ in range(args.repeats)]
    total, built, render, model_t = (statistics.median(r[i] for r in runs) for i in range(4))
    overhead = total - built - render - model_t
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{args.threads} CPU threads"
    print(
        f"{arch}, {args.axis} (sigma {dist.sigmas[0]}), {args.profile} MetaRoom sample: "
        f"{len(sample.points):,} points, {len(sample.crop_points):,} after the crop; "
        f"n0 + n = 1100, batch 200, {where}{', overlapped rendering' if overlap else ''}, median of {args.repeats}"
    )
    print(f"{'':<34}{'seconds':>10}{'vs model alone':>16}")
    for name, value in (
        ("1100 forward passes alone", ref),
        ("certify: total", total),
        ("certify: building the sample", built),
        ("certify: projection", render),
        ("certify: model", model_t),
        ("certify: overhead (sampling, stats)", overhead),
    ):
        print(f"{name:<34}{value:>10.3f}{value / ref:>15.2f}x")
    print(
        f"projection + sample + overhead = {(render + built + overhead) / model_t:.1%} of the model's time; "
        f"total = {total / ref:.2f}x the forward passes alone"
    )
    if device.type == "cuda":
        print(f"peak GPU memory: {torch.cuda.max_memory_allocated(device) / 2**20:.0f} MiB")


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
