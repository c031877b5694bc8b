"""The certification methods a config can select (``method.name``), each built from the
``method`` and ``motion`` config groups."""

from __future__ import annotations

from collections.abc import Callable

from omegaconf import DictConfig

from mrcert.core.method import Method
from mrcert.core.pixelwise import PixelwiseSmoothing
from mrcert.core.smoothing import SmoothingDistribution
from mrcert.errors import MrcertError

METHODS: dict[str, Callable[[DictConfig, DictConfig], Method]] = {
    "motion": lambda method, motion: SmoothingDistribution.from_config(motion),
    "pixelwise": PixelwiseSmoothing.from_config,
}


def build_method(cfg: DictConfig) -> Method:
    """The method ``cfg.method`` names, on ``cfg.motion``."""
    method = cfg.method
    try:
        make = METHODS[str(method.name)]
    except KeyError:
        raise MrcertError(f"method={method.name!r} is not allowed: one of {', '.join(METHODS)}") from None
    return make(method, cfg.motion)
