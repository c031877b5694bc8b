"""Base classifiers: any ``nn.Module`` named by ``model.net._target_``, behind a fixed normaliser.

Inputs are images in [0, 1] (what the projection renders); the first layer normalises them
with mean 0.5 and std 0.5 per channel (docs/method.md §2), so smoothing happens before
normalisation and every architecture sees the same inputs.
"""

from __future__ import annotations

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import nn

from mrcert.errors import MrcertError


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


def build_model(model: DictConfig, num_classes: int) -> nn.Sequential:
    """``Normalize`` followed by ``model.net`` instantiated with ``num_classes``."""
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
