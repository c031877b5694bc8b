"""Base classifiers: any ``nn.Module`` named by ``model.net._target_``, behind a fixed normaliser.

Inputs are images in [0, 1] (what the projection renders); the first layer normalises them
with mean 0.5 and std 0.5 per channel (docs/method.md §2), so smoothing happens before
normalisation and every architecture sees the same inputs.
"""

from __future__ import annotations

import importlib
import typing
from collections.abc import Mapping
from typing import Any, ClassVar

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import nn

from mrcert.core.checks import POSITIVE_INT, Check
from mrcert.errors import ConfigError, MrcertError


class Normalize(nn.Module):
    """``(x - mean) / std`` per channel, with constant buffers."""

    def __init__(self, mean: float = 0.5, std: float = 0.5, channels: int = 3):
        super().__init__()
        self.register_buffer("mean", torch.full((1, channels, 1, 1), float(mean)))
        self.register_buffer("std", torch.full((1, channels, 1, 1), float(std)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class SmallCNN(nn.Module):
    """A small convolutional classifier that trains in minutes on a CPU (quick profile, tests)."""

    config_checks: ClassVar[dict[str, Check]] = {"width": POSITIVE_INT}
    """What its config's values must be (``model.net.width``), checked with the config (:func:`check_net`)."""

    def __init__(self, num_classes: int, width: int = 32):
        super().__init__()

        def block(cin: int, cout: int) -> list[nn.Module]:
            return [nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]

        self.features = nn.Sequential(
            *block(3, width),
            nn.MaxPool2d(2),
            *block(width, 2 * width),
            nn.MaxPool2d(2),
            *block(2 * width, 4 * width),
            nn.MaxPool2d(2),
            *block(4 * width, 4 * width),
            nn.AdaptiveAvgPool2d(1),
        )
        self.head = nn.Linear(4 * width, num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(torch.flatten(self.features(x), 1))


def predicted(logits: torch.Tensor) -> torch.Tensor:
    """The class of each row of ``logits`` (B, C); -1 (no class: never a vote, never correct)
    where a logit is NaN or infinite."""
    return torch.where(torch.isfinite(logits).all(1), logits.argmax(1), -1)


def class_margins(logits: torch.Tensor, c: int):
    """``y_c - max_{j != c} y_j`` per row of ``logits`` (B, C) as float64 NumPy; negative, strictly,
    wherever ``c`` is not the predicted class (a tie lost, a NaN or infinite logit)."""
    import numpy as np

    others = logits.clone()
    others[:, c] = -torch.inf
    margin = (logits[:, c] - others.max(1).values).double().numpy()
    wrong = np.minimum(np.nan_to_num(margin, nan=-np.inf), -np.finfo(np.float64).tiny)
    return np.where(predicted(logits).numpy() == c, margin, wrong)


def non_finite(tensors: dict[str, torch.Tensor]) -> list[str]:
    """The names of the floating-point tensors holding a NaN or an infinity."""
    return [k for k, v in tensors.items() if v.is_floating_point() and not torch.isfinite(v).all()]


def _importable(name: str) -> Any:
    """The object a dotted name refers to (its module imported, nothing called), or None."""
    parts = name.split(".")
    for cut in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for part in parts[cut:]:
                obj = getattr(obj, part)
        except AttributeError:
            return None
        return obj
    return None


def _made_by(target: Any) -> Any:
    """What calling ``target`` makes: the class itself, or a function's return annotation."""
    if isinstance(target, type):
        return target
    try:
        return typing.get_type_hints(target).get("return")
    except Exception:  # annotations that do not resolve: nothing is known
        return None


def _parameters(target: Any) -> dict[str, Any]:
    """The annotation of each parameter ``target`` takes (a class: its ``__init__``'s)."""
    try:
        return typing.get_type_hints(target.__init__ if isinstance(target, type) else target)
    except Exception:
        return {}


def check_net(node: Any, where: str = "model.net", wanted: type = nn.Module) -> None:
    """Refuse, before anything is called, a ``_target_`` that does not make a ``wanted`` (an
    ``nn.Module`` subclass, or a function annotated to return one, such as
    ``torchvision.models.resnet18``), and a nested ``_target_`` anywhere but as a parameter that
    the target itself declares to take such a module (checked the same way): a config builds the
    network it describes and calls nothing else. A class's ``config_checks`` check its values."""
    name = node.get("_target_") if isinstance(node, Mapping) else None
    target = _importable(str(name))
    if target is None:
        raise ConfigError(f"{where}._target_", name, "an importable class or function")
    made = _made_by(target)
    if not (isinstance(made, type) and issubclass(made, wanted)):
        kind = "an nn.Module subclass" if wanted is nn.Module else f"a {wanted.__module__}.{wanted.__qualname__}"
        raise ConfigError(f"{where}._target_", name, f"{kind}, or a function annotated to return one")
    takes = _parameters(target)
    for key, value in node.items():
        inner = value if isinstance(value, Mapping) else {}
        nested = "_target_" in inner or (isinstance(value, (list, tuple)) and _has_target(value))
        if not nested:
            continue
        module = takes.get(str(key))
        if not (isinstance(value, Mapping) and isinstance(module, type) and issubclass(module, nn.Module)):
            raise ConfigError(
                f"{where}.{key}._target_", _target_of(value), f"none: {name} does not take a module as {key}"
            )
        check_net(value, f"{where}.{key}", module)
    for key, check in getattr(made, "config_checks", {}).items():
        if key in node:
            check(f"{where}.{key}", node[key])


def _has_target(value: Any) -> bool:
    if isinstance(value, Mapping):
        return "_target_" in value or any(_has_target(v) for v in value.values())
    return isinstance(value, (list, tuple)) and any(_has_target(v) for v in value)


def _target_of(value: Any) -> Any:
    if isinstance(value, Mapping):
        return value.get("_target_")
    return next((_target_of(v) for v in value if _has_target(v)), None)


def build_model(model: DictConfig, num_classes: int) -> nn.Sequential:
    """``Normalize`` followed by ``model.net`` instantiated with ``num_classes`` (its targets
    checked first: :func:`check_net`)."""
    check_net(model.net)
    try:
        net = instantiate(model.net, num_classes=num_classes)
    except Exception as exc:  # a user's _target_ that does not import or does not take num_classes
        raise MrcertError(f"cannot build model.net ({model.net.get('_target_')}): {exc}") from None
    if not isinstance(net, nn.Module):
        raise MrcertError(f"model.net._target_={model.net.get('_target_')!r} did not give an nn.Module")
    return nn.Sequential(Normalize(), net)


def for_inference(model: nn.Module, device: torch.device | str) -> nn.Module:
    """``model`` in eval mode on ``device`` with channels-last weights: on 2 CPU cores 1.4x
    (ResNet-18) to 1.6x (small CNN) faster on 160x90 batches (docs/performance.md), and the
    predictions are those of the same function (only the order of float accumulation changes;
    no reduced precision)."""
    return model.to(device, memory_format=torch.channels_last).eval()
