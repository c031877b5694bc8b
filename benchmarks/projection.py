"""Projection throughput: mrcert's back ends vs Open3D's project_to_rgbd_image, same cloud.

Prints points x images per second and images per second (medians over repeats), all
measured in this one run on the same threads. Usage: python benchmarks/projection.py
[--points 400000] [--motions 100] [--threads 2] [--repeats 5]
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
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = str(args.threads)
    os.environ["NUMBA_NUM_THREADS"] = str(args.threads)

    import numpy as np
    import open3d as o3d
    import torch

    from mrcert.geometry import motion_to_matrix
    from mrcert.projection import project
    from mrcert.scenes import testscene

    torch.set_num_threads(args.threads)
    pts, cols = testscene.build(args.density)
    points, colors = torch.from_numpy(pts), torch.from_numpy(cols)
    K = torch.tensor([[386.274, 0, 80], [0, 386.274, 45], [0, 0, 1]], dtype=torch.float64)
    rng = np.random.default_rng(0)
    scale = np.array([0.05, 0.05, 0.1, 0.0436, 0.0436, 0.122])
    motions = torch.tensor(rng.normal(size=(args.motions, 6)) * scale)
    H, W, n = 90, 160, len(pts)

    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(np.float32)))
    pcd.point.colors = o3d.core.Tensor(cols)
    K_o3d = K.clone()
    K_o3d[:2, 2] -= 0.5
    K_o3d = o3d.core.Tensor(K_o3d.numpy())
    extrinsics = [o3d.core.Tensor(np.linalg.inv(motion_to_matrix(m).numpy())) for m in motions]

    def open3d_all():
        for ext in extrinsics:
            pcd.project_to_rgbd_image(W, H, K_o3d, ext, depth_scale=1.0, depth_max=100.0)

    cases = {
        "open3d project_to_rgbd_image": open3d_all,
        "mrcert project (numba)": lambda: project(points, colors, K, motions, H, W, backend="numba"),
        "mrcert project (torch)": lambda: project(points, colors, K, motions, H, W, backend="torch"),
    }
    print(
        f"cloud: {n:,} points, {W}x{H}, batch of {args.motions} motions, {args.threads} threads, "
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
    print(f"{'method':<32}{'s/batch':>10}{'images/s':>12}{'Mpoint-images/s':>18}{'vs open3d':>11}")
    base = statistics.median(times["open3d project_to_rgbd_image"])
    for name, ts in times.items():
        med = statistics.median(ts)
        print(
            f"{name:<32}{med:>10.3f}{args.motions / med:>12.1f}{n * args.motions / med / 1e6:>18.1f}"
            f"{base / med:>10.2f}x"
        )


if __name__ == "__main__":
    main()
