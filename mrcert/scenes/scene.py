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
    as are a missing file, no points and NaN or infinite values. No colours: mid grey. The
    last file read is kept (callers must not write into the arrays), so checking a file
    before a run costs no second read.
    """
    path = Path(path)
    if not path.is_file():
        raise MrcertError(f"point cloud file {str(path)!r} does not exist")
    stat = path.stat()
    return _read_point_cloud(str(path.resolve()), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=1)
def _read_point_cloud(path_str: str, size: int, mtime_ns: int) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    path = Path(path_str)
    if path.suffix.lower() not in (".ply", ".pcd"):
        raise MrcertError(f"point cloud file {str(path)!r} has suffix {path.suffix!r}; allowed: .ply, .pcd")
    pcd = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pcd.point or len(pcd.point.positions) == 0:
        raise MrcertError(f"point cloud file {str(path)!r} has no points (or open3d cannot parse it)")
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
