"""The schemas of the ``method`` config group, one per method (registered by
:data:`mrcert.core.methods.METHODS` as ``schema/method/<name>``), with their checks: plain
dataclasses, no torch."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from mrcert.core.axes import AXES, is_translation
from mrcert.core.checks import POSITIVE, Check, checked, integer, number, one_of
from mrcert.errors import ConfigError

SECONDS = Check(
    lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0, "> 0 (the time budget per image)"
)
HALF_WIDTH = Check(lambda v: number(v) and v > 0, "> 0 (the motion's unit)")


def at_least(least: int) -> Check:
    return Check(lambda v: integer(v) and v >= least, f"an integer >= {least}")


def _single_axis(root: Mapping[str, Any]) -> str | None:
    """The motion's one axis, or None for a multi-axis motion or several axes joined by '+'
    (which the method refuses when built, naming the key)."""
    motion = root.get("motion", {})
    axis = motion.get("axis")
    return None if motion.get("axes") or axis not in AXES else axis


@dataclass
class MethodConfig:
    """A method without parameters of its own (camera motion smoothing: all in ``motion.*``)."""

    name: str = MISSING


@dataclass
class PixelwiseCertify:
    half_width: float = checked(HALF_WIDTH)  # the certified interval [-half_width, half_width] on motion.axis
    frames: int = checked(at_least(2))


@dataclass
class PixelwiseConfig(MethodConfig):
    sigma: float = checked(POSITIVE)  # pixel noise, in units of the [0, 1] image
    certify: PixelwiseCertify = field(default_factory=PixelwiseCertify)

    @staticmethod
    def relations(method: Mapping[str, Any], where: str, root: Mapping[str, Any]) -> None:
        """On a rotation, each piece between frames is narrower than pi, the arc a rotation's bound covers."""
        axis, certify = _single_axis(root), method["certify"]
        half_width, frames = certify["half_width"], certify["frames"]
        piece = 2 * half_width / (frames - 1)
        if axis is not None and not is_translation(axis) and piece >= math.pi:
            least = int(math.floor(2 * half_width / math.pi)) + 2  # pieces narrower than pi
            raise ConfigError(
                f"{where}.certify.frames",
                frames,
                f"at least {least} for half_width={half_width} on {axis}: each piece between frames "
                f"must be narrower than pi (here {piece:.6g} rad), the arc a rotation's bound covers",
            )


@dataclass
class BoundPropagationConfig(MethodConfig):
    half_width: float = checked(HALF_WIDTH)  # the certified interval [-half_width, half_width] on motion.axis
    relaxation: str = checked(one_of("interval", "crown"))
    max_pieces: int = checked(at_least(1))  # pieces bounded at most per image
    seconds: float = checked(SECONDS)  # the time budget per image (inf: none)
    samples: int = checked(at_least(2))  # poses sampled evenly for falsification
    batch: int = checked(at_least(1))  # pieces bounded at once
    crown_neurons: int = checked(at_least(0))  # ReLU layers of at most this many neurons get backward-pass bounds

    @staticmethod
    def relations(method: Mapping[str, Any], where: str, root: Mapping[str, Any]) -> None:
        """On a rotation, the interval is narrower than pi (each piece narrower than pi)."""
        axis = _single_axis(root)
        if axis is not None and not is_translation(axis) and method["half_width"] >= math.pi / 2:
            raise ConfigError(
                f"{where}.half_width", method["half_width"], f"< pi/2 on {axis} (each piece narrower than pi)"
            )


@dataclass
class EnumerationConfig(MethodConfig):
    half_width: float = checked(HALF_WIDTH)  # the certified interval [-half_width, half_width] on motion.axis
    relaxation: str = checked(one_of("interval", "crown"))
    run_images: int = checked(at_least(1))  # a run of at most this many images is classified image by image
    max_bounds: int = checked(at_least(1))  # runs bounded at most per image (then: unknown)
    batch: int = checked(at_least(1))  # images classified at once
    crown_neurons: int = checked(at_least(0))  # ReLU layers of at most this many neurons get backward-pass bounds
    incremental: bool = True  # an image recomputed only where its changed pixels reach (false: in full)

    @staticmethod
    def relations(method: Mapping[str, Any], where: str, root: Mapping[str, Any]) -> None:
        """On a rotation, the interval is within [-1, 1] rad (the rotation's 1 exact, cos >= 0.5)."""
        axis = _single_axis(root)
        if axis is not None and not is_translation(axis) and not 0 <= method["half_width"] <= 1:
            why = f"at most 1 rad on {axis} for method=enumeration"
            raise ConfigError(f"{where}.half_width", method["half_width"], why)
