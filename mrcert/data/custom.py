"""Users' own scenes: a point cloud file, a poses file and the camera of ``data.image``.

Poses file (JSON)::

    {"classes": ["mug", "can"],
     "poses": [{"split": "train", "label": "mug", "pose": [[r00, r01, r02, tx], ..., [0, 0, 0, 1]]},
               {"split": "test",  "label": "can", "pose": [[...]]}]}

Poses with ``"split": "validation"`` are optional: when given, they select ``best.pt`` in training
(otherwise a share of the training poses is held out, ``train.val_fraction``).
``pose`` is a 4x4 camera-to-world matrix in OpenCV camera axes (x right, y down, z forward),
the cloud is in the same world frame.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from mrcert.data.cache import file_digest
from mrcert.data.datasets import PosedCloudData, Split
from mrcert.errors import MrcertError
from mrcert.scenes.scene import read_point_cloud

SPLITS = ("train", "test", "validation")  # validation poses are optional (model selection)


def check_rigid(pose: Any, where: str) -> np.ndarray:
    """A 4x4 rigid transform (rotation with det +1, last row 0 0 0 1), or a clear error."""
    try:
        m = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise MrcertError(f"{where}: pose is not a 4x4 matrix of numbers") from None
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise MrcertError(f"{where}: pose must be a finite 4x4 matrix, got shape {m.shape}")
    R = m[:3, :3]
    if (
        not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9)
        or not np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        or np.linalg.det(R) < 0
    ):
        raise MrcertError(
            f"{where}: pose is not a rigid transform (rotation part must be orthonormal with "
            f"det +1 and the last row 0 0 0 1)"
        )
    return m


def read_poses(path: Path) -> tuple[list[str], dict[str, Split]]:
    if not path.is_file():
        raise MrcertError(f"poses file {str(path)!r} does not exist")
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MrcertError(f"poses file {str(path)!r} is not valid UTF-8 JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise MrcertError(f"poses file {str(path)!r} must hold a JSON object with 'classes' and 'poses'")
    classes, entries = doc.get("classes"), doc.get("poses")
    if not isinstance(classes, list) or not classes or not isinstance(entries, list):
        raise MrcertError(f"poses file {str(path)!r} needs a non-empty 'classes' list and a 'poses' list")
    rows: dict[str, list[tuple[np.ndarray, int]]] = {s: [] for s in SPLITS}
    seen: dict[bytes, tuple[int, str, str]] = {}  # a pose (rounded to 1e-9) -> its first entry
    for i, e in enumerate(entries):
        where = f"{path}: poses[{i}]"
        if not isinstance(e, dict):
            raise MrcertError(f"{where}: must be an object with split, label and pose")
        if e.get("split") not in SPLITS:
            raise MrcertError(f"{where}: split {e.get('split')!r} is not allowed: {', '.join(SPLITS)}")
        if e.get("label") not in classes:
            raise MrcertError(f"{where}: label {e.get('label')!r} is not one of the classes {classes}")
        pose = check_rigid(e.get("pose"), where)
        rows[e["split"]].append((pose, classes.index(e["label"])))
        key = np.round(pose, 9).tobytes()
        if key in seen:
            _check_repeat(path, seen[key], (i, e["split"], e["label"]))
        else:
            seen[key] = (i, e["split"], e["label"])
    for s in ("train", "test"):
        if not rows[s]:
            raise MrcertError(f"poses file {str(path)!r} has no {s} poses")
    splits = {
        s: Split(np.stack([p for p, _ in r]), np.zeros((len(r), 4)), np.array([c for _, c in r], np.int64))
        for s, r in rows.items()
        if r
    }
    return list(classes), splits


def _check_repeat(path: Path, first: tuple[int, str, str], again: tuple[int, str, str]) -> None:
    """Refuse a pose given twice where that makes the data wrong: with two labels (one view of
    one scene is one class), twice among the test poses (an image counted twice), or as a test
    pose and a training or validation pose (the classifier would be tested on what it saw)."""
    (i, split_i, label_i), (j, split_j, label_j) = first, again
    both = f"{path}: poses[{i}] and poses[{j}] are the same pose"
    if label_i != label_j:
        raise MrcertError(f"{both}, labelled {label_i!r} and {label_j!r}: one view has one label")
    if split_i == split_j == "test":
        raise MrcertError(f"{both}, twice among the test poses: give each test pose once")
    if "test" in (split_i, split_j) and split_i != split_j:
        raise MrcertError(
            f"{both}, a {split_i} and a {split_j} pose: a test pose must not be one the model is trained or selected on"
        )


class CustomData(PosedCloudData):
    def __init__(self, data: DictConfig):
        super().__init__(data)
        self.cloud_path, self.poses_path = Path(data.path), Path(data.poses)
        self.points, self.colors = read_point_cloud(self.cloud_path)
        self.classes, self.splits = read_poses(self.poses_path)

    def cloud(self, label: int):
        return self.points, self.colors

    def split(self, name: str) -> Split:
        return self.splits[name]

    def has_split(self, name: str) -> bool:
        return name in self.splits

    def identity(self) -> dict[str, Any]:
        return {"cloud": file_digest(self.cloud_path), "poses": file_digest(self.poses_path)}
