"""Projection throughput: mrcert's back ends vs Open3D's project_to_rgbd_image, same cloud,
in the scene's own point order and in a random order (a scan or a merged cloud).

For each order: Open3D, mrcert's numba kernel on the points as given, and on the points in
locality order (what a test sample stores, rendered with their original ranks: the same
images); the torch back end on CPU for reference. Prints points x images per second and
images per second (medians over interleaved repeats), all measured in this one run on the
same threads; "vs open3d" compares with Open3D on the same order.
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
    import open3d as o3d
    import torch

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

    K_o3d = K.clone()
    K_o3d[:2, 2] -= 0.5
    K_o3d = o3d.core.Tensor(K_o3d.numpy())
    extrinsics = [o3d.core.Tensor(np.linalg.inv(motion_to_matrix(m).numpy())) for m in motions]

    def open3d_of(p, c):
        pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(p.numpy().astype(np.float32)))
        pcd.point.colors = o3d.core.Tensor(c.numpy())

        def run():
            for ext in extrinsics:
                pcd.project_to_rgbd_image(W, H, K_o3d, ext, depth_scale=1.0, depth_max=100.0)

        return run

    shuffle = torch.from_numpy(rng.permutation(n))
    orders = {"scene": (points, colors), "shuffled": (points[shuffle].contiguous(), colors[shuffle].contiguous())}
    cases, reference_of = {}, {}
    for order, (p, c) in orders.items():
        local = locality_order(p, K, H, W)
        lp, lc = p[local].contiguous(), c[local].contiguous()
        reference_of.update({f"{k} [{order}]": f"open3d [{order}]" for k in ("open3d", "numba as given",
                             "numba locality order", "torch (CPU) as given")})  # fmt: skip
        cases[f"open3d [{order}]"] = open3d_of(p, c)
        cases[f"numba as given [{order}]"] = lambda p=p, c=c: project(p, c, K, motions, H, W, backend="numba")
        cases[f"numba locality order [{order}]"] = lambda p=lp, c=lc, r=local: project(
            p, c, K, motions, H, W, backend="numba", rank=r
        )
        if order == "scene":
            cases[f"torch (CPU) as given [{order}]"] = lambda p=p, c=c: project(p, c, K, motions, H, W, backend="torch")
        if args.device == "cuda":
            if not torch.cuda.is_available():
                raise SystemExit("--device cuda: no CUDA device here")
            gp, gc, gm, gr = lp.cuda(), lc.cuda(), motions.cuda(), local.cuda()
            reference_of[f"torch (CUDA) locality order [{order}]"] = f"open3d [{order}]"

            def on_gpu(p=gp, c=gc, m=gm, r=gr):
                project(p, c, K, m, H, W, backend="torch", rank=r)
                torch.cuda.synchronize()

            cases[f"torch (CUDA) locality order [{order}]"] = on_gpu
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
            times[name].append(time.perf_counter() - start)
    print(f"{'method [point order]':<42}{'s/batch':>10}{'images/s':>12}{'Mpoint-images/s':>18}{'vs open3d':>11}")
    for name, ts in times.items():
        med, base = statistics.median(ts), statistics.median(times[reference_of[name]])
        print(
            f"{name:<42}{med:>10.3f}{args.motions / med:>12.1f}{n * args.motions / med / 1e6:>18.1f}"
            f"{base / med:>10.2f}x"
        )


if __name__ == "__main__":
    main()
