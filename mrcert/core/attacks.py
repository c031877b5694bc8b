"""The K-perturbed attacks (``attack=...``): which K motions on one axis the attack tries on a
test image. Each is named by ``_target_`` in ``conf/attack/<name>.yaml`` and built from that
node (its ``name``, ``k`` and ``radius``); a new attack is one class here and one YAML."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mrcert.core.axes import axis_index
from mrcert.core.sampling import image_generator


@dataclass(frozen=True)
class Attack:
    """K motions in [-radius, radius] on one axis."""

    name: str
    k: int
    radius: float

    def values(self, seed: int, index: int) -> torch.Tensor:
        """The K displacements (float64) tried on test image ``index`` of a run seeded ``seed``."""
        raise NotImplementedError

    def motions(self, axis: str, seed: int, index: int) -> torch.Tensor:
        """The K motions (K, 6) on ``axis`` tried on test image ``index``."""
        values = self.values(seed, index)
        motions = torch.zeros(len(values), 6, dtype=torch.float64)
        motions[:, axis_index(axis)] = values
        return motions


class Uniform(Attack):
    """K displacements drawn uniformly in [-r, r], from the image's own seeded generator."""

    def values(self, seed: int, index: int) -> torch.Tensor:
        g = image_generator(seed, index, "attack")
        return (torch.rand(int(self.k), generator=g, dtype=torch.float64) * 2 - 1) * float(self.radius)


class Grid(Attack):
    """K evenly spaced displacements from -r to r."""

    def values(self, seed: int, index: int) -> torch.Tensor:
        r = float(self.radius)
        return torch.linspace(-r, r, int(self.k), dtype=torch.float64)
