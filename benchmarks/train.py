"""Training images per second: ``task=train`` beside a plain PyTorch loop, same model and batch.

The task runs for real (in-process, tracking into a temporary SQLite store) on the quick
synthetic MetaRoom with ``--per-class`` training poses per class; its speed is the training
images divided by each epoch's ``epoch_seconds`` as logged in MLflow (the median of the epochs
after the first). The reference, measured in the same run on the same images: the loop a user
would write -- ``model.train()``, NCHW float batches, SGD, cross-entropy -- and the same loop
with channels-last weights and inputs. Medians over epochs.
Usage: python benchmarks/train.py [--arch small_cnn,resnet18] [--threads 2] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--arch", default="small_cnn,resnet18", help="comma-separated model options")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--per-class", type=int, default=16, help="training poses per class (20 classes)")
    ap.add_argument("--epochs", type=int, default=3)
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = os.environ["NUMBA_NUM_THREADS"] = str(args.threads)
    os.environ.setdefault("MLFLOW_ENABLE_ASYNC_LOGGING", "false")
    import torch

    torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device here")
    where = torch.cuda.get_device_name() if args.device == "cuda" else f"{args.threads} CPU threads"
    print(
        f"Training speed, quick synthetic MetaRoom, 20 classes x {args.per_class} poses, 160x90, batch 32, "
        f"{where}; median over epochs 2..{args.epochs}"
    )
    print(f"{'model':<12}{'method':<40}{'images/s':>10}{'vs plain':>10}")
    for arch in args.arch.split(","):
        run(args, arch)


def run(args, arch: str) -> None:
    import mlflow
    import torch
    from hydra import compose, initialize_config_dir
    from torch import nn

    from mrcert.__main__ import run_task
    from mrcert.core.models import build_model
    from mrcert.data.sources import load
    from mrcert.infra.config import CONF_DIR
    from mrcert.tasks.train import as_tensors

    out = Path(tempfile.mkdtemp())
    overrides = [
        "task=train",
        "data=metaroom_synth",
        "profile=quick",
        f"model={arch}",
        f"data.protocol.train.per_class={args.per_class}",
        f"train.epochs={args.epochs}",
        f"device={args.device}",
        f"paths.outputs={out}",
    ] + (["model.net.width=16"] if arch == "small_cnn" else [])
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    bundle = load(cfg.data)
    images, labels = as_tensors(bundle.train())  # rendered once; the task then reads the cache
    device = torch.device(args.device)

    def plain(channels_last: bool) -> float:
        torch.manual_seed(0)
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        model = build_model(cfg.model, 20).to(device, memory_format=fmt)
        opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9, weight_decay=1e-4)
        loss_fn = nn.CrossEntropyLoss()
        times = []
        for epoch in range(args.epochs):
            start = time.perf_counter()
            model.train()
            order = torch.randperm(len(labels), generator=torch.Generator().manual_seed(epoch))
            for s in range(0, len(order), 32):
                idx = order[s : s + 32]
                x = images[idx].to(device).float().div(255).contiguous(memory_format=fmt)
                loss = loss_fn(model(x), labels[idx].to(device))
                opt.zero_grad()
                loss.backward()
                opt.step()
            if device.type == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - start)
        return len(labels) / statistics.median(times[1:])

    def task() -> float:
        run_task(cfg, out / "runs" / arch)
        mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
        client = mlflow.MlflowClient()
        (run,) = client.search_runs([client.get_experiment_by_name(cfg.tracking.experiment).experiment_id])
        seconds = [
            m.value for m in sorted(client.get_metric_history(run.info.run_id, "epoch_seconds"), key=lambda m: m.step)
        ]
        return run.data.metrics["train_images"] / statistics.median(seconds[1:])

    reference = plain(channels_last=False)
    rows = [
        ("plain loop (NCHW)", reference),
        ("plain loop, channels-last", plain(channels_last=True)),
        ("mrcert task=train", task()),
    ]
    for name, speed in rows:
        print(f"{arch:<12}{name:<40}{speed:>10.1f}{speed / reference:>9.2f}x")


if __name__ == "__main__":
    main()
