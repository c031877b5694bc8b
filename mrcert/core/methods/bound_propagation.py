"""Deterministic certification of a pose interval by bound propagation (``method=bound_propagation``).

A test image is certified for the whole interval ``[-a, a]`` on one motion axis, for the base
classifier itself, with no samples and no probability: the interval is cut into pieces; for
each piece :func:`~mrcert.core.verification.image_bounds.image_boxes` bounds every pixel and channel of any
image projected from a pose of the piece (occlusion, rounding, the border, the camera plane and
empty pixels included), and :class:`~mrcert.core.verification.network.BoundNetwork` pushes that box
through the classifier to a lower bound on the margin ``y_c - y_j`` between the class ``c``
predicted at the test pose and every other class. A piece whose bound is positive is verified;
one that is not is bisected, until

* every piece is verified: **verified**, the certificate's radius is ``a`` (a piece that holds
  at most :data:`LEAF_POSES` float64 values -- the only poses the projection can be given -- is
  decided by classifying each of them);
* a pose of the interval is classified otherwise (the interval's evenly sampled poses, then the
  midpoint of every piece that is split, then a local search around the pose of least margin):
  **falsified**, with that pose logged;
* the budget (``max_pieces`` pieces bounded, ``seconds``) is spent: **unknown**.

Guarantee: verified means that ``h(O(V, alpha)) = c`` for every ``|alpha| <= a`` on the axis (every
pose the projection can be given, a float64), where ``h`` is the base classifier in exact
arithmetic (the bounds are computed in float64); nothing is assumed about a distribution.
"""

from __future__ import annotations

import heapq
import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from omegaconf import DictConfig

from mrcert.core.axes import axis_index, unit
from mrcert.core.methods.base import (
    ABSTAIN,
    BaseClassifier,
    Certificate,
    CertifyRequest,
    Method,
    SceneRender,
    WholeInterval,
)
from mrcert.core.models import class_margins, predicted
from mrcert.core.verification.image_bounds import image_boxes
from mrcert.core.verification.network import BoundNetwork
from mrcert.errors import MrcertError

SEARCH_STEPS = 8
"""Steps of the local search for a falsifying pose after the evenly sampled ones."""

LEAF_POSES = 1024
"""A piece that fails its bound and holds at most this many float64 poses is decided by
classifying every one of them (the projection is given float64 poses: there are no others)."""


def float_poses(start: float, end: float, limit: int) -> np.ndarray | None:
    """Every float64 value in ``[start, end]`` (0 once), in order, when there are at most ``limit``; else None."""
    if start < 0 < end:
        below, above = float_poses(start, -0.0, limit), float_poses(0.0, end, limit)
        if below is None or above is None or len(below) + len(above) - 1 > limit:
            return None
        return np.concatenate([below[:-1], above])
    ia, ib = (int(np.float64(v).view(np.int64)) for v in (start, end))
    if abs(ib - ia) + 1 > limit:
        return None
    values = np.arange(min(ia, ib), max(ia, ib) + 1, dtype=np.int64).view(np.float64)
    return np.sort(values)


@dataclass(frozen=True)
class BoundPropagation(WholeInterval, Method):
    """The method (module docstring); its certifier is :class:`IntervalVerifier`."""

    axis: str
    half_width: float
    relaxation: str = "crown"
    max_pieces: int = 512
    seconds: float = 120.0
    samples: int = 33
    batch: int = 8
    crown_neurons: int = 2048

    log_columns: ClassVar[tuple[str, ...]] = ("outcome", "pieces", "bound_passes", "forward_passes", "counterexample")

    @classmethod
    def from_config(cls, method: DictConfig, motion: DictConfig) -> BoundPropagation:
        return cls(
            cls.interval_axis(motion, "bound_propagation"),
            float(method.half_width),
            str(method.relaxation),
            method.max_pieces,
            float(method.seconds),
            method.samples,
            method.batch,
            method.crown_neurons,
        )

    @property
    def noise_scales(self) -> tuple[float, ...]:
        return ()

    def region(self) -> str:
        return (
            f"every pose |{self.axis}| <= {self.half_width:g} {unit(self.axis)} when R > 0, for the base classifier "
            f"itself and with certainty (bound propagation, {self.relaxation}); R is {self.half_width:g} or 0"
        )

    def certifier(self, base: BaseClassifier) -> IntervalVerifier:
        return IntervalVerifier(self, base)


@dataclass(order=True)
class Piece:
    margin: float  # its parent's bound (the first to be bounded: the least)
    start: float
    end: float


class IntervalVerifier:
    """:class:`BoundPropagation` bound to a base classifier: its graph read once for bounds."""

    def __init__(self, method: BoundPropagation, base: BaseClassifier):
        self.method, self.base = method, base
        self.network = BoundNetwork(base.model, method.crown_neurons)

    def certify_sample(self, render, request: CertifyRequest, generator: torch.Generator) -> Certificate:
        """Verify, falsify, or give up on one test sample (module docstring); draws nothing."""
        if not isinstance(render, SceneRender):
            raise MrcertError("bound propagation needs a renderer that shows its scene (TestSample.renderer())")
        return _Run(self, render).result()


class _Run:
    """One test sample's verification: its counters and the search over pieces."""

    def __init__(self, verifier: IntervalVerifier, render):
        self.m, self.base, self.network, self.render = verifier.method, verifier.base, verifier.network, render
        self.start = time.perf_counter()
        self.forward_passes = 0
        self.bound_passes = 0
        self.i = axis_index(self.m.axis)

    def motions(self, amounts) -> torch.Tensor:
        motions = torch.zeros(len(amounts), 6, dtype=torch.float64)
        motions[:, self.i] = torch.as_tensor(np.asarray(amounts, np.float64))
        return motions

    @torch.inference_mode()
    def logits(self, amounts) -> torch.Tensor:
        """The base classifier's logits (float32, CPU) at the poses ``amounts`` on the axis."""
        self.forward_passes += len(amounts)
        out = []
        step = max(int(self.base.batch_size), 1)
        for s in range(0, len(amounts), step):
            images = self.render(self.motions(amounts[s : s + step]))
            out.append(self.base.model(images.to(self.base.device)).float().cpu())
        return torch.cat(out)

    margins = staticmethod(class_margins)

    def result(self) -> Certificate:
        a = self.m.half_width
        centre = self.logits([0.0])
        c = int(predicted(centre)[0])
        if c < 0:
            return self.certificate(ABSTAIN, "unknown", float("nan"), 0, float("nan"))
        poses = np.linspace(-a, a, int(self.m.samples))
        found = self.falsify(poses, c, SEARCH_STEPS)
        if found is not None:
            return self.certificate(c, "falsified", found[1], 0, found[0])
        ends = self.motions([-a, a])
        points, colors, rank = self.render.cloud_for(ends)
        queue = [Piece(-np.inf, -a, a)]
        verified_margin, pieces = np.inf, 0
        while queue:
            if self.bound_passes >= self.m.max_pieces or time.perf_counter() - self.start > self.m.seconds:
                worst = min(p.margin for p in queue)
                return self.certificate(c, "unknown", worst, pieces + len(queue), float("nan"))
            batch = [
                heapq.heappop(queue)
                for _ in range(min(self.m.batch, len(queue), self.m.max_pieces - self.bound_passes))
            ]
            low, high = self.boxes(points, colors, rank, batch)
            bounds = self.network.margins(low, high, c, self.m.relaxation).min(1).values.cpu().numpy()
            self.bound_passes += len(batch)
            split = []
            for piece, bound in zip(batch, bounds, strict=True):
                if bound > 0:
                    verified_margin, pieces = min(verified_margin, float(bound)), pieces + 1
                else:
                    mid = 0.5 * (piece.start + piece.end)
                    split.append((piece, mid, float(bound)))
            if split:
                found = self.falsify(np.array([mid for _, mid, _ in split]), c)
                if found is not None:
                    return self.certificate(c, "falsified", found[1], pieces, found[0])
                for piece, mid, bound in split:
                    poses = float_poses(piece.start, piece.end, LEAF_POSES)
                    if poses is not None:  # few enough poses to classify every one of them
                        margins = self.margins(self.logits(poses), c)
                        if margins.min() < 0:
                            worst = float(poses[int(np.argmin(margins))])
                            alone = self.alone(worst, c)
                            if alone < 0:
                                return self.certificate(c, "falsified", alone, pieces, worst)
                            # classified otherwise in a batch, as predicted alone: float rounding decides
                            return self.certificate(c, "unknown", float(margins.min()), pieces, float("nan"))
                        verified_margin, pieces = min(verified_margin, float(margins.min())), pieces + 1
                        continue
                    heapq.heappush(queue, Piece(bound, piece.start, mid))
                    heapq.heappush(queue, Piece(bound, mid, piece.end))
        return self.certificate(c, "verified", verified_margin, pieces, float("nan"))

    def boxes(self, points, colors, rank, batch: list[Piece]) -> tuple[torch.Tensor, torch.Tensor]:
        """Every pixel's bounds over each piece of ``batch``, where the model runs."""
        low, high = image_boxes(
            points, colors, self.render.K, self.m.axis, [p.start for p in batch], [p.end for p in batch],
            self.render.height, self.render.width, self.render.background, rank,
        )  # fmt: skip
        device = self.base.device
        return torch.from_numpy(low).to(device), torch.from_numpy(high).to(device)

    def falsify(self, poses: np.ndarray, c: int, search: int = 0) -> tuple[float, float] | None:
        """A pose among ``poses`` classified otherwise than ``c``, and its margin, or None. With
        ``search``, that many steps of a pattern search from the pose of least margin follow
        (the neighbours at half the step, the step halved each time), within the interval."""
        margins = self.margins(self.logits(poses), c)
        worst = int(np.argmin(margins))
        pose, margin = float(poses[worst]), float(margins[worst])
        step = 2 * self.m.half_width / max(len(poses) - 1, 1) / 2
        for _ in range(search):
            if margin < 0:
                break
            near = np.clip([pose - step, pose + step], -self.m.half_width, self.m.half_width)
            values = self.margins(self.logits(near), c)
            k = int(np.argmin(values))
            if values[k] < margin:
                pose, margin = float(near[k]), float(values[k])
            step /= 2
        if margin < 0:  # the pose is classified otherwise when it is classified alone, too
            margin = self.alone(pose, c)
        return (pose, margin) if margin < 0 else None

    def alone(self, pose: float, c: int) -> float:
        """The margin at ``pose`` classified on its own (a batch of one, as a user checks a
        logged pose): float rounding in a batch may differ by the last digits."""
        return float(self.margins(self.logits([pose]), c)[0])

    def certificate(self, c: int, outcome: str, margin: float, pieces: int, pose: float) -> Certificate:
        radius = self.m.half_width if outcome == "verified" else 0.0
        return Certificate(
            c,
            radius,
            0,
            float("nan"),
            0,
            self.m.region_unit,
            float(margin),
            {
                "outcome": outcome,
                "pieces": int(pieces),
                "bound_passes": self.bound_passes,
                "forward_passes": self.forward_passes,
                "counterexample": float(pose),
            },
        )
