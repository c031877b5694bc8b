"""The schemas of the ``method`` config group, one per method (registered by
:data:`mrcert.core.methods.METHODS` as ``schema/method/<name>``): plain dataclasses, no torch."""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import MISSING


@dataclass
class MethodConfig:
    """A method without parameters of its own (camera motion smoothing: all in ``motion.*``)."""

    name: str = MISSING


@dataclass
class PixelwiseCertify:
    half_width: float = MISSING  # the certified interval [-half_width, half_width] on motion.axis
    frames: int = MISSING


@dataclass
class PixelwiseConfig(MethodConfig):
    sigma: float = MISSING  # pixel noise, in units of the [0, 1] image
    certify: PixelwiseCertify = field(default_factory=PixelwiseCertify)


@dataclass
class BoundPropagationConfig(MethodConfig):
    half_width: float = MISSING  # the certified interval [-half_width, half_width] on motion.axis
    relaxation: str = MISSING  # interval | crown
    max_pieces: int = MISSING  # pieces bounded at most per image
    seconds: float = MISSING  # time budget per image
    samples: int = MISSING  # poses sampled evenly for falsification
    batch: int = MISSING  # pieces bounded at once
    crown_neurons: int = MISSING  # ReLU layers of at most this many neurons get backward-pass bounds
