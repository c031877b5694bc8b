"""Projection throughput: mrcert's back ends vs Open3D's project_to_rgbd_image, same cloud,
in the scene's own point order and in a random order (a scan or a merged cloud).

For each order: Open3D; ``project()`` on a cloud it has not seen, for one batch (its sort into
locality order included) and per batch over the 1,100 motions of one certified image (the
sort paid once, then kept); the numba kernel without the locality order; the torch back end on
CPU for reference. Prints seconds per batch, images and points x images per second (medians
over interleaved repeats), all measured in this one run on the same threads; "vs ref"
compares with Open3D on the same order (with ``project()`` per batch where Open3D is not
installed, as on a GPU machine without it). With ``--device cuda``, the torch and triton back
ends on the GPU, each checked bit for bit against the CPU kernel.
Usage: python benchmarks/projection.py [--density 0.005] [--motions 100] [--threads 2] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--density", type=float, default=0.005, help="test-scene sampling (0.005 m: ~456k points)")
    ap.add_argument("--motions", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="cuda: add the torch back end on the GPU")
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = str(args.threads)
    os.environ["NUMBA_NUM_THREADS"] = str(args.threads)

    import numpy as np
    import torch

    try:
        import open3d as o3d
    except ImportError:
        o3d = None
        print("Open3D is not installed: its rows are left out, and 'vs' compares with project() per batch")

    from mrcert.core import projection
    from mrcert.core.geometry import motion_to_matrix
    from mrcert.core.projection import locality_order, project
    from mrcert.scenes import testscene

    torch.set_num_threads(args.threads)
    pts, cols = testscene.build(args.density)
    points, colors = torch.from_numpy(pts), torch.from_numpy(cols)
    K = torch.tensor([[386.274, 0, 80], [0, 386.274, 45], [0, 0, 1]], dtype=torch.float64)
    rng = np.random.default_rng(0)
    scale = np.array([0.05, 0.05, 0.1, 0.0436, 0.0436, 0.122])
    motions = torch.tensor(rng.normal(size=(args.motions, 6)) * scale)
    H, W, n = 90, 160, len(pts)

    def open3d_of(p, c):
        K_o3d = K.clone()
        K_o3d[:2, 2] -= 0.5
        K_o3d = o3d.core.Tensor(K_o3d.numpy())
        extrinsics = [o3d.core.Tensor(np.linalg.inv(motion_to_matrix(m).numpy())) for m in motions]
        pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(p.numpy().astype(np.float32)))
        pcd.point.colors = o3d.core.Tensor(c.numpy())

        def run():
            for ext in extrinsics:
                pcd.project_to_rgbd_image(W, H, K_o3d, ext, depth_scale=1.0, depth_max=100.0)

        return run

    shuffle = torch.from_numpy(rng.permutation(n))
    orders = {"scene": (points, colors), "shuffled": (points[shuffle].contiguous(), colors[shuffle].contiguous())}
    per_image = -(-1100 // args.motions)  # batches of one certified image (n0 + n = 1,100 motions)
    cases, batches, reference_of = {}, {}, {}

    def fresh(p, c, calls, **kw):
        def run():
            projection._PREPARED.clear()  # a cloud project() has not seen: its ordering is paid here
            for _ in range(calls):
                project(p, c, K, motions, H, W, **kw)

        return run

    for order, (p, c) in orders.items():
        reference = f"open3d [{order}]" if o3d else f"project() per batch over 1,100 motions [{order}]"
        names = {f"open3d [{order}]": (open3d_of(p, c), 1)} if o3d else {}
        names |= {
            f"project() one batch, ordering included [{order}]": (fresh(p, c, 1), 1),
            f"project() per batch over 1,100 motions [{order}]": (fresh(p, c, per_image), per_image),
            f"numba, no locality order [{order}]": (fresh(p, c, 1, locality=False), 1),
        }
        if order == "scene":
            names[f"torch (CPU) [{order}]"] = (lambda p=p, c=c: project(p, c, K, motions, H, W, backend="torch"), 1)
        if args.device == "cuda":
            if not torch.cuda.is_available():
                raise SystemExit("--device cuda: no CUDA device here")
            local = locality_order(p, K, H, W)
            gp, gc, gm, gr = p[local].cuda(), c[local].cuda(), motions.cuda(), local.cuda()
            cpu = project(p, c, K, motions, H, W)
            for backend in ("torch", "triton"):

                def on_gpu(p=gp, c=gc, m=gm, r=gr, backend=backend):
                    out = project(p, c, K, m, H, W, backend=backend, rank=r)
                    torch.cuda.synchronize()
                    return out

                images, depth = on_gpu()
                same = torch.equal(images.cpu(), cpu[0]) and torch.equal(depth.cpu(), cpu[1])
                print(f"{backend} (CUDA) [{order}]: images and depths equal the CPU kernel's bit for bit: {same}")
                names[f"{backend} (CUDA) locality order [{order}]"] = (on_gpu, 1)
        for name, (fn, calls) in names.items():
            cases[name], batches[name], reference_of[name] = fn, calls, reference
    gpu = f", GPU: {torch.cuda.get_device_name()}" if args.device == "cuda" else ""
    print(
        f"cloud: {n:,} points, {W}x{H}, batch of {args.motions} motions, {args.threads} threads{gpu}, "
        f"median of {args.repeats} interleaved repeats"
    )
    for fn in cases.values():
        fn()  # warm-up (numba compilation, caches)
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.repeats):  # interleaved, so that a slow moment of the machine hits every method
        for name, fn in cases.items():
            start = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - start) / batches[name])
    print(f"{'method [point order]':<52}{'s/batch':>10}{'images/s':>12}{'Mpoint-images/s':>18}{'vs ref':>11}")
    for name, ts in times.items():
        med, base = statistics.median(ts), statistics.median(times[reference_of[name]])
        print(
            f"{name:<52}{med:>10.3f}{args.motions / med:>12.1f}{n * args.motions / med / 1e6:>18.1f}"
            f"{base / med:>10.2f}x"
        )


if __name__ == "__main__":
    main()
