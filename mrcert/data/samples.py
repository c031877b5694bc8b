"""Test samples: what smoothing needs to re-render a test image under any camera motion.

A :class:`TestSample` holds its scene ``V`` in the test pose's camera frame, the camera, and
the label. Sound speed-ups:

* the points that get rendered (the crop, or the whole cloud without one) are stored in
  :func:`~mrcert.projection.locality_order` and rendered with their original positions as the
  tie-break rank: the same images as the order they came in, at a
  speed that does not depend on that order (a user's scan or a down-sampled cloud is
  effectively shuffled; the sample is rendered 1,100 times, so sorting it once is free);
* an exact crop: the points that can land in the image under some motion within a
  :class:`CropBound`. Every other point stays outside the image for such motions, so removing
  it changes no image; motions beyond the bound are rendered from the full cloud.
* optional two-stage down-sampling with open3d (every k-th point, then a voxel grid; the
  paper's per-axis values). The down-sampled cloud *is* the sample's ``V`` for every motion,
  so Lemma 1 still holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np
import torch

from mrcert.projection import Backend, locality_order, project


def frustum_half_angle(K: torch.Tensor, height: int, width: int) -> float:
    """Half-angle of the cone around the optical axis that contains the image's frustum."""
    kx, ky = frustum_slopes(K, height, width)
    return float(np.arctan(np.hypot(kx, ky)))


def frustum_slopes(K: torch.Tensor, height: int, width: int) -> tuple[float, float]:
    """``kx, ky`` with every landing point satisfying ``|X| <= kx Z`` and ``|Y| <= ky Z``."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    return max(cx, width - cx) / fx, max(cy, height - cy) / fy


@dataclass(frozen=True)
class CropBound:
    """The motions a test sample's crop is exact for: ``|t_i| <= translation[i]`` and a
    rotation of angle ``<= rotation``, about the optical axis only when ``roll_only``.

    Tests, for a camera-frame point ``P = (X, Y, Z)`` (each keeps every point that can land):

    * no rotation: the frustum widened by the translation box,
      ``|X| - Tx <= kx (Z + Tz)``, ``|Y| - Ty <= ky (Z + Tz)``;
    * roll only: a roll keeps the distance to the optical axis, so
      ``sqrt(X^2 + Y^2) - sqrt(Tx^2 + Ty^2) <= sqrt(kx^2 + ky^2) (Z + Tz)``;
    * any rotation: the cone test, angle(P, z) <= frustum half-angle + rotation + asin(|T| / |P|).
    """

    translation: tuple[float, float, float]
    rotation: float = 0.0
    roll_only: bool = True

    def contains(self, motions: torch.Tensor) -> torch.Tensor:
        box = torch.tensor(self.translation, dtype=motions.dtype, device=motions.device)
        ok = (motions[:, :3].abs() <= box).all(dim=1)
        if self.roll_only:
            return ok & (motions[:, 3:5] == 0).all(dim=1) & (motions[:, 5].abs() <= self.rotation)
        return ok & (torch.linalg.vector_norm(motions[:, 3:], dim=1) <= self.rotation)

    def mask(self, points: torch.Tensor, K: torch.Tensor, height: int, width: int) -> torch.Tensor:
        pts = np.ascontiguousarray(torch.as_tensor(points, dtype=torch.float64).cpu().numpy())
        kx, ky = frustum_slopes(K, height, width)
        mode = (0 if self.rotation == 0 else 1) if self.roll_only else 2
        out = np.empty(len(pts), np.bool_)
        _crop_kernel(
            pts,
            mode,
            kx,
            ky,
            np.array(self.translation, np.float64),
            frustum_half_angle(K, height, width) + self.rotation + 1e-9,
            out,
        )
        return torch.from_numpy(out).to(torch.as_tensor(points).device)


@numba.njit(parallel=True, cache=True, nogil=True)
def _crop_kernel(P, mode, kx, ky, box, cone_limit, out):  # pragma: no cover - compiled
    slack = 1e-9
    t_xy = np.sqrt(box[0] * box[0] + box[1] * box[1])
    t_norm = np.sqrt(t_xy * t_xy + box[2] * box[2])
    kc = np.sqrt(kx * kx + ky * ky)
    for i in numba.prange(P.shape[0]):
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        depth = z + box[2]
        if mode == 0:
            out[i] = depth > 0 and abs(x) - box[0] <= kx * depth + slack and abs(y) - box[1] <= ky * depth + slack
        elif mode == 1:
            out[i] = depth > 0 and np.sqrt(x * x + y * y) - t_xy <= kc * depth + slack
        else:
            norm = np.sqrt(x * x + y * y + z * z)
            if norm <= t_norm:
                out[i] = True
            else:
                angle = np.arccos(min(1.0, max(-1.0, z / norm)))
                out[i] = angle <= cone_limit + np.arcsin(min(1.0, t_norm / norm))


def downsample(points: np.ndarray, colors: np.ndarray, every_k: int, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """open3d ``uniform_down_sample(every_k)`` then ``voxel_down_sample(voxel)``, in a fixed order."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.colors = o3d.utility.Vector3dVector(colors.astype(np.float64))
    pcd = pcd.uniform_down_sample(int(every_k)).voxel_down_sample(float(voxel))
    pts, cols = np.asarray(pcd.points), np.asarray(pcd.colors, dtype=np.float32)
    order = np.lexsort(pts.T[::-1])  # deterministic point order, whatever open3d's hashing did
    return pts[order], cols[order]


def _in_locality_order(points, colors, rank, sample):
    """``points``, ``colors`` and their ranks (positions in the cloud as given) in locality order."""
    order = locality_order(points, sample.K, sample.height, sample.width)
    rank = order if rank is None else rank[order]
    return points[order].contiguous(), colors[order].contiguous(), rank


@dataclass
class TestSample:
    """A test image's scene in its camera frame, ready to render under motions."""

    __test__ = False  # not a pytest test class, whatever its name

    points: torch.Tensor  # (N, 3) float64, camera frame of the test pose
    colors: torch.Tensor  # (N, C) float32
    K: torch.Tensor
    height: int
    width: int
    label: int
    background: float = 1.0
    bound: CropBound | None = None
    rank: torch.Tensor | None = field(default=None, repr=False)  # each stored point's position as given (None: its row)
    crop_points: torch.Tensor | None = field(default=None, repr=False)  # the crop, in storage order
    crop_colors: torch.Tensor | None = field(default=None, repr=False)
    crop_rank: torch.Tensor | None = field(default=None, repr=False)

    @classmethod
    def build(
        cls,
        points,
        colors,
        K,
        height: int,
        width: int,
        label: int,
        background: float = 1.0,
        bound: CropBound | None = None,
        downsampling: tuple[int, float] | None = None,
    ) -> TestSample:
        points, colors = np.asarray(points, np.float64), np.asarray(colors, np.float32)
        if downsampling is not None:
            points, colors = downsample(points, colors, *downsampling)
        K = torch.as_tensor(K, dtype=torch.float64)
        sample = cls(
            torch.from_numpy(points),
            torch.from_numpy(np.ascontiguousarray(colors)),
            K,
            int(height),
            int(width),
            int(label),
            float(background),
        )
        if bound is None:  # the whole cloud is what gets rendered: store it in locality order
            sample.points, sample.colors, sample.rank = _in_locality_order(sample.points, sample.colors, None, sample)
        else:  # the crop is what gets rendered (rarer motions use the whole cloud as given)
            mask = bound.mask(sample.points, sample.K, sample.height, sample.width)
            sample.bound = bound
            sample.crop_points, sample.crop_colors, sample.crop_rank = _in_locality_order(
                sample.points[mask], sample.colors[mask], torch.nonzero(mask).flatten(), sample
            )
        return sample

    def within_bound(self, motions: torch.Tensor) -> torch.Tensor:
        """Which motions (B, 6) the crop is exact for."""
        if self.bound is None:
            return torch.zeros(len(motions), dtype=torch.bool)
        return self.bound.contains(motions)

    def render(self, motions, backend: Backend = "auto") -> tuple[torch.Tensor, torch.Tensor]:
        """``O(V, alpha)`` for motions (B, 6): images (B, C, H, W) and depth (B, H, W)."""
        motions = torch.as_tensor(motions, dtype=torch.float64, device=self.points.device).reshape(-1, 6)
        inside = self.within_bound(motions).to(self.points.device)
        if bool(inside.all()):
            return self._project(self.crop_points, self.crop_colors, self.crop_rank, motions, backend)
        if not bool(inside.any()):
            return self._project(self.points, self.colors, self.rank, motions, backend)
        images = torch.empty(
            len(motions),
            self.colors.shape[1],
            self.height,
            self.width,
            dtype=self.colors.dtype,
            device=self.points.device,
        )
        depth = torch.empty(len(motions), self.height, self.width, dtype=torch.float64, device=self.points.device)
        crop = self._project(self.crop_points, self.crop_colors, self.crop_rank, motions[inside], backend)
        full = self._project(self.points, self.colors, self.rank, motions[~inside], backend)
        (images[inside], depth[inside]), (images[~inside], depth[~inside]) = crop, full
        return images, depth

    def _project(self, points, colors, rank, motions, backend):
        return project(
            points, colors, self.K, motions, self.height, self.width, self.background, backend=backend, rank=rank
        )
