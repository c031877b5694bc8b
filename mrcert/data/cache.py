"""A content-addressed cache of rendered image sets under ``outputs/data/``.

An entry's key is a hash of everything that determines its images (the generator version,
the dataset config, the split, the augmentation). An entry is written to a temporary
folder and renamed into place when complete, so an interrupted build is never reused.
``meta.json`` records each array's sha256, shape and dtype; every use checks them, and an entry
that fails (a file changed, cut short or gone, or written before arrays were recorded) is set
aside and rendered again, with a warning naming it: a damaged entry is never trained on.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mrcert.core.generator import GENERATOR_VERSION
from mrcert.errors import MrcertError

log = logging.getLogger(__name__)


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
    if hit:
        damage = _damage(folder)
        if damage:
            aside = folder.with_name(f"{folder.name}.damaged-{os.getpid()}")
            with contextlib.suppress(FileNotFoundError):  # another process set it aside first
                os.replace(folder, aside)
            log.warning("the cached images %s are damaged (%s): moved to %s and rendered again", folder, damage, aside)
            shutil.rmtree(aside, ignore_errors=True)
            hit = False
    if not hit:
        tmp = folder.with_name(f"{folder.name}.tmp-{os.getpid()}")
        try:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            arrays = build()
            for key, value in arrays.items():
                np.save(tmp / f"{key}.npy", value)
            recorded = {k: _record(tmp / f"{k}.npy", np.asarray(v)) for k, v in sorted(arrays.items())}
            (tmp / "meta.json").write_text(json.dumps({"spec": spec, "arrays": recorded}, indent=1, default=str))
            if folder.exists():  # another process finished the same entry first
                shutil.rmtree(tmp)
            else:
                os.replace(tmp, folder)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise MrcertError(f"cannot write the data cache at {folder.parent}: {exc}") from None
    names = json.loads(meta.read_text())["arrays"]
    return {k: np.load(folder / f"{k}.npy", mmap_mode="r") for k in names}, folder, hit


def _record(path: Path, array: np.ndarray) -> dict[str, Any]:
    return {"sha256": file_digest(path), "shape": list(array.shape), "dtype": str(array.dtype)}


def _damage(folder: Path) -> str | None:
    """What is wrong with a cache entry (None when each array is the one recorded)."""
    try:
        recorded = json.loads((folder / "meta.json").read_text())["arrays"]
    except (OSError, ValueError, KeyError):
        return "meta.json unreadable"
    if not isinstance(recorded, dict):
        return "written before arrays were recorded"
    for key, want in recorded.items():
        path = folder / f"{key}.npy"
        try:
            if file_digest(path) != want["sha256"]:
                return f"{path.name} is not the array recorded"
            array = np.load(path, mmap_mode="r")
        except (OSError, ValueError) as exc:
            return f"{path.name}: {exc}"
        if list(array.shape) != want["shape"] or str(array.dtype) != want["dtype"]:
            return f"{path.name} has shape {array.shape} {array.dtype}, recorded {tuple(want['shape'])} {want['dtype']}"
    return None


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def folder_size(folder: Path) -> int:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file())
