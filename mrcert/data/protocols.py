"""Camera pose protocols of the paper's datasets (docs/method.md §3).

A pose is given by ``(yaw, pitch, roll, radius)`` around a target point: the camera sits at
``target + radius * (cos p cos y, cos p sin y, sin p)`` (z up), looks at the target, and is
rolled by ``roll`` about its optical axis (a roll is the camera's own ``rz`` motion). Angles
are in degrees here, as in the paper's protocol; poses are 4x4 camera-to-world matrices in
the OpenCV camera convention (x right, y down, z forward).

Separation rules (``protocol.separation_rule``), with the gaps of ``protocol.separation``
(yaw compared circularly):

* ``every`` (MetaRoom, the paper's wording "at least 15 deg away from any yaw, pitch, or roll
  angle of every pose in the test set"): every quantity of a training pose differs by at least
  its gap from that quantity of every test pose;
* ``any`` (the tabletop, where ``every`` is infeasible: 19 random test rolls with 20 deg gaps
  cover the whole -60..60 deg range): for every test pose, at least one quantity differs by
  its gap, so no training pose lies inside the box of half-widths ``gap`` around a test pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

QUANTITIES = ("yaw", "pitch", "roll", "radius")


def look_at_poses(yaw, pitch, roll, radius, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Camera-to-world poses (N, 4, 4) from angles in degrees and radii in metres."""
    y, p, r = (np.deg2rad(np.asarray(a, dtype=np.float64)) for a in (yaw, pitch, roll))
    radius = np.asarray(radius, dtype=np.float64)
    n = np.broadcast(y, p, r, radius).shape
    y, p, r, radius = (np.broadcast_to(a, n).reshape(-1) for a in (y, p, r, radius))
    center = np.asarray(target, np.float64) + radius[:, None] * np.column_stack(
        [np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)]
    )
    forward = -np.column_stack([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)])
    right = np.column_stack([-np.sin(y), np.cos(y), np.zeros_like(y)])  # horizontal, defined at any pitch
    down = np.cross(forward, right)
    c, s = np.cos(r)[:, None], np.sin(r)[:, None]
    x_axis, y_axis = c * right + s * down, -s * right + c * down  # [right down forward] @ Rz(roll)
    poses = np.zeros((len(y), 4, 4))
    poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2], poses[:, :3, 3] = x_axis, y_axis, forward, center
    poses[:, 3, 3] = 1.0
    return poses


@dataclass(frozen=True)
class PoseSet:
    """Poses with their protocol parameters (degrees, metres)."""

    params: np.ndarray  # (N, 4): yaw, pitch, roll, radius
    target: tuple[float, float, float]

    @property
    def poses(self) -> np.ndarray:
        yaw, pitch, roll, radius = self.params.T
        return look_at_poses(yaw, pitch, roll, radius, self.target)

    def __len__(self) -> int:
        return len(self.params)


RULES = ("every", "any")


def differences(poses: np.ndarray, others: np.ndarray) -> np.ndarray:
    """|difference| of every quantity between poses (N, 4) and others (M, 4): (N, M, 4), yaw on the circle."""
    diff = np.abs(poses[:, None, :] - others[None, :, :])
    yaw = QUANTITIES.index("yaw")
    diff[..., yaw] = np.minimum(diff[..., yaw] % 360.0, 360.0 - diff[..., yaw] % 360.0)
    return diff


def separated(candidates: np.ndarray, tests: np.ndarray, gaps: dict[str, float], rule: str = "every") -> np.ndarray:
    """Mask of candidates (N, 4) separated from every test pose (M, 4) by ``rule`` (see above)."""
    if rule not in RULES:
        raise ValueError(f"separation rule {rule!r} is not one of {RULES}")
    if len(tests) == 0 or not gaps:
        return np.ones(len(candidates), bool)
    diff = differences(candidates, tests)
    apart = [diff[:, :, QUANTITIES.index(q)] >= gap for q, gap in gaps.items()]
    far = np.logical_and.reduce(apart) if rule == "every" else np.logical_or.reduce(apart)
    return far.all(axis=1)


PITCH_LAWS = ("angle", "area")


def _draw(quantity: str, bounds: tuple[float, float], size: int, rng: np.random.Generator, law: str) -> np.ndarray:
    if quantity == "pitch" and law == "area":
        low, high = np.sin(np.deg2rad(bounds))
        return np.rad2deg(np.arcsin(rng.uniform(low, high, size=size)))
    return rng.uniform(*bounds, size=size)


def sample_poses(
    n: int,
    ranges: dict[str, tuple[float, float]],
    rng: np.random.Generator,
    *,
    apart: list[tuple[np.ndarray, dict[str, float]]] = (),
    rule: str = "every",
    max_camera_z: float | None = None,
    target=(0.0, 0.0, 0.0),
    max_rounds: int = 1000,
    pitch_law: str = "angle",
) -> PoseSet:
    """``n`` poses uniform in ``ranges`` (by rejection: separated by ``rule`` from each set of
    held-out poses in ``apart`` by that set's gaps, camera below ``max_camera_z``).
    ``pitch_law``: ``angle`` draws the pitch uniformly in angle like the other quantities;
    ``area``, uniformly over the sphere's area (its sine uniform), so that low pitches are
    commoner. Deterministic for a given generator state."""
    if pitch_law not in PITCH_LAWS:
        raise ValueError(f"pitch law {pitch_law!r} is not one of {PITCH_LAWS}")
    kept: list[np.ndarray] = []
    count = 0
    for _ in range(max_rounds):
        batch = np.column_stack([_draw(q, ranges[q], max(2 * n, 64), rng, pitch_law) for q in QUANTITIES])
        ok = np.ones(len(batch), bool)
        for others, gaps in apart:
            ok &= separated(batch, others, gaps, rule)
        if max_camera_z is not None:
            ok &= target[2] + batch[:, 3] * np.sin(np.deg2rad(batch[:, 1])) <= max_camera_z
        kept.append(batch[ok])
        count += int(ok.sum())
        if count >= n:
            return PoseSet(np.concatenate(kept)[:n], tuple(target))
    raise ValueError(
        f"could not draw {n} poses within {ranges} separated ({rule}) from the held-out poses by "
        f"{[gaps for _, gaps in apart]}; widen the ranges or reduce the gaps"
    )


def ring_poses(
    per_class: int, yaw_range: tuple[float, float], pitch: float, roll: float, radius: float, target=(0.0, 0.0, 0.0)
) -> PoseSet:
    """``per_class`` yaws evenly spread over ``yaw_range`` (end excluded) at one pitch, roll, radius."""
    yaws = yaw_range[0] + (yaw_range[1] - yaw_range[0]) * np.arange(per_class) / per_class
    params = np.column_stack([yaws, np.full(per_class, pitch), np.full(per_class, roll), np.full(per_class, radius)])
    return PoseSet(params, tuple(target))
