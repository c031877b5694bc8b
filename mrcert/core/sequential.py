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

from collections.abc import Callable
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
        """Looks at ``first * 2^k`` below ``n_max`` and at ``n_max`` (:func:`geometric_looks`);
        a look of t samples can certify only when even t successes out of t clear ``need``."""
        looks, levels = geometric_looks(
            first, n_max, alpha, lambda t, level: lower_confidence_bound(t, t, level) >= need
        )
        return cls(looks, levels, FUTILITY_SHARE * alpha, need)

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


def geometric_looks(
    first: int, n_max: int, alpha: float, decides: Callable[[int, float], bool]
) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """Looks at ``first * 2^k`` below ``n_max`` and at ``n_max``, and their levels:
    :data:`EARLY_SHARE` of alpha split evenly over the early looks at which unanimous samples
    ``decides(t, level)`` (a look that cannot gives its share to the others, until none is
    dropped), the rest at the last look."""
    early = []
    t = first
    while t < n_max:
        early.append(t)
        t *= 2
    able = list(early)
    while able:
        share = EARLY_SHARE * alpha / len(able)
        kept = [t for t in able if decides(t, share)]
        if kept == able:
            break
        able = kept
    share = EARLY_SHARE * alpha / len(able) if able else 0.0
    levels = tuple(share if t in able else 0.0 for t in early)
    return (*early, n_max), (*levels, alpha - share * len(able))


def check_plan(n: int, alpha: float, first: int) -> None:
    """Refuse a level outside (0, 1) or a first look outside [1, n]."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    if first < 1 or n < first:
        raise ValueError(f"the first look must be between 1 and n = {n} samples, got {first}")


def smallest_last_look(n: int, first: int, design: Callable, matches: Callable):
    """The design ``design(n_max)`` of the smallest last look ``n_max >= n`` (in steps of
    ``first / 5``, up to ``4 n``) that ``matches``; None when none does."""
    for n_max in range(n, 4 * n + 1, max(1, first // 5)):
        candidate = design(n_max)
        if matches(candidate):
            return candidate
    return None


def power_grid(need: float) -> np.ndarray:
    """The ``pA`` values above ``need`` at which designs are compared."""
    return np.linspace(need, 1.0, POWER_GRID + 1)[1:]


@cache
def _plan(n: int, alpha: float, need: float, first: int) -> SequentialDesign:
    check_plan(n, alpha, first)
    grid = power_grid(need)
    reference = SequentialDesign.fixed(n, alpha, need).operating(grid)[0]
    design = smallest_last_look(
        n,
        first,
        lambda n_max: SequentialDesign.geometric(first, n_max, alpha, need),
        lambda d: (d.operating(grid)[0] >= reference - TOLERANCE).all(),
    )
    if design is None:
        raise ValueError(f"no sequential design up to {4 * n} samples matches fixed n = {n} at need {need}")
    return design


# --- sequential PREDICT ---------------------------------------------------------------------


def _two_sided_critical(m: int, level: float) -> int:
    """Smallest count ``a`` of the top class among ``m`` top-two votes whose two-sided binomial
    test against 1/2 (Cohen's PREDICT) rejects at ``level``: ``2 P(X >= a) <= level`` with ``a >
    m / 2``; ``m + 1`` when none does (or at level 0)."""
    if level <= 0 or m == 0:
        return m + 1
    a = np.arange(m // 2 + 1, m + 1)
    passes = np.minimum(1.0, 2.0 * binom.sf(a - 1, m, 0.5)) <= level
    return int(a[passes][0]) if passes.any() else m + 1


@dataclass(frozen=True)
class PredictDesign:
    """Sequential PREDICT: Cohen's PREDICT (the top class of the votes, or ABSTAIN unless the
    two-sided binomial test of the top two counts rejects equality) checked at a few looks
    ``looks`` (sample counts), each at its own level ``levels`` (summing to at most alpha). It
    stops at the first look that decides a class and abstains when the last look does not.

    Every look is Cohen's test at its level, so by the union bound the class returned is the
    smoothed classifier's with probability at least ``1 - alpha`` whatever the stop, as for
    fixed n. :meth:`operating` gives the exact probabilities of returning the top class, the
    other one and abstaining, and the expected samples, for votes of two classes with
    probabilities ``pA >= pB`` (the rest on classes that never come second): fixed-n PREDICT is
    the design with one look."""

    looks: tuple[int, ...]
    levels: tuple[float, ...]

    @classmethod
    def fixed(cls, n: int, alpha: float) -> PredictDesign:
        return cls((n,), (alpha,))

    @classmethod
    def geometric(cls, first: int, n_max: int, alpha: float) -> PredictDesign:
        """Looks at ``first * 2^k`` below ``n_max`` and at ``n_max`` (:func:`geometric_looks`);
        a look of t votes can decide only when t unanimous votes pass the test."""
        return cls(*geometric_looks(first, n_max, alpha, lambda t, level: _two_sided_critical(t, level) <= t))

    @classmethod
    def plan(cls, n: int, alpha: float, first: int) -> PredictDesign:
        """The geometric design whose last look is the smallest ``n_max >= n`` (in steps of
        ``first / 5``) that abstains at most :data:`TOLERANCE` more often than fixed-n PREDICT at
        every pair of a grid of top-two probabilities."""
        return _plan_predict(int(n), float(alpha), int(first))

    @cached_property
    def critical(self) -> list[np.ndarray]:
        """Per look: for each number ``m`` of top-two votes (0..t), the count that decides."""
        return [
            np.array([_two_sided_critical(m, level) for m in range(t + 1)])
            for t, level in zip(self.looks, self.levels, strict=True)
        ]

    def decide(self, counts: np.ndarray, k: int) -> int | None:
        """After look ``k``: the index of the class decided, ABSTAIN (-1) at the last look, or None
        (draw on). The top two as Cohen's PREDICT orders them (ties to the lower index)."""
        top2 = np.argsort(counts, kind="stable")[::-1][:2]
        n_a, n_b = int(counts[top2[0]]), int(counts[top2[1]]) if len(counts) > 1 else 0
        if n_a >= self.critical[k][n_a + n_b]:
            return int(top2[0])
        return -1 if k == len(self.looks) - 1 else None

    def operating(self, pa: np.ndarray, pb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Exact probabilities of returning A, returning B and abstaining, and the expected
        samples, for each pair ``(pA, pB)``: the joint distribution of the two counts is carried
        through the looks (trinomial increments), each look removing the mass it decides."""
        pa, pb = np.atleast_1d(np.asarray(pa, float)), np.atleast_1d(np.asarray(pb, float))
        alive = np.ones((len(pa), 1, 1))  # P(count A = i, count B = j, not stopped), i + j <= t
        won, lost, samples, previous = np.zeros(len(pa)), np.zeros(len(pa)), np.zeros(len(pa)), 0
        for k, t in enumerate(self.looks):
            d = t - previous
            i, j = np.meshgrid(np.arange(d + 1), np.arange(d + 1), indexing="ij")
            step = _trinomial(d, i, j, pa, pb)
            alive = np.clip(fftconvolve(alive, step, axes=(1, 2)), 0.0, None)
            a, b = np.meshgrid(np.arange(t + 1), np.arange(t + 1), indexing="ij")
            m = np.minimum(a + b, t)
            crit = self.critical[k][m]
            to_a = (a + b <= t) & (a >= b) & (a >= crit)
            to_b = (a + b <= t) & (b > a) & (b >= crit)
            won += alive[:, to_a].sum(1)
            lost += alive[:, to_b].sum(1)
            last = k == len(self.looks) - 1
            stops = (to_a | to_b) | last
            samples += t * alive[:, stops & (a + b <= t)].sum(1)
            alive = np.where(stops, 0.0, alive)
            previous = t
        return won, lost, np.clip(1.0 - won - lost, 0.0, 1.0), samples


def _trinomial(d: int, i: np.ndarray, j: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """P(i votes for A, j for B in d draws) for each pair, shape (pairs, d + 1, d + 1)."""
    from scipy.special import gammaln

    ok = i + j <= d
    rest = np.where(ok, d - i - j, 0)
    log_c = gammaln(d + 1) - gammaln(i + 1) - gammaln(j + 1) - gammaln(rest + 1)
    pc = np.clip(1.0 - pa - pb, 0.0, 1.0)
    logs = np.broadcast_to(log_c, (len(pa), *log_c.shape)).copy()
    for count, p in ((i, pa), (j, pb), (rest, pc)):
        with np.errstate(divide="ignore", invalid="ignore"):
            term = count[None] * np.log(p)[:, None, None]
        logs += np.where(count[None] == 0, 0.0, term)  # p^0 = 1, also for p = 0
    return np.where(ok[None], np.exp(logs), 0.0)


def predict_grid() -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``pA >= pB``, ``pA + pB <= 1``, at which PREDICT designs are compared."""
    pairs = [(a, b) for a in np.linspace(0.05, 1.0, 20) for b in np.linspace(0.0, a, 11) if a + b <= 1.0 + 1e-12]
    pa, pb = np.array(pairs).T
    return pa, np.minimum(pb, 1.0 - pa)


@cache
def _plan_predict(n: int, alpha: float, first: int) -> PredictDesign:
    check_plan(n, alpha, first)
    pa, pb = predict_grid()
    reference = PredictDesign.fixed(n, alpha).operating(pa, pb)[2]
    design = smallest_last_look(
        n,
        first,
        lambda n_max: PredictDesign.geometric(first, n_max, alpha),
        lambda d: (d.operating(pa, pb)[2] <= reference + TOLERANCE).all(),
    )
    if design is None:
        raise ValueError(f"no sequential PREDICT design up to {4 * n} samples matches fixed n = {n}")
    return design
