"""The order of float64 values as integers, and a value's pixel level: what the event modules
bisect over when they locate a crossing in the renderer's own arithmetic."""

from __future__ import annotations

import numba
import numpy as np

SIGN = np.int64(-0x8000000000000000)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _key(f, buf, ibuf):  # pragma: no cover - compiled
    """An integer that orders float64 values as they are ordered (both zeros: 0); ``buf`` and
    ``ibuf`` are one float64 and one int64 view of the same eight bytes."""
    buf[0] = f
    b = ibuf[0]
    return b if b >= 0 else -(b & 0x7FFFFFFFFFFFFFFF)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _float(k, buf, ibuf):  # pragma: no cover - compiled
    """The float64 whose :func:`_key` is ``k``."""
    ibuf[0] = k if k >= 0 else ((-k) | SIGN)
    return buf[0]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _level(value, size):  # pragma: no cover - compiled
    """-1 left of (above) the image, ``size`` right of (below) it, else the pixel's column (row)."""
    if value < 0.0:
        return -1
    if value >= size:
        return size
    return int(value)
