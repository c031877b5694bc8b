"""The projection's z-buffer on a GPU: Triton kernels with the CPU kernel's float64 operations.

:func:`render` draws a cloud already in locality order (:mod:`mrcert.core.projection` prepares
it and keeps it on the device) under B motions, with the rule of the numba kernel: a point
with camera coordinates ``R^T (P - t)`` lands on pixel ``(floor(v), floor(u))``, the nearest
point wins and, among points at exactly the same depth, the lowest rank. A GPU has no
64-bit-key-plus-rank atomic, so one kernel makes three passes over the points, each over
every (block of points, motion) pair:

1. ``depth``: every landing point takes ``atomic_min`` of its depth's bits on its pixel
   (positive float64 values order as their bit patterns read as int64);
2. ``rank``: the points at exactly that depth take ``atomic_min`` of their rank;
3. ``colour``: the one point with that depth and rank writes its colour.

Each pass recomputes the points' camera coordinates with the same operations in the same order
as the CPU kernel (multiplications and additions never fused into FMAs:
``enable_fp_fusion=False``; float64 division rounds to nearest), so the depths, winners and
images are the CPU kernel's to the bit. A block of points whose bounding box cannot land in the
image under a motion is skipped (the CPU kernel's culling test, a margin far above rounding).

On a machine without a GPU the kernels run under Triton's interpreter (``TRITON_INTERPRET=1``,
set before this module is imported), which is how the test suite checks them everywhere.
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl

BLOCK = 512
"""Points per program (and per culling box) of the kernels."""

MAX_PIXELS = 1 << 26
"""At most this many motions x pixels rendered by one launch (the z-buffer and rank buffer take
8 bytes each per pixel; the rest waits for the next launch)."""

_INF_BITS = 0x7FF0000000000000  # +inf as int64 bits: above every finite depth's
_NO_RANK = torch.iinfo(torch.int64).max


def interpreting() -> bool:
    """Whether Triton runs its kernels on the CPU, through its interpreter."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


@triton.jit
def _never(w0, w1, w2, c0, c1, c2, h0, h1, h2, t0, t1, t2, below: tl.constexpr):
    """``g(P) = w . (P - t)`` below zero (``below``) or above zero over the whole box (centre
    ``c``, half-extent ``h``), by a margin far above float rounding (the CPU kernel's test)."""
    mid = w0 * (c0 - t0) + w1 * (c1 - t1) + w2 * (c2 - t2)
    spread = tl.abs(w0) * h0 + tl.abs(w1) * h1 + tl.abs(w2) * h2
    slack = 1e-9 * (tl.abs(mid) + spread) + 1e-12
    if below:
        result = mid + spread < -slack
    else:
        result = mid - spread > slack
    return result


@triton.jit
def _zbuffer(
    X, Y, Z, rank, colors, center, half, R, T, intr, zbuf, rbuf, images,
    n, height, width,
    PASS: tl.constexpr, BLOCK: tl.constexpr, C: tl.constexpr,
):  # fmt: skip
    k = tl.program_id(0)  # block of points: the fastest grid axis, so that the programs
    b = tl.program_id(1)  # running at once share a motion and its z-buffer stays in L2
    fx, fy = tl.load(intr + 0), tl.load(intr + 1)
    cx, cy = tl.load(intr + 2), tl.load(intr + 3)
    r00, r01, r02 = tl.load(R + b * 9 + 0), tl.load(R + b * 9 + 1), tl.load(R + b * 9 + 2)
    r10, r11, r12 = tl.load(R + b * 9 + 3), tl.load(R + b * 9 + 4), tl.load(R + b * 9 + 5)
    r20, r21, r22 = tl.load(R + b * 9 + 6), tl.load(R + b * 9 + 7), tl.load(R + b * 9 + 8)
    tx, ty, tz = tl.load(T + b * 3 + 0), tl.load(T + b * 3 + 1), tl.load(T + b * 3 + 2)
    c0, c1, c2 = tl.load(center + k * 3 + 0), tl.load(center + k * 3 + 1), tl.load(center + k * 3 + 2)
    h0, h1, h2 = tl.load(half + k * 3 + 0), tl.load(half + k * 3 + 1), tl.load(half + k * 3 + 2)
    # The cone of camera coordinates that land (Z > 0 and inside the four image borders), each
    # constraint a linear function of the point: the block is skipped when one fails throughout.
    cw = cx - width
    ch = cy - height
    outside = (
        _never(r02, r12, r22, c0, c1, c2, h0, h1, h2, tx, ty, tz, True)
        | _never(
            fx * r00 + cx * r02, fx * r10 + cx * r12, fx * r20 + cx * r22, c0, c1, c2, h0, h1, h2, tx, ty, tz, True
        )
        | _never(
            fx * r00 + cw * r02, fx * r10 + cw * r12, fx * r20 + cw * r22, c0, c1, c2, h0, h1, h2, tx, ty, tz, False
        )
        | _never(
            fy * r01 + cy * r02, fy * r11 + cy * r12, fy * r21 + cy * r22, c0, c1, c2, h0, h1, h2, tx, ty, tz, True
        )
        | _never(
            fy * r01 + ch * r02, fy * r11 + ch * r12, fy * r21 + ch * r22, c0, c1, c2, h0, h1, h2, tx, ty, tz, False
        )
    )
    offs = k * BLOCK + tl.arange(0, BLOCK)
    live = (offs < n) & (outside == 0)
    dx = tl.load(X + offs, mask=live, other=1.0) - tx
    dy = tl.load(Y + offs, mask=live, other=1.0) - ty
    dz = tl.load(Z + offs, mask=live, other=1.0) - tz
    zc = r02 * dx + r12 * dy + r22 * dz
    uf = fx * ((r00 * dx + r10 * dy + r20 * dz) / zc) + cx
    vf = fy * ((r01 * dx + r11 * dy + r21 * dz) / zc) + cy
    lands = live & (zc > 0.0) & (uf >= 0.0) & (uf < width) & (vf >= 0.0) & (vf < height)
    pixel = tl.where(lands, vf, 0.0).to(tl.int32) * width + tl.where(lands, uf, 0.0).to(tl.int32)
    slot = b.to(tl.int64) * height * width + pixel
    bits = zc.to(tl.int64, bitcast=True)
    if PASS == 0:
        tl.atomic_min(zbuf + slot, bits, mask=lands)
    else:
        nearest = lands & (tl.load(zbuf + slot, mask=lands, other=0) == bits)
        mine = tl.load(rank + offs, mask=nearest, other=0)
        if PASS == 1:
            tl.atomic_min(rbuf + slot, mine, mask=nearest)
        else:
            won = nearest & (tl.load(rbuf + slot, mask=nearest, other=0) == mine)
            for c in tl.static_range(C):
                value = tl.load(colors + offs * C + c, mask=won)
                tl.store(images + (b.to(tl.int64) * C + c) * height * width + pixel, value, mask=won)


def render(cloud, R: torch.Tensor, t: torch.Tensor, intr: tuple, background: float):
    """Images (B, C, H, W) and depth (B, H, W) of a prepared cloud on the device (``points``
    (3, N) float64 rows in locality order, ``rank`` (N,), ``colors`` (N, C), culling boxes of
    :data:`BLOCK` points) under rotations ``R`` (B, 3, 3) and translations ``t`` (B, 3)."""
    height, width = cloud.height, cloud.width
    hw = height * width
    device = cloud.points.device
    n, c = cloud.colors.shape
    b = R.shape[0]
    images = torch.full((b, c, hw), background, dtype=cloud.colors.dtype, device=device)
    zbits = torch.full((b, hw), _INF_BITS, dtype=torch.int64, device=device)
    ranks = torch.full((b, hw), _NO_RANK, dtype=torch.int64, device=device)
    intrinsics = torch.tensor(intr, dtype=torch.float64, device=device)
    R, t = R.to(device, torch.float64).contiguous(), t.to(device, torch.float64).contiguous()
    step = max(1, min(65535, MAX_PIXELS // hw))  # the grid's second axis holds at most 65535 motions
    blocks = cloud.center.shape[0]
    for start in range(0, b if n else 0, step):  # no points: every pixel is background
        stop = min(b, start + step)
        parts = (zbits[start:stop], ranks[start:stop], images[start:stop])
        for stage in range(3):
            _zbuffer[(blocks, stop - start)](
                cloud.points[0], cloud.points[1], cloud.points[2], cloud.rank, cloud.colors,
                cloud.center, cloud.half, R[start:stop], t[start:stop], intrinsics, *parts,
                n, height, width, PASS=stage, BLOCK=BLOCK, C=c, enable_fp_fusion=False,
            )  # fmt: skip
    depth = zbits.view(torch.float64)
    return images.view(b, c, height, width), depth.view(b, height, width)
