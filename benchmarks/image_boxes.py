"""How wide image boxes are, by axis and by side of no motion, beside how much the images change.

On one test view of the quick synthetic MetaRoom (``experiment=reproduce_quick``, the view
cropped for the interval as certification crops it), for each axis and each piece -- across no
motion ``[-a, a]`` and on either side, ``[-a, 0]`` and ``[0, a]`` -- the share of pixels whose box
(``mrcert.core.verification.image_bounds.image_boxes``, what bound propagation and pixel-wise smoothing bound
with) has a non-zero width, and their mean width; beside it the share of pixels that differ from
the reference image in the images rendered at poses drawn in the piece (its ends, poses 1e-9
from no motion, and ``--poses`` uniform draws): a lower bound of what any sound box must leave
wide.
Usage: python benchmarks/image_boxes.py [--view 0] [--half-width 1e-5] [--axes tz,rz,rx,ry] [--poses 200]
"""

from __future__ import annotations

import argparse
import os
import tempfile


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--view", type=int, default=0, help="index of the test view (0: the first class's first yaw)")
    ap.add_argument("--half-width", type=float, default=1e-5, help="a, in the axis' unit (m or rad)")
    ap.add_argument("--axes", default="tz,rz,rx,ry")
    ap.add_argument("--poses", type=int, default=200, help="poses drawn uniformly in each piece")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--outputs", default=os.environ.get("MRCERT_OUTPUTS") or tempfile.mkdtemp(), help="its data cache")
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = os.environ["NUMBA_NUM_THREADS"] = str(args.threads)

    import numpy as np
    import torch
    from hydra import compose, initialize_config_dir

    from mrcert.core.axes import axis_index
    from mrcert.core.methods.bound_propagation import BoundPropagation
    from mrcert.core.verification.image_bounds import image_boxes
    from mrcert.data.sources import load
    from mrcert.infra.config import CONF_DIR

    torch.set_num_threads(args.threads)
    a = args.half_width
    print(f"test view {args.view} of experiment=reproduce_quick, pieces of half-width {a:g}")
    print("| axis | piece | pixels wide | mean width | pixels changed by the sampled poses |")
    print("|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    for axis in args.axes.split(","):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(
                "config", overrides=["experiment=reproduce_quick", f"motion={axis}", f"paths.outputs={args.outputs}"]
            )
        sample = load(cfg.data).samples(crop=BoundPropagation(axis, a).crop_bound(1.0))[args.view]
        i = axis_index(axis)
        reference = sample.render(torch.zeros(1, 6, dtype=torch.float64), backend="numba")[0][0]
        for lo, hi in ((-a, a), (-a, 0.0), (0.0, a)):
            amounts = np.concatenate([[lo, hi], np.clip([-1e-9, 1e-9], lo, hi), rng.uniform(lo, hi, args.poses)])
            motions = torch.zeros(len(amounts), 6, dtype=torch.float64)
            motions[:, i] = torch.from_numpy(amounts)
            points, colors, rank = sample.cloud_for(motions[:2])
            low, high = image_boxes(
                points, colors, sample.K, axis, [lo], [hi], sample.height, sample.width, sample.background, rank
            )
            width = (high - low).max(1)[0]
            views = sample.render(motions, backend="numba")[0]
            changed = ((views - reference).abs().amax(1) > 0).any(0).double().mean().item()
            print(f"| {axis} | [{lo:g}, {hi:g}] | {(width > 0).mean():.2%} | {width.mean():.1e} | {changed:.2%} |")


if __name__ == "__main__":
    main()
