"""Every data source: the class that ``conf/data/<name>.yaml`` names by ``_target_``.

Datasets (``metaroom_synth``, ``tabletop_synth``, ``custom``, ``metaroom``) give training and
test images and re-renderable test samples (:class:`~mrcert.data.datasets.DataBundle`: built
from the ``data`` node); scenes (the built-in test scene, a point cloud file) give one cloud to
render (:class:`SceneSource`). A new source is one class and one YAML.
"""

from __future__ import annotations

import importlib

import numpy as np
import torch
from omegaconf import DictConfig

from mrcert.data.datasets import DataBundle
from mrcert.errors import MrcertError
from mrcert.scenes import testscene
from mrcert.scenes.scene import Scene, intrinsics, read_point_cloud


class SceneSource:
    """One cloud to render, from a ``data`` node."""

    @staticmethod
    def cloud(data: DictConfig) -> tuple[np.ndarray, np.ndarray]:
        """World-frame points (N, 3) and colours (N, 3)."""
        raise NotImplementedError


class TestScene(SceneSource):
    """The built-in test scene, sampled ``data.density`` apart."""

    @staticmethod
    def cloud(data: DictConfig) -> tuple[np.ndarray, np.ndarray]:
        return testscene.build(data.density)


class CloudFile(SceneSource):
    """A point cloud file (``data.path``)."""

    @staticmethod
    def cloud(data: DictConfig) -> tuple[np.ndarray, np.ndarray]:
        return read_point_cloud(data.path)


def source_class(data: DictConfig) -> type:
    """The class ``data._target_`` names (a dataset or a scene), or a one-line error."""
    target = str(data.get("_target_") or "")
    module, _, attr = target.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError):
        raise MrcertError(f"data._target_={target!r} names no class; give a dataset or a scene source") from None
    if not (isinstance(cls, type) and issubclass(cls, DataBundle | SceneSource)):
        raise MrcertError(f"data._target_={target!r} is neither a dataset (DataBundle) nor a scene source")
    return cls


def is_scene(data: DictConfig) -> bool:
    """Whether ``data`` names a scene (one cloud) rather than a dataset."""
    return issubclass(source_class(data), SceneSource)


def load(data: DictConfig) -> DataBundle:
    """The dataset a ``data`` config names."""
    cls = source_class(data)
    if not issubclass(cls, DataBundle):
        raise MrcertError(f"data={data.name} is a scene, not a dataset: it renders one cloud (task=render)")
    return cls(data)


def load_scene(data: DictConfig, device: torch.device | str = "cpu") -> Scene:
    """The scene a ``data`` config names: the built-in test scene or a point cloud file."""
    cls = source_class(data)
    if not issubclass(cls, SceneSource):
        raise MrcertError(f"data={data.name} is a dataset, not a scene")
    points, colors = cls.cloud(data)
    return Scene(
        torch.from_numpy(points).to(device),
        torch.from_numpy(np.ascontiguousarray(colors)).to(device),
        intrinsics(data.image),
        int(data.image.height),
        int(data.image.width),
        float(data.image.background),
    )
