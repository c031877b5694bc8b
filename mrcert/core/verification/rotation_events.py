"""The crossings of a rotation (``rz``, ``rx``, ``ry``), located soundly under float rounding.

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
  Sleef's are within 1, which ``tests/test_enumeration.py`` checks against mpmath), and the
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

About ``rx`` and ``ry`` the depth moves too (about rx: ``x = X``, ``y = c Y + s Z``,
``z = c Z - s Y``; about ry: ``x = c X - s Z``, ``y = Y``, ``z = s X + c Z``), so a coordinate is
``F (A cos t + B sin t + C) / (A2 cos t + B2 sin t) + centre``; it reaches ``y`` where an
``A' cos t + B' sin t + C'`` is 0 (:func:`_coordinate_bands`), bands are :data:`RATIO_BAND` wide
and narrowed by corners of both the numerator and the depth (:func:`_corner`), and bands through
an extremum or holding an end are settled where the corners are certain (:func:`_settle`). The
z-buffer's order changes where two depths meet: :func:`_candidate_pairs` finds the pairs that
may share a pixel and be its nearest, :func:`_pair_bands` their *depth bands* (where the exact
depths differ by at most the rounding of both, narrowed by corners); the sweep records, while
one lasts, that the shared pixel may show either, and decides the pixel again at its end.
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
def _camera(X, Y, Z, axis, which, c, s):  # pragma: no cover - compiled
    """Camera coordinate ``which`` (0: x, 1: y, 2: depth) of a point at a rotation about ``axis``
    (3: rx, 4: ry) with entries ``c`` and signed ``s``: the float64 operations of
    :func:`mrcert.core.projection.to_camera` (each product by 0 adds a zero, which changes no value)."""
    if axis == 3:  # R = [[1, 0, 0], [0, c, -s], [0, s, c]]
        if which == 0:
            return X
        if which == 1:
            return c * Y + s * Z
        return (-s) * Y + c * Z
    if which == 0:  # ry: R = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        return c * X + (-s) * Z
    if which == 1:
        return Y
    return s * X + c * Z


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _camera_bound(X, Y, Z, axis, which, c_lo, c_hi, s_lo, s_hi, high):  # pragma: no cover - compiled
    """The greatest (``high``) or least value :func:`_camera` can take with ``c`` and ``s`` in their
    boxes: each coordinate sums two rounded products, each monotone in its entry in the direction
    of the sign of the factor it multiplies (``-s``: the opposite)."""
    if axis == 3:
        if which == 0:
            return X
        if which == 1:
            c = c_hi if (Y >= 0.0) == high else c_lo
            s = s_hi if (Z >= 0.0) == high else s_lo
            return c * Y + s * Z
        s = s_lo if (Y >= 0.0) == high else s_hi
        c = c_hi if (Z >= 0.0) == high else c_lo
        return (-s) * Y + c * Z
    if which == 0:
        c = c_hi if (X >= 0.0) == high else c_lo
        s = s_lo if (Z >= 0.0) == high else s_hi
        return c * X + (-s) * Z
    if which == 1:
        return Y
    s = s_hi if (X >= 0.0) == high else s_lo
    c = c_hi if (Z >= 0.0) == high else c_lo
    return s * X + c * Z


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _corner(P, i, j, axis, coord, t1, t2, high, fx, fy, cx, cy, size):  # pragma: no cover - compiled
    """The greatest (``high``) or least level the renderer can give point ``i``'s column (``coord``
    0) or row (1) at any pose in ``[t1, t2]``: its own float64 operations at the corner of
    :func:`_hull` where they are greatest or least -- each rounding step is monotone in ``c`` and
    in ``s``, in the direction of the sign of the factor each multiplies. About the optical axis
    (``axis`` 5) the rotation's entries are ``c``, ``s``, ``-s``, 0 and 1 in
    :func:`mrcert.core.projection.to_camera`; about ``rx`` or ``ry`` the depth moves too, and the
    quotient is greatest at the greatest numerator over the least depth (or the greatest, for a
    negative numerator). ``coord`` 2 is the order of point ``i``'s depth and point ``j``'s: level
    -1 while ``i`` is certainly nearer, 0 while certainly farther; a tie (the rank decides) is
    neither, so the greatest level is 0 unless ``i`` is nearer at every corner, the least -1
    unless it is farther at every corner."""
    c_lo, c_hi, s_lo, s_hi = _hull(t1, t2)
    X, Y, Z = P[i, 0], P[i, 1], P[i, 2]
    if axis == 5:
        if coord == 0:  # x = c X + s Y + 0 Z
            c = c_hi if (X >= 0.0) == high else c_lo
            s = s_hi if (Y >= 0.0) == high else s_lo
            return _level(fx * ((c * X + s * Y + 0.0 * Z) / Z) + cx, size)
        c = c_hi if (Y >= 0.0) == high else c_lo  # y = -s X + c Y + 0 Z
        s = s_hi if (X <= 0.0) == high else s_lo
        return _level(fy * (((-s) * X + c * Y + 0.0 * Z) / Z) + cy, size)
    if coord == 2:
        X2, Y2, Z2 = P[j, 0], P[j, 1], P[j, 2]
        if high:
            far = _camera_bound(X, Y, Z, axis, 2, c_lo, c_hi, s_lo, s_hi, True)
            return 0 if far >= _camera_bound(X2, Y2, Z2, axis, 2, c_lo, c_hi, s_lo, s_hi, False) else -1
        near = _camera_bound(X, Y, Z, axis, 2, c_lo, c_hi, s_lo, s_hi, False)
        return -1 if near <= _camera_bound(X2, Y2, Z2, axis, 2, c_lo, c_hi, s_lo, s_hi, True) else 0
    z_lo = _camera_bound(X, Y, Z, axis, 2, c_lo, c_hi, s_lo, s_hi, False)
    if not z_lo > 0.0:  # at or behind the camera plane: nothing certain
        return size if high else -1
    z_hi = _camera_bound(X, Y, Z, axis, 2, c_lo, c_hi, s_lo, s_hi, True)
    num = _camera_bound(X, Y, Z, axis, coord, c_lo, c_hi, s_lo, s_hi, high)
    z = (z_lo if num >= 0.0 else z_hi) if high else (z_hi if num >= 0.0 else z_lo)
    if coord == 0:
        return _level(fx * (num / z) + cx, size)
    return _level(fy * (num / z) + cy, size)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _narrow(P, i, j, axis, coord, a, b, before, after, fx, fy, cx, cy, size, buf, ibuf):  # pragma: no cover
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
                return _corner(P, i, j, axis, coord, a, m, True, fx, fy, cx, cy, size) >= edge
            return _corner(P, i, j, axis, coord, a, m, False, fx, fy, cx, cy, size) < edge
        if rising:
            return _corner(P, i, j, axis, coord, m, b, False, fx, fy, cx, cy, size) >= edge
        return _corner(P, i, j, axis, coord, m, b, True, fx, fy, cx, cy, size) < edge

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


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _ratio(A, B, C, A2, B2, C2, F, centre, t):  # pragma: no cover - compiled
    return F * ((A * math.cos(t) + B * math.sin(t) + C) / (A2 * math.cos(t) + B2 * math.sin(t) + C2)) + centre


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _coordinate_bands(A, B, C, A2, B2, C2, F, centre, ratio, size, half, lo, hi, out, start, fill, buf,
                      ibuf):  # pragma: no cover - compiled  # fmt: skip
    """The bands of one coordinate over ``[lo, hi]`` (module docstring), merged where they meet:
    rows (first float before, first float after, level before, level after) written into ``out``
    from ``start`` when ``fill``; returns the new count. The coordinate is ``A cos t + B sin t + C``,
    or (``ratio``) ``F (A cos t + B sin t + C) / (A2 cos t + B2 sin t + C2) + centre`` with
    ``F > 0`` and a denominator (the depth) above 0 throughout: it reaches ``y`` where
    ``A' cos t + B' sin t + C' = 0`` with ``A' = A - m A2`` (and so on), ``m = (y - centre) / F``,
    and is monotone between the zeros of its derivative's numerator
    ``(B A2 - A B2) + (B C2 - C B2) cos t + (C A2 - A C2) sin t``."""
    cuts = [lo]
    if ratio:
        R0, Pc, Qs = B * A2 - A * B2, B * C2 - C * B2, C * A2 - A * C2
        rho = math.hypot(Pc, Qs)
        if rho > 0.0 and abs(R0) <= rho:
            phi, base = math.atan2(Qs, Pc), math.acos(-R0 / rho)
            for m in (phi - base - 2 * math.pi, phi - base, phi - base + 2 * math.pi,
                      phi + base - 2 * math.pi, phi + base, phi + base + 2 * math.pi):  # fmt: skip
                if lo < m < hi:
                    cuts.append(m)
            cuts.sort()
    else:
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
        mid = 0.5 * (p + q)
        if ratio:
            fp, fq = _ratio(A, B, C, A2, B2, C2, F, centre, p), _ratio(A, B, C, A2, B2, C2, F, centre, q)
            rising = R0 + Pc * math.cos(mid) + Qs * math.sin(mid) >= 0.0
        else:
            fp, fq = _f(A, B, C, p), _f(A, B, C, q)
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
            elif ratio:
                m0 = (y0 - centre) / F
                a = _cross(A - m0 * A2, B - m0 * B2, C - m0 * C2, 0.0, p, q, rising, buf, ibuf)[0]
            else:
                a = _cross(A, B, C, y0, p, q, rising, buf, ibuf)[0]
            if (fq < y1) if rising else (fq >= y1):  # it lasts beyond this piece
                b = np.nextafter(q, np.inf)
            elif ratio:
                m1 = (y1 - centre) / F
                b = _cross(A - m1 * A2, B - m1 * B2, C - m1 * C2, 0.0, p, q, rising, buf, ibuf)[1]
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


RATIO_BAND = 2.0**-40
"""About ``rx`` and ``ry``: a band's half-width in a coordinate, relative to
``F N / d (1 + D / d) + (size + |centre|) D / d + |centre|`` (``N``, ``D``: the sums of the
numerator's and the depth's coefficients in absolute value, ``d`` the least depth over the
interval), and in a depth difference relative to the two points' coefficients: the renderer's
error and the band finder's are each within ``2^-47`` of the same scale (module docstring)."""


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _depth_form(X, Y, Z, axis):  # pragma: no cover - compiled
    """The exact depth ``A2 cos t + B2 sin t`` of a point about ``rx`` (3) or ``ry`` (4)."""
    return (Z, -Y) if axis == 3 else (Z, X)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _point_bands(P, i, axis, lo, hi, fx, fy, cx, cy, height, width, out, start, fill, buf, ibuf):  # pragma: no cover
    """Point ``i``'s bands: columns then rows, with a column 4 of 0 (column) or 1 (row) and a
    column 5 of -1 (no partner)."""
    X, Y, Z = P[i, 0], P[i, 1], P[i, 2]
    if axis == 5:
        if not Z > 0.0:
            return start
        scale = (fx * (abs(X) + abs(Y)) / Z + abs(cx), fy * (abs(X) + abs(Y)) / Z + abs(cy))
    else:
        A2, B2 = _depth_form(X, Y, Z, axis)
        d = min(A2 * math.cos(lo) + B2 * math.sin(lo), A2 * math.cos(hi) + B2 * math.sin(hi))
        D = abs(A2) + abs(B2)
        if d < -1e-9 * D:  # behind the camera at both ends, so throughout (the interval is shorter than pi)
            return start
        if not d > 1e-9 * D:
            raise ValueError("a point crosses the camera plane in the interval; such intervals are not enumerated")
        d *= 1.0 - 2.0**-30
    count = start
    for coord in range(2):
        size = width if coord == 0 else height
        if axis == 5:
            if coord == 0:
                A, B, C = fx * X / Z, fx * Y / Z, cx
            else:
                A, B, C = fy * Y / Z, -fy * X / Z, cy
            new = _coordinate_bands(A, B, C, 0.0, 0.0, 1.0, 1.0, 0.0, False, size, BAND * scale[coord], lo, hi,
                                    out[:, :4], count, fill, buf, ibuf)  # fmt: skip
        else:
            if axis == 3:
                A, B, C = (0.0, 0.0, X) if coord == 0 else (Y, Z, 0.0)
            else:
                A, B, C = (X, -Z, 0.0) if coord == 0 else (0.0, 0.0, Y)
            F, centre = (fx, cx) if coord == 0 else (fy, cy)
            N = abs(A) + abs(B) + abs(C)
            half = RATIO_BAND * (F * N / d * (1.0 + D / d) + (size + abs(centre)) * D / d + abs(centre))
            new = _coordinate_bands(A, B, C, A2, B2, 0.0, F, centre, True, size, half, lo, hi, out[:, :4], count,
                                    fill, buf, ibuf)  # fmt: skip
        if fill:
            out[count:new, 4] = coord
            out[count:new, 5] = -1
            for r in range(count, new):
                before, after = np.int64(out[r, 2]), np.int64(out[r, 3])
                if before != after:
                    out[r, 0], out[r, 1] = _narrow(P, i, -1, axis, coord, out[r, 0], out[r, 1], before, after, fx,
                                                   fy, cx, cy, size, buf, ibuf)  # fmt: skip
        count = new
    return count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _certain(P, i, axis, coord, t1, t2, level, fx, fy, cx, cy, size):  # pragma: no cover - compiled
    """Whether point ``i``'s level in ``coord`` is ``level`` at every pose of ``[t1, t2]``."""
    return (_corner(P, i, -1, axis, coord, t1, t2, False, fx, fy, cx, cy, size) == level
            and _corner(P, i, -1, axis, coord, t1, t2, True, fx, fy, cx, cy, size) == level)  # fmt: skip


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _settle(P, bands, owners, axis, lo, hi, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """Bands through an extremum (``rx``, ``ry``: level before = level after) made as narrow as
    the renderer's own arithmetic allows: the point's level is certainly that one (both corners
    of :func:`_corner` on it) over ``[a, a']`` and ``[b', b]``; a band certain throughout (a
    point a rounding error from the principal column, ``u = cx`` up to 1e-13) is dropped, so
    that it does not hold the whole interval open; so is a band that holds an end of the interval
    where, inside the interval, the level is certainly the one beyond the band. Returns which
    bands are kept."""
    keep = np.ones(bands.shape[0], np.bool_)
    for r in numba.prange(bands.shape[0]):
        if bands[r, 4] == 2:
            continue
        i, coord, before, after = owners[r], np.int64(bands[r, 4]), np.int64(bands[r, 2]), np.int64(bands[r, 3])
        size = width if coord == 0 else height
        a, b = bands[r, 0], bands[r, 1]
        if before != after:  # a band that holds an end of the interval, certain there of the level beyond it
            if a < lo and _corner(P, i, -1, axis, coord, lo, min(b, hi), False, fx, fy, cx, cy, size) == after:
                keep[r] = _corner(P, i, -1, axis, coord, lo, min(b, hi), True, fx, fy, cx, cy, size) != after
            elif b > hi and _corner(P, i, -1, axis, coord, max(a, lo), hi, False, fx, fy, cx, cy, size) == before:
                keep[r] = _corner(P, i, -1, axis, coord, max(a, lo), hi, True, fx, fy, cx, cy, size) != before
            continue
        buf = np.empty(1, np.float64)
        ibuf = buf.view(np.int64)
        level = before

        if _certain(P, i, axis, coord, a, b, level, fx, fy, cx, cy, size):
            keep[r] = False
            continue
        ka, kb = _key(a, buf, ibuf), _key(b, buf, ibuf)
        lo_k, hi_k = ka, kb  # the last m with [a, m] certain
        if _certain(P, i, axis, coord, a, a, level, fx, fy, cx, cy, size):
            while hi_k - lo_k > 1:
                m = lo_k + (hi_k - lo_k) // 2
                if _certain(P, i, axis, coord, a, _float(m, buf, ibuf), level, fx, fy, cx, cy, size):
                    lo_k = m
                else:
                    hi_k = m
            left = lo_k
        else:
            left = ka
        lo_k, hi_k = left, kb  # the first m with [m, b] certain
        if _certain(P, i, axis, coord, b, b, level, fx, fy, cx, cy, size):
            while hi_k - lo_k > 1:
                m = lo_k + (hi_k - lo_k) // 2
                if _certain(P, i, axis, coord, _float(m, buf, ibuf), b, level, fx, fy, cx, cy, size):
                    hi_k = m
                else:
                    lo_k = m
            right = hi_k
        else:
            right = kb
        bands[r, 0], bands[r, 1] = _float(left, buf, ibuf), _float(right, buf, ibuf)
    return keep


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _bands(P, axis, lo, hi, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """Every band of every point on rotation ``axis`` (3: rx, 4: ry, 5: rz): (B, 6) rows (start,
    end, level before, level after, coordinate, partner) and (B,) points, in point order."""
    n = P.shape[0]
    counts = np.zeros(n + 1, np.int64)
    dummy = np.empty((0, 6), np.float64)
    for i in numba.prange(n):
        buf = np.empty(1, np.float64)
        counts[i + 1] = _point_bands(P, i, axis, lo, hi, fx, fy, cx, cy, height, width, dummy, 0, False, buf,
                                     buf.view(np.int64))  # fmt: skip
    offsets = np.cumsum(counts)
    out = np.empty((offsets[n], 6), np.float64)
    points = np.empty(offsets[n], np.int64)
    for i in numba.prange(n):
        buf = np.empty(1, np.float64)
        _point_bands(P, i, axis, lo, hi, fx, fy, cx, cy, height, width, out, offsets[i], True, buf,
                     buf.view(np.int64))  # fmt: skip
        points[offsets[i] : offsets[i + 1]] = i
    return out, points


SLICES = 64
"""The stretches of the interval in which :func:`_candidate_pairs` looks for the depths that may meet."""


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _same_depth(P, i, j, axis):  # pragma: no cover - compiled
    """Whether two points' computed depths are one value at every pose: the coordinates the
    depth reads (``Y`` and ``Z`` about ``rx``, ``X`` and ``Z`` about ``ry``) equal bit for bit."""
    return P[i, 2] == P[j, 2] and (P[i, 1] == P[j, 1] if axis == 3 else P[i, 0] == P[j, 0])


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _depth_range(A2, B2, t0, t1):  # pragma: no cover - compiled
    """The least and the greatest exact depth ``A2 cos t + B2 sin t`` over ``[t0, t1]``."""
    z0, z1 = A2 * math.cos(t0) + B2 * math.sin(t0), A2 * math.cos(t1) + B2 * math.sin(t1)
    top = max(z0, z1)
    phi = math.atan2(B2, A2)  # the greatest depth, rho, at t = phi
    if t0 < phi < t1:
        top = math.hypot(A2, B2)
    return min(z0, z1), top


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _slice_boxes(bands, first, lu, lv, t0, t1, height, width, box, fixed):  # pragma: no cover - compiled
    """Per point, the columns and rows it may occupy at a pose of ``[t0, t1]`` (its level after
    the bands that ended before, and both levels of each band that meets the stretch -- one more
    each side for a band through an extremum), clipped to the image (first > last: nowhere), and
    whether it is in one pixel of the image throughout."""
    for i in numba.prange(lu.shape[0]):
        u, v = lu[i], lv[i]
        for k in range(first[i], first[i + 1]):  # each coordinate's bands in pose order
            if bands[k, 1] < t0:
                if bands[k, 4] == 0:
                    u = np.int64(bands[k, 3])
                else:
                    v = np.int64(bands[k, 3])
        u0, u1, v0, v1 = u, u, v, v
        for k in range(first[i], first[i + 1]):
            if bands[k, 1] < t0 or bands[k, 0] > t1:
                continue
            before, after = np.int64(bands[k, 2]), np.int64(bands[k, 3])
            wide = 1 if before == after else 0
            if bands[k, 4] == 0:
                u0, u1 = min(u0, min(before, after) - wide), max(u1, max(before, after) + wide)
            else:
                v0, v1 = min(v0, min(before, after) - wide), max(v1, max(before, after) + wide)
        if lu[i] == -2:  # never lands
            u0, u1 = 1, 0
        fixed[i] = u0 == u1 and v0 == v1 and 0 <= u0 < width and 0 <= v0 < height
        box[i, 0], box[i, 1] = max(u0, 0), min(u1, width - 1)
        box[i, 2], box[i, 3] = max(v0, 0), min(v1, height - 1)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _candidate_pairs(P, axis, bands, first, lu, lv, lo, hi, height, width):  # pragma: no cover - compiled
    """The two points whose depth order may decide what a pixel shows (``rx``, ``ry``), as
    ``i * N + j`` (``i < j``, with repeats): stretch by stretch of the interval (:data:`SLICES`),
    in each pixel, the points that may be there and may be its nearest -- not farther at every
    pose of the stretch than a point that is there throughout (its greatest depth, up to the
    rounding of both, :data:`RATIO_BAND`) -- whose depth ranges over the stretch meet. A point
    farther than one there throughout never shows there, so its order with any other changes
    nothing that pixel shows."""
    n = P.shape[0]
    hw = height * width
    box = np.empty((n, 4), np.int64)
    fixed = np.empty(n, np.bool_)
    zlo, zhi, scale = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        A2, B2 = _depth_form(P[i, 0], P[i, 1], P[i, 2], axis)
        scale[i] = RATIO_BAND * (abs(A2) + abs(B2))
    out = [np.int64(0)]
    out.clear()
    counts = np.zeros(hw + 1, np.int64)
    members = np.empty(0, np.int64)
    front = np.empty(hw)
    for s in range(SLICES):
        t0 = lo + (hi - lo) * (s / SLICES)
        t1 = hi if s == SLICES - 1 else lo + (hi - lo) * ((s + 1) / SLICES)
        _slice_boxes(bands, first, lu, lv, t0, t1, height, width, box, fixed)
        for i in range(n):
            A2, B2 = _depth_form(P[i, 0], P[i, 1], P[i, 2], axis)
            zlo[i], zhi[i] = _depth_range(A2, B2, t0, t1)
        counts[:] = 0
        front[:] = np.inf
        for i in range(n):
            if fixed[i]:  # there throughout the stretch
                p = box[i, 2] * width + box[i, 0]
                front[p] = min(front[p], zhi[i] + scale[i])
            for v in range(box[i, 2], box[i, 3] + 1):
                for u in range(box[i, 0], box[i, 1] + 1):
                    counts[v * width + u + 1] += 1
        offsets = np.cumsum(counts)
        if members.shape[0] < offsets[hw]:
            members = np.empty(offsets[hw], np.int64)
        fill = offsets[:hw].copy()
        for i in range(n):
            for v in range(box[i, 2], box[i, 3] + 1):
                for u in range(box[i, 0], box[i, 1] + 1):
                    p = v * width + u
                    if zlo[i] - scale[i] <= front[p]:  # may be the nearest there
                        members[fill[p]] = i
                        fill[p] += 1
        for p in range(hw):
            for x in range(offsets[p], fill[p]):
                i = members[x]
                for y in range(x + 1, fill[p]):
                    j = members[y]
                    if _same_depth(P, i, j, axis):  # equal at every pose: the lower rank shows, always
                        continue
                    if zlo[i] - scale[i] <= zhi[j] + scale[j] and zlo[j] - scale[j] <= zhi[i] + scale[i]:
                        out.append(min(i, j) * n + max(i, j))
    return np.array(out, np.int64)


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _pair_bands(P, pairs, axis, lo, hi, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """The depth-order bands (``rx``, ``ry``) of the two points of each pair (``i * N + j``):
    where their exact depths differ by at most the rounding of both (:data:`RATIO_BAND`),
    narrowed in the renderer's own arithmetic (:func:`_corner`, coordinate 2), and kept only
    where the two may be in one pixel at once (their columns and rows over the band meet). Rows
    as :func:`_bands`' (coordinate 2, the partner in column 5, level -1: the point nearer than
    its partner, 0: farther) and their points."""
    n = P.shape[0]
    m = pairs.shape[0]
    slots = np.empty((m, 4, 6), np.float64)
    kept = np.zeros(m, np.int64)
    for x in numba.prange(m):
        buf = np.empty(1, np.float64)
        ibuf = buf.view(np.int64)
        local = np.empty((8, 4), np.float64)
        i, j = pairs[x] // n, pairs[x] % n
        Ai, Bi = _depth_form(P[i, 0], P[i, 1], P[i, 2], axis)
        Aj, Bj = _depth_form(P[j, 0], P[j, 1], P[j, 2], axis)
        half = RATIO_BAND * (abs(Ai) + abs(Bi) + abs(Aj) + abs(Bj))
        count = _coordinate_bands(Ai - Aj, Bi - Bj, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, False, 0, half, lo, hi, local, 0,
                                  True, buf, ibuf)  # fmt: skip
        for r in range(count):
            a, b, before, after = local[r, 0], local[r, 1], np.int64(local[r, 2]), np.int64(local[r, 3])
            if before != after:
                a, b = _narrow(P, i, j, axis, 2, a, b, before, after, fx, fy, cx, cy, 0, buf, ibuf)
            meet = True
            for coord in range(2):
                size = width if coord == 0 else height
                low = max(_corner(P, i, -1, axis, coord, a, b, False, fx, fy, cx, cy, size),
                          _corner(P, j, -1, axis, coord, a, b, False, fx, fy, cx, cy, size))  # fmt: skip
                high = min(_corner(P, i, -1, axis, coord, a, b, True, fx, fy, cx, cy, size),
                           _corner(P, j, -1, axis, coord, a, b, True, fx, fy, cx, cy, size))  # fmt: skip
                meet = meet and max(low, 0) <= min(high, size - 1)
            if meet:  # at most one band per piece, and at most two pieces on an interval shorter than pi
                row = slots[x, kept[x]]
                row[0], row[1], row[2], row[3], row[4], row[5] = a, b, before, after, 2, j
                kept[x] += 1
    total = kept.sum()
    out = np.empty((total, 6), np.float64)
    who = np.empty(total, np.int64)
    r = 0
    for x in range(m):
        for q in range(kept[x]):
            out[r] = slots[x, q]
            who[r] = pairs[x] // n
            r += 1
    return out, who


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
def _timeline(bands, owners, twin, lo, hi, lu, lv, height, width):  # pragma: no cover - compiled
    """From the bands: the moves (pose, point, new pixel) in pose order, and the windows whose
    images must be recorded (start, end, and per window its free points' possible pixels). A band
    whose ``twin`` is an earlier one is of the same coordinate computed from the same numbers:
    the two points move at one pose, so the two bands overlap without making a window, and in a
    window they make one unit (its root band, else ``-1 - point`` where a point has two bands):
    its points' candidate pixels, listed level by level in one order, are taken together."""
    n_b = bands.shape[0]
    order = np.argsort(bands[:, 0], kind="mergesort")
    # groups of overlapping bands, by their starts
    group = np.empty(n_b, np.int64)
    g_flag = [False]  # per group, whether it is recorded
    g_flag.clear()
    reach = -np.inf
    for r in range(n_b):
        k = order[r]
        if twin[k] != k:
            group[k] = group[twin[k]]
            continue
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
    c_window, c_point, c_pixel, c_unit = [0], [0], [0], [0]
    c_window.clear(), c_point.clear(), c_pixel.clear(), c_unit.clear()
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
            own, alone = 0, k
            for k2 in rows:
                if owners[k2] == i:
                    own += 1
                    alone = k2
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
                    # one band of the point's here: its twins' points take its level at every pose
                    c_unit.append(twin[alone] if own == 1 else -1 - i)
    return (times, points, targets, np.array(w_start), np.array(w_end), np.array(c_window, np.int64),
            np.array(c_point, np.int64), np.array(c_pixel, np.int64), np.array(c_unit, np.int64))  # fmt: skip


ROTATIONS = {"rx": 3, "ry": 4, "rz": 5}
"""The rotations enumerated here, by their index in a motion."""


def rotation_bands(P: np.ndarray, K, axis: str, lo: float, hi: float, height: int, width: int):
    """Every band on the rotation ``axis`` over ``[lo, hi]``: (B, 6) rows (start, end, level before,
    level after, coordinate: 0 column, 1 row, 2 depth order; partner: the other point of a depth
    order, else -1) and their points, and each point's column and row level at ``lo`` (-2: behind)."""
    if not -1.0 <= lo <= hi <= 1.0:  # cos >= 0.5: the rotation's 1 is exact, and one extremum at most
        raise ValueError(f"an {axis} interval within [-1, 1] rad is enumerated, got [{lo}, {hi}]")
    a = ROTATIONS[axis]
    K = torch.as_tensor(K, dtype=torch.float64)
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    motion = torch.zeros(1, 6, dtype=torch.float64)
    motion[0, a] = lo
    R = np.ascontiguousarray(rotations(motion)[0].numpy())
    n = len(P)
    lu, lv = np.empty(n, np.int64), np.empty(n, np.int64)
    _start_levels(P, R, fx, fy, cx, cy, height, width, lu, lv)
    bands, owners = _bands(P, a, float(lo), float(hi), fx, fy, cx, cy, int(height), int(width))
    if a != 5:  # the depths move: each two points that may share a pixel, where their order may change
        keep = _settle(P, bands, owners, a, float(lo), float(hi), fx, fy, cx, cy, int(height), int(width))
        bands, owners = bands[keep], owners[keep]
        first = np.searchsorted(owners, np.arange(n + 1)).astype(np.int64)  # each point's bands, in order
        pairs = np.unique(_candidate_pairs(P, a, bands, first, lu, lv, float(lo), float(hi), int(height), int(width)))
        pairs, who = _pair_bands(P, pairs, a, float(lo), float(hi), fx, fy, cx, cy, int(height), int(width))
        bands, owners = np.concatenate([bands, pairs]), np.concatenate([owners, who])
    return bands, owners, lu, lv


READS = {("rx", 0): (0, 1, 2), ("rx", 1): (1, 2), ("ry", 0): (0, 2), ("ry", 1): (0, 1, 2), ("rz", 0): (0, 1, 2),
         ("rz", 1): (0, 1, 2)}  # fmt: skip
"""The coordinates of a point each camera coordinate's level reads: about rx a row depends on
``Y`` and ``Z`` alone, about ry a column on ``X`` and ``Z``."""


def _twins(P: np.ndarray, bands: np.ndarray, owners: np.ndarray, axis: str) -> np.ndarray:
    """Per band, the first band of the same coordinate whose point has the same numbers where
    that coordinate reads them (bit for bit): the renderer computes one level for both at every
    pose, so they cross together (points on a line of a grid, along rx's or ry's own axis)."""
    key = np.zeros((len(bands), 5))
    key[:, 0], key[:, 1] = bands[:, 4], bands[:, 0]
    for coord in (0, 1):
        rows = bands[:, 4] == coord
        for slot, c in enumerate(READS[(axis, coord)]):
            key[rows, 2 + slot] = P[owners[rows], c]
    raw = np.ascontiguousarray(key).view(np.dtype((np.void, key.itemsize * key.shape[1]))).ravel()
    _, first, inverse = np.unique(raw, return_index=True, return_inverse=True)
    return first[inverse.ravel()].astype(np.int64)


def rotation_moves(P: np.ndarray, K, axis: str, lo: float, hi: float, height: int, width: int):
    """What the sweep needs on the rotation ``axis`` over ``[lo, hi]``: each point's pixel at
    ``lo`` (-1: none), the moves (pose, point, new pixel) in pose order, the recorded windows
    (start and end pose, offsets into the rows, and per row a point and a pixel it may occupy, -1:
    off the image), the bands' count, on rx and ry the pairs of points whose depths are within
    rounding at ``lo`` (``i * N + j``). There the moves also hold each depth band's start
    (target ``-2 - N - j``) and end (``-2 - j``): a sweep records, while it lasts, that the pixel
    the two share may show either (as it records near-equal depths on tz). Last, per row of the
    windows, its point's unit: the points of one unit (twins, each with one band in the window)
    take their ``r``-th pixels together."""
    bands, owners, lu, lv = rotation_bands(P, K, axis, lo, hi, height, width)
    start = np.where((lu >= 0) & (lu < width) & (lv >= 0) & (lv < height), lv * width + lu, -1)
    depth = bands[:, 4] == 2
    moving, movers = bands[~depth], owners[~depth]
    times, points, targets, w_start, w_end, c_window, c_point, c_pixel, c_unit = _timeline(
        moving, movers, _twins(P, moving, movers, axis), float(lo), float(hi), lu, lv, int(height), int(width)
    )
    n, pairs, who = len(P), bands[depth], owners[depth]
    partner = pairs[:, 5].astype(np.int64)
    begins = pairs[:, 0] >= lo  # a band that holds lo is open from the start
    ends = pairs[:, 1] <= hi
    times = np.concatenate([times, pairs[begins, 0], pairs[ends, 1]])
    points = np.concatenate([points, who[begins], who[ends]])
    targets = np.concatenate([targets, -2 - n - partner[begins], -2 - partner[ends]])
    order = np.argsort(times, kind="stable")
    tied = np.minimum(who, partner)[~begins] * n + np.maximum(who, partner)[~begins]
    rows = np.bincount(c_window, minlength=len(w_start))
    groups = (w_start, w_end, np.r_[0, np.cumsum(rows)].astype(np.int64), c_point, c_pixel)
    return start.astype(np.int64), times[order], points[order], targets[order], groups, len(bands), tied, c_unit
