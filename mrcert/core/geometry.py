"""Rigid camera motions in the conventions of docs/method.md §1.

A motion is a 6-vector ``(tx, ty, tz, rx, ry, rz)``: a translation and a rotation vector
``theta * n`` with ``R = exp(theta n^)``. It acts in the camera's own frame:
``new_pose = pose @ [[R, t], [0, 1]]``, so a point with camera coordinates ``P`` has
coordinates ``R^T (P - t)`` after the motion. Everything here is batched over leading
dimensions and computed in float64.
"""

from __future__ import annotations

import torch


def _hat(v: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrices ``v^`` with ``v^ w = v x w``; ``v`` has shape (..., 3)."""
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v.unbind(-1)
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def rotvec_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula ``R = cos(t) I + sin(t) n^ + (1 - cos(t)) n n^T``.

    Written in this form so that a rotation about a coordinate axis has exactly the entries
    ``cos``, ``sin`` and 0 of docs/method.md §1 (no rounding from ``1 - (1 - cos)``).
    """
    rotvec = torch.as_tensor(rotvec, dtype=torch.float64)
    theta = torch.linalg.vector_norm(rotvec, dim=-1, keepdim=True)
    safe = torch.where(theta > 0, theta, torch.ones_like(theta))
    n = torch.where(theta > 0, rotvec / safe, torch.zeros_like(rotvec))
    c = torch.cos(theta)[..., None]
    s = torch.sin(theta)[..., None]
    eye = torch.eye(3, dtype=torch.float64, device=rotvec.device).expand(rotvec.shape[:-1] + (3, 3))
    outer = n[..., :, None] * n[..., None, :]
    return c * eye + s * _hat(n) + (1 - c) * outer


def matrix_to_rotvec(R: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rotvec_to_matrix` for rotations with angle in [0, pi]."""
    R = torch.as_tensor(R, dtype=torch.float64)
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    theta = torch.arccos(cos)
    axis = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = torch.sin(theta)
    small = theta < 1e-6
    near_pi = ~small & (sin < 1e-6)
    # Generic case: axis * theta / (2 sin theta); small angles: the first-order term axis / 2.
    denom = torch.where(small | near_pi, torch.ones_like(sin), 2 * sin)
    out = torch.where(small[..., None], axis / 2, axis * (theta / denom)[..., None])
    if bool(near_pi.any()):
        # theta ~ pi: n n^T = (R + I) / 2; take its column of largest norm as the axis.
        B = (R + torch.eye(3, dtype=R.dtype, device=R.device)) / 2
        idx = B.diagonal(dim1=-2, dim2=-1).argmax(-1)
        col = torch.gather(B, -1, idx[..., None, None].expand(B.shape[:-1] + (1,)))[..., 0]
        n = col / torch.linalg.vector_norm(col, dim=-1, keepdim=True)
        out = torch.where(near_pi[..., None], n * theta[..., None], out)
    return out


def motion_to_matrix(motion: torch.Tensor) -> torch.Tensor:
    """4x4 homogeneous matrices ``[[R, t], [0, 1]]`` of motions of shape (..., 6)."""
    motion = torch.as_tensor(motion, dtype=torch.float64)
    T = torch.zeros(motion.shape[:-1] + (4, 4), dtype=torch.float64, device=motion.device)
    T[..., :3, :3] = rotvec_to_matrix(motion[..., 3:])
    T[..., :3, 3] = motion[..., :3]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_motion(T: torch.Tensor) -> torch.Tensor:
    """Motion 6-vectors of 4x4 rigid transforms (inverse of :func:`motion_to_matrix`)."""
    T = torch.as_tensor(T, dtype=torch.float64)
    return torch.cat([T[..., :3, 3], matrix_to_rotvec(T[..., :3, :3])], -1)


def compose(a1: torch.Tensor, a2: torch.Tensor) -> torch.Tensor:
    """Lemma 1: ``a1 o a2 = (R1 R2, R1 t2 + t1)`` -- first move by ``a1``, then by ``a2``.

    For motions along one fixed axis (and pure translations) this equals ``a1 + a2``.
    """
    return matrix_to_motion(motion_to_matrix(a1) @ motion_to_matrix(a2))
