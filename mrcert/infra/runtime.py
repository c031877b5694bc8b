"""Run-time choices shared by tasks: the device, a description of the machine and the code, and
the command that launched the run.
torch is imported where a run asks for it, so that ``mrcert --help`` and config validation
stay light."""

from __future__ import annotations

import functools
import re
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

from mrcert.errors import MrcertError
from mrcert.infra.schema import AUTO_BATCH


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available, else CPU; asking for CUDA without one is an error."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise MrcertError(f"device={name!r} asks for CUDA but none is available; use device=cpu or device=auto")
    return device


def batch_size(setting: int | str, device: torch.device) -> int:
    """``task.batch_size``: a number as given, ``auto`` the device type's (:data:`AUTO_BATCH`).
    Results do not depend on it: every sample's noise comes from its own generator."""
    return AUTO_BATCH.get(device.type, AUTO_BATCH["cpu"]) if setting == "auto" else int(setting)


RENDER_PIXELS = 1 << 21
"""Pixels a smoothed classifier renders at once, at most (unless one model batch has more):
about 40 MB of images and depths for 3 channels."""


def render_batch(batch: int, height: int, width: int) -> int:
    """The samples a smoothed classifier renders at once for model batches of ``batch``: the
    most whole batches within :data:`RENDER_PIXELS`, at least one. A render call costs a fixed
    amount besides its images (rotations, the crop's bound, launching the kernel's threads, and
    threads idle at its end): on 2 CPU cores a certified image's 1,100 motions of the quick
    MetaRoom rendered in 0.61 s in calls of 144 against 0.75 s in calls of 16 (docs/performance.md)."""
    return batch * max(1, RENDER_PIXELS // (batch * height * width))


EVIDENCE_STORE = "docs/results_store"
"""The store committed beside the evidence page, inside the checkout: its files are the records of
runs, not code, so a change to them leaves the code version clean."""


@functools.cache
def code_version() -> str:
    """mrcert's version and, run from a git checkout, its commit (``+dirty`` when tracked files
    other than the :data:`EVIDENCE_STORE` differ from it): ``0.1.0 git:1f02dea...`` or ``0.1.0`` for
    an installed copy."""
    from mrcert import __version__

    return checkout_version(Path(__file__).resolve().parents[2], __version__)


def checkout_version(root: Path, version: str) -> str:
    """``version`` and the commit of the git checkout at ``root`` (:func:`code_version`)."""

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD") if (root / ".git").exists() else None
    if not commit:
        return version
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".", f":(exclude){EVIDENCE_STORE}")
    return f"{version} git:{commit}{'+dirty' if dirty else ''}"


def machine() -> str:
    """The machine a run executes on, in words: CPU model, cores, and the GPU when there is one."""
    import os
    import platform

    import torch

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


def launch_command() -> str | None:
    """The command that launched this run, as typed (None outside a launch: the API)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    return " ".join(["mrcert", *(["-m"] if hc.mode == RunMode.MULTIRUN else []), *as_typed(hc.overrides.task)])


def as_typed(overrides: list[str]) -> list[str]:
    """A launch's overrides as a user types them: a sweep's jobs get theirs back from Hydra's
    parser, which writes a bool as ``True``/``False``; typed, ``true``/``false`` (the same value;
    a quoted string keeps its quotes, so it never matches)."""
    return [re.sub(r"=(True|False)$", lambda m: "=" + m.group(1).lower(), o) for o in overrides]
