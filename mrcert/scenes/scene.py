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


def missing_data(path: Path) -> str | None:
    """Why a ``.ply`` or ``.pcd`` file holds less data than its header declares (a cut copy:
    Open3D then only warns and fills the points it could not read), or None. Checks the points
    (PLY: the vertices, when they come first) in ASCII and binary files."""
    data = path.read_bytes()
    end = data.find(b"end_header\n") if path.suffix.lower() == ".ply" else -1
    if path.suffix.lower() == ".ply" and end >= 0:
        header, body = data[:end].decode("latin-1").splitlines(), data[end + len(b"end_header\n") :]
        fmt = next((line.split()[1] for line in header if line.startswith("format ")), "ascii")
        elements: list[tuple[str, int, list[str]]] = []
        for line in header:
            words = line.split()
            if words[:1] == ["element"] and len(words) == 3:
                elements.append((words[1], int(words[2]), []))
            elif words[:1] == ["property"] and elements:
                elements[-1][2].append(words[1])
        if not elements or elements[0][0] != "vertex":
            return None
        _, count, types = elements[0]
        if fmt == "ascii":
            have = _whole_lines(body, count, len(types))
        elif "list" in types or any(t not in _PLY_SIZES for t in types):
            return None
        else:
            have = len(body) // sum(_PLY_SIZES[t] for t in types)
        return None if have >= count else f"declares {count} points but holds data for {have}"
    if path.suffix.lower() == ".pcd":
        fields: dict[str, list[str]] = {}
        lines = data.split(b"\n")
        for k, raw in enumerate(lines):
            words = raw.decode("latin-1").split()
            if words:
                fields[words[0]] = words[1:]
            if words[:1] == ["DATA"]:
                count = int(fields.get("POINTS", ["0"])[0])
                kind = words[1] if len(words) > 1 else ""
                body = b"\n".join(lines[k + 1 :])
                if kind == "ascii":
                    have = _whole_lines(body, count, sum(int(c) for c in fields.get("COUNT", ["1"])))
                elif kind == "binary":
                    sizes = [
                        int(a) * int(b) for a, b in zip(fields.get("SIZE", []), fields.get("COUNT", []), strict=False)
                    ]
                    have = len(body) // max(sum(sizes), 1)
                else:
                    return None
                return None if have >= count else f"declares {count} points but holds data for {have}"
    return None


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
