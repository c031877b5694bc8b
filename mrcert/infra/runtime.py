"""Run-time choices shared by tasks: the device, and a description of the machine."""

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


def machine() -> str:
    """The machine a run executes on, in words: CPU model, cores, and the GPU when there is one."""
    import os
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = f", GPU {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ", no GPU"
    return f"{cpu}, {os.cpu_count()} cores{gpu}"
