"""Camera motion smoothing (paper Section 3, Theorem 1, Corollary 1) with Cohen et al.'s
CERTIFY and PREDICT.

The smoothed classifier votes over the base classifier's predictions on the test sample's
scene re-rendered under random camera motions ``eps ~ N(0, diag(sigma^2))`` on the smoothed
components (one axis, or translations plus a rotation about one fixed axis).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import torch
from omegaconf import DictConfig
from scipy.stats import binomtest, norm

from mrcert.core.crop import CropBound
from mrcert.core.geometry import axis_index, compose, is_translation, unit
from mrcert.core.method import ABSTAIN, Certificate, Method, Render, single_axis
from mrcert.core.models import predicted
from mrcert.core.sequential import SequentialDesign, lower_confidence_bound
from mrcert.errors import ConfigError, MrcertError

DECISIONS = ("predict", "vote")
"""How a smoothed prediction is decided from its votes (:meth:`SmoothedClassifier.decide`)."""


@dataclass(frozen=True)
class CameraMotionSmoothing(Method):
    """Camera motion smoothing (``method=camera_motion``): a zero-mean Gaussian over some motion
    components, one sigma each, that augments the training images and smooths the classifier."""

    axes: tuple[str, ...]
    sigmas: tuple[float, ...]

    def __post_init__(self):
        if len(self.axes) != len(self.sigmas) or not self.axes:
            raise MrcertError(f"smoothing needs one sigma per axis, got axes {self.axes} and sigmas {self.sigmas}")
        for a, s in zip(self.axes, self.sigmas, strict=True):
            axis_index(a)
            if not s > 0:
                raise MrcertError(f"smoothing sigma for {a} must be > 0, got {s}")
        licensed(self.axes, self.sigmas)

    sequential = True

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

    def certify(self, smoothed, render, n0, n, alpha, generator) -> Certificate:
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
        box = [0.0, 0.0, 0.0]
        rotation, axis = 0.0, None
        for a, s in zip(self.axes, self.sigmas, strict=True):
            if is_translation(a):
                box[axis_index(a)] = sigmas * s
            else:
                rotation, axis = sigmas * s, a
        return CropBound(tuple(box), rotation, roll_only=axis in (None, "rz"))


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


def image_generator(seed: int, index: int, *stream) -> torch.Generator:
    """The generator for test image ``index`` (and an optional sub-stream such as an attack
    motion): a function of these values only, so results do not depend on batch size, device
    or sharding."""
    digest = hashlib.sha256("/".join(map(str, ("mrcert", seed, index, *stream))).encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 63) - 1))


class VoteCounter:
    """The base classifier's votes over the images of a :data:`Render`, in batches.

    The model classifies ``batch_size`` images at once; the render draws ``render_batch`` at
    once (a multiple of ``batch_size``, default ``batch_size``), since each call to a render
    costs a fixed amount besides its images (:func:`~mrcert.infra.runtime.render_batch`).
    With ``overlap``, a worker thread renders the next ``render_batch`` inputs while the model
    classifies the current ones (the projection kernel and torch both release the GIL).
    ``timings`` adds up the seconds spent waiting for renders and in the model (for benchmarks).
    The votes do not depend on either size: each image is its input's, whatever it is drawn with.
    """

    def __init__(
        self,
        base: torch.nn.Module,
        num_classes: int,
        batch_size: int = 200,
        device="cpu",
        overlap=False,
        render_batch: int | None = None,
    ):
        render_batch = batch_size if render_batch is None else render_batch
        if render_batch < batch_size or render_batch % batch_size:
            raise ValueError(f"render_batch={render_batch} must be a multiple of batch_size={batch_size}")
        self.base, self.num_classes, self.batch_size, self.render_batch = base, num_classes, batch_size, render_batch
        self.device, self.overlap = device, overlap
        self.timings = {"render": 0.0, "model": 0.0}

    @torch.inference_mode()
    def __call__(self, render: Callable[[torch.Tensor], torch.Tensor], inputs: torch.Tensor) -> np.ndarray:
        """Votes over ``render(inputs)``, in batches (``inputs``: motions, or sample indices)."""
        parts = [inputs[s : s + self.render_batch] for s in range(0, len(inputs), self.render_batch)]
        votes = np.zeros(self.num_classes, np.int64)
        with ThreadPoolExecutor(max_workers=1) if self.overlap else nullcontext() as pool:
            pending = pool.submit(render, parts[0]) if pool and parts else None
            for k, part in enumerate(parts):
                start = time.perf_counter()
                if pool:
                    images = pending.result()
                    if k + 1 < len(parts):
                        pending = pool.submit(render, parts[k + 1])
                else:
                    images = render(part)
                rendered = time.perf_counter()
                for s in range(0, len(images), self.batch_size):
                    batch = images[s : s + self.batch_size].to(self.device, non_blocking=True)
                    classes = predicted(self.base(batch)).cpu().numpy()
                    votes += np.bincount(classes[classes >= 0], minlength=self.num_classes)
                self.timings["render"] += rendered - start
                self.timings["model"] += time.perf_counter() - rendered
        return votes


class SmoothedClassifier:
    """g(x) = argmax_c P(h(O(V, a o eps)) = c), eps ~ the smoothing distribution (for camera
    motion smoothing; another :class:`~mrcert.core.method.Method` draws other noisy views).

    Built once from the base classifier ``h``, the method and the number of classes;
    :meth:`certify` and :meth:`predict` take the input: a :data:`Render` of the test sample's
    scene ``V``, and ``a`` is the motion it is looked at from (zero for the test pose).
    Guarantee (Cohen et al. 2019; Theorem 1 of the paper, for the combinations
    :func:`licensed` admits): if :meth:`certify` returns class ``c`` with radius ``R``, then with
    probability at least ``1 - alpha`` over its sampling, ``g(phi(x, delta)) = c`` for every
    camera motion ``delta`` on the smoothed components inside the region of
    :meth:`CameraMotionSmoothing.region` (``|delta| < R`` on one axis). :meth:`predict` returns
    ``g(x)`` or :data:`ABSTAIN`, and is wrong with probability at most ``alpha``.
    """

    def __init__(
        self,
        base: torch.nn.Module,
        method: Method,
        num_classes: int,
        batch_size: int = 200,
        device: torch.device | str = "cpu",
        overlap: bool = False,
        render_batch: int | None = None,
    ):
        self.method = method
        self.votes = VoteCounter(base, num_classes, batch_size, device, overlap, render_batch)

    def sample_counts(
        self, render: Render, n: int, generator: torch.Generator, center: torch.Tensor | None = None
    ) -> np.ndarray:
        """Votes over the method's ``n`` noisy views after the camera motion ``center``."""
        return self.votes(*self.method.views(render, n, generator, center))

    def predict(
        self,
        render: Render,
        n: int,
        alpha: float,
        generator: torch.Generator,
        center: torch.Tensor | None = None,
        rule: str = "predict",
    ) -> int:
        """The smoothed prediction at the pose moved by ``center`` (default: the test pose itself),
        by ``rule`` (:meth:`decide`)."""
        return self.decide(self.sample_counts(render, n, generator, center), alpha, rule)

    @staticmethod
    def decide(counts: np.ndarray, alpha: float, rule: str = "predict") -> int:
        """``predict`` (Cohen's PREDICT): the top class, or ABSTAIN unless the two-sided binomial
        test of the top two counts rejects equality at level ``alpha``. ``vote`` (the paper's
        robot experiment): the most frequent class, ties to the lowest class index; it never
        abstains and carries no guarantee (``alpha`` unused)."""
        if rule == "vote":
            return int(np.argmax(counts))
        if rule != "predict":
            raise ValueError(f"decision rule {rule!r} is not one of {DECISIONS}")
        top2 = np.argsort(counts, kind="stable")[::-1][:2]
        n_a, n_b = int(counts[top2[0]]), int(counts[top2[1]])
        if n_a + n_b == 0 or binomtest(n_a, n_a + n_b, 0.5).pvalue > alpha:
            return ABSTAIN
        return int(top2[0])

    def certify(self, render: Render, n0: int, n: int, alpha: float, generator: torch.Generator) -> Certificate:
        """The method's CERTIFY of the test sample (for motion smoothing :meth:`certify_view`)."""
        return self.method.certify(self, render, n0, n, alpha, generator)

    def certify_view(
        self, render: Render, n0: int, n: int, alpha: float, generator: torch.Generator, center=None
    ) -> Certificate:
        """Cohen's CERTIFY of the view after the camera motion ``center``: select the top class
        on ``n0`` samples, estimate its probability on ``n`` fresh samples, and certify
        ``method.radius(pA_lower)`` when ``pA_lower >= 1/2``."""
        selection = self.sample_counts(render, n0, generator, center)
        c_a = int(np.argmax(selection))
        count_a = int(self.sample_counts(render, n, generator, center)[c_a])
        p_a = lower_confidence_bound(count_a, n, alpha)
        return self._certificate(c_a, count_a, n, p_a)

    def _certificate(self, c_a: int, count_a: int, n: int, p_a: float) -> Certificate:
        view_unit = self.method.view_unit
        if p_a < 0.5:
            return Certificate(ABSTAIN, 0.0, count_a, p_a, n, view_unit)
        return Certificate(c_a, self.method.radius(p_a), count_a, p_a, n, view_unit)

    def certify_sequential(
        self, render: Render, n0: int, n: int, alpha: float, radius: float, first_look: int, generator: torch.Generator
    ) -> Certificate:
        """CERTIFY with early stopping, for a requested ``radius``, never less powerful than
        :meth:`certify` with ``n`` samples.

        After ``n0`` selection samples, estimation samples are drawn up to the looks of the
        :class:`~mrcert.core.sequential.SequentialDesign` planned for ``n``, ``alpha`` and the
        probability the radius needs (looks at ``first_look``, doubling, and a last look at
        ``n_max >= n``); it stops at the first look whose count certifies ``radius`` or shows
        that it cannot be reached, and reports ``radius(pA_lower)`` with that look's bound.
        With probability at least ``1 - alpha`` every look's bound holds, so the certificate
        is valid at the data-dependent stop. Looks are fixed in number of samples, so the
        result does not depend on the batch size.
        """
        need = max(self.method.probability_for(radius), 0.5)
        design = SequentialDesign.plan(n, alpha, need, first_look)
        c_a = int(np.argmax(self.sample_counts(render, n0, generator)))
        count_a, drawn = 0, 0
        for k, look in enumerate(design.looks):
            count_a += int(self.sample_counts(render, look - drawn, generator)[c_a])
            drawn = look
            stop, p_a = design.decide(count_a, k)
            if stop:
                break
        return self._certificate(c_a, count_a, drawn, p_a)
