"""Camera motion smoothing (paper Section 3, Theorem 1, Corollary 1) with Cohen et al.'s
CERTIFY and PREDICT.

The smoothed classifier votes over the base classifier's predictions on the test sample's
scene re-rendered under random camera motions ``eps ~ N(0, diag(sigma^2))`` on the smoothed
components (one axis, or translations plus a rotation about one fixed axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from omegaconf import DictConfig
from scipy.stats import norm

from mrcert.core.axes import axis_index, is_translation, unit
from mrcert.core.crop import CropBound
from mrcert.core.geometry import compose
from mrcert.core.methods.base import Certificate, Render, single_axis
from mrcert.core.sampling import SmoothedClassifier, Smoothing
from mrcert.errors import ConfigError, MrcertError


@dataclass(frozen=True)
class CameraMotionSmoothing(Smoothing):
    """Camera motion smoothing (``method=camera_motion``): a zero-mean Gaussian over some motion
    components, one sigma each, that augments the training images and smooths the classifier."""

    axes: tuple[str, ...]
    sigmas: tuple[float, ...]
    """One sigma per axis, in the axis's unit (the config's ranges: the motion schema's checks)."""

    def __post_init__(self):
        if len(self.axes) != len(self.sigmas) or not self.axes:
            raise MrcertError(f"smoothing needs one sigma per axis, got axes {self.axes} and sigmas {self.sigmas}")
        for a in self.axes:
            axis_index(a)
        licensed(self.axes, self.sigmas)

    serves = frozenset({"train", "smooth", "attack", "sequential"})

    @property
    def noise_scales(self) -> tuple[float, ...]:
        return self.sigmas

    @classmethod
    def from_config(cls, method: DictConfig | None, motion: DictConfig) -> CameraMotionSmoothing:
        """``motion.axes`` + ``motion.sigmas`` (multi-axis), else ``motion.axis`` + ``motion.sigma``
        (``method=camera_motion`` has no parameters of its own)."""
        if motion.get("axes"):
            try:
                return cls(tuple(motion.axes), tuple(float(s) for s in motion.sigmas))
            except (MrcertError, ValueError) as exc:  # an axis, a sigma or a combination Theorem 1 does not license
                raise ConfigError("motion.axes", list(motion.axes), str(exc)) from None
        return cls((single_axis(motion),), (float(motion.sigma),))

    def region(self) -> str:
        """What a certified radius R means for this distribution."""
        if self.single:
            return f"|{self.axes[0]}| < R ({self.region_unit})"
        terms = " + ".join(f"({a}/{s:g})^2" for a, s in zip(self.axes, self.sigmas, strict=True))
        return (
            f"sqrt({terms}) < R (ellipsoid in sigma units, Theorem 1). Licensed because at most one axis "
            "rotates and the two translation axes that rotation mixes are smoothed with equal sigma or not at all, "
            "so the noise around a moved camera is the same Gaussian, shifted"
        )

    @property
    def view_unit(self) -> str:
        """The axis's unit (``m``, ``rad``); ``sigma`` for several axes (Theorem 1's ellipsoid)."""
        return unit(self.axes[0]) if self.single else "sigma"

    @property
    def region_unit(self) -> str:
        return self.view_unit  # the region is the one view's ball

    @property
    def sigma_unit(self) -> str:
        return "+".join(unit(a) for a in self.axes)

    def radius(self, p_a_lower: float) -> float:
        """Certified radius for a lower bound on the top class probability (pB = 1 - pA).

        One axis: ``sigma * Phi^-1(pA)`` in the axis's units (Corollary 1); several axes: the
        ellipsoid's radius ``Phi^-1(pA)`` in sigma units (Theorem 1 with pB = 1 - pA).
        """
        z = float(norm.ppf(p_a_lower))
        return self.sigmas[0] * z if self.single else z

    def largest_radius(self, n: int, alpha: float) -> float:
        """The radius of n votes out of n: Clopper-Pearson's lower bound is then alpha^(1/n)."""
        return self.radius(alpha ** (1.0 / n)) if n > 0 else 0.0

    def probability_for(self, radius: float) -> float:
        """The ``pA`` lower bound that :meth:`radius` turns into ``radius`` (inverse of it)."""
        return float(norm.cdf(radius / self.sigmas[0] if self.single else radius))

    def training_motions(self, n: int, seed: int) -> torch.Tensor:
        """Each axis's motions from its own NumPy stream ``(seed, 1000 + axis index)``."""
        motions = torch.zeros(n, 6, dtype=torch.float64)
        for a, s in zip(self.axes, self.sigmas, strict=True):
            rng = np.random.default_rng([seed, 1000 + axis_index(a)])
            motions[:, axis_index(a)] = torch.from_numpy(rng.normal(0.0, s, n))
        return motions

    def training_key(self, seed: int) -> dict:
        if self.single:  # the key single-axis augmentation has always had (its cached images stay valid)
            return {"axis": self.axes[0], "sigma": self.sigmas[0], "seed": seed}
        return {"axes": list(self.axes), "sigmas": list(self.sigmas), "seed": seed}

    def views(self, render: Render, n: int, generator: torch.Generator, center: torch.Tensor | None):
        """The view re-rendered under ``center o eps`` (Lemma 1): the camera moved by ``center``,
        then by the noise in its own frame. On the one smoothed axis this is ``center + eps`` exactly."""
        motions = self.sample(n, generator)
        if center is not None:
            center = center.to(torch.float64).reshape(1, 6)
            moved = set(torch.nonzero(center[0]).flatten().tolist())
            if self.single and moved <= {axis_index(self.axes[0])}:
                motions = motions + center  # along the one smoothed axis composition is addition, exactly
            else:
                motions = compose(center.expand(n, 6), motions)
        return render, motions

    def certify_smoothed(self, smoothed: SmoothedClassifier, render, n0, n, alpha, generator) -> Certificate:
        """Cohen's CERTIFY at the test pose: the radius is the motion's (:meth:`radius`)."""
        return smoothed.certify_view(render, n0, n, alpha, generator)

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """``n`` motions (n, 6) float64 drawn on CPU from ``generator``."""
        noise = torch.randn(n, len(self.axes), generator=generator, dtype=torch.float64)
        motions = torch.zeros(n, 6, dtype=torch.float64)
        for j, (a, s) in enumerate(zip(self.axes, self.sigmas, strict=True)):
            motions[:, axis_index(a)] = noise[:, j] * s
        return motions

    def crop_bound(self, sigmas: float) -> CropBound:
        """The exact-crop bound covering ``sigmas`` standard deviations on every smoothed axis."""
        return CropBound.covering({a: sigmas * s for a, s in zip(self.axes, self.sigmas, strict=True)})


ORTHOGONAL = {"rx": ("ty", "tz"), "ry": ("tx", "tz"), "rz": ("tx", "ty")}
"""The two translation axes a rotation about each axis mixes."""


def licensed(axes: tuple[str, ...], sigmas: tuple[float, ...]) -> None:
    """Raise unless Theorem 1 licenses smoothing over ``axes`` with ``sigmas``.

    Around a moved camera the smoothing draws ``alpha o eps = (R_a R_e, R_a t_e + t_a)``
    (Lemma 1): the translation noise is *rotated* by the certified motion's rotation. The
    Gaussian in parameter space is then merely shifted by ``alpha`` -- what the certificate
    assumes -- only if the translation noise is invariant under rotations about the smoothed
    rotation axis k: the two translation axes orthogonal to k are both smoothed with equal
    sigma, or neither. At most one rotation axis; each axis once.
    """
    name = "+".join(axes)
    rotations = [a for a in axes if not is_translation(a)]
    if len(set(axes)) != len(axes) or len(rotations) > 1:
        raise MrcertError(
            f"smoothing over {name} is not licensed by Theorem 1: use each axis once and at most one rotation "
            "axis (translations plus a rotation about one fixed axis)"
        )
    if not rotations:
        return
    sigma = dict(zip(axes, sigmas, strict=True))
    pair = ORTHOGONAL[rotations[0]]
    smoothed = [a for a in pair if a in sigma]
    if not smoothed or (len(smoothed) == 2 and sigma[pair[0]] == sigma[pair[1]]):
        return
    given = ", ".join(f"sigma_{a[1]}={sigma[a]:g}" for a in smoothed)
    raise MrcertError(
        f"smoothing over {name} ({given}) is not licensed by Theorem 1: around a moved camera the translation "
        f"noise is rotated by the certified rotation about {rotations[0][1]}, so {pair[0]} and {pair[1]} must both "
        f"be smoothed with equal sigma, or neither (allowed e.g. {pair[0]}+{pair[1]}+{rotations[0]} with "
        f"sigma_{pair[0][1]} = sigma_{pair[1][1]}, or {rotations[0]} with translations along {rotations[0][1]} only)"
    )
