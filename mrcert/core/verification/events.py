"""Every image a point cloud renders over a one-axis translation interval, enumerated exactly.

Along a translation the projection's rotation is the identity exactly, so the renderer computes
a point's depth ``zc = Z - t_z`` and column ``uf = fx * ((X - t_x) / zc) + cx`` (row alike) with
rounding steps that are each monotone in the pose: a point's column, row and whether it lies in
front of the camera change only at finitely many poses, and between two of them every point
keeps its pixel. Those poses are found in closed form (``t = X - (k - cx) Z / fx`` on ``tx``,
``t = Z - fx X / (k - cx)`` on ``tz``) and then located in the renderer's own float64
arithmetic: the first float pose at which the point's pixel class has changed, found by
bisection over the floats between two poses that bracket it, checked on both sides (the class
at the float before it is the old one). The image border (columns ``-1`` and ``W`` stand for
"left of" and "right of" the image) and the camera plane (``zc > 0``, on ``tz``) are crossings
like any other.

A sweep over the crossings in pose order keeps, per pixel, the points in it and the winner of
the z-buffer (the nearest, the lowest rank among equal depths). On ``tx`` and ``ty`` a point's
depth is ``Z`` itself at every pose; on ``tz`` the computed depths ``Z - t`` keep the order of the
``Z`` (subtraction is monotone) but two depths at most one float spacing apart may round to
equal at some poses and not at others, handing the pixel to the lower rank there. The sweep
flags every such pixel (:attr:`Enumeration.fragile`), with the colours it may take, so that
nothing the renderer draws is missed.

The result, :class:`Enumeration`, is the sequence of images along the interval: image ``k``
is what every float pose in ``[starts[k], starts[k+1])`` renders (the last up to the interval's
end), given incrementally: the first image's winners and, per later image, the pixels whose
winner changed (a few pixels each, where re-rendering would project every point again).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numba
import numpy as np
import torch

from mrcert.core.axes import axis_index
from mrcert.core.verification.float_order import _float, _key, _level
from mrcert.core.verification.rotation_events import ROTATIONS, _camera

TRANSLATIONS = ("tx", "ty", "tz")
"""The translations, enumerated here."""

AXES = (*TRANSLATIONS, *ROTATIONS)
"""The axes enumerated: the translations here, the rotations in
:mod:`mrcert.core.verification.rotation_events`."""


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _coords(X, Y, Z, axis, t, fx, fy, cx, cy):  # pragma: no cover - compiled
    """The renderer's float64 operations for one point at the pose ``t`` on translation ``axis``
    (the rotation the identity): its depth, column and row, before the floor."""
    tx = t if axis == 0 else 0.0
    ty = t if axis == 1 else 0.0
    tz = t if axis == 2 else 0.0
    dx = X - tx
    dy = Y - ty
    dz = Z - tz
    zc = 0.0 * dx + 0.0 * dy + 1.0 * dz
    uf = fx * ((1.0 * dx + 0.0 * dy + 0.0 * dz) / zc) + cx
    vf = fy * ((0.0 * dx + 1.0 * dy + 0.0 * dz) / zc) + cy
    return zc, uf, vf


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _classes(P, i, axis, t, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """(front, column level, row level) of point ``i`` at pose ``t``."""
    zc, uf, vf = _coords(P[i, 0], P[i, 1], P[i, 2], axis, t, fx, fy, cx, cy)
    if not zc > 0.0:
        return 0, -1, -1
    return 1, _level(uf, width), _level(vf, height)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def pixel_at(P, i, axis, t, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """The pixel point ``i`` lands on at pose ``t`` (-1: none), exactly as the renderer decides."""
    front, u, v = _classes(P, i, axis, t, fx, fy, cx, cy, height, width)
    if front == 0 or u < 0 or u >= width or v < 0 or v >= height:
        return -1
    return v * width + u


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _first(
    P, i, axis, coord, level, rising, lo, hi, guess, fx, fy, cx, cy, height, width, buf, ibuf
):  # pragma: no cover - compiled
    """The first float pose in ``(lo, hi]`` at which point ``i``'s column (``coord`` 1) or row
    (2) level has reached ``level`` (is at least it when ``rising``, at most otherwise), given
    that it has not at ``lo`` and has at ``hi``; ``guess`` (the closed form) narrows the search."""

    def reached(t):
        c = _classes(P, i, axis, t, fx, fy, cx, cy, height, width)[coord]
        return c >= level if rising else c <= level

    a, b = _key(lo, buf, ibuf), _key(hi, buf, ibuf)
    if lo < guess < hi:  # bracket the closed form by a few units in the last place, widening as needed
        g = _key(guess, buf, ibuf)
        step = 4
        while True:
            left, right = max(a, g - step), min(b, g + step)
            ok_left = left == a or not reached(_float(left, buf, ibuf))
            ok_right = right == b or reached(_float(right, buf, ibuf))
            if ok_left and ok_right:
                a, b = left, right
                break
            step *= 16
            if left == a and right == b:
                break
    while b - a > 1:  # invariant: not reached at a, reached at b
        m = a + (b - a) // 2
        if reached(_float(m, buf, ibuf)):
            b = m
        else:
            a = m
    return _float(b, buf, ibuf)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _point_events(P, i, axis, lo, hi, fx, fy, cx, cy, height, width, times, count, fill, buf, ibuf):  # pragma: no cover
    """The poses in ``(lo, hi]`` at which point ``i``'s pixel class changes: counted (``fill``
    False) or written into ``times`` from ``count``; returns the new count."""
    end = hi
    plane = False
    if axis == 2:
        if P[i, 2] <= lo:  # behind the camera throughout
            return count
        if P[i, 2] <= hi:  # it crosses the camera plane at the first pose t >= Z: Z itself
            plane = True
            end = _float(_key(P[i, 2], buf, ibuf) - 1, buf, ibuf)
    f0, u0, v0 = _classes(P, i, axis, lo, fx, fy, cx, cy, height, width)
    f1, u1, v1 = _classes(P, i, axis, end, fx, fy, cx, cy, height, width)
    if f0 == 0:  # behind the camera (tx, ty: throughout)
        return count
    X, Y, Z = P[i, 0], P[i, 1], P[i, 2]
    for coord in (1, 2):
        if (coord == 1 and axis == 1) or (coord == 2 and axis == 0):
            continue  # this coordinate does not move on this axis
        c0, c1 = (u0, u1) if coord == 1 else (v0, v1)
        if c0 == c1:
            continue
        rising = c1 > c0
        step = 1 if rising else -1
        focal, centre, along = (fx, cx, X) if coord == 1 else (fy, cy, Y)
        level = c0 + step
        while (level <= c1) if rising else (level >= c1):
            edge = float(level if rising else level + 1)  # the column edge the point crosses
            if axis == 2:
                guess = Z - focal * along / (edge - centre) if edge != centre else lo
            else:
                guess = along - (edge - centre) * Z / focal
            if fill:
                times[count] = _first(P, i, axis, coord, level, rising, lo, end, guess, fx, fy, cx, cy, height,
                                      width, buf, ibuf)  # fmt: skip
            count += 1
            level += step
    if plane:
        if fill:
            times[count] = Z
        count += 1
    return count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _events(P, axis, lo, hi, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """Every (pose, point) at which a point's pixel class changes in ``(lo, hi]``, in pose order."""
    buf = np.empty(1, np.float64)
    ibuf = buf.view(np.int64)
    n = P.shape[0]
    counts = np.empty(n + 1, np.int64)
    counts[0] = 0
    dummy = np.empty(0, np.float64)
    for i in range(n):
        counts[i + 1] = _point_events(P, i, axis, lo, hi, fx, fy, cx, cy, height, width, dummy, counts[i], False,
                                      buf, ibuf)  # fmt: skip
    times = np.empty(counts[n], np.float64)
    points = np.empty(counts[n], np.int64)
    for i in range(n):
        _point_events(P, i, axis, lo, hi, fx, fy, cx, cy, height, width, times, counts[i], True, buf, ibuf)
        points[counts[i] : counts[i + 1]] = i
    order = np.argsort(times, kind="mergesort")
    return times[order], points[order]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _before(P, rank, i, j):  # pragma: no cover - compiled
    """Whether point ``i`` beats point ``j`` for a pixel (nearer, or as near and of lower rank)."""
    return P[i, 2] < P[j, 2] or (P[i, 2] == P[j, 2] and rank[i] < rank[j])


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _nearer(P, rank, i, j, axis, c, s):  # pragma: no cover - compiled
    """:func:`_before` at a pose of ``rx`` (``axis`` 3) or ``ry`` (4) with the rotation's entries
    ``c`` and signed ``s``, where the depths move: the renderer's computed depths compared (the
    caller evaluates where no two depths of one pixel are within rounding, or records the pose)."""
    if axis == 3 or axis == 4:
        zi = _camera(P[i, 0], P[i, 1], P[i, 2], axis, 2, c, s)
        zj = _camera(P[j, 0], P[j, 1], P[j, 2], axis, 2, c, s)
        return zi < zj or (zi == zj and rank[i] < rank[j])
    return _before(P, rank, i, j)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _entries(t):  # pragma: no cover - compiled
    """A rotation's ``cos |t|`` and ``sign(t) sin |t|`` (:func:`mrcert.core.geometry.rotvec_to_matrix`)."""
    return math.cos(abs(t)), math.copysign(math.sin(abs(t)), t)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _translation_moves(P, axis, lo, times, points, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """Each point's pixel at ``lo`` and at each of its crossings, as the renderer decides."""
    start = np.empty(P.shape[0], np.int64)
    for i in range(P.shape[0]):
        start[i] = pixel_at(P, i, axis, lo, fx, fy, cx, cy, height, width)
    targets = np.empty(times.shape[0], np.int64)
    for k in range(times.shape[0]):
        targets[k] = pixel_at(P, points[k], axis, times[k], fx, fy, cx, cy, height, width)
    return start, targets


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sweep(P, rank, axis, lo, times, points, targets, start, g_start, g_end, g_row, g_point, g_pixel, tied, height,
           width):  # pragma: no cover - compiled  # fmt: skip
    """The images along the interval: the first image's winners, each later image's start pose,
    per image the pixels whose winner changed (image index, pixel, new winner; -1: none), and
    the points rounding may hand a pixel to (from image, to image, pixel, point): on tz (``axis``
    2) near-equal depths, and for each recorded group ``g`` (poses ``g_start[g]`` to ``g_end[g]``,
    its points' possible pixels in rows ``g_row[g]`` to ``g_row[g + 1]`` of ``g_point`` and
    ``g_pixel``) the colours those pixels may show. Each point starts in pixel ``start[i]`` and
    moves to ``targets[k]`` at ``times[k]`` (-1: no pixel); on rx and ry (``axis`` 3, 4) a target
    ``-2 - j`` ends, and ``-2 - N - j`` begins, a stretch where the point's depth and point
    ``j``'s are within rounding (``tied``: the pairs ``i * N + j``, ``i < j``, within it at
    ``lo``): while it lasts, the one that is not the winner of their pixel may show there."""
    n, hw = P.shape[0], height * width
    pix = np.full(n, -1, np.int64)
    head = np.full(hw, -1, np.int64)
    nxt = np.full(n, -1, np.int64)
    prv = np.full(n, -1, np.int64)
    winner = np.full(hw, -1, np.int64)
    shown = np.full(hw, -1, np.int64)
    dirty = np.zeros(hw, np.bool_)
    touched = np.empty(hw, np.int64)

    c, s = _entries(lo)

    def insert(i, p, c, s):
        pix[i] = p
        prv[i] = -1
        nxt[i] = head[p]
        if head[p] >= 0:
            prv[head[p]] = i
        head[p] = i
        w = winner[p]
        if w < 0 or _nearer(P, rank, i, w, axis, c, s):
            winner[p] = i

    def find(p, c, s):
        best = -1
        q = head[p]
        while q >= 0:
            if best < 0 or _nearer(P, rank, q, best, axis, c, s):
                best = q
            q = nxt[q]
        return best

    for i in range(n):
        if start[i] >= 0:
            insert(i, start[i], c, s)
    for p in range(hw):
        shown[p] = winner[p]
    first = shown.copy()
    starts = [lo]
    c_image, c_pixel, c_winner = [0], [0], [0]
    c_image.clear(), c_pixel.clear(), c_winner.clear()
    f_from, f_to, f_pixel, f_point = [0], [0], [0], [0]
    f_from.clear(), f_to.clear(), f_pixel.clear(), f_point.clear()
    open_from = np.full(hw, -1, np.int64)  # the image from which a pixel's fragile records hold
    open_count = np.zeros(hw, np.int64)
    ties = {np.int64(0): True}  # the pairs of points whose depths are within rounding now
    ties.clear()
    for x in tied:
        ties[x] = True
    scans = axis == 2 or axis == 3 or axis == 4
    if scans:
        for p in range(hw):
            _fragile_scan(P, rank, axis, ties, p, head, nxt, winner, lo, 0, open_from, open_count, f_from, f_to,
                          f_pixel, f_point)  # fmt: skip
    member = np.zeros(n, np.bool_)
    u_record, u_pose = [0], [0.0]  # a group's record, and the pose up to which it holds
    u_record.clear(), u_pose.clear()
    w_rec = [0]  # per window, its first record
    w_rec.clear()
    m = times.shape[0]
    j = 0
    g = 0
    while j < m or g < g_start.shape[0]:
        t = times[j] if j < m else np.inf
        if g < g_start.shape[0] and g_start[g] < t:  # a group's records, from the state at its start
            w_rec.append(len(f_from))
            c, s = _entries(g_start[g])
            _group_records(P, rank, axis, c, s, ties, head, nxt, member, g_point[g_row[g] : g_row[g + 1]],
                           g_pixel[g_row[g] : g_row[g + 1]], len(starts) - 1, g_end[g], f_from, f_to, f_pixel,
                           f_point, u_record, u_pose)  # fmt: skip
            g += 1
            continue
        k = j
        ntouched = 0
        c, s = _entries(t)
        while k < m and times[k] == t:
            i = points[k]
            new = targets[k]
            k += 1
            if new <= -2:  # rx, ry: two depths within rounding from now on, or no longer
                j2 = (-2 - new) % n
                key = min(i, j2) * n + max(i, j2)
                if -2 - new >= n:
                    ties[key] = True
                elif key in ties:
                    ties.pop(key)
                for p in (pix[i], pix[j2]):
                    if p >= 0:
                        winner[p] = find(p, c, s)
                        if not dirty[p]:
                            dirty[p] = True
                            touched[ntouched] = p
                            ntouched += 1
                continue
            old = pix[i]
            if new == old:
                continue
            if old >= 0:  # out of its pixel: unlinked, the winner found again if it was the winner
                if prv[i] >= 0:
                    nxt[prv[i]] = nxt[i]
                else:
                    head[old] = nxt[i]
                if nxt[i] >= 0:
                    prv[nxt[i]] = prv[i]
                pix[i] = -1
                if winner[old] == i:
                    winner[old] = find(old, c, s)
                if not dirty[old]:
                    dirty[old] = True
                    touched[ntouched] = old
                    ntouched += 1
            if new >= 0:
                insert(i, new, c, s)
                if not dirty[new]:
                    dirty[new] = True
                    touched[ntouched] = new
                    ntouched += 1
        changed = False
        for q in range(ntouched):
            p = touched[q]
            dirty[p] = False
            if winner[p] != shown[p]:
                if not changed:
                    starts.append(t)
                    changed = True
                shown[p] = winner[p]
                c_image.append(len(starts) - 1)
                c_pixel.append(p)
                c_winner.append(winner[p])
        if scans:  # the touched pixels' fragile records closed, and opened anew from this pose on
            cur = len(starts) - 1
            end = cur if changed else cur + 1  # a record closed inside an image covers all of it
            for q in range(ntouched):
                p = touched[q]
                if open_from[p] >= 0:
                    left = open_count[p]
                    for r in range(len(f_pixel) - 1, -1, -1):
                        if left == 0:
                            break
                        if f_pixel[r] == p and f_to[r] < 0:
                            f_to[r] = max(end, f_from[r] + 1)
                            left -= 1
                    open_from[p] = -1
                    open_count[p] = 0
                _fragile_scan(P, rank, axis, ties, p, head, nxt, winner, lo, cur, open_from, open_count, f_from,
                              f_to, f_pixel, f_point)  # fmt: skip
        j = k
    m_images = len(starts)
    begins = np.array(starts)
    for r in range(len(f_to)):
        if f_to[r] < 0:
            f_to[r] = m_images
    for j in range(len(u_record)):  # through the image that holds the group's last pose
        r = u_record[j]
        f_to[r] = max(f_from[r] + 1, np.searchsorted(begins, u_pose[j], side="right"))
    fragile = np.empty((len(f_from), 4), np.int64)
    for r in range(len(f_from)):
        fragile[r, 0], fragile[r, 1], fragile[r, 2], fragile[r, 3] = f_from[r], f_to[r], f_pixel[r], f_point[r]
    w_rec.append(len(f_from))
    return first, np.array(starts), np.array(c_image), np.array(c_pixel), np.array(c_winner), fragile, np.array(w_rec)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _group_records(
    P,
    rank,
    axis,
    c,
    s,
    ties,
    head,
    nxt,
    member,
    g_point,
    g_pixel,
    image,
    until,
    f_from,
    f_to,
    f_pixel,
    f_point,
    u_record,
    u_pose,
):  # pragma: no cover - compiled
    """Records from ``image`` on (until the pose ``until``) of the colours each pixel ``g_pixel``
    may show while the group's points ``g_point`` may be in any of their pixels (-1: off the
    image): each of those points that may be there, and the nearest other point there (the
    background if none), and on rx and ry each point whose depth is within rounding of one of
    those (``ties``), a pixel's records nearest first (the background last)."""
    n = P.shape[0]
    for r in range(g_point.shape[0]):
        member[g_point[r]] = True
    for r in range(g_pixel.shape[0]):
        p = g_pixel[r]
        if p < 0:
            continue
        done = False
        for r2 in range(r):
            done = done or g_pixel[r2] == p
        if done:
            continue
        best = -1
        q = head[p]
        while q >= 0:
            if not member[q] and (best < 0 or _nearer(P, rank, q, best, axis, c, s)):
                best = q
            q = nxt[q]
        options = [best]
        for r2 in range(g_pixel.shape[0]):
            if g_pixel[r2] == p and g_point[r2] not in options:
                options.append(g_point[r2])
        if len(ties):  # rx, ry: a point whose depth is within rounding of an option's may show instead
            q = head[p]
            while q >= 0:
                if q not in options:
                    for o in options:
                        if o >= 0 and (min(o, q) * n + max(o, q)) in ties:
                            options.append(q)
                            break
                q = nxt[q]
        for x in range(1, len(options)):  # nearest first: the z-buffer's order
            y = x
            while (
                y > 0
                and options[y] >= 0
                and (options[y - 1] < 0 or _nearer(P, rank, options[y], options[y - 1], axis, c, s))
            ):
                options[y - 1], options[y] = options[y], options[y - 1]
                y -= 1
        for q in options:
            u_record.append(len(f_from))
            u_pose.append(until)
            f_from.append(image)
            f_to.append(-1)
            f_pixel.append(p)
            f_point.append(q)
    for r in range(g_point.shape[0]):
        member[g_point[r]] = False


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fragile_scan(
    P, rank, axis, ties, p, head, nxt, winner, lo, image, open_from, open_count, f_from, f_to, f_pixel, f_point
):  # pragma: no cover - compiled
    """Open a record for each point of pixel ``p`` that rounding may hand it to from ``image`` on.
    On tz: of lower rank than the winner ``w`` (it then wins a tie) and deeper by at most the
    spacing of the floats above its largest computed depth ``fl(Z_q - lo)``. Two depths further
    apart never round to one value: if ``fl(Z_w - t) = fl(Z_q - t) = g``, each is within half the
    spacing around ``g`` of it, so ``Z_q - Z_w`` is at most the spacing above ``g <= fl(Z_q - lo)``.
    On rx and ry: each point whose depth is within rounding of the winner's now (``ties``)."""
    w = winner[p]
    if w < 0:
        return
    n = P.shape[0]
    zw = P[w, 2]
    q = head[p]
    while q >= 0:
        if axis != 2:
            may = q != w and (min(q, w) * n + max(q, w)) in ties
        else:
            zq = P[q, 2]
            top = zq - lo
            may = zq > zw and rank[q] < rank[w] and zq - zw <= np.nextafter(top, np.inf) - top
        if may:
            f_from.append(image)
            f_to.append(-1)
            f_pixel.append(p)
            f_point.append(q)
            open_from[p] = image
            open_count[p] += 1
        q = nxt[q]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _images(first, c_image, c_pixel, c_winner, table, start, stop, out):  # pragma: no cover - compiled
    """Images ``start`` to ``stop - 1`` from the first image's winners and the changes after it."""
    current = first.copy()
    r = 0
    while r < c_image.shape[0] and c_image[r] <= start:
        current[c_pixel[r]] = c_winner[r]
        r += 1
    for k in range(start, stop):
        while r < c_image.shape[0] and c_image[r] <= k:
            current[c_pixel[r]] = c_winner[r]
            r += 1
        image = out[k - start]
        for p in range(current.shape[0]):
            w = current[p]
            for ch in range(table.shape[1]):
                image[ch, p] = table[w, ch]


def record_options(records: np.ndarray) -> dict[int, list[int]]:
    """Per pixel of fragile ``records`` (from, to, pixel, point), in order of first record, the
    points (-1: the background) they allow there, each once (two windows may record one)."""
    options: dict[int, list[int]] = {}
    for _, _, p, q in records.tolist():
        if q not in options.setdefault(p, []):
            options[p].append(q)
    return options


@dataclass
class Enumeration:
    """The images along ``[lo, hi]`` on ``axis`` (module docstring)."""

    axis: str
    lo: float
    hi: float
    starts: np.ndarray  # (M,) the first float pose of each image
    first: np.ndarray  # (H*W,) the first image's winner per pixel (-1: background)
    change_image: np.ndarray  # (D,) the image at which a pixel's winner changes
    change_pixel: np.ndarray
    change_winner: np.ndarray
    colors: np.ndarray  # (N, C) float32, and the background
    background: float
    height: int
    width: int
    events: int  # crossings located
    fragile: np.ndarray  # (F, 4): from image, to image (exclusive), pixel, a point rounding may hand it to (tz)
    # a rotation: window w's records are rows window_records[w] to window_records[w + 1] of ``fragile`` (a
    # pixel's nearest first); its free points and the pixels each may occupy (-1: off the image)
    # rows window_rows[w] to window_rows[w + 1] of ``free`` (point, pixel, unit: the points of one unit
    # take their r-th pixels together, :meth:`free_points`)
    window_records: np.ndarray
    window_rows: np.ndarray
    free: np.ndarray

    def __len__(self) -> int:
        return len(self.starts)

    def pose(self, k: int) -> float:
        """A pose that renders image ``k`` (its first)."""
        return float(self.starts[k])

    def ends(self) -> np.ndarray:
        """(M,) the last float pose of each image."""
        nxt = np.nextafter(self.starts[1:], -np.inf)
        return np.append(nxt, self.hi)

    def table(self) -> np.ndarray:
        """(N + 1, C): each point's colour, and the background last (index -1)."""
        bg = np.full((1, self.colors.shape[1]), self.background, self.colors.dtype)
        return np.concatenate([self.colors, bg])

    def images(self, start: int, stop: int) -> np.ndarray:
        """Images ``start`` to ``stop - 1`` as (B, C, H, W), in the colours' dtype."""
        out = np.empty((stop - start, self.colors.shape[1], self.height * self.width), self.colors.dtype)
        _images(self.first, self.change_image, self.change_pixel, self.change_winner, self.table(), start, stop, out)
        return out.reshape(stop - start, self.colors.shape[1], self.height, self.width)

    def alternates(self, start: int, stop: int) -> np.ndarray:
        """The fragile records (from, to, pixel, point) that hold for some image ``start`` to ``stop - 1``."""
        f = self.fragile
        return f[(f[:, 0] < stop) & (f[:, 1] > start)] if len(f) else f

    def windows_at(self, k: int) -> list[int]:
        """The windows (a rotation) whose records hold image ``k``."""
        r = self.window_records
        held = np.nonzero(r[1:] > r[:-1])[0]
        first = self.fragile[r[held]] if len(held) else np.empty((0, 4), np.int64)
        return held[(first[:, 0] <= k) & (first[:, 1] > k)].tolist()

    def beside_windows(self, k: int, windows: list[int]) -> np.ndarray:
        """The fragile records holding image ``k`` that are not the ``windows``' (on rx and ry:
        two depths within rounding of each other, a pair along the whole interval among them)."""
        f = self.fragile
        if not len(f):
            return f
        held = (f[:, 0] <= k) & (f[:, 1] > k)
        for w in windows:
            held[self.window_records[w] : self.window_records[w + 1]] = False
        return f[held]

    def free_points(self, w: int) -> tuple[dict[int, list[int]], dict[int, list[int]], dict[int, list[int]]]:
        """Window ``w`` (a rotation): each free point's pixels (-1: off the image), per pixel of its
        records the points that may show there, nearest first (-1: the background): every free
        point that may be there, and the nearest other point, which is there throughout; and the
        free points in units: points on one line along the rotation's axis, whose level the
        renderer computes from the same numbers, are in their ``r``-th pixels together."""
        pixels: dict[int, list[int]] = {}
        units: dict[int, list[int]] = {}
        for q, p, unit in self.free[self.window_rows[w] : self.window_rows[w + 1]].tolist():
            pixels.setdefault(q, []).append(p)  # a pixel per level: a unit's points' lists align
            if q not in units.setdefault(unit, []):
                units[unit].append(q)
        ranked: dict[int, list[int]] = {}
        for _, _, p, q in self.fragile[self.window_records[w] : self.window_records[w + 1]].tolist():
            ranked.setdefault(p, []).append(q)
        return pixels, ranked, units

    def variants(self, k: int, limit: int) -> np.ndarray | None:
        """Image ``k`` with every combination of the points its fragile records allow at their
        pixels, the nominal image excluded: (V, C, H, W), empty without records; None when there
        would be more than ``limit``."""
        records = self.alternates(k, k + 1)
        if not len(records):
            return np.empty((0, self.colors.shape[1], self.height, self.width), self.colors.dtype)
        options = record_options(records)
        count = 1
        for points in options.values():
            count *= len(points) + 1
        if count - 1 > limit:
            return None
        nominal = self.images(k, k + 1)[0].reshape(self.colors.shape[1], -1)
        table = self.table()
        out = []
        for combo in itertools.product(*([None, *points] for points in options.values())):
            if all(q is None for q in combo):
                continue
            image = nominal.copy()
            for p, q in zip(options, combo, strict=True):
                if q is not None:
                    image[:, p] = table[q]
            out.append(image.reshape(-1, self.height, self.width))
        return np.stack(out)

    def hull(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel and channel, the least and the greatest value images ``start`` to ``stop - 1``
        take (and any colour rounding may hand a fragile pixel): (C, H, W) each."""
        table = self.table()
        current = self.first.copy()
        upto = np.searchsorted(self.change_image, start, side="right")
        current[self.change_pixel[:upto]] = self.change_winner[:upto]
        low = table[current].copy()
        high = low.copy()
        hi = np.searchsorted(self.change_image, stop - 1, side="right")
        if hi > upto:
            values = table[self.change_winner[upto:hi]]
            pixels = self.change_pixel[upto:hi]
            np.minimum.at(low, pixels, values)
            np.maximum.at(high, pixels, values)
        for _, _, p, q in self.alternates(start, stop):
            low[p] = np.minimum(low[p], table[q])
            high[p] = np.maximum(high[p], table[q])
        shape = (self.height, self.width, table.shape[1])
        return low.reshape(shape).transpose(2, 0, 1), high.reshape(shape).transpose(2, 0, 1)


def enumerate_images(
    points: torch.Tensor | np.ndarray,
    colors: torch.Tensor | np.ndarray,
    rank: torch.Tensor | np.ndarray | None,
    K: torch.Tensor,
    height: int,
    width: int,
    background: float,
    axis: str,
    lo: float,
    hi: float,
) -> Enumeration:
    """The images a cloud (camera frame, every point that can land) renders at the float poses
    ``[lo, hi]`` on the translation ``axis`` (module docstring)."""
    if axis not in AXES:
        raise ValueError(f"exact enumeration reads {', '.join(AXES)}, got {axis!r}")
    if not lo <= hi:
        raise ValueError(f"an interval needs lo <= hi, got [{lo}, {hi}]")
    P = np.ascontiguousarray(torch.as_tensor(points, dtype=torch.float64).cpu().numpy())
    table = np.ascontiguousarray(torch.as_tensor(colors).cpu().numpy())
    table = table.astype(np.float32) if not np.issubdtype(table.dtype, np.floating) else table
    ranks = (
        np.arange(len(P), dtype=np.int64)
        if rank is None
        else np.ascontiguousarray(torch.as_tensor(rank).cpu().numpy().astype(np.int64))
    )
    K = torch.as_tensor(K, dtype=torch.float64)
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    a = axis_index(axis)
    if axis in ROTATIONS:
        from mrcert.core.verification.rotation_events import rotation_moves

        # Points at one position (bit for bit) land together at every pose and at one depth, where
        # the lowest rank wins: the others never show, and would only blur the records.
        order = np.argsort(ranks, kind="stable")
        keys = np.ascontiguousarray(P[order]).view(np.dtype((np.void, 3 * P.itemsize))).ravel()
        keep = np.sort(order[np.unique(keys, return_index=True)[1]])
        if len(keep) < len(P):
            P, table, ranks = np.ascontiguousarray(P[keep]), np.ascontiguousarray(table[keep]), ranks[keep]
        start, times, pts, targets, groups, events, tied, units = rotation_moves(P, K, axis, float(lo), float(hi),
                                                                          int(height), int(width))  # fmt: skip
    else:
        times, pts = _events(P, a, float(lo), float(hi), fx, fy, cx, cy, int(height), int(width))
        start, targets = _translation_moves(P, a, float(lo), times, pts, fx, fy, cx, cy, int(height), int(width))
        none = np.empty(0, np.int64)
        groups, events, tied = (np.empty(0), np.empty(0), np.zeros(1, np.int64), none, none), len(times), none
        units = none
    first, starts, c_image, c_pixel, c_winner, fragile, records = _sweep(
        P, ranks, a, float(lo), times, pts, targets, start, *groups, tied, int(height), int(width)
    )
    return Enumeration(axis, float(lo), float(hi), starts, first, c_image, c_pixel, c_winner, table,
                       float(background), int(height), int(width), events, fragile, records, groups[2],
                       np.column_stack([groups[3], groups[4], units]).astype(np.int64))  # fmt: skip
