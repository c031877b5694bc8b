"""Pixel-wise smoothing (PwS; Hu et al., AISTATS 2024): certify every camera pose of a one-axis
interval ``[-a, a]`` by smoothing in pixel space at finitely many frames.

The interval is cut into ``K - 1`` pieces by ``K`` evenly spaced frames ``alpha_k``; each frame
is rendered (``x_k = O(V, alpha_k)``) and certified with Gaussian pixel noise of standard
deviation ``sigma`` (Cohen et al.: ``g(x') = c`` for every image ``x'`` with
``||x' - x_k||_2 < R_k = sigma Phi^-1(pA_k)``). For every piece, :func:`piece_bounds` bounds the
l2 distance between the image at *any* pose of the piece and each of its two end frames. The
interval is certified when every frame certifies the same class and, in every piece, one end
frame's radius exceeds that end's bound: every pose's image then lies inside a certified ball.
Why the bound covers every pose, occlusion changes included: docs/method.md §8.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from omegaconf import DictConfig
from scipy.stats import norm

from mrcert.core.axes import axis_index, unit
from mrcert.core.methods.base import ABSTAIN, Certificate, SceneRender, WholeInterval
from mrcert.core.sampling import SmoothedClassifier, Smoothing, image_generator
from mrcert.core.sequential import lower_confidence_bound
from mrcert.core.verification.image_bounds import piece_bounds
from mrcert.errors import MrcertError

NOISE_BLOCK = 16
"""Pixel-noise draws come in blocks of this many images, each block from its own seeded
generator, so that the noise of sample ``j`` does not depend on the batch it is classified in."""


@dataclass(frozen=True)
class PixelNoise:
    """Gaussian noise ``N(0, sigma^2 I)`` added to an image in [0, 1] (``sigma`` in those units)."""

    sigma: float

    def __post_init__(self):
        if not self.sigma > 0:
            raise ValueError(f"pixel noise sigma must be > 0, got {self.sigma}")

    def around(self, image: torch.Tensor, seed: int):
        """Sample indices (B,) -> noisy copies (B, C, H, W) of ``image`` (C, H, W); the noise of
        index ``j`` is a function of ``seed`` and ``j`` only."""

        def render(indices: torch.Tensor) -> torch.Tensor:
            idx = torch.as_tensor(indices).long().flatten()
            if not len(idx):
                return image.new_empty((0, *image.shape))
            first, last = int(idx.min()) // NOISE_BLOCK, int(idx.max()) // NOISE_BLOCK
            noise = torch.cat([self._block(seed, b, image.shape) for b in range(first, last + 1)])
            return image + self.sigma * noise[idx - first * NOISE_BLOCK].to(image.device, image.dtype)

        return render

    def perturb(self, images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Training: ``images`` plus fresh noise from ``generator`` (drawn on CPU)."""
        noise = torch.randn(images.shape, generator=generator, dtype=torch.float32)
        return images + self.sigma * noise.to(images.device, images.dtype)

    @staticmethod
    def _block(seed: int, block: int, shape) -> torch.Tensor:
        g = image_generator(seed, block, "pixel noise")
        return torch.randn((NOISE_BLOCK, *shape), generator=g, dtype=torch.float32)


def frame_motions(axis: str, half_width: float, count: int) -> torch.Tensor:
    """``count`` motions (count, 6) evenly spaced on ``axis`` from ``-half_width`` to ``half_width``."""
    if count < 2:
        raise ValueError(f"pixel-wise smoothing needs at least 2 frames, got {count}")
    if not half_width > 0:
        raise ValueError(f"the certified interval's half-width must be > 0, got {half_width}")
    motions = torch.zeros(count, 6, dtype=torch.float64)
    motions[:, axis_index(axis)] = torch.linspace(-half_width, half_width, count, dtype=torch.float64)
    return motions


def interval_certified(classes: np.ndarray, radii: np.ndarray, left: np.ndarray, right: np.ndarray) -> bool:
    """Whether the frames' certificates cover the whole interval: one class at every frame (no
    abstention) and, in every piece, an end frame whose certified radius exceeds its bound."""
    return len(classes) == len(left) + 1 and interval_coverable(classes, radii, left, right, 0.0)


def interval_coverable(classes, radii, left: np.ndarray, right: np.ndarray, reach: float) -> bool:
    """Whether the interval can still be certified once its first ``len(classes)`` frames are:
    they agree on one class (no abstention) and every piece has an end whose radius exceeds its
    bound, a frame not yet certified counting as ``reach``, the largest radius one can get."""
    classes = np.asarray(classes)
    if len(classes) and ((classes < 0).any() or (classes != classes[0]).any()):
        return False
    return piece_margin(radii, left, right, reach) > 0


def piece_margin(radii, left: np.ndarray, right: np.ndarray, reach: float) -> float:
    """The smallest, over pieces, of the better end's radius less its bound (positive: every
    piece covered), the frames after the ``len(radii)`` certified ones counting as ``reach``."""
    radii = np.concatenate([np.asarray(radii, np.float64), np.full(len(left) + 1 - len(radii), reach)])
    return float(np.min(np.maximum(radii[:-1] - left, radii[1:] - right)))


@dataclass(frozen=True)
class PixelwiseSmoothing(WholeInterval, Smoothing):
    """Pixel-wise smoothing (``method=pixelwise``): Gaussian pixel noise of ``sigma`` trains the
    augmented model and smooths it at ``frames`` frames of ``[-half_width, half_width]`` on
    ``axis``; a test sample is certified for the whole interval or not at all (its radius is
    ``half_width`` or 0). Frames are certified at ``alpha / frames`` each (Bonferroni), so all
    of them hold together with probability at least ``1 - alpha``."""

    axis: str
    sigma: float
    half_width: float
    frames: int

    @classmethod
    def from_config(cls, method: DictConfig, motion: DictConfig) -> PixelwiseSmoothing:
        return cls(
            cls.interval_axis(motion, "pixelwise"),
            float(method.sigma),
            float(method.certify.half_width),
            method.certify.frames,
        )

    @property
    def noise_scales(self) -> tuple[float, ...]:
        return (self.sigma,)

    @property
    def noise(self) -> PixelNoise:
        return PixelNoise(self.sigma)

    def perturb(self, images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return self.noise.perturb(images, generator)

    def views(self, render, n: int, generator: torch.Generator, center: torch.Tensor | None):
        """The view rendered once at ``center`` (the test pose when None), plus pixel noise."""
        pose = torch.zeros(1, 6, dtype=torch.float64) if center is None else center.to(torch.float64).reshape(1, 6)
        seed = int(torch.randint(0, 1 << 62, (1,), generator=generator))
        return self.noise.around(render(pose)[0], seed), torch.arange(n)

    def radius(self, p_a_lower: float) -> float:
        return self.sigma * float(norm.ppf(p_a_lower))

    def probability_for(self, radius: float) -> float:
        """The ``pA`` lower bound a frame needs for an image radius ``radius`` (intensity)."""
        return float(norm.cdf(radius / self.sigma))

    @property
    def view_unit(self) -> str:
        """A frame's radius: the l2 norm of a change of the [0, 1] image."""
        return "intensity"

    @property
    def sigma_unit(self) -> str:
        return "intensity"

    def region(self) -> str:
        return (
            f"the whole interval |{self.axis}| <= {self.half_width:g} {unit(self.axis)} when R > 0 (pixel-wise "
            f"smoothing, {self.frames} frames, pixel sigma {self.sigma:g}); R is {self.half_width:g} or 0"
        )

    def reach(self, n: int, alpha: float) -> float:
        """The largest radius a frame can be certified for: all ``n`` votes for one class, at
        ``alpha / frames``. A piece whose bounds both reach it can never be covered."""
        return self.radius(lower_confidence_bound(n, n, alpha / self.frames))

    def certify_smoothed(
        self, smoothed: SmoothedClassifier, render, n0: int, n: int, alpha: float, generator: torch.Generator
    ) -> Certificate:
        """The frames certified in order at ``alpha / frames`` each, stopping at the first after
        which the interval can no longer be certified (:func:`interval_coverable`: the bounds are
        computed first, so an interval no frame's radius can cover stops after its first frame);
        the interval when every frame is certified and :func:`interval_certified`. Stopping early
        only leaves tests out, so all the frames certified hold together with probability at
        least ``1 - alpha``; ``n`` counts the estimation samples of the frames certified."""
        if not isinstance(render, SceneRender):
            raise MrcertError("pixel-wise certification needs a renderer that shows its scene (TestSample.renderer())")
        frames = frame_motions(self.axis, self.half_width, self.frames)
        images = render(frames)  # each frame projected once, for its votes and for the bounds
        points, colors, rank = render.cloud_for(frames)
        left, right = piece_bounds(points, colors, render.K, self.axis, frames, images, render.background, rank=rank)
        reach = self.reach(n, alpha)
        certs: list[Certificate] = []
        for k, f in enumerate(frames):
            view = lambda _frame, k=k: images[k : k + 1]  # noqa: E731
            certs.append(smoothed.certify_view(view, n0, n, alpha / self.frames, generator, f))
            classes, radii = [c.prediction for c in certs], [c.radius for c in certs]
            if not interval_coverable(classes, radii, left, right, reach):
                break
        agreed = min(classes) >= 0 and len(set(classes)) == 1
        worst = min(certs, key=lambda c: c.p_a_lower)
        return Certificate(
            classes[0] if agreed else ABSTAIN,
            self.half_width if interval_certified(classes, radii, left, right) else 0.0,
            worst.count_a,
            worst.p_a_lower,
            n * len(certs),
            self.region_unit,
            piece_margin(radii, left, right, reach),
            n0=n0,  # per frame estimated, as its n
        )
