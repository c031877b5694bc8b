"""A content-addressed cache of rendered image sets under ``outputs/data/``.

An entry's key is a hash of everything that determines its images (the generator version,
the dataset config, the split, the augmentation). An entry is written to a temporary
folder and renamed into place when complete, so an interrupted build is never reused.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mrcert.core.generator import GENERATOR_VERSION
from mrcert.errors import MrcertError


def cache_key(spec: dict[str, Any]) -> str:
    blob = json.dumps({"version": GENERATOR_VERSION, **spec}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def cached_arrays(
    root: Path, name: str, spec: dict[str, Any], build: Callable[[], dict[str, np.ndarray]]
) -> tuple[dict[str, np.ndarray], Path, bool]:
    """The arrays of entry ``name-<key>``: loaded (memory-mapped) when present, else built and stored.

    Returns ``(arrays, folder, hit)``.
    """
    folder = Path(root) / f"{name}-{cache_key(spec)}"
    meta = folder / "meta.json"
    hit = meta.is_file()
    if not hit:
        tmp = folder.with_name(f"{folder.name}.tmp-{os.getpid()}")
        try:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            arrays = build()
            for key, value in arrays.items():
                np.save(tmp / f"{key}.npy", value)
            (tmp / "meta.json").write_text(json.dumps({"spec": spec, "arrays": sorted(arrays)}, indent=1, default=str))
            if folder.exists():  # another process finished the same entry first
                shutil.rmtree(tmp)
            else:
                os.replace(tmp, folder)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise MrcertError(f"cannot write the data cache at {folder.parent}: {exc}") from None
    names = json.loads(meta.read_text())["arrays"]
    return {k: np.load(folder / f"{k}.npy", mmap_mode="r") for k in names}, folder, hit


def folder_size(folder: Path) -> int:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file())
