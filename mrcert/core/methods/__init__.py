"""The certification methods a config can select (``method.name``): one line each.

A line names the method's class (imported only when a method is built: it brings torch), the
schema of its ``method`` config group, and what its results never depend on. This module
imports nothing heavy, so that the schemas register and run keys are computed without torch.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

from omegaconf import DictConfig

from mrcert.core.methods.schemas import BoundPropagationConfig, EnumerationConfig, MethodConfig, PixelwiseConfig
from mrcert.errors import ConfigError

if TYPE_CHECKING:
    from mrcert.core.methods.base import Method


@dataclass(frozen=True)
class Registered:
    """A method as configs and run keys see it."""

    target: str
    """``"module:Class"``, a :class:`~mrcert.core.methods.base.Method`."""
    schema: type
    """The dataclass its ``conf/method/<name>.yaml`` is checked against."""
    unkeyed: tuple[str, ...] = ()
    """Config prefixes none of its results depend on, left out of every run key."""
    unkeyed_model: tuple[str, ...] = ()
    """Further prefixes a model trained for it never depends on, left out of a train run's key."""

    def load(self) -> type[Method]:
        module, name = self.target.split(":")
        return getattr(importlib.import_module(module), name)


METHODS: dict[str, Registered] = {
    # Camera motion smoothing's parameters are all in motion.*: its method group adds nothing.
    "camera_motion": Registered(
        "mrcert.core.methods.camera_motion:CameraMotionSmoothing", MethodConfig, unkeyed=("method",)
    ),
    # Pixel noise: one model serves every axis.
    "pixelwise": Registered(
        "mrcert.core.methods.pixelwise:PixelwiseSmoothing", PixelwiseConfig, unkeyed_model=("motion",)
    ),
    # Deterministic: it certifies a model trained for another method (model.trained_for) or vanilla.
    "bound_propagation": Registered("mrcert.core.methods.bound_propagation:BoundPropagation", BoundPropagationConfig),
    # Deterministic and complete: every image of a translation interval enumerated.
    "enumeration": Registered("mrcert.core.methods.enumeration:ImageEnumeration", EnumerationConfig),
}

FORMER_NAMES = {"motion": "camera_motion"}
"""Names methods had in runs made by earlier versions (``method=motion``, beside the ``motion``
config group): a stored config is read with the current name (:func:`current_names`)."""


def current_names(data: dict) -> dict:
    """A stored config (plain data) with every former method name it holds (``method.name``,
    ``model.trained_for.name``) replaced by the current one."""
    for node in (data.get("method"), (data.get("model") or {}).get("trained_for")):
        if isinstance(node, dict) and node.get("name") in FORMER_NAMES:
            node["name"] = FORMER_NAMES[node["name"]]
    return data


def registered(name: str) -> Registered:
    """The method ``method.name`` names, or a one-line error listing those there are."""
    if name not in METHODS:
        raise ConfigError("method.name", name, f"one of {', '.join(METHODS)}")
    return METHODS[name]


def unkeyed(name: str | None, model: bool) -> tuple[str, ...]:
    """What method ``name``'s run keys leave out (a train run's: ``model``); nothing for an
    unknown name, which config validation refuses."""
    method = METHODS.get(str(name))
    if method is None:
        return ()
    return (*method.unkeyed, *method.unkeyed_model) if model else method.unkeyed


def build_method(cfg: DictConfig) -> Method:
    """The method ``cfg.method`` names, on ``cfg.motion``."""
    return registered(str(cfg.method.name)).load().from_config(cfg.method, cfg.motion)
