"""The released MetaRoom layout (docs/method.md §3), read from a folder the user names.

``<root>/metaroom_<axis>[_vanilla]/{train,test}/<class>/*.png`` are image folders (labels =
alphabetical order of the class folders); ``.../certify/<class>/*.pkl`` hold one test sample
each: ``intrinsic_matrix`` (full resolution; fx, fy, cx, cy are divided by 8),
``pose`` (4x4 camera-to-world) and ``point_cloud`` (N x 6: xyz in the world frame, rgb in
[0, 1]). Pickles can run code when loaded, so they are read only from ``data.path`` /
``METAROOM_DIR`` and through an unpickler that admits plain containers and numpy arrays only.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image

from mrcert.core.crop import CropBound
from mrcert.core.geometry import matrix_to_motion
from mrcert.core.methods.base import Method
from mrcert.data.datasets import DataBundle, ImageSet, SampleSet
from mrcert.data.samples import TestSample
from mrcert.errors import MrcertError

INTRINSICS_SCALE = 8.0
_ALLOWED = (
    {("builtins", n) for n in ("dict", "list", "tuple", "set", "frozenset", "int", "float", "complex", "str", "bytes")}
    | {(m, n) for m in ("numpy.core.multiarray", "numpy._core.multiarray") for n in ("_reconstruct", "scalar")}
    | {("numpy", "ndarray"), ("numpy", "dtype"), ("collections", "OrderedDict")}
)


class _SafeUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) not in _ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an untrusted pickle")
        return super().find_class(module, name)


def read_certify_pickle(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            record = _SafeUnpickler(f).load()
    except (pickle.UnpicklingError, EOFError, OSError) as exc:
        raise MrcertError(f"cannot read certify pickle {str(path)!r}: {exc}") from None
    missing = {"intrinsic_matrix", "pose", "point_cloud"} - set(record) if isinstance(record, dict) else {"a dict"}
    if missing:
        raise MrcertError(f"certify pickle {str(path)!r} lacks {sorted(missing)}")
    cloud = np.asarray(record["point_cloud"], np.float64)
    if cloud.ndim != 2 or cloud.shape[1] != 6:
        raise MrcertError(f"certify pickle {str(path)!r}: point_cloud must be N x 6, got {cloud.shape}")
    return record


def _image_folder(folder: Path, classes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    files = [(label, p) for label, c in enumerate(classes) for p in sorted((folder / c).glob("*.png"))]
    if not files:
        raise MrcertError(f"no PNG images under {folder}/<class>/")
    images = np.stack([np.asarray(Image.open(p).convert("RGB")) for _, p in files])
    return images, np.array([label for label, _ in files], np.int64)


class ReleasedMetaRoom(DataBundle):
    def __init__(self, data: DictConfig):
        super().__init__(data)
        root = data.get("path") or os.environ.get("METAROOM_DIR")
        if not root:
            raise MrcertError("data=metaroom needs the released data: set data.path=/path/to/metaroom or METAROOM_DIR")
        suffix = "_vanilla" if data.variant == "vanilla" else ""
        self.folder = Path(root) / f"metaroom_{data.axis}{suffix}"
        if not self.folder.is_dir():
            raise MrcertError(
                f"released MetaRoom folder {str(self.folder)!r} does not exist "
                f"(data.path={root!r}, axis {data.axis!r}, variant {data.variant!r})"
            )
        split_dir = self.folder / "test"
        self.classes = sorted(p.name for p in split_dir.iterdir() if p.is_dir()) if split_dir.is_dir() else []
        if not self.classes:
            raise MrcertError(f"no class folders under {split_dir}")

    def train(self, augment: Method | None = None, seed: int = 0) -> ImageSet:
        if augment is not None and augment.training_key(seed) is not None:
            raise MrcertError("released MetaRoom images are pre-rendered: choose data.variant=augmented instead")
        return ImageSet(*_image_folder(self.folder / "train", self.classes), self.classes)

    def test(self) -> ImageSet:
        return ImageSet(*_image_folder(self.folder / "test", self.classes), self.classes)

    def samples(self, downsampling: tuple[int, float] | None = None, crop: CropBound | None = None) -> SampleSet:
        files = [
            (label, p)
            for label, c in enumerate(self.classes)
            for p in sorted((self.folder / "certify" / c).glob("*.pkl"))
        ]
        if not files:
            raise MrcertError(f"no certify pickles under {self.folder / 'certify'}/<class>/")

        def make(i: int) -> TestSample:
            label, path = files[i]
            record = read_certify_pickle(path)
            K = torch.as_tensor(np.asarray(record["intrinsic_matrix"], np.float64)).clone()
            K[:2, :3] /= INTRINSICS_SCALE
            K[2] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
            cloud = np.asarray(record["point_cloud"], np.float64)
            pose = torch.as_tensor(np.asarray(record["pose"], np.float64))
            return TestSample.build(
                np.ascontiguousarray(cloud[:, :3]),
                cloud[:, 3:].astype(np.float32),
                K,
                self.height,
                self.width,
                label,
                self.background,
                downsampling=downsampling,
                frame=matrix_to_motion(pose),
                **self.crop_args(crop),
            )

        return SampleSet(np.array([label for label, _ in files]), make)
