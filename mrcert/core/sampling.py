"""The sampling engine the smoothing methods share: the base classifier's votes over a
method's noisy views, Cohen et al.'s CERTIFY and PREDICT with their explicit ABSTAIN, and the
seeded generators every draw comes from.

:class:`Smoothing` is the part of the plug point (:class:`~mrcert.core.methods.base.Method`) that a
smoothing method fills in -- its noisy views, the radius of one view's certificate, and its
certification procedure on a :class:`SmoothedClassifier`; its certifier is that smoothed
classifier.
"""

from __future__ import annotations

import hashlib
import time
from abc import abstractmethod
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from typing import ClassVar

import numpy as np
import torch
from scipy.stats import binomtest

from mrcert.core.methods.base import ABSTAIN, BaseClassifier, Certificate, CertifyRequest, Method, Render
from mrcert.core.models import predicted
from mrcert.core.sequential import PredictDesign, SequentialDesign, lower_confidence_bound

DECISIONS = ("predict", "vote")
"""How a smoothed prediction is decided from its votes (:meth:`SmoothedClassifier.decide`)."""


class Smoothing(Method):
    """A smoothing method: a classifier smoothed over the method's noise, certified and asked
    for predictions by :class:`SmoothedClassifier`."""

    serves: ClassVar[frozenset[str]] = frozenset({"train", "smooth", "attack"})

    @abstractmethod
    def views(self, render: Render, n: int, generator: torch.Generator, center: torch.Tensor | None):
        """The ``n`` noisy samples of the view seen after the camera motion ``center`` (None: the
        test pose): ``(render_batch, inputs)``, where ``render_batch(inputs[s:e])`` gives the
        images of samples ``s..e-1`` whatever the batches."""

    @abstractmethod
    def radius(self, p_a_lower: float) -> float:
        """The radius of Cohen's certificate at one view for a lower bound on ``pA``, in the
        units of the method's noise (:attr:`view_unit`)."""

    @abstractmethod
    def probability_for(self, radius: float) -> float:
        """The ``pA`` lower bound that :meth:`radius` turns into ``radius`` (its inverse)."""

    @property
    @abstractmethod
    def view_unit(self) -> str:
        """The unit of :meth:`radius`: Cohen's radius at one view, in the noise's space."""

    @abstractmethod
    def certify_smoothed(
        self, smoothed: SmoothedClassifier, render: Render, n0: int, n: int, alpha: float, generator: torch.Generator
    ) -> Certificate:
        """CERTIFY one test sample with ``smoothed``; the radius is in :attr:`region_unit`."""

    def certifier(self, base: BaseClassifier) -> SmoothedClassifier:
        return SmoothedClassifier(
            base.model, self, base.num_classes, base.batch_size, base.device, base.overlap, base.render_batch
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
    motion smoothing; another :class:`Smoothing` draws other noisy views).

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
        method: Smoothing,
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

    def predict_sequential(
        self,
        render: Render,
        n: int,
        alpha: float,
        first_look: int,
        generator: torch.Generator,
        center: torch.Tensor | None = None,
    ) -> tuple[int, np.ndarray]:
        """Cohen's PREDICT with early stopping (:class:`~mrcert.core.sequential.PredictDesign`
        planned for ``n``, ``alpha`` and looks from ``first_look``): the smoothed prediction or
        ABSTAIN, wrong with probability at most ``alpha`` as :meth:`predict` is, and the votes
        it drew (their sum: the samples). Looks are fixed in samples, so the result does not
        depend on the batch size."""
        design = PredictDesign.plan(n, alpha, first_look)
        counts, drawn = None, 0
        for k, look in enumerate(design.looks):
            votes = self.sample_counts(render, look - drawn, generator, center)
            counts = votes if counts is None else counts + votes
            drawn = look
            decided = design.decide(counts, k)
            if decided is not None:
                return decided, counts
        raise AssertionError("the last look always decides")

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
        return self.method.certify_smoothed(self, render, n0, n, alpha, generator)

    def certify_sample(self, render: Render, request: CertifyRequest, generator: torch.Generator) -> Certificate:
        """What ``task=certify`` asks: :meth:`certify`, or with ``request.sequential``
        :meth:`certify_sequential` at ``request.radius``."""
        if request.sequential:
            return self.certify_sequential(
                render, request.n0, request.n, request.alpha, request.radius, request.look, generator
            )
        return self.certify(render, request.n0, request.n, request.alpha, generator)

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
        return self._certificate(c_a, count_a, n, p_a, n0)

    def _certificate(self, c_a: int, count_a: int, n: int, p_a: float, n0: int = 0) -> Certificate:
        view_unit = self.method.view_unit
        if p_a < 0.5:
            return Certificate(ABSTAIN, 0.0, count_a, p_a, n, view_unit, n0=n0)
        return Certificate(c_a, self.method.radius(p_a), count_a, p_a, n, view_unit, n0=n0)

    def certify_sequential(
        self, render: Render, n0: int, n: int, alpha: float, radius: float, first_look: int, generator: torch.Generator
    ) -> Certificate:
        """CERTIFY with early stopping, for a requested ``radius``, never less powerful than
        :meth:`certify` with ``n0`` and ``n`` samples, and with no separate class guess.

        Samples are drawn up to the looks of the
        :class:`~mrcert.core.sequential.SequentialDesign` planned for ``n0``, ``n``, ``alpha``
        and the probability the radius needs (looks at ``first_look``, doubling, and a last look
        at ``n_max >= n``); at each look the class with the most votes is certified once its
        count certifies ``radius``, and the search stops there, or when no class can reach
        ``radius`` (then ABSTAIN, radius 0). With probability at least ``1 - alpha`` the
        reported ``pA_lower`` holds for the class certified, so the certificate is valid at
        the data-dependent stop. The samples are the ones :meth:`certify` estimates with
        (its ``n0`` selection samples are drawn from the generator first, and not classified),
        so the two procedures are compared on the same samples of every image; the looks are
        fixed in number of samples, so the result does not depend on the batch size.
        """
        need = max(self.method.probability_for(radius), 0.5)
        design = SequentialDesign.plan(n0, n, alpha, need, first_look)
        self.method.views(render, n0, generator, None)  # fixed-n CERTIFY's selection samples
        segments = [self.method.views(render, n, generator, None)]
        if design.n_max > n:
            segments.append(self.method.views(render, design.n_max - n, generator, None))
        counts, drawn = np.zeros(self.votes.num_classes, np.int64), 0
        for k, look in enumerate(design.looks):
            counts += self._votes_between(segments, n, drawn, look)
            drawn = look
            stop, certified, p_a = design.decide(counts, k)
            if stop:
                break
        if certified is None:  # no claim, even where the bound is above 1/2
            return Certificate(ABSTAIN, 0.0, int(counts.max()), p_a, drawn, self.method.view_unit)
        return self._certificate(certified, int(counts[certified]), drawn, p_a)

    def _votes_between(self, segments: list, n: int, start: int, end: int) -> np.ndarray:
        """Votes over samples ``start..end-1`` of the stream: the first ``n`` from the first
        segment's views, the rest from the second's."""
        votes = np.zeros(self.votes.num_classes, np.int64)
        for (render_batch, inputs), offset in zip(segments, (0, n), strict=False):
            lo, hi = max(start - offset, 0), min(end - offset, len(inputs))
            if lo < hi:
                votes += self.votes(render_batch, inputs[lo:hi])
        return votes
