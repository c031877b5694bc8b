"""A coloured point cloud in a reference camera frame, with the intrinsics to render it."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from mrcert.core.projection import Backend, project
from mrcert.errors import MrcertError


@dataclass
class Scene:
    """Points (N, 3) in the reference camera frame, colours (N, C) in [0, 1], and a camera."""

    points: torch.Tensor
    colors: torch.Tensor
    K: torch.Tensor
    height: int
    width: int
    background: float = 1.0

    def render(self, motions, backend: Backend = "auto") -> tuple[torch.Tensor, torch.Tensor]:
        """Images (B, C, H, W) and depth (B, H, W) under camera motions (B, 6)."""
        motions = torch.as_tensor(motions, dtype=torch.float64, device=self.points.device)
        return project(
            self.points, self.colors, self.K, motions, self.height, self.width, self.background, backend=backend
        )


def intrinsics(image: DictConfig) -> torch.Tensor:
    return torch.tensor([[image.fx, 0.0, image.cx], [0.0, image.fy, image.cy], [0.0, 0.0, 1.0]], dtype=torch.float64)


def read_point_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """xyz (N, 3) float64 and RGB (N, 3) float32 in [0, 1] of a ``.ply`` / ``.pcd`` file.

    Colours may be stored in [0, 1] or 0-255 (integer or float); anything else is an error,
    as are a missing file, no points, NaN or infinite values and a file read in part (fewer
    points than its header declares: a cut copy). No colours: mid grey. The
    last file read is kept (callers must not write into the arrays), so checking a file
    before a run costs no second read.
    """
    path = Path(path)
    if not path.is_file():
        raise MrcertError(f"point cloud file {str(path)!r} does not exist")
    stat = path.stat()
    return _read_point_cloud(str(path.resolve()), stat.st_size, stat.st_mtime_ns)


_PLY_SIZES = {
    **dict.fromkeys(("char", "uchar", "int8", "uint8"), 1),
    **dict.fromkeys(("short", "ushort", "int16", "uint16"), 2),
    **dict.fromkeys(("int", "uint", "float", "int32", "uint32", "float32"), 4),
    **dict.fromkeys(("double", "float64"), 8),
}


def _whole_lines(body: bytes, count: int, tokens: int) -> int:
    """How many of the first ``count`` lines of an ASCII body hold ``tokens`` values each."""
    return sum(1 for line in body.splitlines()[:count] if len(line.split()) == tokens)


def _header(path: Path, last: bytes) -> tuple[list[str], int] | None:
    """A cloud file's header lines, through the line that starts with ``last``, and the byte
    offset where its data begin; None when the first 64 KiB hold no such line."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    at = head.find(b"\n" + last)
    if at < 0:
        return None
    stop = head.find(b"\n", at + 1)
    if stop < 0:
        return None
    return head[:stop].decode("latin-1").splitlines(), stop + 1


def missing_data(path: Path) -> str | None:
    """Why a ``.ply`` or ``.pcd`` file holds less data than its header declares (a cut copy:
    Open3D then only warns and fills the points it could not read), or None. Checks the points
    (PLY: the vertices, when they come first) in ASCII and binary files; a binary file's data is
    measured by its size, only an ASCII file's is read."""
    suffix = path.suffix.lower()
    found = _header(path, b"end_header" if suffix == ".ply" else b"DATA ") if suffix in (".ply", ".pcd") else None
    if found is None:
        return None
    header, start = found
    words = [line.split() for line in header]
    if suffix == ".ply":
        fmt = next((w[1] for w in words if w[:1] == ["format"] and len(w) > 1), "ascii")
        elements: list[tuple[str, int, list[str]]] = []
        for w in words:
            if w[:1] == ["element"] and len(w) == 3:
                elements.append((w[1], int(w[2]), []))
            elif w[:1] == ["property"] and elements:
                elements[-1][2].append(w[1])
        if not elements or elements[0][0] != "vertex":
            return None
        _, count, types = elements[0]
        ascii_, tokens = fmt == "ascii", len(types)
        if not ascii_ and ("list" in types or any(t not in _PLY_SIZES for t in types)):
            return None
        record = 0 if ascii_ else sum(_PLY_SIZES[t] for t in types)
    else:
        fields = {w[0]: w[1:] for w in words if w}
        count, kind = int(fields.get("POINTS", ["0"])[0]), (fields["DATA"] + [""])[0]
        if kind not in ("ascii", "binary"):
            return None
        ascii_, tokens = kind == "ascii", sum(int(c) for c in fields.get("COUNT", ["1"]))
        sizes = zip(fields.get("SIZE", []), fields.get("COUNT", []), strict=False)
        record = max(sum(int(a) * int(b) for a, b in sizes), 1)
    if ascii_:
        have = _whole_lines(path.read_bytes()[start:], count, tokens)
    else:
        have = (path.stat().st_size - start) // record
    return None if have >= count else f"declares {count} points but holds data for {have}"


@functools.lru_cache(maxsize=1)
def _read_point_cloud(path_str: str, size: int, mtime_ns: int) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    path = Path(path_str)
    if path.suffix.lower() not in (".ply", ".pcd"):
        raise MrcertError(f"point cloud file {str(path)!r} has suffix {path.suffix!r}; allowed: .ply, .pcd")
    pcd = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pcd.point or len(pcd.point.positions) == 0:
        raise MrcertError(f"point cloud file {str(path)!r} has no points (or open3d cannot parse it)")
    cut = missing_data(path)
    if cut:
        raise MrcertError(f"point cloud file {str(path)!r} {cut}: it is cut short or damaged; copy it again")
    points = pcd.point.positions.numpy().astype(np.float64)
    if not np.isfinite(points).all():
        raise MrcertError(f"point cloud file {str(path)!r} has NaN or infinite coordinates")
    if "colors" not in pcd.point:
        return points, np.full((len(points), 3), 0.5, np.float32)
    raw = pcd.point.colors.numpy()
    colors = raw.astype(np.float64)
    if not np.isfinite(colors).all() or colors.min() < 0 or colors.max() > 255:
        raise MrcertError(
            f"point cloud file {str(path)!r} has colours outside [0, 1] and 0-255 "
            f"(min {colors.min()}, max {colors.max()})"
        )
    if raw.dtype == np.uint8 or colors.max() > 1:
        colors = colors / 255.0
    return points, colors.astype(np.float32)
