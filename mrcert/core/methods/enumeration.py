"""Exact certification of a pose interval by enumerating the images it renders (``method=enumeration``).

Along a translation a z-buffered point cloud renders finitely many images over an interval
``[-a, a]`` (:mod:`mrcert.core.verification.events`: every pose at which a point's pixel
changes, located in the renderer's own float64 arithmetic). The classifier's answer on the
interval is therefore decided by those images alone, and this method decides it completely:

* the image at the test pose gives the class ``c``; a few images spread over the interval are
  classified first (a falsifying pose is usually found there);
* a run of consecutive images gets its exact hull -- per pixel and channel, the least and the
  greatest value the run's images take -- and bound propagation
  (:class:`~mrcert.core.verification.network.BoundNetwork`) proves ``y_c > y_j`` over the hull,
  hence over every image of the run; a run it does not prove is halved;
* a run of at most ``run_images`` images is classified image by image, in batches; an image whose
  margin is within float rounding of 0 is classified again on its own; where rounding may hand a
  pixel to a point of near-equal depth (tz), the image's hull (which holds those colours) is
  bounded, and where that fails every image the records allow is classified too.

Outcomes: **verified** (every image of the interval is classified ``c``: the radius is ``a``),
**falsified** (an image classified otherwise, with the first float pose that renders it logged
as the counterexample, checked by rendering and classifying that pose alone), **unknown** only
when the budget (``max_bounds`` runs bounded) is spent or an image rounding may render is
classified otherwise (or there are more than :data:`VARIANTS` of one image).

Guarantee: verified means ``h(O(V, alpha)) = c`` for every float64 ``|alpha| <= a`` on the axis,
where ``h`` is the base classifier as it classifies one image (the hulls' bounds hold for it in
exact arithmetic, the classified images are its own float32 answers); nothing is assumed about
a distribution. Translations only (``tx``, ``ty``, ``tz``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from omegaconf import DictConfig

from mrcert.core.axes import axis_index, unit
from mrcert.core.methods.base import (
    BaseClassifier,
    Certificate,
    CertifyRequest,
    Method,
    SceneRender,
    WholeInterval,
)
from mrcert.core.models import class_margins, predicted
from mrcert.core.verification.events import TRANSLATIONS, Enumeration, enumerate_images
from mrcert.core.verification.network import BoundNetwork
from mrcert.errors import ConfigError, MrcertError

SPREAD = 33
"""Images spread evenly over the interval, classified before any run is bounded."""

VARIANTS = 64
"""The most images rounding may render beside an enumerated one that are classified (then: unknown)."""

ROUNDING = 1e-4
"""A batched margin below this (relative to the logits' scale) is checked on the image alone."""


@dataclass(frozen=True)
class ImageEnumeration(WholeInterval, Method):
    """The method (module docstring); its certifier is :class:`EnumerationVerifier`."""

    axis: str
    half_width: float
    relaxation: str = "interval"
    run_images: int = 512
    max_bounds: int = 4096
    batch: int = 256
    crown_neurons: int = 2048

    log_columns: ClassVar[tuple[str, ...]] = (
        "outcome", "events", "images", "classified", "runs_bounded", "counterexample",
    )  # fmt: skip

    def __post_init__(self):
        super().__post_init__()
        if self.axis not in TRANSLATIONS:
            allowed = f"a translation ({', '.join(TRANSLATIONS)}) for method=enumeration"
            raise ConfigError("motion.axis", self.axis, allowed)

    @classmethod
    def from_config(cls, method: DictConfig, motion: DictConfig) -> ImageEnumeration:
        return cls(
            cls.interval_axis(motion, "enumeration"), float(method.half_width), str(method.relaxation),
            int(method.run_images), int(method.max_bounds), int(method.batch), int(method.crown_neurons),
        )  # fmt: skip

    @property
    def noise_scales(self) -> tuple[float, ...]:
        return ()

    def region(self) -> str:
        return (
            f"every pose |{self.axis}| <= {self.half_width:g} {unit(self.axis)} when R > 0, for the base classifier "
            f"itself and with certainty (every image of the interval enumerated); R is {self.half_width:g} or 0"
        )

    def certifier(self, base: BaseClassifier) -> EnumerationVerifier:
        return EnumerationVerifier(self, base)


class EnumerationVerifier:
    """:class:`ImageEnumeration` bound to a base classifier: its graph read once for bounds."""

    def __init__(self, method: ImageEnumeration, base: BaseClassifier):
        self.method, self.base = method, base
        self.network = BoundNetwork(base.model, method.crown_neurons)

    def certify_sample(self, render, request: CertifyRequest, generator: torch.Generator) -> Certificate:
        """Verify or falsify one test sample (module docstring); draws nothing."""
        if not isinstance(render, SceneRender):
            raise MrcertError("enumeration needs a renderer that shows its scene (TestSample.renderer())")
        return _Run(self, render).result()


class _Run:
    """One test sample's certification: the enumeration, its counters and the search over runs."""

    def __init__(self, verifier: EnumerationVerifier, render):
        self.m, self.base, self.network, self.render = verifier.method, verifier.base, verifier.network, render
        self.classified = 0
        self.bounded = 0
        self.i = axis_index(self.m.axis)

    def motions(self, poses) -> torch.Tensor:
        motions = torch.zeros(len(poses), 6, dtype=torch.float64)
        motions[:, self.i] = torch.as_tensor(np.asarray(poses, np.float64))
        return motions

    @torch.inference_mode()
    def classify(self, images: np.ndarray) -> torch.Tensor:
        """The base classifier's logits (float32, CPU) on images (B, C, H, W), in batches."""
        out = []
        step = max(int(self.base.batch_size), 1)
        for s in range(0, len(images), step):
            x = torch.from_numpy(images[s : s + step]).to(self.base.device)
            out.append(self.base.model(x).float().cpu())
        self.classified += len(images)
        return torch.cat(out)

    margins = staticmethod(class_margins)

    def alone(self, pose: float, c: int) -> float:
        """The margin at ``pose``, rendered and classified on its own."""
        with torch.inference_mode():
            image = self.render(self.motions([pose])).to(self.base.device)
            logits = self.base.model(image).float().cpu()
        self.classified += 1
        return float(self.margins(logits, c)[0])

    def result(self) -> Certificate:
        a = self.m.half_width
        with torch.inference_mode():
            centre = self.base.model(self.render(self.motions([0.0])).to(self.base.device)).float().cpu()
        c = int(predicted(centre)[0])
        if c < 0:
            return self.certificate(c, "unknown", float("nan"), None, float("nan"))
        points, colors, rank = self.render.cloud_for(self.motions([-a, a]))
        e = enumerate_images(points, colors, rank, self.render.K, self.render.height, self.render.width,
                             self.render.background, self.m.axis, -a, a)  # fmt: skip
        self.e = e
        spread = np.unique(np.linspace(0, len(e) - 1, min(SPREAD, len(e))).round().astype(int))
        found = self.classify_images(e, spread, c)
        if found is not None:
            return self.certificate(c, "falsified", found[1], e, found[0])
        least = np.inf
        undecided = False  # an image rounding may render otherwise, classified otherwise that way
        todo = [(0, len(e))]
        short: list[tuple[int, int]] = []
        while todo or short:
            if short and (not todo or sum(t - s for s, t in short) >= self.m.batch):
                found, margin = self.classify_runs(e, short, c)
                undecided |= not self.variants_hold(e, short, c)
                short = []
                if found is not None:
                    return self.certificate(c, "falsified", found[1], e, found[0])
                least = min(least, margin)
                continue
            s, t = todo.pop()
            if t - s <= self.m.run_images:
                short.append((s, t))
                continue
            if self.bounded >= self.m.max_bounds:
                return self.certificate(c, "unknown", least, e, float("nan"))
            bound = self.bound(e, s, t, c)
            if bound > 0:
                least = min(least, bound)
            else:
                mid = (s + t) // 2
                todo += [(mid, t), (s, mid)]
        if undecided:
            return self.certificate(c, "unknown", least, e, float("nan"))
        return self.certificate(c, "verified", least, e, float("nan"))

    def variants_hold(self, e: Enumeration, runs: list[tuple[int, int]], c: int) -> bool:
        """Whether every image the runs' fragile records allow beside the enumerated ones (a pixel
        that rounding may hand to a point of near-equal depth) is classified ``c`` too; such an
        image is not known to be rendered, so one classified otherwise leaves the interval unknown."""
        for s, t in runs:
            records = e.alternates(s, t)
            for k in sorted({k for a, b, _, _ in records.tolist() for k in range(max(a, s), min(b, t))}):
                if self.bound(e, k, k + 1, c) > 0:  # its hull holds every colour the records allow
                    continue
                images = e.variants(k, VARIANTS)
                if images is None or (len(images) and (self.margins(self.classify(images), c) < 0).any()):
                    return False
        return True

    def bound(self, e: Enumeration, s: int, t: int, c: int) -> float:
        """A lower bound of the least margin over the hull of images ``s`` to ``t - 1``."""
        low, high = e.hull(s, t)
        device = self.base.device
        self.bounded += 1
        return float(
            self.network.margins(
                torch.from_numpy(low[None]).to(device), torch.from_numpy(high[None]).to(device), c, self.m.relaxation
            ).min()
        )

    def classify_images(self, e: Enumeration, indices: np.ndarray, c: int) -> tuple[float, float] | None:
        """A pose of one of the images ``indices`` classified otherwise than ``c``, and its margin."""
        images = np.concatenate([e.images(int(k), int(k) + 1) for k in indices])
        margins = self.margins(self.classify(images), c)
        return self.decide(e, indices, margins, c)[0]

    def classify_runs(self, e: Enumeration, runs: list[tuple[int, int]], c: int):
        """Every image of the ``runs`` classified: a falsifying pose (or None), and the least margin."""
        images = np.concatenate([e.images(s, t) for s, t in runs])
        indices = np.concatenate([np.arange(s, t) for s, t in runs])
        margins = self.margins(self.classify(images), c)
        return self.decide(e, indices, margins, c)

    def decide(self, e: Enumeration, indices: np.ndarray, margins: np.ndarray, c: int):
        """Margins near 0 checked on the image alone; the first negative one's pose."""
        scale = ROUNDING * max(1.0, float(np.abs(margins[np.isfinite(margins)]).max(initial=1.0)))
        for j in np.nonzero(np.abs(margins) <= scale)[0]:
            margins[j] = self.alone(e.pose(int(indices[j])), c)
        if (margins < 0).any():
            j = int(np.argmin(margins))
            pose = e.pose(int(indices[j]))
            alone = self.alone(pose, c)
            if alone < 0:
                return (pose, alone), float(margins.min())
            margins[j] = alone  # a batch's rounding: decided alone
            return self.decide(e, indices, margins, c) if (margins < 0).any() else (None, float(margins.min()))
        return None, float(margins.min())

    def certificate(self, c: int, outcome: str, margin: float, e: Enumeration | None, pose: float) -> Certificate:
        radius = self.m.half_width if outcome == "verified" else 0.0
        return Certificate(
            c, radius, 0, float("nan"), 0, self.m.region_unit, float(margin),
            {
                "outcome": outcome,
                "events": 0 if e is None else e.events,
                "images": 0 if e is None else len(e),
                "classified": self.classified,
                "runs_bounded": self.bounded,
                "counterexample": float(pose),
            },
        )  # fmt: skip
