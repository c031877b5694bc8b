"""Run-time choices shared by tasks: the device."""

from __future__ import annotations

import torch

from mrcert.errors import MrcertError


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available, else CPU; asking for CUDA without one is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise MrcertError(f"device={name!r} asks for CUDA but none is available; use device=cpu or device=auto")
    return device
