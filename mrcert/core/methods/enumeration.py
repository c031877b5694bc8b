"""Exact certification of a pose interval by enumerating the images it renders (``method=enumeration``).

Along a translation a z-buffered point cloud renders finitely many images over an interval
``[-a, a]`` (:mod:`mrcert.core.verification.events`: every pose at which a point's pixel
changes, located in the renderer's own float64 arithmetic). The classifier's answer on the
interval is therefore decided by those images alone, and this method decides it completely:

* the image at the test pose gives the class ``c``; a few images spread over the interval are
  classified first (a falsifying pose is usually found there);
* every image is then classified incrementally
  (:mod:`mrcert.core.verification.incremental`): each from the one before it, recomputing only
  what its changed pixels reach, up to :data:`LANES` pieces of the interval at once; a network
  whose graph it cannot follow is classified image by image, in batches. A margin within float
  rounding of 0 is classified again on the image alone;
* where rounding may hand a pixel to another point (tz: near-equal depths; a rotation: a point
  within rounding of a pixel edge, and on rx and ry two depths within rounding of each other),
  every image those records allow is decided too: by an interval bound over the few pixels, else
  by classifying each (with an affine tail, as the nominal logits plus one change per group of
  pixels whose windows meet, :func:`_groups`; on a rotation the images of each recorded window
  unit by unit, each free point -- or line of twins along the rotation's axis -- in one of its
  pixels or shown nowhere, :func:`_point_groups`, with the records beside the windows pixel by
  pixel); a group with too many images is one box, bounded as a whole (:class:`_Box`), and split
  in two by one pixel's colours while its bound leaves an image below the margin open, down to
  boxes of a few images, classified (:func:`_open_images`, within :data:`BOX_BOUNDS`);
* optionally (``run_images`` below the number of images), a longer run first gets its exact hull
  -- per pixel and channel, the least and the greatest value the run's images take -- and bound
  propagation (:class:`~mrcert.core.verification.network.BoundNetwork`) proves ``y_c > y_j`` over
  it, hence over every image of the run; a run it does not prove is halved.

Outcomes: **verified** (every image of the interval is classified ``c``: the radius is ``a``),
**falsified** (an image classified otherwise, with the first float pose that renders it logged
as the counterexample, checked by rendering and classifying that pose alone), **unknown** only
when the budget (``max_bounds`` runs bounded, :data:`BOX_BOUNDS` boxes) is spent or an image
rounding may render is classified otherwise (or there are more than :data:`VARIANTS` of one image).

Guarantee: verified means ``h(O(V, alpha)) = c`` for every float64 ``|alpha| <= a`` on the axis,
where ``h`` is the base classifier as it classifies one image (the bounds hold for it in exact
arithmetic; the incremental logits are its float32 forward pass up to a different order of
summation, far below the rounding margin within which an image is classified alone); nothing is
assumed about a distribution. Translations (``tx``, ``ty``, ``tz``) and rotations (``rx``,
``ry``, ``rz``, :mod:`mrcert.core.verification.rotation_events`: sound while the library's ``cos``
and ``sin`` are within a few units in the last place).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from omegaconf import DictConfig
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

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
from mrcert.core.verification.events import AXES, Enumeration, enumerate_images, record_options
from mrcert.core.verification.incremental import IncrementalNetwork
from mrcert.core.verification.network import BoundNetwork
from mrcert.core.verification.rotation_events import ROTATIONS
from mrcert.errors import ConfigError, MrcertError

SPREAD = 33
"""Images spread evenly over the interval, classified before any run is bounded."""

VARIANTS = 64
"""The most images rounding may render beside an enumerated one that are classified (then: unknown)."""

BOX_IMAGES = 16
"""A box split into its images once it holds at most this many (:func:`_split`)."""

BOX_SPLIT = 65536
"""The most images of a box that is split (:func:`_split`); a larger one left open is not."""

BOX_BOUNDS = 256
"""The most boxes bounded for one sample (:func:`_open_images`; then: unknown). A box's bound
costs about one interval pass over the pixels it reaches."""

GROUP_VARIANTS = 1024
"""An affine tail: the most such images of one group of fragile pixels near one another whose
changes of the logits are computed (:func:`_groups`; then: unknown)."""

LANES = 32
"""Pieces of the interval followed at once by the incremental classifier."""

LANE_IMAGES = 128
"""About the fewest images of a piece (its first image is classified in full)."""

ROUNDING = 1e-4
"""A batched margin below this (relative to the logits' scale) is checked on the image alone."""


@dataclass(frozen=True)
class ImageEnumeration(WholeInterval, Method):
    """The method (module docstring); its certifier is :class:`EnumerationVerifier`."""

    axis: str
    half_width: float
    relaxation: str = "interval"
    run_images: int = 1048576
    max_bounds: int = 4096
    batch: int = 256
    crown_neurons: int = 2048
    incremental: bool = True

    log_columns: ClassVar[tuple[str, ...]] = (
        "outcome", "events", "images", "classified", "runs_bounded", "counterexample",
    )  # fmt: skip

    def __post_init__(self):
        super().__post_init__()
        if self.axis not in AXES:
            raise ConfigError("motion.axis", self.axis, f"one of {', '.join(AXES)} for method=enumeration")
        if self.axis in ROTATIONS and not 0 <= self.half_width <= 1:
            why = f"at most 1 rad on {self.axis} for method=enumeration"
            raise ConfigError("method.half_width", self.half_width, why)

    @classmethod
    def from_config(cls, method: DictConfig, motion: DictConfig) -> ImageEnumeration:
        return cls(
            cls.interval_axis(motion, "enumeration"), float(method.half_width), str(method.relaxation),
            int(method.run_images), int(method.max_bounds), int(method.batch), int(method.crown_neurons),
            bool(method.get("incremental", True)),
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
        self.incremental = IncrementalNetwork.of(base.model) if method.incremental else None

    def certify_sample(self, render, request: CertifyRequest, generator: torch.Generator) -> Certificate:
        """Verify or falsify one test sample (module docstring); draws nothing."""
        if not isinstance(render, SceneRender):
            raise MrcertError("enumeration needs a renderer that shows its scene (TestSample.renderer())")
        return _Run(self, render).result()


class _Run:
    """One test sample's certification: the enumeration, its counters and the search over runs."""

    def __init__(self, verifier: EnumerationVerifier, render):
        self.m, self.base, self.network, self.render = verifier.method, verifier.base, verifier.network, render
        self.incremental = verifier.incremental
        self.undecided = False  # an image rounding may render, classified otherwise (incremental pass)
        self.classified = 0
        self.bounded = 0
        self.box_bounds = 0
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
                undecided |= self.undecided if self.incremental is not None else not self.variants_hold(e, short, c)
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
        indices = np.concatenate([np.arange(s, t) for s, t in runs])
        if self.incremental is not None:
            logits = self.incremental_logits(e, runs, c)
        else:
            logits = self.classify(np.concatenate([e.images(s, t) for s, t in runs]))
        return self.decide(e, indices, self.margins(logits, c), c)

    def incremental_logits(self, e: Enumeration, runs: list[tuple[int, int]], c: int) -> torch.Tensor:
        """The logits of every image of the ``runs``, in order: the stretches without fragile
        records many at a time (:meth:`lanes`), the others one image after the other with their
        variants (:meth:`along`)."""
        cover = np.zeros(len(e) + 1, np.int64)
        if len(e.fragile):
            np.add.at(cover, e.fragile[:, 0], 1)
            np.add.at(cover, e.fragile[:, 1], -1)
        fragile = np.cumsum(cover)[:-1] > 0
        segments = []
        for s, t in runs:
            cuts = np.r_[s, s + 1 + np.nonzero(fragile[s + 1 : t] != fragile[s : t - 1])[0], t]
            segments += [(int(a), int(b), bool(fragile[a])) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
        net = self.incremental
        net.start(torch.from_numpy(e.images(0, 1)))
        if not net.affine():  # the variants need the whole network at each image: one after the other
            plain = self.lanes(e, [(a, b) for a, b, f in segments if not f])
            out, j = [], 0
            for a, b, f in segments:
                if f:
                    out.append(self.along(e, a, b, c))
                else:
                    out.append(plain[j])
                    j += 1
            return torch.cat(out)
        logits = self.lanes(e, [(a, b) for a, b, _ in segments])
        for (a, b, f), nominal in zip(segments, logits, strict=True):
            if f and not self.undecided and not self.variants_along(e, a, b, nominal, c):
                self.undecided = True
        return torch.cat(logits)

    @torch.inference_mode()
    def variants_along(self, e: Enumeration, a: int, b: int, nominal: torch.Tensor, c: int) -> bool:
        """Whether every image the fragile records of images ``a`` to ``b - 1`` allow is classified
        ``c``, given the nominal images' logits: each variant's logits are the nominal ones plus a
        change that depends on the pixels near the fragile ones alone (the tail is affine), so the
        incremental network follows only the changes that reach what that change read."""
        net = self.incremental
        table = torch.from_numpy(e.table())
        records = e.alternates(a, b)
        cuts = np.unique(np.r_[a, b, np.clip(records[:, 0], a, b), np.clip(records[:, 1], a, b)])
        spans = np.searchsorted(e.change_image, np.arange(a, b + 1), side="left")
        for u, v in zip(cuts[:-1].tolist(), cuts[1:].tolist(), strict=True):
            here = records[(records[:, 0] <= u) & (records[:, 1] > u)]
            if not len(here):
                continue
            net.start(torch.from_numpy(e.images(u, u + 1)))
            # a record closes where its pixel changes, so the pixels keep their colour over [u, v)
            pixels, options, low, high = _allowed(net, here, table)
            if not len(pixels):
                continue
            # What the bound reads, while the image is whole: the same windows at every later
            # image, so only the changes inside what it depends on are followed; the variants'
            # changes join it (from the whole image then) at the first image the bound leaves open.
            net.offsets(pixels, low, high, c)
            reach, groups = net.reach(), None
            for k in range(u, v):
                if k > u:
                    lo, hi = spans[k - a], spans[k - a + 1]
                    changed = e.change_pixel[lo:hi]
                    rows, cols = changed // e.width, changed % e.width
                    if ((rows >= reach[0]) & (rows < reach[1]) & (cols >= reach[2]) & (cols < reach[3])).any():
                        net.step(changed, table[e.change_winner[lo:hi]].T)
                logits = nominal[k - a].to(net.values[0].device)
                scale = ROUNDING * max(1.0, float(logits.abs().max()))
                least = logits[c] - logits + net.offsets(pixels, low, high, c)
                least[c] = torch.inf
                if float(least.min()) <= scale:
                    if groups is None:  # each window's groups and their images, from the whole image
                        net.start(torch.from_numpy(e.images(k, k + 1)))
                        # a rotation: the images of each window apart (one holds at any pose), point by
                        # point, with the records beside every window's (rx, ry: two depths within
                        # rounding) pixel by pixel, groups whose changes may meet boxed together
                        windows = e.windows_at(u)
                        beside = _groups(net, *_allowed(net, e.beside_windows(u, windows), table)[:2])
                        groups = [_joint(net, _point_groups(net, *e.free_points(w), table), beside)
                                  for w in windows] or [beside]  # fmt: skip
                        net.offsets(pixels, low, high, c)
                    for one in groups:
                        if not self.window_holds(e, k, net, one, logits, c, scale):
                            return False
                    reach = net.reach()
        return True

    def window_holds(self, e: Enumeration, k: int, net: IncrementalNetwork, groups: list, logits: torch.Tensor,
                     c: int, scale: float) -> bool:  # fmt: skip
        """Whether every image of one window's ``groups`` beside image ``k`` whose margin may be
        at most ``scale`` (:func:`_open_images`) is classified ``c`` on its own; not known once
        :data:`BOX_BOUNDS` boxes have been bounded for the sample."""
        before = net.deltas
        images, bounds = _open_images(net, groups, logits, c, scale, BOX_BOUNDS - self.box_bounds)
        self.classified += net.deltas - before  # each change computed: a variant classified
        self.box_bounds += bounds
        return images is not None and all(self.variant_alone(e, k, *image, c) >= 0 for image in images)

    def variant_alone(self, e: Enumeration, k: int, pixels: np.ndarray, values: torch.Tensor, c: int) -> float:
        """The margin of image ``k`` changed at ``pixels`` to ``values``, classified on its own."""
        image = torch.from_numpy(e.images(k, k + 1))
        image.view(image.shape[1], -1)[:, torch.from_numpy(pixels)] = values.to(image.dtype)
        with torch.inference_mode():
            return float(self.margins(self.base.model(image.to(self.base.device)).float().cpu(), c)[0])

    @torch.inference_mode()
    def lanes(self, e: Enumeration, stretches: list[tuple[int, int]]) -> list[torch.Tensor]:
        """The logits of each stretch's images (one tensor per stretch): the stretches cut into
        up to :data:`LANES` pieces of about equal changes, followed at once,
        each step changing one pixel of every piece (:meth:`IncrementalNetwork.lanes`)."""
        total = sum(b - a for a, b in stretches)
        if not total:
            return []
        # pieces of about equal numbers of changed pixels (the steps they take), cut at images
        changes = np.diff(np.searchsorted(e.change_image, np.arange(len(e) + 1), side="left"))
        count = max(1, min(LANES, total // LANE_IMAGES))
        share = sum(int(changes[a:b].sum()) for a, b in stretches) / count
        pieces = []
        for a, b in stretches:
            ends = np.cumsum(changes[a:b])
            cuts = np.unique(np.r_[0, np.searchsorted(ends, np.arange(share, ends[-1], share)), b - a])
            pieces += [(a + int(u), a + int(v)) for u, v in zip(cuts[:-1], cuts[1:], strict=True) if v > u]
        table = torch.from_numpy(e.table())
        logits: list[torch.Tensor] = []
        for g in range(0, len(pieces), LANES):
            group = pieces[g : g + LANES]
            firsts = torch.from_numpy(np.concatenate([e.images(a, a + 1) for a, _ in group]))
            spans = [np.searchsorted(e.change_image, [a + 1, b], side="left") for a, b in group]
            steps = max(int(hi - lo) for lo, hi in spans)
            pixels = np.full((len(group), steps), -1, np.int64)
            colours = torch.zeros(len(group), steps, table.shape[1], dtype=table.dtype)
            shown = np.zeros((len(group), steps), bool)
            for r, (lo, hi) in enumerate(spans):
                n = int(hi - lo)
                pixels[r, :n] = e.change_pixel[lo:hi]
                colours[r, :n] = table[e.change_winner[lo:hi]]
                images = e.change_image[lo:hi]
                shown[r, :n] = np.r_[images[1:] != images[:-1], True] if n else shown[r, :n]
            rows = self.incremental.lanes(firsts, pixels, colours, shown)
            at = 0
            for a, b in group:
                logits.append(rows[at : at + b - a])
                at += b - a
        self.classified += total
        out, j = [], 0
        for a, b in stretches:  # the pieces back into their stretches
            parts = []
            while sum(len(p) for p in parts) < b - a:
                parts.append(logits[j])
                j += 1
            out.append(torch.cat(parts))
        return out

    @torch.inference_mode()
    def along(self, e: Enumeration, s: int, t: int, c: int) -> torch.Tensor:
        """The logits of images ``s`` to ``t - 1``, each recomputed from the one before it where
        its pixels changed (:mod:`mrcert.core.verification.incremental`); an image with fragile
        records has its variants decided too (:meth:`variants_hold_here`)."""
        net = self.incremental
        table = torch.from_numpy(e.table())
        bounds = np.searchsorted(e.change_image, np.arange(s, t + 1), side="left")
        records = e.alternates(s, t)
        out = torch.empty(t - s, self.base.num_classes)
        for k in range(s, t):
            lo, hi = bounds[k - s], bounds[k - s + 1]
            if k == s:
                logits = net.start(torch.from_numpy(e.images(s, s + 1)))
            elif hi > lo:
                logits = net.step(e.change_pixel[lo:hi], table[e.change_winner[lo:hi]].T)
            out[k - s] = logits.float().cpu()[0]
            if len(records) and not self.undecided:
                here = records[(records[:, 0] <= k) & (records[:, 1] > k)]
                if len(here) and not self.variants_hold_here(here, table, out[k - s], c):
                    self.undecided = True
        self.classified += t - s
        return out

    def variants_hold_here(self, records: np.ndarray, table: torch.Tensor, logits: torch.Tensor, c: int) -> bool:
        """Whether every image the fragile ``records`` allow beside the current one (each of their
        pixels its winner's colour or a record's point's) is classified ``c``: by an interval bound
        over them all, else each classified (at most :data:`VARIANTS`)."""
        net = self.incremental
        pixels, options, low, high = _allowed(net, records, table)
        if not len(pixels):
            return True
        scale = ROUNDING * max(1.0, float(logits.abs().max()))
        if net.bound(pixels, low, high, c) > scale:
            return True
        variants = _combinations(pixels, options)
        if variants is None:
            return False
        for where, colours in variants:
            margin = float(self.margins(net.variant(where, colours).float().cpu(), c)[0])
            self.classified += 1
            if margin <= scale:  # near 0 or below: the variant classified on its own decides
                image = net.values[0].clone()
                flat = image.view(image.shape[1], -1)
                flat[:, torch.from_numpy(where)] = colours.to(image.dtype)
                with torch.inference_mode():
                    margin = float(self.margins(self.base.model(image.to(self.base.device)).float().cpu(), c)[0])
                if margin < 0:
                    return False
        return True

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


def _allowed(net: IncrementalNetwork, records: np.ndarray, table: torch.Tensor):
    """The fragile records' pixels, the colours each may take besides its current one (each
    colour once: a point of the current colour, or two of one colour, make no other image), and
    the least and greatest colour per pixel and channel (the current one included), (C, P) each.
    A pixel whose records allow its current colour alone is left out."""
    allowed = record_options(records)
    pixels = np.array(sorted(allowed), np.int64)
    current = net.values[0].reshape(net.values[0].shape[1], -1)[:, torch.from_numpy(pixels)].cpu()
    keep, options = [], []
    for j, pixel in enumerate(pixels.tolist()):
        colours: list[torch.Tensor] = []
        for q in allowed[pixel]:
            colour = table[q].to(current.dtype)
            if not torch.equal(colour, current[:, j]) and not any(torch.equal(colour, o) for o in colours):
                colours.append(colour)
        if colours:
            keep.append(j)
            options.append(colours)
    pixels, current = pixels[keep], current[:, keep]
    low, high = current.clone(), current.clone()
    for j, colours in enumerate(options):
        for colour in colours:
            low[:, j], high[:, j] = torch.minimum(low[:, j], colour), torch.maximum(high[:, j], colour)
    return pixels, options, low, high


@dataclass(frozen=True)
class _Box:
    """Images of a group of pixels too many to classify: every pixel one of its ``choices``
    (C, m) (the current colour among them), in every combination; ``low`` and ``high`` (C, n),
    per pixel and channel, the least and the greatest of them. An interval bound over the box
    stands for them all; a box may be split into boxes of fewer images (:func:`_split`)."""

    pixels: np.ndarray
    choices: tuple[torch.Tensor, ...]
    low: torch.Tensor
    high: torch.Tensor

    @classmethod
    def of(cls, pixels: np.ndarray, choices) -> _Box:
        choices = tuple(choices)
        return cls(pixels, choices, torch.stack([x.min(1).values for x in choices], 1),
                   torch.stack([x.max(1).values for x in choices], 1))  # fmt: skip

    def count(self) -> float:
        """How many images the box holds."""
        return float(np.prod([x.shape[1] for x in self.choices], dtype=float))


def _groups(net: IncrementalNetwork, pixels: np.ndarray, options: list) -> list:
    """The fragile pixels in groups that reach disjoint boxes of the affine tail's first layer,
    each group's images beside the current one as (pixels changed, their colours (C, n)) (as
    :func:`_combinations`), or one :class:`_Box` where a group has more than :data:`GROUP_VARIANTS`
    images. A change of one group leaves the values the others reach as they are, so (the tail
    being affine) the logits of any image the records allow are the current ones plus one change
    per group."""
    groups: list = []
    for js in _clusters([net.boundary_box(pixels[j : j + 1]) for j in range(len(pixels))]):
        choices = _combinations(pixels[js], [options[j] for j in js], GROUP_VARIANTS)
        groups.append([_boxed(net, [[(pixels[j : j + 1], o[:, None]) for o in options[j]] for j in js])]
                      if choices is None else choices)  # fmt: skip
    return groups


def _boxed(net: IncrementalNetwork, groups: list) -> _Box:
    """One box over ``groups`` (each a list of images as (pixels, their colours (C, n)), or of
    :class:`_Box`): per pixel, the current colour and every colour a group may give it."""
    current = net.values[0].reshape(net.values[0].shape[1], -1).cpu()
    choices: dict[int, list[torch.Tensor]] = {}

    def add(p: int, colours: torch.Tensor) -> None:  # colours (C, m)
        have = choices.setdefault(p, [current[:, p].clone()])
        for colour in colours.T.to(current.dtype):
            if not any(torch.equal(colour, h) for h in have):
                have.append(colour)

    for group in groups:
        for part in group:
            box = isinstance(part, _Box)
            pixels, colours = (part.pixels, part.choices) if box else (part[0], part[1].T[..., None])
            for p, x in zip(pixels.tolist(), colours, strict=True):
                add(p, x)
    where = sorted(choices)
    return _Box.of(np.array(where, np.int64), [torch.stack(choices[p], 1) for p in where])


def _split(current: torch.Tensor, box: _Box) -> list:
    """A box as parts that hold its images between them: its images beside the current one
    (``current`` (C, H*W), the image's colours) as (pixels changed, their colours) where it holds
    at most :data:`BOX_IMAGES`, else two boxes, the pixel of the widest choices in one half of its
    choices or the other."""
    now = current[:, torch.from_numpy(box.pixels)]
    if box.count() <= BOX_IMAGES:
        out = []
        for combo in itertools.product(*(range(x.shape[1]) for x in box.choices)):
            colours = torch.stack([x[:, r] for x, r in zip(box.choices, combo, strict=True)], 1)
            changed = (colours != now.to(colours.dtype)).any(0).numpy()
            if changed.any():
                out.append((box.pixels[changed], colours[:, torch.from_numpy(changed)].contiguous()))
        return out
    widths = [float((x.max(1).values - x.min(1).values).sum()) if x.shape[1] > 1 else -1.0 for x in box.choices]
    j = int(np.argmax(widths))
    x = box.choices[j]
    order = torch.argsort(x.sum(0))  # by brightness: each half's colours near one another
    halves = (x[:, order[: x.shape[1] // 2]], x[:, order[x.shape[1] // 2 :]])
    return [_Box.of(box.pixels, (*box.choices[:j], half, *box.choices[j + 1 :])) for half in halves]


def _pixels_of(group) -> np.ndarray:
    """Every pixel a group (its images and boxes) may change."""
    pixels = [part.pixels if isinstance(part, _Box) else part[0] for part in group]
    return np.unique(np.concatenate(pixels)) if pixels else np.empty(0, np.int64)


def _joint(net: IncrementalNetwork, own: list, beside: list) -> list:
    """A window's groups (:func:`_point_groups`) with the groups of the records beside it
    (:func:`_groups`), which hold at the same poses: a group beside whose changes may meet one of
    the window's (a pixel's box of the affine tail's first layer meeting one of the other's) is
    boxed with it (:func:`_boxed`), so the groups left reach disjoint boxes and their changes add."""
    if not own or not beside:
        return own + beside
    parts = own + beside
    boxes = [_pixel_boxes(net, _pixels_of(g)) for g in parts]
    meet = np.zeros((len(parts), len(parts)), bool)
    for i in range(len(own)):
        for j in range(len(own), len(parts)):
            meet[i, j] = len(boxes[i]) > 0 and len(boxes[j]) > 0 and bool(_box_meets(boxes[i], boxes[j]).any())
    return [parts[js[0]] if len(js) == 1 else [_boxed(net, [parts[j] for j in js])] for js in _components(meet)]


def _pixel_boxes(net: IncrementalNetwork, pixels: np.ndarray) -> np.ndarray:
    """(n, 4): the box of the affine tail's first layer each pixel's change reaches (those that
    reach none left out)."""
    boxes = [net.boundary_box(pixels[j : j + 1]) for j in range(len(pixels))]
    return np.array([b for b in boxes if b is not None], np.int64).reshape(-1, 4)


def _box_meets(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m): whether box ``i`` of ``a`` (n, 4) meets box ``j`` of ``b`` (m, 4), as
    :func:`mrcert.core.verification.incremental._meets` decides for two."""
    A, B = a[:, None, :], b[None, :, :]
    return (A[..., 0] < B[..., 1]) & (B[..., 0] < A[..., 1]) & (A[..., 2] < B[..., 3]) & (B[..., 2] < A[..., 3])


def _components(meet: np.ndarray) -> list[list[int]]:
    """The indices in groups joined by ``meet`` (n, n), in order of their first members."""
    _, labels = connected_components(csr_matrix(meet), directed=False)
    members: dict[int, list[int]] = {}
    for j, label in enumerate(labels.tolist()):
        members.setdefault(label, []).append(j)
    return list(members.values())


def _change(net: IncrementalNetwork, group: list, c: int) -> tuple[torch.Tensor, set[int]]:
    """A group's changes for :func:`_low_variants`: per part, one row (n, K) of the change of
    each margin ``y_c - y_j`` -- an image's exactly, a :class:`_Box`'s the least over it -- and
    which rows are boxes."""
    rows, boxes = [], set()
    K = net.values[net.output].shape[1]
    for r, part in enumerate(group):
        if isinstance(part, _Box):
            rows.append(net.offsets(part.pixels, part.low, part.high, c).double().cpu())
            boxes.add(r)
        else:
            d = net.delta(*part)[0].double().cpu()
            rows.append(d[c] - d)
    return (torch.stack(rows) if rows else torch.zeros(0, K, dtype=torch.float64)), boxes


def _point_groups(
    net: IncrementalNetwork,
    pixels: dict[int, list[int]],
    ranked: dict[int, list[int]],
    units: dict[int, list[int]],
    table: torch.Tensor,
) -> list:
    """A window's images (a rotation), unit by unit: each unit of free points (one point, or
    twins on a line along the rotation's axis, which take their ``r``-th pixels together) in one
    of its choices (a pixel per point, -1: off the image), each pixel then showing the nearest of
    the points there (``ranked``, nearest first: the free points that may be there and the nearest
    other point, there throughout). The units in groups whose pixels reach disjoint boxes of the
    affine tail's first layer (as :func:`_groups`); each group's images as (its pixels, their
    colours (C, n)), every pixel any of its points may occupy set, so each holds beside any
    current image. Some k units with two choices each make at most 2^k images, where their
    pixels' colours would make far more, and fewer where a nearer point hides them: the images
    are found unit by unit, equal ones kept once; a group with more than :data:`GROUP_VARIANTS`
    is a :class:`_Box` over every point that may show at each of its pixels."""
    free = set(pixels)
    members_of = []
    for qs in units.values():
        if len({len(pixels[q]) for q in qs}) == 1:
            members_of.append(qs)
        else:  # not aligned choices: each point on its own (a superset of the unit's images)
            members_of += [[q] for q in qs]
    units_ = [qs for qs in members_of if any(p >= 0 for q in qs for p in pixels[q])]
    boxes = [net.boundary_box(np.array(sorted({p for q in qs for p in pixels[q] if p >= 0}), np.int64))
             for qs in units_]  # fmt: skip
    groups = []
    for js in _clusters(boxes):
        members = [units_[j] for j in js]
        where = sorted({p for qs in members for q in qs for p in pixels[q] if p >= 0})
        at = {p: j for j, p in enumerate(where)}
        # a state: per pixel, the place in its ranked points of the nearest one there so far; the
        # units taken one by one (each in each of its choices), equal states kept once
        states = {tuple(next(i for i, r in enumerate(ranked[p]) if r not in free) for p in where)}
        for qs in members:
            choices = []
            for r in range(len(pixels[qs[0]])):
                places = [(at[pixels[q][r]], ranked[pixels[q][r]].index(q)) for q in qs if pixels[q][r] >= 0]
                if places not in choices:
                    choices.append(places)
            grown = set()
            for st in states:
                for places in choices:
                    new = list(st)
                    for x, i in places:
                        new[x] = min(new[x], i)
                    grown.add(tuple(new))
            states = grown
            if len(states) > GROUP_VARIANTS:
                break
        pix = np.array(where, np.int64)
        if len(states) > GROUP_VARIANTS:  # every point that may show at each pixel, boxed
            shows = [(pix[x : x + 1], table[q][:, None]) for x, p in enumerate(where) for q in ranked[p]]
            groups.append([_boxed(net, [shows])])
            continue
        groups.append([(pix, table[[ranked[p][i] for p, i in zip(where, s, strict=True)]].T.contiguous())
                       for s in sorted(states)])  # fmt: skip
    return groups


def _clusters(boxes: list) -> list[list[int]]:
    """The indices of ``boxes`` (r0, r1, c0, c1; None: reaches nothing) in groups, two whose
    boxes meet in one (in order of their first members)."""
    n = len(boxes)
    some = [j for j in range(n) if boxes[j] is not None]
    meet = np.zeros((n, n), bool)
    if some:
        b = np.array([boxes[j] for j in some], np.int64)
        meet[np.ix_(some, some)] = _box_meets(b, b)
    return _components(meet)


def _open_images(
    net: IncrementalNetwork, groups: list, logits: torch.Tensor, c: int, scale: float, budget: int = BOX_BOUNDS
) -> tuple[list | None, int]:
    """The images of one window's ``groups`` (their changes add) beside the current one whose
    margin may be at most ``scale``, as (pixels changed, their colours (C, n)), each to be
    classified on its own (:func:`_low_variants`); every other image of the groups has a margin
    above ``scale``. A box whose bound leaves such an image open is split (:func:`_split`) in
    place, so that later images of the window start from the finer groups. None where there
    are more than :data:`VARIANTS`, or more than ``budget`` boxes would be bounded; and how many
    boxes were bounded."""
    bounds = 0
    while True:
        bounds += sum(isinstance(part, _Box) for group in groups for part in group)
        if bounds > budget:
            return None, bounds
        low_ones, open_ = _low_variants(logits, [_change(net, group, c) for group in groups], c, scale)
        if low_ones is None:
            return None, bounds
        if not open_:
            break
        if any(groups[g][r].count() > BOX_SPLIT for g, r in open_):
            return None, bounds
        current = net.values[0].reshape(net.values[0].shape[1], -1).cpu()
        for g in sorted({g for g, _ in open_}):
            split = {r for h, r in open_ if h == g}
            parts = [_split(current, part) if r in split else [part] for r, part in enumerate(groups[g])]
            groups[g] = [x for made in parts for x in made]
    images = []
    for combo in low_ones:
        picked = [groups[g][r] for g, r in enumerate(combo) if r >= 0]
        images.append((np.concatenate([w for w, _ in picked]), torch.cat([v for _, v in picked], 1)))
    return images, bounds


def _low_variants(
    logits: torch.Tensor, changes: list[tuple[torch.Tensor, set[int]]], c: int, scale: float
) -> tuple[list[tuple] | None, set[tuple[int, int]]]:
    """The images, one part per group (row ``r`` of its changes, -1 for none; not all none),
    whose margin -- the logits (K,) plus the chosen rows of each group's changes (n_g, K, as
    :func:`_change`) -- is at most ``scale``: found group by group, a partial choice dropped as
    soon as even the least changes of the groups left keep every class's margin above ``scale``.
    A box's row is a bound, not an image's change: a choice of one whose margin bound is at most
    ``scale`` leaves those images open, and the second answer names such boxes (group, row), up
    to :data:`VARIANTS` choices of them. The images are None where there are more than
    :data:`VARIANTS`; they are all only where nothing is open."""
    base = (logits[c] - logits).double().cpu()
    zero = torch.zeros(1, len(base), dtype=torch.float64)
    rows = [torch.cat([zero, d]) for d, _ in changes]
    boxes = [{r + 1 for r in b} for _, b in changes]
    rest = [torch.zeros(len(base), dtype=torch.float64)]
    for m in reversed(rows):
        rest.insert(0, rest[0] + m.min(0).values)
    found: set[tuple] = set()
    open_: set[tuple[int, int]] = set()
    opened = 0
    for j in range(len(base)):
        if j == c or float(base[j] + rest[0][j]) > scale:
            continue
        stack = [(0, float(base[j]), ())]
        while stack:
            g, total, combo = stack.pop()
            if g == len(rows):
                boxed = [(h, r - 1) for h, r in enumerate(combo) if r in boxes[h]]
                if boxed:
                    open_.update(boxed)
                    opened += 1
                    if opened > VARIANTS:
                        return sorted(found), open_  # enough open boxes: split them before going on
                elif any(r > 0 for r in combo):
                    found.add(tuple(r - 1 for r in combo))
                    if len(found) > VARIANTS:
                        return None, open_
                continue
            for r in range(len(rows[g])):
                if total + float(rows[g][r, j] + rest[g + 1][j]) <= scale:
                    stack.append((g + 1, total + float(rows[g][r, j]), (*combo, r)))
    return sorted(found), open_


def _combinations(
    pixels: np.ndarray, options: list, limit: int = VARIANTS
) -> list[tuple[np.ndarray, torch.Tensor]] | None:
    """Every image the records allow beside the current one, as (pixels changed, their colours
    (C, n)): each pixel its current colour or one of its options, not all current; None where
    there are more than ``limit``."""
    if float(np.prod([len(o) + 1 for o in options], dtype=float)) - 1 > limit:
        return None
    out = []
    for combo in itertools.product(*([None, *o] for o in options)):
        which = [j for j, colour in enumerate(combo) if colour is not None]
        if which:
            out.append((pixels[which], torch.stack([combo[j] for j in which], 1)))
    return out
