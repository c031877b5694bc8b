"""Every image projected from any pose of a piece of a one-axis pose interval, bounded.

One geometry serves two methods. For a piece ``[a0, a1]`` on one axis, :func:`_piece_reach`
finds, per point, the box of pixels its path can cross (the path of a translation is a
segment, that of a rotation an arc, held in a triangle) and, per pixel, whether some point
stays in it throughout (so that it is never empty) and how deep such a point can be. A point
whose path crosses a pixel may show there unless a staying point is always strictly nearer,
or it is of lower rank (it then wins every tie) and never farther (:func:`_hides`): along a
translation or a roll, where two points of equal depth keep equal depths, at most as far in the
reference frame; along a pitch or a yaw, at the same reference depth and height (pitch) or
abscissa (yaw), which give the same depth, bit for bit, at every pose (:func:`_axis_terms`), or,
on a piece on one side of no rotation, on the side of each that never brings the point nearer.
The colours a pixel can take anywhere in the piece are therefore those of the points that may
show there, plus the background unless a point stays in it. Points that may cross the camera
plane may land anywhere; extents are widened so that rounding never moves a point out of its box: by
:data:`PIXEL_SLACK` pixels, or along a translation by :data:`ROUNDING` (module constant's note).

* :func:`piece_bounds` (pixel-wise smoothing): upper bounds on the l2 distance between the
  image at any pose of each piece of a frame sequence and each of the piece's end frames.
* :func:`image_boxes` (bound propagation): per pixel and channel, the lowest and highest value
  of any image projected from a pose of each piece.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from mrcert.core.axes import axis_index, is_translation

PIXEL_SLACK = 1e-6
"""Pixels by which every projected extent is widened (and a 'stays in one pixel' test
narrowed), far above float64 rounding, so the bounds hold for the kernels' own arithmetic."""

ROUNDING = 2.0**-50
"""The widening along a translation, relative to ``|u| + |fx X / Z| + 1``: there the projection's
rotation is the identity exactly, so it computes a point's column as ``fx * (X / Z) + cx`` from
``X = P_x - t_x`` and ``Z = P_z - t_z`` -- the operations this module applies to a piece's ends
-- and every rounding step is monotone, so the computed column at any pose of the piece lies
between those at its ends, up to the roundings by which a fused multiply-add (the GPU kernels')
may differ: half a unit in the last place of each term, 8 times over. A point a hair off the
principal axis (``X`` ~ 1e-16, common in synthetic scenes) then stays in its column where
:data:`PIXEL_SLACK` would let it straddle two (one exactly on a column's edge still may)."""


def _scene(points, colors, K, rank):
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    xyz = np.ascontiguousarray(torch.as_tensor(points, dtype=torch.float64).cpu().numpy())
    table = np.ascontiguousarray(torch.as_tensor(colors).to(torch.float64).cpu().numpy())
    ranks = (
        np.arange(len(xyz))
        if rank is None
        else np.ascontiguousarray(torch.as_tensor(rank).to(torch.int64).cpu().numpy())
    )
    return xyz, table, ranks, (fx, fy, cx, cy)


def _axis_terms(axis: str) -> tuple[int, bool, int]:
    """The kernels' view of ``axis``: its index among the translations or the rotations, whether
    it is a translation, and which of a point's reference coordinates its depth at every pose
    depends on besides its reference depth, in the projection's arithmetic
    (``r02 dx + r12 dy + r22 dz``, the rotation made on the CPU for every device): ``-1`` for
    none -- along a translation the depth is ``Z`` less 0 or t, along a roll ``Z`` itself (the
    column is exactly (0, 0, 1)), so the order and the ties of depths are kept -- ``1`` (``Y``)
    along a pitch, whose column is exactly (0, -sin, cos), and ``0`` (``X``) along a yaw, (sin, 0,
    cos): there two points of equal ``Z`` and equal ``Y`` (or ``X``) have the same depth, bit for
    bit, at every pose, and the one of lower rank wins every tie; every rounding step being
    monotone, a depth also never decreases with ``Z`` within a quarter turn, nor with ``Y`` (or
    ``X``) times the sign of its coefficient on a piece on one side of no rotation."""
    i, translation = axis_index(axis), is_translation(axis)
    shared = -1 if translation or axis == "rz" else {"rx": 1, "ry": 0}[axis]
    return (i if translation else i - 3), translation, shared


def _check_rotation(axis: str, widest: float) -> None:
    if not is_translation(axis) and widest >= np.pi:
        raise ValueError(f"a rotation piece must be narrower than pi (its arc's bound); got {widest}")


def piece_bounds(
    points: torch.Tensor,
    colors: torch.Tensor,
    K: torch.Tensor,
    axis: str,
    frames: torch.Tensor,
    images: torch.Tensor,
    background: float,
    per_pixel: bool = False,
    rank: torch.Tensor | None = None,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each piece ``[alpha_k, alpha_k+1]`` of a one-axis frame sequence: upper bounds on
    ``||O(V, alpha) - x_k||_2`` (``left``) and ``||O(V, alpha) - x_k+1||_2`` (``right``) over every
    pose ``alpha`` of the piece.

    Args:
        points, colors: the cloud (N, 3) in the reference camera frame and its colours (N, C)
            -- every point that can land in the image for some pose of the interval.
        K: intrinsics; axis: the moving axis; frames: (K, 6) motions on that axis, increasing.
        images: (K, C, H, W) the frames' renders ``x_k``; background: the value of empty pixels.
        rank: each point's index for the projection's tie rule (default: its row).

    Each pixel contributes its largest squared distance to the frame's pixel over the colours
    it can take (the module docstring); with ``per_pixel`` those (K - 1, H, W) maps come back
    too (left, right, left map, right map).
    """
    i = axis_index(axis)
    amounts = frames[:, i].to(torch.float64).cpu().numpy()
    if len(amounts) < 2 or not np.all(np.diff(amounts) > 0):
        raise ValueError("frames must be at least 2 motions on one axis, in increasing order")
    _check_rotation(axis, float(np.diff(amounts).max()))
    xyz, table, ranks, camera = _scene(points, colors, K, rank)
    c, height, width = images.shape[1:]
    frames_np = np.ascontiguousarray(images.to(torch.float64).reshape(len(amounts), c, height * width).cpu().numpy())
    pieces = len(amounts) - 1
    left, right = np.empty(pieces), np.empty(pieces)
    maps = np.empty((2, pieces if per_pixel else 0, height * width))
    j, translation, shared = _axis_terms(axis)
    _distance_kernel(
        xyz,
        ranks,
        table,
        amounts,
        j,
        translation,
        shared,
        *camera,
        height,
        width,
        float(background),
        frames_np,
        left,
        right,
        maps,
    )
    if per_pixel:
        return left, right, maps[0].reshape(pieces, height, width), maps[1].reshape(pieces, height, width)
    return left, right


def image_boxes(
    points: torch.Tensor,
    colors: torch.Tensor,
    K: torch.Tensor,
    axis: str,
    starts,
    ends,
    height: int,
    width: int,
    background: float,
    rank: torch.Tensor | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per piece ``[starts[k], ends[k]]`` on ``axis`` (motion units): the lowest and highest value
    (each (P, C, H, W), float64) of every pixel and channel of any image projected from a pose
    of the piece; ``points``, ``colors``, ``K``, ``background`` and ``rank`` as for
    :func:`piece_bounds`. Extents are widened by :data:`ROUNDING` along a translation, by
    :data:`PIXEL_SLACK` along a rotation."""
    j, translation, shared = _axis_terms(axis)
    starts = np.ascontiguousarray(np.asarray(starts, np.float64).reshape(-1))
    ends = np.ascontiguousarray(np.asarray(ends, np.float64).reshape(-1))
    if len(starts) != len(ends) or not np.all(ends >= starts):
        raise ValueError("each piece needs a start at most its end")
    if len(starts):
        _check_rotation(axis, float((ends - starts).max()))
    xyz, table, ranks, camera = _scene(points, colors, K, rank)
    low = np.empty((len(starts), table.shape[1], height * width))
    high = np.empty_like(low)
    slack = (0.0, ROUNDING) if translation else (PIXEL_SLACK, 0.0)
    _box_kernel(
        xyz, ranks, table, starts, ends, j, translation, shared, *camera, height, width, *slack,
        float(background), low, high,
    )  # fmt: skip
    shape = (len(starts), table.shape[1], height, width)
    return low.reshape(shape), high.reshape(shape)


@numba.njit(cache=True, nogil=True)
def _path_vertices(P, a0, a1, j, translation, out):  # pragma: no cover - compiled
    """Vertices (rows of ``out``) of a convex polygon holding the point's camera coordinates for
    every motion from ``a0`` to ``a1`` on axis ``j``; returns how many (2 or 3).

    A translation ``t`` moves ``P`` to ``P - t``: the segment between the ends. A rotation
    by ``theta`` about axis ``j`` moves it to ``R(theta)^T P``, an arc about that axis; the arc
    (of angle ``< pi``) lies in the triangle of its ends and the meeting point of their tangents."""
    if translation:
        for k in range(3):
            out[0, k] = P[k]
            out[1, k] = P[k]
        out[0, j] -= a0
        out[1, j] -= a1
        return 2
    p, q = (j + 1) % 3, (j + 2) % 3  # R(theta)^T turns (P_p, P_q) by -theta
    mid = 0.5 * (a0 + a1)
    half = 0.5 * (a1 - a0)
    for row, angle, scale in ((0, a0, 1.0), (1, a1, 1.0), (2, mid, 1.0 / np.cos(half))):
        cs, sn = np.cos(angle), np.sin(angle)
        out[row, j] = P[j]
        out[row, p] = (cs * P[p] + sn * P[q]) * scale
        out[row, q] = (-sn * P[p] + cs * P[q]) * scale
    return 3


@numba.njit(cache=True, nogil=True)
def _piece_reach(
    P, rank, a0, a1, j, translation, shared, fx, fy, cx, cy, height, width, slack, relative
):  # pragma: no cover - compiled
    """The geometry of one piece (module docstring): per point its pixel box (u0, u1, v0, v1;
    u0 > u1: it cannot land) and least depth; per pixel the largest depth of a point staying in
    it, minimised (inf: it may be empty), and two staying points that may hide others there
    (rows; -1: none): the one of least (reference depth, rank) and, along a pitch or a yaw on one
    side of no rotation, the one of least (reference depth, signed shared coordinate, rank); and
    the piece's signs for :func:`_hides`. Extents are widened by ``slack`` pixels plus
    ``relative`` times ``|u| + |u - cx| + 1`` (the two terms the column is summed from, and one)."""
    n = P.shape[0]
    hw = height * width
    box = np.zeros((n, 4), np.int64)
    zlow = np.empty(n)
    cover = np.full(hw, np.inf)
    tie = np.full(hw, -1, np.int64)
    tie2 = np.full(hw, -1, np.int64)
    # Along a pitch or a yaw within a quarter turn of no rotation, a depth is the rounded sum of
    # the rounded products (shared coordinate) x (-sin or sin) and Z x cos with cos >= 0: it never
    # decreases with Z, and with the shared coordinate times ``wsign`` on a piece on one side of
    # no rotation (on a piece across it that coordinate must be equal).
    wsign, zsign = 0, 1
    if shared >= 0:
        zsign = 1 if max(abs(a0), abs(a1)) <= 0.5 * np.pi else 0
        side = 0 if zsign == 0 else (1 if a0 >= 0.0 else (-1 if a1 <= 0.0 else 0))
        wsign = -side if shared == 1 else side
    verts = np.empty((3, 3))
    for i in range(n):
        m = _path_vertices(P[i], a0, a1, j, translation, verts)
        zmin, zmax = np.inf, -np.inf
        umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
        for r in range(m):
            z = verts[r, 2]
            zmin, zmax = min(zmin, z), max(zmax, z)
            if z > 0.0:
                u = fx * (verts[r, 0] / z) + cx
                v = fy * (verts[r, 1] / z) + cy
                umin, umax, vmin, vmax = min(umin, u), max(umax, u), min(vmin, v), max(vmax, v)
        zlow[i] = zmin - 1e-9 * abs(zmin)
        if zmax <= 0.0:  # behind the camera throughout
            box[i, 0], box[i, 1] = 1, 0
            continue
        if zmin <= 1e-9 * zmax:  # may cross the camera plane: anywhere in the image
            box[i, 0], box[i, 1], box[i, 2], box[i, 3] = 0, width - 1, 0, height - 1
            zlow[i] = -np.inf
            continue
        if relative == 0.0:
            su0 = su1 = sv0 = sv1 = slack
        else:
            su0 = slack + relative * (abs(umin) + abs(umin - cx) + 1.0)
            su1 = slack + relative * (abs(umax) + abs(umax - cx) + 1.0)
            sv0 = slack + relative * (abs(vmin) + abs(vmin - cy) + 1.0)
            sv1 = slack + relative * (abs(vmax) + abs(vmax - cy) + 1.0)
        lo_u, hi_u = np.floor(umin - su0), np.floor(umax + su1)
        lo_v, hi_v = np.floor(vmin - sv0), np.floor(vmax + sv1)
        if hi_u < 0 or lo_u >= width or hi_v < 0 or lo_v >= height:
            box[i, 0], box[i, 1] = 1, 0
            continue
        box[i, 0], box[i, 1] = int(max(lo_u, 0.0)), int(min(hi_u, width - 1.0))
        box[i, 2], box[i, 3] = int(max(lo_v, 0.0)), int(min(hi_v, height - 1.0))
        if lo_u == hi_u and lo_v == hi_v:  # stays in this pixel for the whole piece
            p = int(lo_v) * width + int(lo_u)
            cover[p] = min(cover[p], zmax + 1e-9 * abs(zmax))
            k = tie[p]
            if k < 0 or P[i, 2] < P[k, 2] or (P[i, 2] == P[k, 2] and rank[i] < rank[k]):
                tie[p] = i
            k = tie2[p]
            if wsign != 0 and (
                k < 0
                or P[i, 2] < P[k, 2]
                or (P[i, 2] == P[k, 2] and wsign * P[i, shared] < wsign * P[k, shared])
                or (P[i, 2] == P[k, 2] and P[i, shared] == P[k, shared] and rank[i] < rank[k])
            ):
                tie2[p] = i
    return box, zlow, cover, tie, tie2, wsign, zsign


@numba.njit(cache=True, nogil=True)
def _hides(k, i, P, rank, shared, wsign, zsign):  # pragma: no cover - compiled
    """Whether the staying point ``k`` wins against point ``i`` at every pose of the piece: it
    is of lower rank (it wins every tie) and i's depth is never less than its, because every
    rounding step of the projection's depth is monotone (:func:`_axis_terms`): along a
    translation or a roll i is no nearer in the reference frame; along a pitch or a yaw i's
    reference depth and shared coordinate are each equal to k's or, where the piece's signs
    allow (:func:`_piece_reach`), on the deeper side."""
    if k < 0 or rank[i] <= rank[k]:  # none, or i itself (ranks are unique)
        return False
    zi, zk = P[i, 2], P[k, 2]
    if not (zi == zk or (zsign > 0 and zi > zk)):
        return False
    if shared < 0:
        return True
    wi, wk = P[i, shared], P[k, shared]
    return wi == wk or (wsign != 0 and wsign * wi > wsign * wk)


@numba.njit(cache=True, nogil=True)
def _may_show(i, p, P, rank, zlow, cover, tie, tie2, shared, wsign, zsign):  # pragma: no cover - compiled
    """Whether point ``i``, whose path crosses pixel ``p``, can be the one seen there."""
    if zlow[i] > cover[p]:  # a point staying here is always nearer
        return False
    return not (_hides(tie[p], i, P, rank, shared, wsign, zsign) or _hides(tie2[p], i, P, rank, shared, wsign, zsign))


@numba.njit(parallel=True, cache=True, nogil=True)
def _distance_kernel(
    P, rank, colors, amounts, j, translation, shared, fx, fy, cx, cy, height, width, background, frames, left,
    right, maps
):  # pragma: no cover - compiled  # fmt: skip
    n, nc = P.shape[0], colors.shape[1]
    hw = height * width
    for k in numba.prange(len(amounts) - 1):
        box, zlow, cover, tie, tie2, wsign, zsign = _piece_reach(
            P, rank, amounts[k], amounts[k + 1], j, translation, shared, fx, fy, cx, cy, height, width, PIXEL_SLACK, 0.0
        )
        worst_l = np.zeros(hw)
        worst_r = np.zeros(hw)
        for i in range(n):
            if box[i, 0] > box[i, 1]:
                continue
            for v in range(box[i, 2], box[i, 3] + 1):
                for u in range(box[i, 0], box[i, 1] + 1):
                    p = v * width + u
                    if not _may_show(i, p, P, rank, zlow, cover, tie, tie2, shared, wsign, zsign):
                        continue
                    dl, dr = 0.0, 0.0
                    for ch in range(nc):
                        dl += (colors[i, ch] - frames[k, ch, p]) ** 2
                        dr += (colors[i, ch] - frames[k + 1, ch, p]) ** 2
                    worst_l[p] = max(worst_l[p], dl)
                    worst_r[p] = max(worst_r[p], dr)
        total_l, total_r = 0.0, 0.0
        for p in range(hw):
            if cover[p] == np.inf:  # may be empty somewhere in the piece
                dl, dr = 0.0, 0.0
                for ch in range(nc):
                    dl += (background - frames[k, ch, p]) ** 2
                    dr += (background - frames[k + 1, ch, p]) ** 2
                worst_l[p] = max(worst_l[p], dl)
                worst_r[p] = max(worst_r[p], dr)
            total_l += worst_l[p]
            total_r += worst_r[p]
        left[k] = np.sqrt(total_l) * (1.0 + 1e-9)
        right[k] = np.sqrt(total_r) * (1.0 + 1e-9)
        if maps.shape[1]:
            maps[0, k] = worst_l
            maps[1, k] = worst_r


@numba.njit(parallel=True, cache=True, nogil=True)
def _box_kernel(
    P, rank, colors, starts, ends, j, translation, shared, fx, fy, cx, cy, height, width, slack, relative,
    background, low, high
):  # pragma: no cover - compiled  # fmt: skip
    n, nc = P.shape[0], colors.shape[1]
    hw = height * width
    for k in numba.prange(len(starts)):
        box, zlow, cover, tie, tie2, wsign, zsign = _piece_reach(
            P, rank, starts[k], ends[k], j, translation, shared, fx, fy, cx, cy, height, width, slack, relative
        )
        lo = np.full((nc, hw), np.inf)
        hi = np.full((nc, hw), -np.inf)
        for i in range(n):
            if box[i, 0] > box[i, 1]:
                continue
            for v in range(box[i, 2], box[i, 3] + 1):
                for u in range(box[i, 0], box[i, 1] + 1):
                    p = v * width + u
                    if not _may_show(i, p, P, rank, zlow, cover, tie, tie2, shared, wsign, zsign):
                        continue
                    for ch in range(nc):
                        lo[ch, p] = min(lo[ch, p], colors[i, ch])
                        hi[ch, p] = max(hi[ch, p], colors[i, ch])
        for p in range(hw):
            if cover[p] == np.inf:  # may be empty somewhere in the piece
                for ch in range(nc):
                    lo[ch, p] = min(lo[ch, p], background)
                    hi[ch, p] = max(hi[ch, p], background)
        low[k] = lo
        high[k] = hi
