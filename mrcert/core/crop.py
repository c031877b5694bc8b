"""The exact crop of a test sample: the points that can land in the image under some motion
within a bound. Every other point stays outside the image for such motions, so removing it
changes no image; motions beyond the bound are rendered from the full cloud."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch

from mrcert.core.axes import axis_index, is_translation
from mrcert.core.projection import rotations, to_camera


def frustum_half_angle(K: torch.Tensor, height: int, width: int) -> float:
    """Half-angle of the cone around the optical axis that contains the image's frustum."""
    kx, ky = frustum_slopes(K, height, width)
    return float(np.arctan(np.hypot(kx, ky)))


def frustum_slopes(K: torch.Tensor, height: int, width: int) -> tuple[float, float]:
    """``kx, ky`` with every landing point satisfying ``|X| <= kx Z`` and ``|Y| <= ky Z``."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    return max(cx, width - cx) / fx, max(cy, height - cy) / fy


@dataclass(frozen=True)
class CropBound:
    """The motions a test sample's crop is exact for: ``|t_i| <= translation[i]`` and a
    rotation of angle ``<= rotation``, about the optical axis only when ``roll_only``.

    Tests, for a camera-frame point ``P = (X, Y, Z)`` (each keeps every point that can land):

    * no rotation: the frustum widened by the translation box,
      ``|X| - Tx <= kx (Z + Tz)``, ``|Y| - Ty <= ky (Z + Tz)``;
    * roll only: a roll keeps the distance to the optical axis, so
      ``sqrt(X^2 + Y^2) - sqrt(Tx^2 + Ty^2) <= sqrt(kx^2 + ky^2) (Z + Tz)``;
    * any rotation: the cone test, angle(P, z) <= frustum half-angle + rotation + asin(|T| / |P|).
    """

    translation: tuple[float, float, float]
    rotation: float = 0.0
    roll_only: bool = True

    @classmethod
    def covering(cls, extents: dict[str, float]) -> CropBound:
        """The bound for motions of at most ``extents[axis]`` on each of its axes (a translation
        in metres; the rotation axis, at most one, in radians)."""
        box = [0.0, 0.0, 0.0]
        rotation, about = 0.0, None
        for axis, extent in extents.items():
            if is_translation(axis):
                box[axis_index(axis)] = extent
            else:
                rotation, about = extent, axis
        return cls(tuple(box), rotation, roll_only=about in (None, "rz"))

    def contains(self, motions: torch.Tensor) -> torch.Tensor:
        box = torch.tensor(self.translation, dtype=motions.dtype, device=motions.device)
        ok = (motions[:, :3].abs() <= box).all(dim=1)
        if self.roll_only:
            return ok & (motions[:, 3:5] == 0).all(dim=1) & (motions[:, 5].abs() <= self.rotation)
        return ok & (torch.linalg.vector_norm(motions[:, 3:], dim=1) <= self.rotation)

    def mask(
        self, points: torch.Tensor, K: torch.Tensor, height: int, width: int, frame: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Which of ``points`` (N, 3) to keep: points in the camera frame, or, given ``frame`` (a
        motion (6,)), in a frame whose camera frame is ``camera_points(points, frame)``, each
        point moved there with exactly its operations (the cloud's camera-frame copy is not made)."""
        pts = np.ascontiguousarray(torch.as_tensor(points, dtype=torch.float64).cpu().numpy())
        moved = frame is not None
        frame = torch.zeros(6, dtype=torch.float64) if frame is None else torch.as_tensor(frame, dtype=torch.float64)
        R = rotations(frame.reshape(1, 6).cpu())[0].numpy()
        kx, ky = frustum_slopes(K, height, width)
        mode = (0 if self.rotation == 0 else 1) if self.roll_only else 2
        out = np.empty(len(pts), np.bool_)
        _crop_kernel(
            pts,
            moved,
            R,
            frame[:3].cpu().numpy(),
            mode,
            kx,
            ky,
            np.array(self.translation, np.float64),
            frustum_half_angle(K, height, width) + self.rotation + 1e-9,
            out,
        )
        return torch.from_numpy(out).to(torch.as_tensor(points).device)


@numba.njit(parallel=True, cache=True, nogil=True)
def _crop_kernel(P, moved, R, t, mode, kx, ky, box, cone_limit, out):  # pragma: no cover - compiled
    slack = 1e-9
    t_xy = np.sqrt(box[0] * box[0] + box[1] * box[1])
    t_norm = np.sqrt(t_xy * t_xy + box[2] * box[2])
    kc = np.sqrt(kx * kx + ky * ky)
    for i in numba.prange(P.shape[0]):
        x, y, z = to_camera(P, i, R, t) if moved else (P[i, 0], P[i, 1], P[i, 2])
        depth = z + box[2]
        if mode == 0:
            out[i] = depth > 0 and abs(x) - box[0] <= kx * depth + slack and abs(y) - box[1] <= ky * depth + slack
        elif mode == 1:
            out[i] = depth > 0 and np.sqrt(x * x + y * y) - t_xy <= kc * depth + slack
        else:
            norm = np.sqrt(x * x + y * y + z * z)
            if norm <= t_norm:
                out[i] = True
            else:
                angle = np.arccos(min(1.0, max(-1.0, z / norm)))
                out[i] = angle <= cone_limit + np.arcsin(min(1.0, t_norm / norm))
