"""Sequential CERTIFY beside fixed-n CERTIFY: exact probability of certifying a radius and
expected samples classified (the class guess included: fixed n's n0 + n; sequential CERTIFY
has no separate guess), at each pA of votes of two classes, from the same dynamic programme
(:meth:`mrcert.core.sequential.SequentialDesign.operating`; fixed n's power times the chance
its guess is right, :func:`mrcert.core.sequential.guessed`); no sampling, so the figures are exact.

For each radius (in sigmas: r = sigma is Table 3's, 2 sigma the robot experiment's) it prints
both procedures' power and mean samples on a grid of pA, the largest power deficit of the
sequential design on a fine grid, and its error rate at the threshold; with ``--figure PATH`` it
draws the curves (docs/sequential_power.png).
Usage: python benchmarks/sequential.py [--n0 100] [--n 1000] [--alpha 0.01] [--first 40] [--figure PATH]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.stats import norm

from mrcert.core.sequential import SequentialDesign, guessed

RATIOS = (0.5, 1.0, 2.0)
SHOWN = (0.5, 0.7, 0.8, 0.85, 0.87, 0.9, 0.95, 0.98, 0.99, 0.995, 0.999, 1.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n0", type=int, default=100)
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--alpha", type=float, default=0.01)
    ap.add_argument("--first", type=int, default=40, help="the first look (task.look)")
    ap.add_argument("--figure", default=None)
    args = ap.parse_args()
    curves = {}
    for ratio in RATIOS:
        need = float(norm.cdf(ratio))
        fixed = SequentialDesign.fixed(args.n, args.alpha, need)
        seq = SequentialDesign.plan(args.n0, args.n, args.alpha, need, args.first)

        def fixed_n(p, fixed=fixed):
            """Power (the guess included) and samples of fixed-n CERTIFY."""
            return guessed(p, args.n0) * fixed.operating(p)[0], np.full(len(p), float(args.n0 + args.n))

        def sequential(p, seq=seq):
            top, _, samples = seq.operating(p)
            return top, samples

        print(
            f"\nr = {ratio:g} sigma (pA must be >= {need:.4f}); fixed n0 = {args.n0}, n = {args.n}, "
            f"alpha = {args.alpha}; sequential: looks {list(seq.looks)}, levels {[round(x, 5) for x in seq.levels]}"
        )
        print(f"{'pA':>7} | {'P(certify) fixed':>16} {'sequential':>10} | {'samples fixed':>13} {'sequential':>10}")
        shown = np.array(SHOWN)
        (pf, ef), (ps, es) = fixed_n(shown), sequential(shown)
        for row in zip(shown, pf, ps, ef, es, strict=True):
            print("{:7.3f} | {:16.4f} {:10.4f} | {:13.0f} {:10.1f}".format(*row))
        fine = np.linspace(need, 1.0, 2000)[1:]
        deficit = (fixed_n(fine)[0] - sequential(fine)[0]).max()
        below = np.linspace(0.5, need, 200)
        print(
            f"largest power deficit over pA in ({need:.4f}, 1]: {deficit:.4f} (planned <= 0.005 on a coarser grid); "
            f"P(certify) at the threshold: fixed {fixed_n(np.array([need]))[0][0]:.4f}, "
            f"sequential {sequential(np.array([need]))[0][0]:.4f}; a wrong certificate: at most "
            f"{seq.error_bound():.4f} (bound), {sum(seq.operating(below)[:2]).max():.4f} (two classes, exact, "
            f"pA <= {need:.4f})"
        )
        grid = np.linspace(0.5, 1.0, 1001)
        curves[ratio] = (grid, fixed_n(grid), sequential(grid), need)
    if args.figure:
        figure(curves, args).savefig(args.figure, dpi=110, bbox_inches="tight")
        print(f"\nwrote {args.figure}")


def figure(curves, args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(curves), figsize=(4.2 * len(curves), 6.4), sharex=True)
    for col, (ratio, (grid, (pf, ef), (ps, es), need)) in enumerate(curves.items()):
        top, bottom = axes[0, col], axes[1, col]
        top.plot(grid, pf, label=f"fixed n0 + n = {args.n0} + {args.n}", lw=1.6)
        top.plot(grid, ps, label="sequential", lw=1.6, ls="--")
        top.set(title=f"r = {ratio:g} sigma", ylabel="P(certify r)", ylim=(-0.02, 1.02))
        bottom.plot(grid, ef, label=f"fixed n0 + n = {args.n0} + {args.n}", lw=1.6)
        bottom.plot(grid, es, label="sequential", lw=1.6, ls="--")
        bottom.set(xlabel="pA (top class's probability)", ylabel="expected samples classified")
        for ax in (top, bottom):
            ax.axvline(need, color="grey", lw=1, ls=":")
            ax.grid(alpha=0.3)
        top.legend(loc="upper left", fontsize=8)
    fig.suptitle(f"CERTIFY at alpha = {args.alpha}: exact power and cost (dotted: pA = Phi(r / sigma))")
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    main()
