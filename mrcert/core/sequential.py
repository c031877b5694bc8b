"""Sequential CERTIFY: a group-sequential test of ``pA >= need`` that is as powerful as fixed-n
CERTIFY and stops far earlier on clear images.

CERTIFY at a radius ``r`` decides one question about the top class's probability ``pA``: is
``pA >= need = Phi(r / sigma)``? Fixed-n CERTIFY draws ``n`` samples and certifies when the
one-sided Clopper-Pearson lower bound at level ``alpha`` reaches ``need``. A
:class:`SequentialDesign` checks the count at a few *looks* instead, spaced geometrically
(``first``, ``2 first``, ``4 first``, ... and a last look at ``n_max``):

* at look ``k`` (``t_k`` samples) the Clopper-Pearson lower bound at level ``alpha_k`` is the
  certificate's ``pA_lower``; it certifies ``r`` (and stops) once that bound reaches ``need``.
  The levels add up to ``alpha`` (a tenth spread over the early looks that can certify at all,
  the rest at the last look), so by the union bound the reported bound exceeds the true ``pA``
  with probability at most ``alpha`` whatever the stopping rule: the radius reported at the stop
  is valid, as for fixed n;
* it also stops, without certifying ``r``, when the Clopper-Pearson *upper* bound at level
  ``alpha / 10`` is below ``need`` (futility: the image cannot reach ``r``); this never makes
  a wrong certificate, and it loses at most ``alpha / 10`` of power per look at any
  ``pA >= need``;
* ``n_max`` is the smallest sample count ``>= n`` at which, on a grid of ``pA`` above ``need``,
  the exact probability of certifying ``r`` is at least fixed-n CERTIFY's minus
  :data:`TOLERANCE` -- the few borderline images draw a little more than ``n`` so that no image
  is less likely to be certified than under the paper's procedure.

Every probability here is exact: :meth:`SequentialDesign.operating` runs the distribution of the
count through the looks (binomial increments, stopped mass removed), for any ``pA``. A fixed-n
CERTIFY is the design with one look (:meth:`SequentialDesign.fixed`), so both procedures' power
and cost come from the same function (docs/method.md §7 plots them).

(Recomputing a fixed-n bound at *every* look at the full ``alpha`` has no such guarantee: its
error rate grows with the number of looks; docs/method.md §6.)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property

import numpy as np
from scipy.signal import fftconvolve
from scipy.stats import beta, binom

EARLY_SHARE = 0.1
"""Share of ``alpha`` spent on the early looks (the rest goes to the last look)."""

FUTILITY_SHARE = 0.1
"""Level of each look's futility bound, as a share of ``alpha``."""

TOLERANCE = 0.005
"""How much less likely than fixed-n CERTIFY to certify, at any ``pA``, a design may be."""

POWER_GRID = 400
"""``pA`` values between ``need`` and 1 at which a design's power is compared with fixed n's."""


def lower_confidence_bound(count: int, t: int, level: float) -> float:
    """One-sided (1 - level) Clopper-Pearson lower bound on a binomial proportion (0 for no
    success or at level 0; below 1 even when every trial succeeded, so radii stay finite)."""
    if count <= 0 or level <= 0:
        return 0.0
    return float(beta.ppf(level, count, t - count + 1))


def upper_confidence_bound(count: int, t: int, level: float) -> float:
    """One-sided (1 - level) Clopper-Pearson upper bound."""
    return 1.0 - lower_confidence_bound(t - count, t, level)


def _first_count(t: int, bound, level: float, need: float) -> int:
    """Smallest count in 0..t whose ``bound(count, t, level)`` reaches ``need`` (t + 1 when none
    does); the bounds grow with the count, so a bisection finds it."""
    lo, hi = 0, t + 1
    while lo < hi:
        mid = (lo + hi) // 2
        if bound(mid, t, level) >= need:
            hi = mid
        else:
            lo = mid + 1
    return lo


@dataclass(frozen=True)
class SequentialDesign:
    """Looks ``looks`` (sample counts, increasing), the Clopper-Pearson level of each look's
    lower bound (``levels``, summing to at most alpha; 0 where the look cannot certify), the
    level of the futility bound (0: none) and the probability ``need`` that the radius asks."""

    looks: tuple[int, ...]
    levels: tuple[float, ...]
    futility: float
    need: float

    @classmethod
    def fixed(cls, n: int, alpha: float, need: float) -> SequentialDesign:
        """Fixed-n CERTIFY (Cohen et al.) as a design with one look."""
        return cls((n,), (alpha,), 0.0, need)

    @classmethod
    def geometric(cls, first: int, n_max: int, alpha: float, need: float) -> SequentialDesign:
        """Looks at ``first * 2^k`` below ``n_max`` and at ``n_max``; :data:`EARLY_SHARE` of
        alpha split evenly over the early looks at which a count could certify ``need``."""
        early = []
        t = first
        while t < n_max:
            early.append(t)
            t *= 2
        early_alpha = EARLY_SHARE * alpha
        # A look of t samples can certify only when even t successes out of t clear `need`;
        # dropping a look that cannot raises the others' share, so repeat until none is dropped.
        able = list(early)
        while able:
            share = early_alpha / len(able)
            kept = [t for t in able if lower_confidence_bound(t, t, share) >= need]
            if kept == able:
                break
            able = kept
        share = early_alpha / len(able) if able else 0.0
        levels = tuple(share if t in able else 0.0 for t in early)
        return cls((*early, n_max), (*levels, alpha - share * len(able)), FUTILITY_SHARE * alpha, need)

    @classmethod
    def plan(cls, n: int, alpha: float, need: float, first: int) -> SequentialDesign:
        """The geometric design whose last look is the smallest ``n_max >= n`` (in steps of
        ``first / 5``) that certifies at least as often as fixed-n CERTIFY, less
        :data:`TOLERANCE`, at every ``pA`` of a grid above ``need``."""
        return _plan(int(n), float(alpha), float(need), int(first))

    @property
    def n_max(self) -> int:
        return self.looks[-1]

    @cached_property
    def critical(self) -> tuple[np.ndarray, np.ndarray]:
        """Per look: the smallest count that certifies (``t + 1`` when none) and the largest
        count that stops for futility (-1 when none; never at the last look). Computed once per
        design."""
        certify, futile = [], []
        last = len(self.looks) - 1
        for k, (t, level) in enumerate(zip(self.looks, self.levels, strict=True)):
            certify.append(_first_count(t, lower_confidence_bound, level, self.need) if level > 0 else t + 1)
            if self.futility > 0 and k < last:
                futile.append(_first_count(t, upper_confidence_bound, self.futility, self.need) - 1)
            else:
                futile.append(-1)
        return np.array(certify), np.array(futile)

    def decide(self, count: int, k: int) -> tuple[bool, float]:
        """After look ``k`` with ``count`` successes: whether to stop, and the lower bound on pA."""
        certify, futile = self.critical
        stop = count >= certify[k] or count <= futile[k] or k == len(self.looks) - 1
        return bool(stop), lower_confidence_bound(count, self.looks[k], self.levels[k])

    def operating(self, p: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Exact probability of certifying ``need`` and expected number of samples, at each ``pA``
        in ``p``: the distribution of the count is carried through the looks, each look
        removing the mass that stops there."""
        p = np.atleast_1d(np.asarray(p, dtype=float))
        certify, futile = self.critical
        alive = np.ones((len(p), 1))  # P(count = s, not stopped yet), s = 0..t
        certified, samples, previous = np.zeros(len(p)), np.zeros(len(p)), 0
        for k, t in enumerate(self.looks):
            step = binom.pmf(np.arange(t - previous + 1)[None, :], t - previous, p[:, None])
            alive = np.clip(fftconvolve(alive, step, axes=1), 0.0, None)
            counts = np.arange(t + 1)
            stops = (counts >= certify[k]) | (counts <= futile[k]) | (k == len(self.looks) - 1)
            certified += alive[:, counts >= certify[k]].sum(1)
            samples += t * alive[:, stops].sum(1)
            alive = np.where(stops, 0.0, alive)
            previous = t
        return certified, samples


def power_grid(need: float) -> np.ndarray:
    """The ``pA`` values above ``need`` at which designs are compared."""
    return np.linspace(need, 1.0, POWER_GRID + 1)[1:]


@cache
def _plan(n: int, alpha: float, need: float, first: int) -> SequentialDesign:
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    if first < 1 or n < first:
        raise ValueError(f"the first look must be between 1 and n = {n} samples, got {first}")
    grid = power_grid(need)
    reference = SequentialDesign.fixed(n, alpha, need).operating(grid)[0]
    step = max(1, first // 5)
    for n_max in range(n, 4 * n + 1, step):
        design = SequentialDesign.geometric(first, n_max, alpha, need)
        if (design.operating(grid)[0] >= reference - TOLERANCE).all():
            return design
    raise ValueError(f"no sequential design up to {4 * n} samples matches fixed n = {n} at need {need}")
