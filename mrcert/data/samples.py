"""Test samples: what smoothing needs to re-render a test image under any camera motion.

A :class:`TestSample` holds its scene ``V`` in the test pose's camera frame, the camera, and
the label. Two sound speed-ups (issue 3, item 7):

* an exact crop: the points that can land in the image under some motion with
  ``|t| <= max_translation`` and rotation angle ``<= max_rotation``. Every other point stays
  outside the image for such motions, so removing it changes no image; motions beyond the
  bound are rendered from the full cloud.
* optional two-stage down-sampling with open3d (every k-th point, then a voxel grid; the
  paper's per-axis values). The down-sampled cloud *is* the sample's ``V`` for every motion,
  so Lemma 1 still holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from mrcert.projection import Backend, project


def frustum_half_angle(K: torch.Tensor, height: int, width: int) -> float:
    """Half-angle of the cone around the optical axis that contains the image's frustum."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    return float(np.arctan(np.hypot(max(cx, width - cx) / fx, max(cy, height - cy) / fy)))


def crop_mask(
    points: torch.Tensor, K: torch.Tensor, height: int, width: int, max_translation: float, max_rotation: float
) -> torch.Tensor:
    """Points (camera frame) that may land in the image under a motion within the bound.

    If ``R^T (P - t)`` is in the frustum, the angle between ``P`` and the optical axis is at
    most the frustum's cone half-angle + the rotation angle + ``asin(|t| / |P|)``; points
    beyond that can never land (points within ``max_translation`` of the camera are kept).
    """
    norm = torch.linalg.vector_norm(points, dim=1)
    cos = (points[:, 2] / norm.clamp_min(1e-300)).clamp(-1, 1)
    shift = torch.asin((max_translation / norm.clamp_min(1e-300)).clamp(max=1.0))
    limit = frustum_half_angle(K, height, width) + max_rotation + shift + 1e-9
    return (norm <= max_translation) | (torch.arccos(cos) <= limit)


def downsample(points: np.ndarray, colors: np.ndarray, every_k: int, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """open3d ``uniform_down_sample(every_k)`` then ``voxel_down_sample(voxel)``, in a fixed order."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.colors = o3d.utility.Vector3dVector(colors.astype(np.float64))
    pcd = pcd.uniform_down_sample(int(every_k)).voxel_down_sample(float(voxel))
    pts, cols = np.asarray(pcd.points), np.asarray(pcd.colors, dtype=np.float32)
    order = np.lexsort(pts.T[::-1])  # deterministic point order, whatever open3d's hashing did
    return pts[order], cols[order]


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
    max_translation: float = 0.0
    max_rotation: float = 0.0
    crop_points: torch.Tensor | None = field(default=None, repr=False)  # the crop, in point order
    crop_colors: torch.Tensor | None = field(default=None, repr=False)

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
        max_translation: float | None = None,
        max_rotation: float | None = None,
        downsampling: tuple[int, float] | None = None,
    ) -> TestSample:
        points, colors = np.asarray(points, np.float64), np.asarray(colors, np.float32)
        if downsampling is not None:
            points, colors = downsample(points, colors, *downsampling)
        sample = cls(
            torch.from_numpy(points),
            torch.from_numpy(np.ascontiguousarray(colors)),
            torch.as_tensor(K, dtype=torch.float64),
            int(height),
            int(width),
            int(label),
            float(background),
        )
        if max_translation is not None and max_rotation is not None:
            sample.max_translation, sample.max_rotation = float(max_translation), float(max_rotation)
            mask = crop_mask(
                sample.points, sample.K, sample.height, sample.width, sample.max_translation, sample.max_rotation
            )
            sample.crop_points, sample.crop_colors = sample.points[mask], sample.colors[mask]
        return sample

    def within_bound(self, motions: torch.Tensor) -> torch.Tensor:
        """Which motions (B, 6) the crop is exact for."""
        if self.crop_points is None:
            return torch.zeros(len(motions), dtype=torch.bool)
        t = torch.linalg.vector_norm(motions[:, :3], dim=1)
        r = torch.linalg.vector_norm(motions[:, 3:], dim=1)
        return (t <= self.max_translation) & (r <= self.max_rotation)

    def to(self, device: torch.device | str) -> TestSample:
        moved = {k: (v.to(device) if isinstance(v, torch.Tensor) and k != "K" else v) for k, v in vars(self).items()}
        return TestSample(**moved)

    def render(self, motions, backend: Backend = "auto") -> tuple[torch.Tensor, torch.Tensor]:
        """``O(V, alpha)`` for motions (B, 6): images (B, C, H, W) and depth (B, H, W)."""
        motions = torch.as_tensor(motions, dtype=torch.float64, device=self.points.device).reshape(-1, 6)
        inside = self.within_bound(motions).to(self.points.device)
        if bool(inside.all()):
            return self._project(self.crop_points, self.crop_colors, motions, backend)
        if not bool(inside.any()):
            return self._project(self.points, self.colors, motions, backend)
        images = torch.empty(
            len(motions),
            self.colors.shape[1],
            self.height,
            self.width,
            dtype=self.colors.dtype,
            device=self.points.device,
        )
        depth = torch.empty(len(motions), self.height, self.width, dtype=torch.float64, device=self.points.device)
        images[inside], depth[inside] = self._project(self.crop_points, self.crop_colors, motions[inside], backend)
        images[~inside], depth[~inside] = self._project(self.points, self.colors, motions[~inside], backend)
        return images, depth

    def _project(self, points, colors, motions, backend):
        return project(points, colors, self.K, motions, self.height, self.width, self.background, backend=backend)
