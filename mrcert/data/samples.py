"""Test samples: what smoothing needs to re-render a test image under any camera motion.

A :class:`TestSample` holds its scene ``V`` in the test pose's camera frame, the camera, and
the label. Sound speed-ups:

* the points that get rendered (the crop, or the whole cloud without one) are stored in
  :func:`~mrcert.core.projection.locality_order` and rendered with their original positions as the
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

import numpy as np
import torch

from mrcert.core.crop import CropBound
from mrcert.core.projection import Backend, locality_order, project


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

    def renderer(self, backend: Backend = "auto"):
        """The sample as a smoothed classifier sees it: motions (B, 6) -> images (B, C, H, W)."""
        return lambda motions: self.render(motions, backend)[0]

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
