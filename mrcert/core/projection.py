"""The projection ``O(V, alpha)`` of a coloured point cloud under camera motions (paper Def. 2).

Rule (docs/method.md §2): a point with camera coordinates ``P`` is moved to ``P' = R^T (P - t)``,
lands on column ``u = floor(fx X'/Z' + cx)`` and row ``v = floor(fy Y'/Z' + cy)`` when
``Z' > 0``, ``0 <= u < W`` and ``0 <= v < H``, and each pixel takes the colour of its point of
minimum depth ``Z'``; among equal depths the lowest point index wins. Pixels no point hits
take ``background``.

A point's *index* for that tie rule is its row, or ``rank[row]`` when the caller passes
``rank``, so the images never depend on the order a cloud is stored in. The speed does: the
numba back end renders every cloud in :func:`locality_order` (the z-buffer's memory accesses
are then coherent), with the points' ranks carried along, so that a cloud in any order -- a
scan, a merged or down-sampled cloud -- renders as fast as a well-ordered one. The order, the
reordered copy and its culling boxes are kept for the last :data:`PREPARED_CLOUDS` clouds
rendered (by tensor identity and torch's version counter), so a cloud rendered again and
again -- a test sample under 1,100 motions -- is ordered once.

Three back ends compute exactly the same float64 operations in the same order, so their
images are identical to the bit:

* ``numba``: a compiled z-buffer kernel, parallel over motions (CPU tensors, the default there);
* ``triton``: Triton kernels, parallel over blocks of points and motions, on the cloud in
  locality order kept on the device (:mod:`mrcert.core.projection_cuda`; CUDA tensors, the
  default there);
* ``torch``: scatter-min over pixels, chunked over motions to bound memory (any device).
"""

from __future__ import annotations

import functools
import importlib.util
import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
import torch

from mrcert.core.geometry import rotvec_to_matrix

# OpenMP first: thread-safe, and skips probing an old system TBB (which only warns).
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

Backend = Literal["auto", "numba", "torch", "triton"]

DEFAULT_CHUNK_ELEMENTS = 1 << 22
"""Upper bound on motions x points held at once by the torch back end (about 32 MB per buffer)."""


def project(
    points: torch.Tensor,
    colors: torch.Tensor,
    K: torch.Tensor,
    motions: torch.Tensor,
    height: int,
    width: int,
    background: float = 1.0,
    *,
    backend: Backend = "auto",
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
    rank: torch.Tensor | None = None,
    locality: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render ``points`` (N, 3, reference camera frame) with ``colors`` (N, C) under ``motions``.

    Args:
        points: (N, 3) xyz in the reference camera frame (metres).
        colors: (N, C) values in [0, 1].
        K: (3, 3) intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
        motions: (B, 6) ``(tx, ty, tz, rx, ry, rz)`` camera motions (docs/method.md §1).
        height, width: image size H x W.
        background: value of pixels that no point hits.
        backend: ``"numba"``, ``"triton"``, ``"torch"`` or ``"auto"`` (numba on CPU, triton on CUDA
            where Triton is installed, torch elsewhere).
        chunk_elements: torch back end only: at most this many motions x points at once.
        rank: (N,) distinct integers: the index each point has for the tie rule (default: its row).
        locality: numba and triton back ends: render the cloud in :func:`locality_order` for the
            unmoved camera, kept for the next calls (the default: smoothing's motions are small);
            False renders it in the order given (for poses far from the reference camera, such
            as views of a world-frame scene). The images are the same either way.

    The numba and triton back ends keep the cloud's locality order for the next calls (module docstring):
    change a cloud in place through torch (which counts versions) or pass a new tensor, never
    write into it through a NumPy view between calls.

    Returns:
        ``images`` (B, C, H, W) in the dtype of ``colors`` (float32 for integer colours) and
        ``depth`` (B, H, W) float64 with ``+inf`` where no point lands; both on the device of
        ``points``.
    """
    points = torch.as_tensor(points)
    device = points.device
    colors = torch.as_tensor(colors, device=device)
    motions = torch.as_tensor(motions, dtype=torch.float64)  # where given: rotations are made on the CPU
    K = torch.as_tensor(K, dtype=torch.float64)
    _check_inputs(points, colors, K, motions, height, width)
    if backend == "auto":
        backend = "numba" if device.type == "cpu" else _cuda_backend() if device.type == "cuda" else "torch"
    if backend not in ("numba", "torch", "triton"):
        raise ValueError(f"unknown projection backend {backend!r}; allowed: auto, numba, torch, triton")

    if rank is not None:
        rank = torch.as_tensor(rank, device=device)  # the same tensor when given one (project() keeps its order)
        if tuple(rank.shape) != (points.shape[0],):
            raise ValueError(f"rank must have shape ({points.shape[0]},), got {tuple(rank.shape)}")
    R = rotations(motions).to(device)  # motions on the CPU: the GPU's queue is not waited for
    t = motions[:, :3].to(device)
    intr = tuple(float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    if backend == "numba":
        if device.type != "cpu":
            raise ValueError(f"the numba projection backend needs CPU tensors, got device {device}")
        return _project_numba(
            _prepared(points, colors, rank, K, height, width, locality, BLOCK), R, t, intr, background
        )
    if backend == "triton":
        from mrcert.core import projection_cuda

        if device.type != "cuda" and not projection_cuda.interpreting():
            raise ValueError(f"the triton projection backend needs CUDA tensors, got device {device}")
        cloud = _prepared(points, colors, rank, K, height, width, locality, projection_cuda.BLOCK, device)
        return projection_cuda.render(cloud, R, t, intr, background)
    rank = torch.arange(points.shape[0], device=device) if rank is None else rank.to(torch.int64)
    winner, depth = _zbuffer_torch(points.to(torch.float64), rank, R, t, intr, height, width, chunk_elements)
    images = _gather_colors(colors, winner, background, height, width)
    return images, depth.view(-1, height, width)


@functools.cache
def _cuda_backend() -> str:
    """What ``auto`` renders with on CUDA: triton where Triton is installed, else torch (looked
    up once, not on every render)."""
    return "triton" if importlib.util.find_spec("triton") else "torch"


def rotations(motions: torch.Tensor) -> torch.Tensor:
    """The (B, 3, 3) rotations of (B, 6) motions, on the motions' device but always computed on the
    CPU: CUDA's float64 sin and cos round differently from the CPU's, and matrices made on a GPU
    moved depths by float rounding there (docs/performance.md), where every device must give the
    CPU kernel's bits."""
    return rotvec_to_matrix(motions[:, 3:].cpu()).to(motions.device)


def to_uint8(images: torch.Tensor) -> np.ndarray:
    """(..., C, H, W) float in [0, 1] to (..., H, W, C) uint8; exact for values that are k/255."""
    return (images.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8).movedim(-3, -1).numpy()


def camera_points(points: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """``R^T (P - t)`` for one motion (6,), computed with exactly the projection's float64 operations.

    So ``project(camera_points(P, m), zero motion)`` equals ``project(P, m)`` bit for bit; use it
    to move a cloud into a camera's frame (for a camera-to-world pose: ``m = matrix_to_motion(pose)``).
    CPU tensors go through a compiled parallel kernel, others through torch; both give the same bits.
    """
    xyz = torch.as_tensor(points).to(torch.float64)
    motion = torch.as_tensor(motion, dtype=torch.float64, device=xyz.device).reshape(1, 6)
    r = rotations(motion)
    if xyz.device.type == "cpu":
        out = np.empty((xyz.shape[0], 3), np.float64)
        _camera_kernel(np.ascontiguousarray(xyz.numpy()), r[0].numpy(), motion[0, :3].numpy(), out)
        return torch.from_numpy(out)
    dx, dy, dz = (xyz[:, i][None, :] - motion[:, i : i + 1] for i in range(3))
    return torch.stack([_camera_coordinate(r, j, dx, dy, dz)[0] for j in range(3)], dim=1)


@numba.njit(parallel=True, cache=True, nogil=True)
def _camera_kernel(P, R, t, out):  # pragma: no cover - compiled
    for i in numba.prange(P.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = to_camera(P, i, R, t)


@numba.njit(cache=True, nogil=True, inline="always")
def to_camera(P, i, R, t):  # pragma: no cover - compiled
    """Row ``i`` of ``P`` as ``R^T (P_i - t)``: the float64 operations of :func:`camera_points`,
    for compiled kernels that need a point's camera coordinates without storing the cloud's."""
    dx = P[i, 0] - t[0]
    dy = P[i, 1] - t[1]
    dz = P[i, 2] - t[2]
    return (
        R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz,
        R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz,
        R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz,
    )


MARGIN = 4
"""How far the locality key's tiles extend the image plane: image sizes on each side."""


def _key_layout(height: int, width: int, tile: int) -> tuple[int, int, int]:
    """The locality key's layout: tiles per row of the extended plane, and the bits of the tile
    number (its largest value, all ones, means "behind the camera") and of the pixel in the tile."""
    tiles_x = -(-(2 * MARGIN + 1) * width // tile)
    tiles_y = -(-(2 * MARGIN + 1) * height // tile)
    return tiles_x, int(tiles_x * tiles_y).bit_length(), (tile * tile - 1).bit_length()


def locality_order(points: torch.Tensor, K: torch.Tensor, height: int, width: int, tile: int = 32) -> torch.Tensor:
    """A permutation of ``points`` (N, 3, camera frame) that renders fast whatever order they came in.

    Points in front of the camera are grouped by the ``tile`` x ``tile`` pixel tile they fall in
    at the unmoved camera -- on the image plane extended well beyond the image, since a motion
    brings points from outside into view -- tiles row by row, nearest first within a tile;
    points behind the camera come last. Under the small motions of smoothing, consecutive points
    then touch nearby z-buffer entries, a block of them spans a small solid angle (so that the
    kernel's culling works), and each pixel mostly meets its nearest point first, so that the
    z-test rarely replaces a winner and its branch is predictable (nearest first within a tile
    rather than within a pixel: a motion moves points between pixels, not much between tiles).
    Rendering the permuted cloud with ``rank=perm`` gives exactly the images of the original
    order (:func:`project` does this itself). One stable sort of one integer key per point: the
    key's high bits hold the tile, then the depth, then the pixel within the tile (points at one
    depth, as on a wall facing the camera, stay in image order whatever order they came in).
    """
    xyz = np.ascontiguousarray(torch.as_tensor(points, dtype=torch.float64).cpu().numpy())
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    tiles_x, tile_bits, pixel_bits = _key_layout(height, width, tile)
    keys = np.empty(xyz.shape[0], np.int64)
    _locality_keys(
        xyz, fx, fy, cx, cy, height, width, tile, MARGIN, tiles_x, tile_bits, pixel_bits, _farthest(xyz), keys
    )
    return torch.sort(torch.from_numpy(keys), stable=True).indices


@numba.njit(cache=True, nogil=True)
def _farthest(P):  # pragma: no cover - compiled
    """The largest positive depth (1 when no point is in front of the camera)."""
    far = 0.0
    for i in range(P.shape[0]):
        far = max(far, P[i, 2])
    return far if far > 0.0 else 1.0


@numba.njit(parallel=True, cache=True, nogil=True)
def _locality_keys(
    P, fx, fy, cx, cy, height, width, tile, margin, tiles_x, tile_bits, pixel_bits, far, out
):  # pragma: no cover
    depth_bits = 62 - tile_bits - pixel_bits
    depth_levels = (1 << depth_bits) - 1
    behind = (1 << tile_bits) - 1
    for i in numba.prange(P.shape[0]):
        z = P[i, 2]
        if not z > 0.0:
            out[i] = behind << (62 - tile_bits)
            continue
        u = min(max(np.floor(fx * (P[i, 0] / z) + cx), -margin * width), (margin + 1) * width - 1) + margin * width
        v = min(max(np.floor(fy * (P[i, 1] / z) + cy), -margin * height), (margin + 1) * height - 1) + margin * height
        iu, iv = int(u), int(v)
        cell = (iv // tile) * tiles_x + iu // tile
        depth = int(min(z / far, 1.0) * depth_levels)
        out[i] = (cell << (62 - tile_bits)) | (depth << pixel_bits) | ((iv % tile) * tile + iu % tile)


PREPARED_CLOUDS = 2
"""How many clouds :func:`project` keeps in locality order (a test sample's crop and its whole cloud)."""


@dataclass(frozen=True)
class _Cloud:
    """A cloud as the kernels read it: points (3, N: the x, y and z rows, so that a kernel
    loads each coordinate of consecutive points as one vector), ranks and colours in locality
    order, and the culling box of every block of consecutive points (:data:`BLOCK` for the numba
    kernel); NumPy arrays for the numba kernel, tensors on the device for the triton kernels."""

    points: np.ndarray
    rank: np.ndarray
    colors: np.ndarray
    center: np.ndarray
    half: np.ndarray
    height: int
    width: int


@numba.njit(parallel=True, cache=True, nogil=True)
def _gather(order, P, C, R, out_p, out_c, out_r):  # pragma: no cover - compiled
    """Row ``order[i]`` of the points, colours and ranks into row ``i`` of the outputs."""
    for i in numba.prange(order.shape[0]):
        j = order[i]
        for k in range(3):
            out_p[i, k] = P[j, k]
        for k in range(C.shape[1]):
            out_c[i, k] = C[j, k]
        out_r[i] = R[j]


_PREPARED: OrderedDict[tuple, tuple[tuple, _Cloud]] = OrderedDict()
_PREPARED_LOCK = threading.Lock()


def _prepared(points, colors, rank, K, height, width, locality: bool, block: int, device=None) -> _Cloud:
    """The cloud in locality order (or as given) with culling boxes of ``block`` points, as
    NumPy arrays or (``device``) tensors there, from the cache when these very tensors (same
    versions) were prepared for this camera. Tensors made under ``torch.inference_mode`` have no
    version counter, so a cloud holding one is prepared afresh at every call."""
    tensors = (points, colors, rank)
    if any(isinstance(x, torch.Tensor) and x.is_inference() for x in tensors):
        return _prepare(points, colors, rank, K, height, width, locality, block, device)
    key = (
        locality,
        block,
        str(device),
        *(id(x) for x in tensors),
        *(-1 if x is None else x._version for x in tensors),
        *(float(v) for v in K.flatten()),
        height,
        width,
    )
    with _PREPARED_LOCK:
        hit = _PREPARED.get(key)
        if hit is not None and all(
            (ref is None and x is None) or (ref is not None and ref() is x)
            for ref, x in zip(hit[0], tensors, strict=True)
        ):
            _PREPARED.move_to_end(key)
            return hit[1]
    cloud = _prepare(points, colors, rank, K, height, width, locality, block, device)
    refs = tuple(None if x is None else weakref.ref(x) for x in tensors)
    with _PREPARED_LOCK:
        _PREPARED[key] = (refs, cloud)
        while len(_PREPARED) > PREPARED_CLOUDS:
            _PREPARED.popitem(last=False)
    return cloud


def _prepare(points, colors, rank, K, height, width, locality: bool, block: int, device) -> _Cloud:
    if device is not None:
        return _prepare_on(torch.device(device), points, colors, rank, K, height, width, locality, block)
    xyz = np.ascontiguousarray(points.to(torch.float64).cpu().numpy())
    dtype = colors.dtype if colors.is_floating_point() else torch.float32
    table = np.ascontiguousarray(colors.to(dtype).cpu().numpy())
    ranks = np.arange(len(xyz)) if rank is None else np.ascontiguousarray(rank.to(torch.int64).cpu().numpy())
    if locality:
        order = locality_order(torch.from_numpy(xyz), K, height, width).numpy()
        stored = np.empty_like(xyz), np.empty_like(table), np.empty_like(ranks)
        _gather(order, xyz, table, ranks, *stored)
        xyz, table, ranks = stored
    center, half = _block_bounds(xyz, block)
    arrays = (np.ascontiguousarray(xyz.T), ranks, table, center, half)
    if device is not None:
        arrays = tuple(torch.from_numpy(a).to(device) for a in arrays)
    return _Cloud(*arrays, height, width)


def _prepare_on(device, points, colors, rank, K, height, width, locality: bool, block: int) -> _Cloud:
    """:func:`_prepare` with tensor operations on ``device``, where the cloud already is (a
    sample rendering on a GPU): the same keys from the same float64 operations, the same stable
    sort and the same boxes, so the same arrays as the CPU path, without a round trip through it."""
    xyz = points.to(device=device, dtype=torch.float64)
    table = colors.to(device=device, dtype=colors.dtype if colors.is_floating_point() else torch.float32)
    n = xyz.shape[0]
    ranks = torch.arange(n, device=device) if rank is None else rank.to(device=device, dtype=torch.int64)
    if locality and n:
        order = torch.sort(_locality_keys_on(xyz, K, height, width), stable=True).indices
        xyz, table, ranks = xyz[order], table[order], ranks[order]
    nb = -(-n // block)
    padded = torch.full((nb * block, 3), torch.nan, dtype=torch.float64, device=device)
    padded[:n] = xyz
    boxes = padded.reshape(nb, block, 3)
    lo, hi = boxes.nan_to_num(nan=torch.inf).amin(1), boxes.nan_to_num(nan=-torch.inf).amax(1)
    center, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return _Cloud(xyz.T.contiguous(), ranks.contiguous(), table.contiguous(), center, half, height, width)


def _locality_keys_on(xyz: torch.Tensor, K: torch.Tensor, height: int, width: int, tile: int = 32) -> torch.Tensor:
    """:func:`_locality_keys` as tensor operations, element for element the same arithmetic."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    margin = MARGIN
    tiles_x, tile_bits, pixel_bits = _key_layout(height, width, tile)
    depth_levels = (1 << (62 - tile_bits - pixel_bits)) - 1
    x, y, z = xyz.unbind(1)
    front = z > 0.0
    far = float(z[front].max()) if bool(front.any()) else 1.0
    safe = torch.where(front, z, 1.0)
    u = torch.clamp(torch.floor(fx * (x / safe) + cx), -margin * width, (margin + 1) * width - 1) + margin * width
    v = torch.clamp(torch.floor(fy * (y / safe) + cy), -margin * height, (margin + 1) * height - 1) + margin * height
    iu, iv = u.to(torch.int64), v.to(torch.int64)
    cell = (iv // tile) * tiles_x + iu // tile
    depth = (torch.clamp(safe / far, max=1.0) * depth_levels).to(torch.int64)
    keys = (cell << (62 - tile_bits)) | (depth << pixel_bits) | ((iv % tile) * tile + iu % tile)
    behind = ((1 << tile_bits) - 1) << (62 - tile_bits)
    return torch.where(front, keys, torch.full_like(keys, behind))


def _check_inputs(points, colors, K, motions, height, width) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(points.shape)}")
    if colors.ndim != 2 or colors.shape[0] != points.shape[0]:
        raise ValueError(f"colors must have shape (N, C) with N = {points.shape[0]}, got {tuple(colors.shape)}")
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {tuple(K.shape)}")
    if motions.ndim != 2 or motions.shape[1] != 6:
        raise ValueError(f"motions must have shape (B, 6), got {tuple(motions.shape)}")
    for name, value in (("height", height), ("width", width)):
        if int(value) != value or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if height * width >= 2**31:
        raise ValueError(f"height x width must be under 2**31 pixels, got {height} x {width}")


def _gather_colors(colors, winner, background, height, width) -> torch.Tensor:
    """Images (B, C, H, W) from per-pixel winning point indices (-1 = background)."""
    dtype = colors.dtype if colors.is_floating_point() else torch.float32
    n, c = colors.shape
    table = torch.cat([colors.to(dtype), torch.full((1, c), background, dtype=dtype, device=colors.device)])
    idx = torch.where(winner < 0, torch.full_like(winner, n), winner)
    return table[idx].permute(0, 2, 1).reshape(-1, c, height, width).contiguous()


def _camera_coordinate(r, j, dx, dy, dz):
    """Coordinate ``j`` of ``R^T (P - t)``, summed left to right exactly like the kernel."""
    return r[:, 0, j : j + 1] * dx + r[:, 1, j : j + 1] * dy + r[:, 2, j : j + 1] * dz


def _zbuffer_torch(xyz, rank, R, t, intr, height, width, chunk_elements):
    """Per-pixel winner row and depth, (B, H*W) each, by scatter-min (depth, then rank among
    the points at the minimum depth); chunked over motions."""
    fx, fy, cx, cy = intr
    n = xyz.shape[0]
    hw = height * width
    X, Y, Z = (c[None, :] for c in xyz.unbind(1))
    rank_sorted, row_of = torch.sort(rank)  # the row of each rank, for mapping winners back
    point_rank = rank[None, :]
    none = torch.iinfo(torch.int64).max
    winners, depths = [], []
    step = max(1, chunk_elements // max(n, 1))
    for start in range(0, R.shape[0], step):
        r = R[start : start + step]
        tt = t[start : start + step]
        b = r.shape[0]
        dx, dy, dz = X - tt[:, 0:1], Y - tt[:, 1:2], Z - tt[:, 2:3]
        zc = _camera_coordinate(r, 2, dx, dy, dz)
        uf = fx * (_camera_coordinate(r, 0, dx, dy, dz) / zc) + cx
        vf = fy * (_camera_coordinate(r, 1, dx, dy, dz) / zc) + cy
        valid = (zc > 0) & (uf >= 0) & (uf < width) & (vf >= 0) & (vf < height)
        pix = torch.floor(vf).clamp(0, height - 1).long() * width + torch.floor(uf).clamp(0, width - 1).long()
        offset = torch.arange(b, device=xyz.device)[:, None] * hw
        dump = b * hw  # one spare bin collects every invalid point
        lin = torch.where(valid, pix + offset, torch.full_like(pix, dump)).reshape(-1)
        zflat = zc.reshape(-1)
        zmin = torch.full((dump + 1,), torch.inf, dtype=torch.float64, device=xyz.device)
        zmin.scatter_reduce_(0, lin, zflat, reduce="amin")
        is_min = valid.reshape(-1) & (zflat == zmin[lin])
        cand = torch.where(is_min, point_rank.expand(b, n).reshape(-1), torch.full_like(lin, none))
        win = torch.full((dump + 1,), none, dtype=torch.long, device=xyz.device)
        win.scatter_reduce_(0, lin, cand, reduce="amin")
        win = win[:dump].view(b, hw)
        found = win != none
        rows = row_of[torch.searchsorted(rank_sorted, torch.where(found, win, rank_sorted[0]))]
        winners.append(torch.where(found, rows, torch.full_like(win, -1)))
        depths.append(zmin[:dump].view(b, hw))
    return torch.cat(winners), torch.cat(depths)


def _project_numba(cloud: _Cloud, R, t, intr, background):
    """Images and depth from the compiled kernel, which also fills each image from its z-buffer."""
    height, width = cloud.height, cloud.width
    b, c = R.shape[0], cloud.colors.shape[1]
    images = np.empty((b, c, height * width), dtype=cloud.colors.dtype)
    depth = np.empty((b, height * width), dtype=np.float64)  # the kernel fills each motion's, in parallel
    if b:
        _zbuffer_kernel(
            cloud.points,
            cloud.rank,
            cloud.center,
            cloud.half,
            BLOCK,
            cloud.colors,
            R.numpy(),
            t.numpy(),
            *intr,
            height,
            width,
            background,
            images,
            depth,
        )
    return torch.from_numpy(images).view(b, c, height, width), torch.from_numpy(depth).view(b, height, width)


BLOCK = 128
"""Points per culling block of the numba kernel (consecutive in storage order)."""


@numba.njit(cache=True, nogil=True)
def _block_bounds(P, block):  # pragma: no cover - compiled
    """Per block of ``block`` consecutive points: the centre and half-extent of the axis-aligned
    box holding them."""
    n = P.shape[0]
    nb = (n + block - 1) // block
    center = np.empty((nb, 3))
    half = np.empty((nb, 3))
    for k in range(nb):
        for j in range(3):
            lo, hi = np.inf, -np.inf
            for i in range(k * block, min(n, (k + 1) * block)):
                v = P[i, j]
                lo = min(lo, v)
                hi = max(hi, v)
            center[k, j] = 0.5 * (lo + hi)
            half[k, j] = 0.5 * (hi - lo)
    return center, half


@numba.njit(cache=True, nogil=True, inline="always")
def _never(w0, w1, w2, c, h, t, below):  # pragma: no cover - compiled
    """True when ``g(P) = w . (P - t)`` is, over the whole box (centre ``c``, half-extent ``h``),
    below zero (``below``) or above zero (not ``below``) by a margin far above float rounding."""
    mid = w0 * (c[0] - t[0]) + w1 * (c[1] - t[1]) + w2 * (c[2] - t[2])
    spread = abs(w0) * h[0] + abs(w1) * h[1] + abs(w2) * h[2]
    slack = 1e-9 * (abs(mid) + spread) + 1e-12
    return mid + spread < -slack if below else mid - spread > slack


@numba.njit(cache=True, nogil=True, inline="always")
def _outside(c, h, R, t, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """True when no point of the box (centre ``c``, half-extent ``h``) can land in the image
    under the motion ``(R, t)``.

    The points that land form the cone ``Z > 0``, ``fx X + cx Z >= 0``, ``fx X + (cx - W) Z < 0``,
    ``fy Y + cy Z >= 0``, ``fy Y + (cy - H) Z < 0`` of camera coordinates ``R^T (P - t)``; each
    is a linear function ``w . (P - t)`` of the point, whose extremes over a box are
    ``w . (c - t) +- |w| . h``. When one constraint fails over the whole box -- by a margin far
    above float rounding -- no point of the box lands, and skipping it changes no pixel."""
    zx, zy, zz = R[0, 2], R[1, 2], R[2, 2]  # Z = column 2 of R . (P - t)
    xx, xy, xz = R[0, 0], R[1, 0], R[2, 0]
    yx, yy, yz = R[0, 1], R[1, 1], R[2, 1]
    return (
        _never(zx, zy, zz, c, h, t, True)
        or _never(fx * xx + cx * zx, fx * xy + cx * zy, fx * xz + cx * zz, c, h, t, True)
        or _never(fx * xx + (cx - width) * zx, fx * xy + (cx - width) * zy, fx * xz + (cx - width) * zz, c, h, t, False)
        or _never(fy * yx + cy * zx, fy * yy + cy * zy, fy * yz + cy * zz, c, h, t, True)
        or _never(
            fy * yx + (cy - height) * zx, fy * yy + (cy - height) * zy, fy * yz + (cy - height) * zz, c, h, t, False
        )
    )


@numba.njit(parallel=True, cache=True, nogil=True, error_model="numpy")  # x / 0 is inf or nan, then not landing
def _zbuffer_kernel(
    P, rank, center, half, block, colors, R, t, fx, fy, cx, cy, height, width, background, images, depth
):  # pragma: no cover
    """For each motion (in parallel): the z-buffer over all points in storage order, a point
    replacing the pixel's winner when nearer, or as near with a lower rank, skipping blocks of
    points that cannot land (:func:`_outside`); then the image from the winners.

    Each block is two passes: every point's depth and pixel (-1 when it does not land), with
    no branch, so that the compiler computes several points per vector instruction (1.7-1.8x
    the one-pass loop, the same float64 operations and so the same bits); then the z-test
    of the points that land, in storage order. The pixel index is an int32 made by truncation,
    which is the floor on the image (``0 <= u < width``) and which AVX2 converts four at a time,
    where a float64 -> int64 conversion has no vector instruction there (1.23-1.25x the whole
    kernel on a certified image's 1,100 motions, docs/performance.md)."""
    n = P.shape[1]
    X, Y, Z = P[0], P[1], P[2]
    for b in numba.prange(R.shape[0]):
        r00, r01, r02 = R[b, 0, 0], R[b, 0, 1], R[b, 0, 2]
        r10, r11, r12 = R[b, 1, 0], R[b, 1, 1], R[b, 1, 2]
        r20, r21, r22 = R[b, 2, 0], R[b, 2, 1], R[b, 2, 2]
        tx, ty, tz = t[b, 0], t[b, 1], t[b, 2]
        zbuf = depth[b]
        zbuf[:] = np.inf
        wbuf = np.full(height * width, -1, np.int64)
        pixel = np.empty(block, np.int32)
        zs = np.empty(block, np.float64)
        for k in range(center.shape[0]):
            if _outside(center[k], half[k], R[b], t[b], fx, fy, cx, cy, height, width):
                continue
            start = k * block
            m = min(n, start + block) - start
            for j in range(m):  # branch-free: vectorised
                dx = X[start + j] - tx
                dy = Y[start + j] - ty
                dz = Z[start + j] - tz
                zc = r02 * dx + r12 * dy + r22 * dz
                uf = fx * ((r00 * dx + r10 * dy + r20 * dz) / zc) + cx
                vf = fy * ((r01 * dx + r11 * dy + r21 * dz) / zc) + cy
                lands = (zc > 0.0) & (uf >= 0.0) & (uf < width) & (vf >= 0.0) & (vf < height)
                pixel[j] = np.int32(vf) * np.int32(width) + np.int32(uf) if lands else np.int32(-1)
                zs[j] = zc
            for j in range(m):
                p = pixel[j]
                if p < 0:
                    continue
                zc = zs[j]
                i = start + j
                if zc <= zbuf[p] and (zc < zbuf[p] or rank[i] < rank[wbuf[p]]):
                    zbuf[p] = zc
                    wbuf[p] = i
        image = images[b]
        for p in range(height * width):
            w = wbuf[p]
            for ch in range(image.shape[0]):
                image[ch, p] = colors[w, ch] if w >= 0 else background
