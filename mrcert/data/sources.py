"""Every data source, by ``data.source``: the one place that maps a source's name to its code.

Datasets (``metaroom_synth``, ``tabletop_synth``, ``custom``, ``metaroom``) give training and
test images and re-renderable test samples (:class:`~mrcert.data.datasets.DataBundle`);
scenes (``builtin``: the test scene, ``file``: a point cloud file) give one cloud to render
(:class:`~mrcert.scenes.scene.Scene`).
"""

from __future__ import annotations

import numpy as np
import torch
from omegaconf import DictConfig

from mrcert.data.custom import CustomData
from mrcert.data.datasets import DataBundle
from mrcert.data.release import ReleasedMetaRoom
from mrcert.data.synthetic import SyntheticData
from mrcert.errors import MrcertError
from mrcert.scenes import testscene
from mrcert.scenes.scene import Scene, intrinsics, read_point_cloud

DATASETS = {
    "metaroom_synth": SyntheticData,
    "tabletop_synth": SyntheticData,
    "custom": CustomData,
    "metaroom": ReleasedMetaRoom,
}
SCENES = {
    "builtin": lambda data: testscene.build(data.density),
    "file": lambda data: read_point_cloud(data.path),
}


def is_scene(data: DictConfig) -> bool:
    """Whether ``data`` names a scene (one cloud) rather than a dataset."""
    return data.source in SCENES


def load(data: DictConfig) -> DataBundle:
    """The dataset a ``data`` config names."""
    if data.source not in DATASETS:
        raise MrcertError(f"data.source={data.source!r} is not a dataset; allowed: {', '.join(DATASETS)}")
    return DATASETS[data.source](data)


def load_scene(data: DictConfig, device: torch.device | str = "cpu") -> Scene:
    """The scene a ``data`` config names: the built-in test scene or a point cloud file."""
    if data.source not in SCENES:
        raise MrcertError(f"data.source={data.source!r} is not a scene; allowed: {', '.join(SCENES)}")
    points, colors = SCENES[data.source](data)
    return Scene(
        torch.from_numpy(points).to(device),
        torch.from_numpy(np.ascontiguousarray(colors)).to(device),
        intrinsics(data.image),
        int(data.image.height),
        int(data.image.width),
        float(data.image.background),
    )
