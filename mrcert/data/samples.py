"""Test samples: what smoothing needs to re-render a test image under any camera motion.

A :class:`TestSample` holds its scene ``V`` (in the test pose's camera frame, or in a world frame
with the motion into it), the camera, and the label. Sound speed-ups:

* the same cloud tensors are rendered for every motion, so :func:`~mrcert.core.projection.project`
  sorts each into locality order once and keeps it (a user's scan or a down-sampled cloud is
  effectively shuffled; the sample is rendered 1,100 times, so sorting it once is free); the
  crop keeps its points' positions in the whole cloud as their tie-break rank, so it renders
  exactly the whole cloud's images;
* an exact crop: the points that can land in the image under some motion within a
  :class:`CropBound`. Every other point stays outside the image for such motions, so removing
  it changes no image; motions beyond the bound are rendered from the full cloud. A cloud given
  in a world frame is tested point by point in the camera frame and only the crop is stored
  there; the whole cloud is moved when a motion beyond the bound first needs it.
* optional two-stage down-sampling with open3d (every k-th point, then a voxel grid; the
  paper's per-axis values). The down-sampled cloud *is* the sample's ``V`` for every motion,
  so Lemma 1 still holds.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np
import torch

from mrcert.core.crop import CropBound
from mrcert.core.projection import Backend, camera_points, project


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
    """A test image's scene, ready to render under motions from its camera.

    ``cloud`` is the scene in the test pose's camera frame, or, with ``frame`` (a motion (6,)),
    in a frame whose camera frame is ``camera_points(cloud, frame)`` (a data set's world frame):
    then :attr:`points`, the camera-frame cloud, is made only when first needed -- by a motion
    beyond the crop's bound, which is rare -- and the crop is moved into the camera frame alone.
    """

    __test__ = False  # not a pytest test class, whatever its name

    cloud: torch.Tensor  # (N, 3) float64, the camera frame of the test pose or the frame ``frame`` moves
    colors: torch.Tensor  # (N, C) float32
    K: torch.Tensor
    height: int
    width: int
    label: int
    background: float = 1.0
    bound: CropBound | None = None
    crop_points: torch.Tensor | None = field(default=None, repr=False)  # the crop, in the cloud's order
    crop_colors: torch.Tensor | None = field(default=None, repr=False)
    crop_rank: torch.Tensor | None = field(default=None, repr=False)  # each crop point's row in the cloud
    frame: torch.Tensor | None = None  # (6,) the motion from the cloud's frame to the test pose's camera
    device: torch.device | None = None  # where it renders (None: where its cloud is; see to())

    @functools.cached_property
    def points(self) -> torch.Tensor:
        """(N, 3) float64: the cloud in the test pose's camera frame."""
        if self.frame is None:
            return self.cloud
        with torch.inference_mode(False):  # a plain tensor, which project() can recognise (build())
            return camera_points(self.cloud, self.frame)

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
        frame=None,
    ) -> TestSample:
        """A sample of ``points`` in the camera frame, or, given ``frame`` (a motion (6,)), in the
        frame that ``camera_points(points, frame)`` moves into it; ``bound``: crop it exactly for
        the motions inside; ``downsampling``: :func:`downsample` it in the camera frame first."""
        # Plain tensors even when built under torch.inference_mode (as the attack does): project()
        # recognises a cloud it has sorted by the tensors' version counters, which only they have.
        with torch.inference_mode(False):
            return cls._build(points, colors, K, height, width, label, background, bound, downsampling, frame)

    @classmethod
    def _build(cls, points, colors, K, height, width, label, background, bound, downsampling, frame) -> TestSample:
        points, colors = np.asarray(points, np.float64), np.asarray(colors, np.float32)
        frame = None if frame is None else torch.as_tensor(frame, dtype=torch.float64).reshape(6)
        if downsampling is not None:  # in the camera frame, where the voxel grid is defined
            if frame is not None:
                points, frame = camera_points(torch.from_numpy(points), frame).numpy(), None
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
            frame=frame,
        )
        if bound is not None:  # the crop is what gets rendered (rarer motions use the whole cloud)
            mask = bound.mask(sample.cloud, sample.K, sample.height, sample.width, frame)
            kept = sample.cloud[mask]
            sample.bound = bound
            sample.crop_points = kept if frame is None else camera_points(kept, frame)
            sample.crop_colors = sample.colors[mask]
            sample.crop_rank = torch.nonzero(mask).flatten()
        return sample

    @property
    def render_device(self) -> torch.device:
        """Where the sample renders and its images are made."""
        return self.colors.device if self.device is None else self.device

    def to(self, device: torch.device | str) -> TestSample:
        """The sample rendering on ``device`` (itself when it already does): its crop moves there
        now, the whole cloud only when a motion beyond the crop's bound first needs it."""
        device = torch.device(device)
        if self.render_device == device:
            return self
        crop = {name: getattr(self, name) for name in ("crop_points", "crop_colors", "crop_rank")}
        return dataclasses.replace(
            self, device=device, **{k: None if v is None else v.to(device) for k, v in crop.items()}
        )

    @functools.cached_property
    def _whole(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The camera-frame cloud and its colours where the sample renders (moved once)."""
        return self.points.to(self.render_device), self.colors.to(self.render_device)

    def within_bound(self, motions: torch.Tensor) -> torch.Tensor:
        """Which motions (B, 6) the crop is exact for."""
        if self.bound is None:
            return torch.zeros(len(motions), dtype=torch.bool)
        return self.bound.contains(motions)

    def renderer(self, backend: Backend = "auto") -> SampleRenderer:
        """The sample as a smoothed classifier sees it: motions (B, 6) -> images (B, C, H, W)."""
        return SampleRenderer(self, backend)

    def cloud_for(self, motions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Points, colours and tie-break ranks holding every point that can land in the image for
        a motion within the bound of ``motions``: the crop when the bound holds them all, else the cloud."""
        if bool(self.within_bound(torch.as_tensor(motions, dtype=torch.float64).reshape(-1, 6)).all()):
            return self.crop_points, self.crop_colors, self.crop_rank
        return self.points, self.colors, torch.arange(len(self.points))

    def render(self, motions, backend: Backend = "auto") -> tuple[torch.Tensor, torch.Tensor]:
        """``O(V, alpha)`` for motions (B, 6): images (B, C, H, W) and depth (B, H, W)."""
        device = self.render_device
        # On the CPU, where motions are drawn: deciding the crop then never waits for a GPU's queue.
        motions = torch.as_tensor(motions, dtype=torch.float64).reshape(-1, 6).cpu()
        inside = self.within_bound(motions)
        if bool(inside.all()):
            return self._project(self.crop_points, self.crop_colors, self.crop_rank, motions, backend)
        if not bool(inside.any()):
            return self._project(*self._whole, None, motions, backend)
        images = torch.empty(
            len(motions),
            self.colors.shape[1],
            self.height,
            self.width,
            dtype=self.colors.dtype,
            device=device,
        )
        depth = torch.empty(len(motions), self.height, self.width, dtype=torch.float64, device=device)
        crop = self._project(self.crop_points, self.crop_colors, self.crop_rank, motions[inside], backend)
        full = self._project(*self._whole, None, motions[~inside], backend)
        inside = inside.to(device)
        (images[inside], depth[inside]), (images[~inside], depth[~inside]) = crop, full
        return images, depth

    def _project(self, points, colors, rank, motions, backend):
        return project(
            points, colors, self.K, motions, self.height, self.width, self.background, backend=backend, rank=rank
        )


@dataclass
class SampleRenderer:
    """:meth:`TestSample.renderer`: a callable ``motions -> images`` that also shows its scene
    (a :class:`~mrcert.core.methods.base.SceneRender`, for a method that reasons about the cloud
    itself) and counts the camera poses it has projected (``projected``: a certificate's
    rendering cost)."""

    sample: TestSample
    backend: Backend = "auto"
    projected: int = 0

    def __call__(self, motions: torch.Tensor) -> torch.Tensor:
        self.projected += len(motions)
        return self.sample.render(motions, self.backend)[0]

    @property
    def K(self) -> torch.Tensor:
        return self.sample.K

    @property
    def background(self) -> float:
        return self.sample.background

    @property
    def height(self) -> int:
        return self.sample.height

    @property
    def width(self) -> int:
        return self.sample.width

    def cloud_for(self, motions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.sample.cloud_for(motions)
