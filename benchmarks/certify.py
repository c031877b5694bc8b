"""Seconds per certified image, split into projection, model and overhead, beside the model alone;
and the forward passes themselves, eager NCHW in batches of 200 (mrcert before) against the
inference path the tasks use (channels-last weights, ``task.batch_size``) and, with
``--compile``, torch.compile.

ResNet-18 (20 classes; with ``--device cuda`` ResNet-18 and ResNet-50), 160x90, CERTIFY with
n0 + n = 100 + 1000 in batches of ``task.batch_size``, rendered several batches at once as the
tasks do, on a test sample of the quick synthetic
MetaRoom (cropped for the axis's smoothing, exact), on the given threads or GPU; the reference
is the same 1100 forward passes on the sample's own renders, measured in the same run, and
every variant of the forward passes must predict the same classes on them. On CUDA the
rendering of the next batch overlaps the model (as in the tasks) and the peak GPU memory is
printed. Medians over repeats, interleaved (the reference with certify, the forward-pass
variants with one another).
The images of the chosen projection back end (``--backend``; on CUDA the default renders on the
GPU with the triton kernels) are checked bit for bit against the CPU kernel's.
Usage: python benchmarks/certify.py [--axis tz] [--threads 2] [--device cpu|cuda] [--backend auto|numba|triton|torch]
       [--compile] [override ...]
"""

from __future__ import annotations

import argparse
import copy
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
    ap.add_argument("--backend", default="auto", help="projection back end (auto: numba on CPU, triton on CUDA)")
    ap.add_argument("--compile", action="store_true", help="add torch.compile's forward passes (needs a C++ compiler)")
    ap.add_argument("overrides", nargs="*", help="config overrides, e.g. task.batch_size=200 model.net.width=16")
    args = ap.parse_args()
    archs = (args.arch or ("resnet18,resnet50" if args.device == "cuda" else "resnet18")).split(",")
    for arch in archs:
        run(args, arch)


def run(args, arch: str) -> None:
    os.environ["OMP_NUM_THREADS"] = os.environ["NUMBA_NUM_THREADS"] = str(args.threads)

    import torch
    from hydra import compose, initialize_config_dir

    from mrcert.core.methods.camera_motion import CameraMotionSmoothing
    from mrcert.core.models import build_model, for_inference
    from mrcert.core.sampling import SmoothedClassifier, image_generator
    from mrcert.data.sources import load
    from mrcert.infra.config import CONF_DIR
    from mrcert.infra.runtime import batch_size, render_batch

    torch.set_num_threads(args.threads)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "task=certify",
                "data=metaroom_synth",
                f"profile={args.profile}",
                f"motion={args.axis}",
                f"model={arch}",
                "data.classes=[mug]",
                f"paths.outputs={tempfile.mkdtemp()}",
                *args.overrides,
            ],
        )
    bundle = load(cfg.data)
    dist = CameraMotionSmoothing.from_config(None, cfg.motion)
    samples = bundle.samples(crop=dist.crop_bound(6.0))
    sample = samples[0]
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device here")
    overlap = args.overlap or device.type == "cuda"
    batch = batch_size(cfg.task.batch_size, device)
    chunk = render_batch(batch, sample.height, sample.width)
    eager = build_model(cfg.model, 20).to(device).eval()
    model = for_inference(copy.deepcopy(eager), device)
    motions = dist.sample(1100, image_generator(0, 0))
    renders = sample.renderer("numba")(motions).to(device)  # the CPU kernel's images: the reference

    def on_device(test_sample):
        """The sample's renderer as the tasks build it: on the model's device unless numba is asked for."""
        return (test_sample if args.backend == "numba" else test_sample.to(device)).renderer(args.backend)

    same = torch.equal(on_device(sample)(motions).to(device), renders)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    @torch.inference_mode()
    def classes(net, size: int) -> torch.Tensor:
        """The predicted classes of ``net`` on the 1100 renders, in batches of ``size``."""
        out = torch.cat([net(renders[s : s + n]).argmax(1) for s, n in _starts(1100, size)])
        sync()
        return out

    def model_alone():
        classes(model, batch)

    def certify():
        start = time.perf_counter()
        test_sample = samples[0]  # building the sample (cloud in the camera frame, crop) is per-image work
        built = time.perf_counter() - start
        smoothed = SmoothedClassifier(model, dist, 20, batch, device, overlap, chunk)
        smoothed.certify(on_device(test_sample), 100, 1000, 0.01, image_generator(0, 0))
        total = time.perf_counter() - start
        return total, built, smoothed.votes.timings["render"], smoothed.votes.timings["model"]

    model_alone()
    certify()  # warm-up: numba compilation, allocator, cuDNN
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    if args.cprofile:
        import cProfile
        import pstats

        profiler = cProfile.Profile()
        profiler.runcall(certify)
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(14)
    refs, runs = [], []
    for _ in range(args.repeats):  # interleaved, so that a drift in the machine's speed hits both alike
        refs.append(_timed(model_alone))
        runs.append(certify())
    ref = statistics.median(refs)
    total, built, render, model_t = (statistics.median(r[i] for r in runs) for i in range(4))
    overhead = total - built - render - model_t
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{args.threads} CPU threads"
    print(
        f"{arch}, {args.axis} (sigma {dist.noise_scales[0]}), {args.profile} MetaRoom sample: "
        f"{len(sample.points):,} points, {len(sample.crop_points):,} after the crop; "
        f"n0 + n = 1100, batch {batch} (rendered {chunk} at once), {where}"
        f"{', overlapped rendering' if overlap else ''}, projection back end {args.backend}, median of {args.repeats}"
    )
    print(f"its 1100 images equal the CPU kernel's bit for bit: {'yes' if same else 'NO'}")
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
    forward_passes(args, classes, eager, model, batch)


def forward_passes(args, classes, eager, model, batch: int) -> None:
    """The 1100 forward passes per variant, each timed against the tasks' path and checked to
    predict the same classes."""
    import torch

    variants = [
        ("eager, NCHW, batch 200 (before)", eager, 200),
        ("channels-last, batch 200", model, 200),
        (f"channels-last, batch {batch} (the tasks)", model, batch),
    ]
    compiled = ""
    if args.compile:
        start = time.perf_counter()
        fast = torch.compile(model, dynamic=False)
        classes(fast, batch)  # compiles once per batch shape
        compiled = f"; torch.compile took {time.perf_counter() - start:.1f} s (once per batch shape)"
        variants.append((f"torch.compile, batch {batch}", fast, batch))
    expected = classes(model, batch)
    print(f"\n1100 forward passes on the sample's renders, median of {args.repeats}{compiled}")
    print(f"{'':<42}{'seconds':>10}{'speed-up vs eager':>19}{'same classes':>14}")
    times = [[] for _ in variants]
    for _ in range(args.repeats):  # interleaved, so that a drift in the machine's speed hits every variant alike
        for spent, (_name, net, size) in zip(times, variants, strict=True):
            spent.append(_timed(lambda n=net, b=size: classes(n, b)))
    before = statistics.median(times[0])
    for spent, (name, net, size) in zip(times, variants, strict=True):
        seconds = statistics.median(spent)
        same = bool(torch.equal(classes(net, size), expected))
        print(f"{name:<42}{seconds:>10.3f}{before / seconds:>18.2f}x{'yes' if same else 'NO':>14}")


def _starts(n: int, size: int) -> list[tuple[int, int]]:
    """(start, length) of the batches of ``size`` covering ``n`` items."""
    return [(s, min(size, n - s)) for s in range(0, n, size)]


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
