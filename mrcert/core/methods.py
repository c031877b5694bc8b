"""The certification methods a config can select (``method.name``), each built from the
``method`` and ``motion`` config groups."""

from __future__ import annotations

from omegaconf import DictConfig

from mrcert.core.method import Method
from mrcert.core.pixelwise import PixelwiseSmoothing
from mrcert.core.smoothing import SmoothingDistribution
from mrcert.errors import ConfigError

METHODS: dict[str, type[Method]] = {"motion": SmoothingDistribution, "pixelwise": PixelwiseSmoothing}


def build_method(cfg: DictConfig) -> Method:
    """The method ``cfg.method`` names, on ``cfg.motion``."""
    method = cfg.method
    if method.name not in METHODS:
        raise ConfigError("method.name", method.name, f"one of {', '.join(METHODS)}")
    return METHODS[str(method.name)].from_config(method, cfg.motion)
