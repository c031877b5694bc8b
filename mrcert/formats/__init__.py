"""The verification community's formats: ONNX classifiers (:mod:`.onnx_model`) and VNN-LIB
properties (:mod:`.vnnlib`), read for ``task=verify`` and written for ``task=export``."""

from pathlib import Path


def shipped(path: Path) -> Path:
    """``path``, or ``path.gz`` where only that exists: a benchmark may name a file it ships gzipped."""
    zipped = path.with_name(path.name + ".gz")
    return zipped if not path.is_file() and zipped.is_file() else path
