"""The crossings of a rotation about the optical axis (``rz``), located soundly under float rounding.

About the optical axis the renderer's rotation has the entries ``c = cos|t|``, ``±s = ±sin|t|``,
0 and 1 exactly (:func:`mrcert.core.geometry.rotvec_to_matrix`), so a point keeps its depth
``Z`` at every pose -- the z-buffer's order never changes -- and only its column and row move:

    u(t) = fx (X cos t + Y sin t) / Z + cx,        v(t) = fy (Y cos t - X sin t) / Z + cy.

Unlike a translation, the renderer's arithmetic is not monotone in the pose (``c`` and ``s``
come from the library's ``cos`` and ``sin``, and ``c X + s Y`` sums two terms that move in
opposite directions), so the float pose at which a point's pixel changes is not one well-defined
float. Instead each crossing of a pixel edge ``k`` is a *band*: every float pose at which
``|u(t) - k| <= B`` holds, with ``B = 2^-47 (fx (|X| + |Y|) / Z + |cx|)`` (rows alike). Outside
its bands a point's pixel is certain:

* the renderer's computed column differs from the exact ``u(t)`` by at most
  ``e (7.1 fx (|X| + |Y|) / Z + |cx|)`` (``e = 2^-53``; each product, sum and quotient rounds
  once, and ``cos`` and ``sin`` are assumed within 16 units in the last place: glibc's and
  Sleef's are within 1, which ``tests/test_rotation_events.py`` checks against mpmath), and the
  float evaluation of ``u(t)`` used to find the bands differs from it by at most ``8 e`` times the
  same scale; both far inside ``B``;
* on a piece of the interval where ``u`` is monotone (split at its extremum), a band's ends are
  the last float before it whose evaluated ``u`` is below ``k - B`` and the first after it above
  ``k + B`` (closed form, then bisection over the floats), so every pose beyond them is further
  than ``B / 2`` from the edge.

``B`` holds the arithmetic's rounding, which scales with ``|cx|``, while the library's ``c`` and
``s`` are wrong by a few units in their own last place only. So each band is then narrowed in the
renderer's own arithmetic (:func:`_narrow`): over a span of poses the library's ``c`` and ``s``
lie in a small box around ours at the span's ends (the exact ``cos`` and ``sin`` are monotone
there), every rounding step of the column is monotone in ``c`` and in ``s``, so the column's
greatest and least computed levels over the span are those at two corners of the box, computed
exactly. Where they agree the point's pixel is certain over the whole span. Near ``rz = 0`` a
band shrinks from about ``B / |u'|`` to a few units in the last place of the pose, which orders
the crossings of points a scan puts on the principal column or row (``X`` or ``Y`` a rounding
error from 0), all within 1e-12 rad of 0.

A band that no other band overlaps changes nothing the enumeration misses: while it lasts the
point is in its old pixel or its new one and every other point is certain, so the renderer draws
either the image before the band or the image after it, and both are enumerated (the point moves
at the band's end, the first pose certain of the new pixel). Where bands overlap (two points,
or one point's column and row, ambiguous at once), or a band holds an end of the interval, or a
point turns back inside one, the images while they last are recorded as fragile, window by
window between the bands' ends: in each window only the points whose bands hold all of it may
be in either pixel (the others are certain there), and at each pixel such a point may occupy the
record holds the colours it may show (that point, or the nearest other point there, or the
background), exactly as rounding ties are recorded on ``tz``. Points at one position (bit for
bit) move as one and the lowest rank among them always wins, so the enumeration keeps that one
(:func:`mrcert.core.verification.events.enumerate_images`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from mrcert.core.projection import rotations, to_camera
from mrcert.core.verification.float_order import _float, _key, _level

BAND = 2.0**-47
"""A band's half-width in a coordinate, relative to ``fx (|X| + |Y|) / Z + |cx|`` (module docstring)."""

LIBM_ULPS = 16
"""How far from the exact value (units in the last place) ``cos`` and ``sin`` may be for :data:`BAND` to hold."""


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _f(A, B, C, t):  # pragma: no cover - compiled
    return A * math.cos(t) + B * math.sin(t) + C


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _cross(A, B, C, y, p, q, rising, buf, ibuf):  # pragma: no cover - compiled
    """On ``[p, q]``, where ``A cos t + B sin t + C`` is monotone (rising or not): the last float
    not yet past ``y`` and the first one past it (past: ``>= y`` rising, ``< y`` falling), given
    that ``p`` is not past and ``q`` is."""

    def past(t):
        f = _f(A, B, C, t)
        return f >= y if rising else f < y

    if not past(q):  # only at an edge the piece's end touches exactly: nothing to find inside
        return q, np.nextafter(q, np.inf)
    a, b = _key(p, buf, ibuf), _key(q, buf, ibuf)
    rho = math.hypot(A, B)
    x = (y - C) / rho if rho > 0 else 2.0
    if -1.0 <= x <= 1.0:  # the closed form: rho cos(t - phi) = y - C
        phi = math.atan2(B, A)
        base = math.acos(x)
        for g in (phi + base, phi - base, phi + base - 2 * math.pi, phi - base + 2 * math.pi):
            if p < g < q:
                k = _key(g, buf, ibuf)
                step = 4
                while True:
                    left, right = max(a, k - step), min(b, k + step)
                    ok_left = left == a or not past(_float(left, buf, ibuf))
                    if ok_left and (right == b or past(_float(right, buf, ibuf))):
                        a, b = left, right
                        break
                    if left == a and right == b:
                        break
                    step *= 16
                break
    while b - a > 1:  # invariant: not past at a, past at b
        m = a + (b - a) // 2
        if past(_float(m, buf, ibuf)):
            b = m
        else:
            a = m
    return _float(a, buf, ibuf), _float(b, buf, ibuf)


SLACK = 4.0 * LIBM_ULPS * 2.0**-52
"""Relative room around an evaluated ``cos`` or ``sin`` that holds the library's value at every
pose between two ends (:func:`_hull`): ours and the library's each within :data:`LIBM_ULPS`."""

TINY = 2.0**-1060
"""Absolute room beside :data:`SLACK`, for sines below the normal floats."""


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _hull(t1, t2):  # pragma: no cover - compiled
    """Bounds on the ``c`` and signed ``s = sign(t) sin|t|`` the renderer's library computes at
    any pose in ``[t1, t2]`` (within [-1, 1]): the exact ``cos`` and ``sin`` are monotone there (the
    cosine's greatest value 1 where the span holds 0), each library's value is within
    :data:`LIBM_ULPS` of the exact one, so :data:`SLACK` around ours at the ends holds them."""
    c1, c2 = math.cos(t1), math.cos(t2)
    c_lo, c_hi = min(c1, c2), max(c1, c2)
    if t1 <= 0.0 <= t2:
        c_hi = 1.0
    s_lo, s_hi = math.sin(t1), math.sin(t2)
    return (c_lo - SLACK * abs(c_lo) - TINY, c_hi + SLACK * abs(c_hi) + TINY,
            s_lo - SLACK * abs(s_lo) - TINY, s_hi + SLACK * abs(s_hi) + TINY)  # fmt: skip


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _corner(X, Y, Z, coord, t1, t2, high, fx, fy, cx, cy, size):  # pragma: no cover - compiled
    """The greatest (``high``) or least level the renderer can give the point's column (``coord``
    0) or row at any pose in ``[t1, t2]``: its own float64 operations (the rotation's entries
    ``c``, ``s``, ``-s``, 0 and 1 in :func:`mrcert.core.projection.to_camera`) at the corner of
    :func:`_hull` where they are greatest or least -- each rounding step is monotone in ``c`` and
    in ``s``, in the direction of the sign of the factor each multiplies."""
    c_lo, c_hi, s_lo, s_hi = _hull(t1, t2)
    if coord == 0:  # x = c X + s Y + 0 Z
        c = c_hi if (X >= 0.0) == high else c_lo
        s = s_hi if (Y >= 0.0) == high else s_lo
        return _level(fx * ((c * X + s * Y + 0.0 * Z) / Z) + cx, size)
    c = c_hi if (Y >= 0.0) == high else c_lo  # y = -s X + c Y + 0 Z
    s = s_hi if (X <= 0.0) == high else s_lo
    return _level(fy * (((-s) * X + c * Y + 0.0 * Z) / Z) + cy, size)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _narrow(X, Y, Z, coord, a, b, before, after, fx, fy, cx, cy, size, buf, ibuf):  # pragma: no cover
    """A band ``(a, b)`` of one edge made as narrow as the renderer's own arithmetic allows: the
    last pose ``a'`` up to which every pose of ``[a, a']`` is certain of the old level, and the
    first ``b'`` from which every pose of ``[b', b]`` is certain of the new one (:func:`_corner`
    over those spans; each answer holds for the whole span, so the bisection needs no
    monotonicity). Inside the band the level is the old one or the new one (the band's own
    guarantee), so a corner on the right side of the edge is certain of it."""
    edge = max(before, after)
    rising = after > before

    def passed(m, at_end):
        """Past the band's start (``[a, m]`` not certain of the old level) or, ``at_end``, its
        end (``[m, b]`` certain of the new one); false at the search's left end, true at its right."""
        if not at_end:
            if rising:
                return _corner(X, Y, Z, coord, a, m, True, fx, fy, cx, cy, size) >= edge
            return _corner(X, Y, Z, coord, a, m, False, fx, fy, cx, cy, size) < edge
        if rising:
            return _corner(X, Y, Z, coord, m, b, False, fx, fy, cx, cy, size) >= edge
        return _corner(X, Y, Z, coord, m, b, True, fx, fy, cx, cy, size) < edge

    def first(lo_k, hi_k, at_end):
        while hi_k - lo_k > 1:
            m = lo_k + (hi_k - lo_k) // 2
            if passed(_float(m, buf, ibuf), at_end):
                hi_k = m
            else:
                lo_k = m
        return lo_k, hi_k

    ka, kb = _key(a, buf, ibuf), _key(b, buf, ibuf)
    left = ka if passed(a, False) else first(ka, kb, False)[0]
    right = kb if not passed(b, True) else first(left, kb, True)[1]
    return _float(left, buf, ibuf), _float(right, buf, ibuf)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _coordinate_bands(A, B, C, size, half, lo, hi, out, start, fill, buf, ibuf):  # pragma: no cover - compiled
    """The bands of one coordinate ``A cos t + B sin t + C`` over ``[lo, hi]`` (module docstring),
    merged where they meet: rows (first float before, first float after, level before, level
    after) written into ``out`` from ``start`` when ``fill``; returns the new count."""
    cuts = [lo]
    phi = math.atan2(B, A)
    for m in (phi - math.pi, phi, phi + math.pi):  # where the derivative -A sin t + B cos t is 0
        if lo < m < hi:
            cuts.append(m)
    cuts.append(hi)
    count = start
    n_open = 0  # a band left open at a piece's end, continued by the next piece
    open_a, open_end, open_before, open_after = 0.0, 0.0, 0, 0
    for j in range(len(cuts) - 1):
        p, q = cuts[j], cuts[j + 1]
        fp, fq = _f(A, B, C, p), _f(A, B, C, q)
        mid = 0.5 * (p + q)
        rising = -A * math.sin(mid) + B * math.cos(mid) >= 0.0
        low, high = (fp, fq) if rising else (fq, fp)
        first, last = max(0, int(math.ceil(low - half))), min(size, int(math.floor(high + half)))
        if first > last:
            continue
        edges = range(first, last + 1) if rising else range(last, first - 1, -1)
        for e in edges:
            y0, y1 = (e - half, e + half) if rising else (e + half, e - half)
            before, after = (e - 1, e) if rising else (e, e - 1)
            if (fp >= y0) if rising else (fp < y0):  # the band began before this piece
                a = np.nextafter(p, -np.inf)
            else:
                a = _cross(A, B, C, y0, p, q, rising, buf, ibuf)[0]
            if (fq < y1) if rising else (fq >= y1):  # it lasts beyond this piece
                b = np.nextafter(q, np.inf)
            else:
                b = _cross(A, B, C, y1, p, q, rising, buf, ibuf)[1]
            if n_open and a <= open_end:
                a, before = open_a, open_before  # the band continued from the piece before
                n_open = 0
            elif n_open:
                if fill:
                    out[count, 0], out[count, 1] = open_a, open_end
                    out[count, 2], out[count, 3] = open_before, open_after
                count += 1
                n_open = 0
            if b > q and j < len(cuts) - 2:
                n_open = 1
                open_a, open_end, open_before, open_after = a, b, before, after
                continue
            if fill:
                out[count, 0], out[count, 1], out[count, 2], out[count, 3] = a, b, before, after
            count += 1
    if n_open:
        if fill:
            out[count, 0], out[count, 1] = open_a, open_end
            out[count, 2], out[count, 3] = open_before, open_after
        count += 1
    return count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _point_bands(P, i, lo, hi, fx, fy, cx, cy, height, width, out, start, fill, buf, ibuf):  # pragma: no cover
    """Point ``i``'s bands: columns then rows, with a last column 0 (column) or 1 (row)."""
    X, Y, Z = P[i, 0], P[i, 1], P[i, 2]
    if not Z > 0.0:
        return start
    scale = (fx * (abs(X) + abs(Y)) / Z + abs(cx), fy * (abs(X) + abs(Y)) / Z + abs(cy))
    count = start
    for coord in range(2):
        if coord == 0:
            A, B, C, size = fx * X / Z, fx * Y / Z, cx, width
        else:
            A, B, C, size = fy * Y / Z, -fy * X / Z, cy, height
        new = _coordinate_bands(A, B, C, size, BAND * scale[coord], lo, hi, out[:, :4], count, fill, buf, ibuf)
        if fill:
            out[count:new, 4] = coord
            for r in range(count, new):
                before, after = np.int64(out[r, 2]), np.int64(out[r, 3])
                if before != after:
                    out[r, 0], out[r, 1] = _narrow(X, Y, Z, coord, out[r, 0], out[r, 1], before, after, fx, fy,
                                                   cx, cy, size, buf, ibuf)  # fmt: skip
        count = new
    return count


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _bands(P, lo, hi, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """Every band of every point: (B, 5) rows (start, end, level before, level after, coordinate)
    and (B,) points, in point order."""
    n = P.shape[0]
    counts = np.zeros(n + 1, np.int64)
    dummy = np.empty((0, 5), np.float64)
    for i in numba.prange(n):
        buf = np.empty(1, np.float64)
        counts[i + 1] = _point_bands(P, i, lo, hi, fx, fy, cx, cy, height, width, dummy, 0, False, buf,
                                     buf.view(np.int64))  # fmt: skip
    offsets = np.cumsum(counts)
    out = np.empty((offsets[n], 5), np.float64)
    points = np.empty(offsets[n], np.int64)
    for i in numba.prange(n):
        buf = np.empty(1, np.float64)
        _point_bands(P, i, lo, hi, fx, fy, cx, cy, height, width, out, offsets[i], True, buf, buf.view(np.int64))
        points[offsets[i] : offsets[i + 1]] = i
    return out, points


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _start_levels(P, R, fx, fy, cx, cy, height, width, lu, lv):  # pragma: no cover - compiled
    """Each point's column and row level at the interval's start, in the renderer's own arithmetic."""
    t = np.zeros(3)
    for i in range(P.shape[0]):
        xc, yc, zc = to_camera(P, i, R, t)
        if zc > 0.0:
            lu[i], lv[i] = _level(fx * (xc / zc) + cx, width), _level(fy * (yc / zc) + cy, height)
        else:
            lu[i], lv[i] = -2, -2  # never lands


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pixel(lu, lv, height, width):  # pragma: no cover - compiled
    if lu < 0 or lu >= width or lv < 0 or lv >= height:
        return -1
    return lv * width + lu


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _timeline(bands, owners, lo, hi, lu, lv, height, width):  # pragma: no cover - compiled
    """From the bands: the moves (pose, point, new pixel) in pose order, and the windows whose
    images must be recorded (start, end, and per window its free points' possible pixels)."""
    n_b = bands.shape[0]
    order = np.argsort(bands[:, 0], kind="mergesort")
    # groups of overlapping bands, by their starts
    group = np.empty(n_b, np.int64)
    g_flag = [False]  # per group, whether it is recorded
    g_flag.clear()
    reach = -np.inf
    for r in range(n_b):
        k = order[r]
        a, b = bands[k, 0], bands[k, 1]
        flagged = a < lo or b > hi or bands[k, 2] == bands[k, 3]
        if len(g_flag) and a < reach:
            g = len(g_flag) - 1
            g_flag[g] = True  # two bands at once
        else:
            g_flag.append(flagged)
            g = len(g_flag) - 1
        g_flag[g] = g_flag[g] or flagged
        group[k] = g
        reach = max(reach, b)
    # moves, at each band's end
    moves = np.nonzero((bands[:, 1] <= hi) & (bands[:, 2] != bands[:, 3]))[0]
    moves = moves[np.argsort(bands[moves, 1], kind="mergesort")]
    times = bands[moves, 1].copy()
    points = owners[moves].copy()
    targets = np.empty(len(moves), np.int64)
    # A recorded group is cut at its bands' ends into windows; in each, the points whose bands
    # hold all of it may be at either level (the others' levels are certain there), so the
    # window's record lets those points alone be in any of their pixels.
    n_g = len(g_flag)
    members = [[np.int64(0)] for _ in range(n_g)]
    for g in range(n_g):
        members[g].clear()
    for r in range(n_b):
        k = order[r]
        if g_flag[group[k]]:
            members[group[k]].append(k)
    w_start, w_end = [0.0], [0.0]
    w_start.clear(), w_end.clear()
    w_rows = [[np.int64(0)]]
    w_rows.clear()
    for g in range(n_g):
        rows = members[g]
        if not len(rows):
            continue
        ends = np.empty(2 * len(rows))
        for q in range(len(rows)):
            ends[2 * q], ends[2 * q + 1] = bands[rows[q], 0], bands[rows[q], 1]
        ends = np.unique(ends)
        active = [np.int64(0)]
        active.clear()
        nxt_row = 0
        for x in range(len(ends) - 1):
            left, right = ends[x], ends[x + 1]
            while nxt_row < len(rows) and bands[rows[nxt_row], 0] <= left:  # rows in order of start
                active.append(rows[nxt_row])
                nxt_row += 1
            active = [k for k in active if bands[k, 1] >= right]
            if len(active):
                w_start.append(left)
                w_end.append(right)
                w_rows.append(active.copy())
    # candidate pixels of each window's points, from the levels at the window's start
    c_window, c_point, c_pixel = [0], [0], [0]
    c_window.clear(), c_point.clear(), c_pixel.clear()
    n_w = len(w_start)
    j = 0
    for w in range(n_w + 1):
        t_next = np.inf if w == n_w else w_start[w]
        while j < len(moves) and times[j] <= t_next:
            k = moves[j]
            i = owners[k]
            if bands[k, 4] == 0:
                lu[i] = np.int64(bands[k, 3])
            else:
                lv[i] = np.int64(bands[k, 3])
            targets[j] = _pixel(lu[i], lv[i], height, width)
            j += 1
        if w == n_w:
            break
        rows = w_rows[w]
        seen = [np.int64(0)]
        seen.clear()
        for k in rows:
            i = owners[k]
            if i in seen:
                continue
            seen.append(i)
            us, vs = [lu[i]], [lv[i]]
            for k2 in rows:
                if owners[k2] == i:
                    before, after = np.int64(bands[k2, 2]), np.int64(bands[k2, 3])
                    # a band through an extremum that comes back (before == after) touched a
                    # level on one side or the other
                    wide = 1 if before == after else 0
                    for level in range(min(before, after) - wide, max(before, after) + wide + 1):
                        if bands[k2, 4] == 0 and level not in us:
                            us.append(level)
                        if bands[k2, 4] == 1 and level not in vs:
                            vs.append(level)
            for u in us:
                for v in vs:  # -1: off the image, where the point shows nowhere
                    p = _pixel(u, v, height, width)
                    c_window.append(w)
                    c_point.append(i)
                    c_pixel.append(p)
    return (times, points, targets, np.array(w_start), np.array(w_end), np.array(c_window, np.int64),
            np.array(c_point, np.int64), np.array(c_pixel, np.int64))  # fmt: skip


def rz_moves(P: np.ndarray, K, lo: float, hi: float, height: int, width: int):
    """What the sweep needs on ``rz`` over ``[lo, hi]``: each point's pixel at ``lo`` (-1: none),
    the moves (pose, point, new pixel) in pose order, the recorded windows (start and end pose,
    offsets into the rows, and per row a point and a pixel it may occupy, -1: off the image), and
    the bands' count."""
    if not -1.0 <= lo <= hi <= 1.0:  # cos >= 0.5: the rotation's 1 is exact, and one extremum at most
        raise ValueError(f"an rz interval within [-1, 1] rad is enumerated, got [{lo}, {hi}]")
    K = torch.as_tensor(K, dtype=torch.float64)
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    motion = torch.zeros(1, 6, dtype=torch.float64)
    motion[0, 5] = lo
    R = np.ascontiguousarray(rotations(motion)[0].numpy())
    n = len(P)
    lu, lv = np.empty(n, np.int64), np.empty(n, np.int64)
    _start_levels(P, R, fx, fy, cx, cy, height, width, lu, lv)
    start = np.where((lu >= 0) & (lu < width) & (lv >= 0) & (lv < height), lv * width + lu, -1)
    bands, owners = _bands(P, float(lo), float(hi), fx, fy, cx, cy, int(height), int(width))
    times, points, targets, w_start, w_end, c_window, c_point, c_pixel = _timeline(
        bands, owners, float(lo), float(hi), lu, lv, int(height), int(width)
    )
    rows = np.bincount(c_window, minlength=len(w_start))
    groups = (w_start, w_end, np.r_[0, np.cumsum(rows)].astype(np.int64), c_point, c_pixel)
    return start.astype(np.int64), times, points, targets, groups, len(bands)
