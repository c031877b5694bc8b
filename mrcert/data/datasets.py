"""torch Datasets of rendered images and of re-renderable test samples: what every data source
provides (the sources themselves: :mod:`mrcert.data.sources`). A :class:`DataBundle` has

* ``train()`` / ``test()``: :class:`ImageSet` of rendered images (cached under
  ``data.cache_dir``; training images optionally rendered under a method's training motions),
* ``samples()``: :class:`SampleSet` of :class:`~mrcert.data.samples.TestSample`, which carry
  their cloud in the camera frame, ``K``, the image size and the label.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import Dataset

from mrcert.core.crop import CropBound
from mrcert.core.geometry import matrix_to_motion, motion_to_matrix
from mrcert.core.methods.base import Method
from mrcert.core.projection import project, to_uint8
from mrcert.data.cache import cached_arrays
from mrcert.data.samples import TestSample
from mrcert.scenes.scene import intrinsics


@dataclass(frozen=True)
class Split:
    """Poses (N, 4, 4) camera-to-world, protocol parameters (N, 4) and labels (N,)."""

    poses: np.ndarray
    params: np.ndarray
    labels: np.ndarray

    def __len__(self) -> int:
        return len(self.labels)


class ImageSet(Dataset):
    """Images (N, H, W, C) uint8 with labels; items are (float image (C, H, W) in [0, 1], label)."""

    def __init__(self, images: np.ndarray, labels: np.ndarray, classes: list[str]):
        self.images, self.labels, self.classes = images, np.array(labels, np.int64), classes

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, int]:
        img = torch.from_numpy(np.array(self.images[i])).permute(2, 0, 1).float() / 255.0
        return img, int(self.labels[i])


class SampleSet(Dataset):
    """Test samples built on demand by ``make(i)``."""

    def __init__(self, labels: np.ndarray, make):
        self.labels, self._make = np.asarray(labels, np.int64), make

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> TestSample:
        if not 0 <= i < len(self):
            raise IndexError(f"test sample {i} out of range 0..{len(self) - 1}")
        return self._make(i)


def render_poses(
    cloud,
    poses: np.ndarray,
    K: torch.Tensor,
    height: int,
    width: int,
    background: float,
    motions: torch.Tensor | None = None,
    batch: int = 64,
) -> np.ndarray:
    """uint8 images of a world-frame cloud seen from camera-to-world ``poses`` (each moved by ``motions``)."""
    points, colors = (torch.from_numpy(np.ascontiguousarray(a)) for a in cloud)
    pose_t = torch.from_numpy(np.asarray(poses, np.float64))
    if motions is not None:
        pose_t = pose_t @ motion_to_matrix(motions)
    # The world frame is the reference camera, so a pose is the motion that reaches it; poses are
    # far from it, so the cloud is rendered in its own order, not in the reference camera's locality order.
    camera_motions = matrix_to_motion(pose_t)
    out = np.empty((len(poses), height, width, colors.shape[1]), np.uint8)
    for s in range(0, len(poses), batch):
        imgs, _ = project(points, colors, K, camera_motions[s : s + batch], height, width, background, locality=False)
        out[s : s + batch] = to_uint8(imgs)
    return out


class DataBundle(ABC):
    """What a data source provides: classes, image sets and test samples."""

    classes: list[str]

    def __init__(self, data: DictConfig):
        self.data = data
        self.K = intrinsics(data.image)
        self.height, self.width = int(data.image.height), int(data.image.width)
        self.background = float(data.image.background)
        self.cache_info: dict[str, dict[str, Any]] = {}

    def crop_args(self, crop: CropBound | None = None) -> dict[str, Any]:
        """Crop bound for test samples: ``crop``, else ``data.crop`` (each translation component
        up to ``max_translation``, a rotation about any axis up to ``max_rotation``)."""
        if crop is None and self.data.get("crop"):
            t = float(self.data.crop.max_translation)
            crop = CropBound((t, t, t), float(self.data.crop.max_rotation), roll_only=False)
        return {} if crop is None else {"bound": crop}

    @abstractmethod
    def train(self, augment: Method | None = None, seed: int = 0) -> ImageSet:
        """Training images, rendered under ``augment``'s training motions for ``seed`` when it has any."""

    @abstractmethod
    def test(self) -> ImageSet:
        """Clean test images."""

    def validation(self) -> ImageSet | None:
        """Clean images of the source's validation poses (model selection), or None when it has
        none; training then holds out a share of the training images (``train.val_fraction``)."""
        return None

    @abstractmethod
    def samples(self, downsampling: tuple[int, float] | None = None, crop: CropBound | None = None) -> SampleSet:
        """Re-renderable test samples, in the order of :meth:`test` (``crop`` overrides ``data.crop``)."""


class PosedCloudData(DataBundle):
    """Data rendered from world-frame clouds at known poses (synthetic and custom scenes)."""

    @abstractmethod
    def cloud(self, label: int) -> tuple[np.ndarray, np.ndarray]:
        """World-frame points and colours of class ``label``'s scene."""

    @abstractmethod
    def split(self, name: str) -> Split:
        """Poses and labels of the ``train``, ``test`` or (where :meth:`has_split`) ``validation`` split."""

    def has_split(self, name: str) -> bool:
        return name in ("train", "test")

    @abstractmethod
    def identity(self) -> dict[str, Any]:
        """Everything besides the split that determines the rendered images."""

    def _images(self, name: str, augment: Method | None, seed: int = 0) -> ImageSet:
        split = self.split(name)
        key = None if augment is None else augment.training_key(seed)
        spec = {
            "data": self.identity(),
            "split": name,
            "image": OmegaConf.to_container(self.data.image),
            "augment": key,
        }

        def build() -> dict[str, np.ndarray]:
            images = np.empty((len(split), self.height, self.width, 3), np.uint8)
            motions = augment.training_motions(len(split), seed) if key is not None else None
            for label in np.unique(split.labels):
                idx = np.nonzero(split.labels == label)[0]
                images[idx] = render_poses(
                    self.cloud(int(label)),
                    split.poses[idx],
                    self.K,
                    self.height,
                    self.width,
                    self.background,
                    None if motions is None else motions[idx],
                )
            return {"images": images, "labels": split.labels, "poses": split.poses}

        tag = name if key is None else f"{name}-{augment.axes_label}-aug"
        arrays, folder, hit = cached_arrays(Path(self.data.cache_dir), f"{self.data.name}-{tag}", spec, build)
        self.cache_info[tag] = {
            "folder": str(folder),
            "key": folder.name.rsplit("-", 1)[1],
            "hit": hit,
            "images": len(split),
        }
        return ImageSet(arrays["images"], arrays["labels"], self.classes)

    def train(self, augment: Method | None = None, seed: int = 0) -> ImageSet:
        return self._images("train", augment, seed)

    def test(self) -> ImageSet:
        return self._images("test", None)

    def validation(self) -> ImageSet | None:
        return self._images("validation", None) if self.has_split("validation") else None

    def samples(self, downsampling: tuple[int, float] | None = None, crop: CropBound | None = None) -> SampleSet:
        split = self.split("test")

        def make(i: int) -> TestSample:
            label = int(split.labels[i])
            points, colors = self.cloud(label)
            return TestSample.build(
                points,
                colors,
                self.K,
                self.height,
                self.width,
                label,
                self.background,
                downsampling=downsampling,
                frame=matrix_to_motion(torch.from_numpy(split.poses[i])),
                **self.crop_args(crop),
            )

        return SampleSet(split.labels, make)
