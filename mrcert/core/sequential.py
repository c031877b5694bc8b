"""Sequential CERTIFY: a group-sequential test of ``pA >= need`` that is as powerful as fixed-n
CERTIFY and stops far earlier on clear images, with no separate class guess.

CERTIFY at a radius ``r`` decides one question about the top class's probability ``pA``: is
``pA >= need = Phi(r / sigma)``? Fixed-n CERTIFY guesses the top class on ``n0`` samples, draws
``n`` more and certifies when the one-sided Clopper-Pearson lower bound of the guessed class's
count at level ``alpha`` reaches ``need``. A :class:`SequentialDesign` checks the votes at a few
*looks* instead, spaced geometrically (``first``, ``2 first``, ``4 first``, ... and a last look
at ``n_max``), and needs no guess:

* at look ``k`` (``t_k`` samples) it certifies the class with the most votes once their count
  reaches ``certify_k``, the smallest count whose Clopper-Pearson lower bound at level
  ``alpha_k`` reaches ``need``; that bound is the certificate's ``pA_lower``. Because
  ``need >= 1/2``, ``certify_k > t_k / 2``: at most one class can reach it, so guessing and
  estimating on the same samples costs only a small, exact correction (below);
* it stops, certifying nothing, when the Clopper-Pearson *upper* bound of the most votes at level
  :data:`FUTILITY` is below ``need`` (no class can reach ``r``); this never makes a wrong
  certificate;
* a wrong certificate at look ``k`` is either the top class's bound above its ``pA``
  (probability at most ``alpha_k``) or another class reaching ``certify_k``; since no two
  classes reach it together, that is at most ``P(Binomial(t_k, 1/2) >= certify_k)``
  (:meth:`SequentialDesign.error_bound`). The levels are scaled so that these terms add up to
  at most ``alpha``, so by the union bound the reported
  bound exceeds the certified class's probability with probability at most ``alpha``, whatever
  the stopping rule: the radius reported at the stop is valid, as for fixed n;
* ``n_max`` is the smallest sample count ``>= n`` at which, on a grid of ``pA`` above ``need``,
  the probability of certifying ``r`` is at least fixed-n CERTIFY's minus :data:`TOLERANCE`
  (fixed n's with its guess on ``n0`` samples, :func:`guessed`, for votes of two classes) -- the
  few borderline images draw a little more than ``n`` so that no image is less likely to be
  certified than under the paper's procedure.

Every probability here is exact: :meth:`SequentialDesign.operating` runs the distribution of the
top class's count through the looks (binomial increments, stopped mass removed), for votes of
two classes with any ``pA``. A fixed-n CERTIFY is the design with one look
(:meth:`SequentialDesign.fixed`; times :func:`guessed`, the chance its guess is right), so both
procedures' power and cost come from the same function (docs/method.md §7 plots them).

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

CERTIFY_EARLY_SHARE = 0.2
"""Share of ``alpha`` that sequential CERTIFY spends on its early looks (the rest, less the
correction for other classes, goes to the last look)."""

FUTILITY = 0.05
"""Level of each look's futility bound (an upper bound on the most votes' probability): it
makes no wrong certificate, and the power it costs is checked against fixed n's."""

PREDICT_EARLY_SHARE = 0.1
"""Share of ``alpha`` that sequential PREDICT spends on its early looks (the rest at the last)."""

TOLERANCE = 0.005
"""How much less likely than the fixed-n procedure (to certify; to answer) a design may be."""

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


def _early_looks(first: int, n_max: int) -> list[int]:
    """The looks before the last: ``first * 2^k`` below ``n_max``."""
    looks, t = [], first
    while t < n_max:
        looks.append(t)
        t *= 2
    return looks


def _certify_count(t: int, level: float, need: float) -> int:
    """The smallest count of ``t`` votes whose lower bound at ``level`` reaches ``need`` (t + 1:
    none, or level 0)."""
    return _first_count(t, lower_confidence_bound, level, need) if level > 0 else t + 1


@dataclass(frozen=True)
class SequentialDesign:
    """Looks ``looks`` (sample counts, increasing), the Clopper-Pearson level of each look's
    lower bound (``levels``; 0 where the look cannot certify), the level of the futility bound
    (0: none) and the probability ``need >= 1/2`` that the radius asks. A planned design makes a
    wrong certificate with probability at most alpha (:meth:`error_bound`)."""

    looks: tuple[int, ...]
    levels: tuple[float, ...]
    futility: float
    need: float

    @classmethod
    def fixed(cls, n: int, alpha: float, need: float) -> SequentialDesign:
        """Fixed-n CERTIFY (Cohen et al.) as a design with one look, its class guessed
        beforehand (so :meth:`operating` is its power when the guess is right)."""
        return cls((n,), (alpha,), 0.0, need)

    @classmethod
    def geometric(cls, first: int, n_max: int, alpha: float, need: float) -> SequentialDesign:
        """Looks at ``first * 2^k`` below ``n_max`` and at ``n_max``. The early looks spend
        :data:`CERTIFY_EARLY_SHARE` of alpha (at most half of :data:`TOLERANCE`: just above
        ``need`` either procedure certifies about as often as its last look's level, and that
        gap must stay within the tolerance), halving from one look to the next: half of it at
        the first look at which unanimous votes certify at that level, a quarter at the next,
        ... and the rest at the last early look (a look of twice the samples at half the level
        certifies unanimous votes whenever its predecessor does). Looks before it cannot
        certify (level 0). The last look takes the rest of alpha; then every level is scaled by
        the largest factor (1 when other classes cannot matter) that keeps :meth:`error_bound`
        at most alpha."""
        early = _early_looks(first, n_max)
        budget = min(CERTIFY_EARLY_SHARE * alpha, TOLERANCE / 2)
        able = [t for t in early if lower_confidence_bound(t, t, budget / 2) >= need]
        shares = [budget / 2 ** (i + 1) for i in range(len(able))]
        if shares:
            shares[-1] *= 2  # the last early look takes the remainder
        levels = np.array([0.0] * (len(early) - len(able)) + shares + [alpha - sum(shares)])

        def scaled(factor: float) -> SequentialDesign:
            return cls((*early, n_max), tuple(float(x) for x in factor * levels), FUTILITY, need)

        lo, hi = 0.0, 1.0  # the largest factor whose design's error bound is at most alpha
        if scaled(hi).error_bound() <= alpha:
            return scaled(hi)
        for _ in range(40):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if scaled(mid).error_bound() <= alpha else (lo, mid)
        return scaled(lo)

    @classmethod
    def plan(cls, n0: int, n: int, alpha: float, need: float, first: int) -> SequentialDesign:
        """The geometric design whose last look is the smallest ``n_max >= n`` (in steps of
        ``first / 5``) that certifies the top class at least as often as fixed-n CERTIFY (its
        guess on ``n0`` samples included), less :data:`TOLERANCE`, at every ``pA`` of a grid
        above ``need``, for votes of two classes (:meth:`operating`)."""
        return _plan(int(n0), int(n), float(alpha), float(need), int(first))

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
            certify.append(_certify_count(t, level, self.need))
            if self.futility > 0 and k < last:
                futile.append(_first_count(t, upper_confidence_bound, self.futility, self.need) - 1)
            else:
                futile.append(-1)
        return np.array(certify), np.array(futile)

    def error_bound(self) -> float:
        """The probability, at most, of a wrong certificate: a reported ``pA_lower`` above the
        certified class's probability (at most alpha for a planned design). At look ``k`` let
        ``f_k = P(Binomial(t_k, 1/2) >= certify_k)``; ``certify_k > t_k / 2``, so no two
        classes reach it together, and the chance ``g(p)`` that a class of probability ``p``
        does is convex for ``p <= 1/2``. When the top class has probability at least 1/2, its
        certificate is wrong with probability at most the look's level, and the other classes
        (at most 1/2 in all) reach the count with probability at most ``max sum g = f_k``;
        when no class has 1/2, at most ``2 f_k`` (the most a convex sum reaches over
        probabilities of at most 1/2: two classes of 1/2), which is no more since ``f_k`` is
        at most the level (``need >= 1/2``). Summed over the looks (union bound)."""
        certify = self.critical[0]
        return float(
            sum(level + binom.sf(c - 1, t, 0.5) for t, c, level in zip(self.looks, certify, self.levels, strict=True))
        )

    def decide(self, counts: np.ndarray, k: int) -> tuple[bool, int | None, float]:
        """After look ``k`` with the votes ``counts`` per class: whether to stop, the class
        certified (None: none), and the lower bound on the top class's probability. The top
        class is the one with the most votes (ties to the lower index; a tie cannot certify)."""
        certify, futile = self.critical
        top = int(np.argmax(counts))
        count = int(counts[top])
        certified = count >= certify[k]
        stop = certified or count <= futile[k] or k == len(self.looks) - 1
        return bool(stop), top if certified else None, lower_confidence_bound(count, self.looks[k], self.levels[k])

    def operating(self, p: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact probabilities of certifying the top class and of certifying the other one, and
        the expected number of samples, at each ``pA`` in ``p``, for votes of two classes (the
        top one with probability ``pA``, the other ``1 - pA``; more classes can only lower the
        chance that one of the others is certified, as in :meth:`error_bound`): the
        distribution of the top class's count is carried through the looks, each look removing
        the mass that stops there."""
        p = np.atleast_1d(np.asarray(p, dtype=float))
        certify, futile = self.critical
        alive = np.ones((len(p), 1))  # P(count = s, not stopped yet), s = 0..t
        top, other, samples, previous = np.zeros(len(p)), np.zeros(len(p)), np.zeros(len(p)), 0
        for k, t in enumerate(self.looks):
            step = binom.pmf(np.arange(t - previous + 1)[None, :], t - previous, p[:, None])
            alive = np.clip(fftconvolve(alive, step, axes=1), 0.0, None)
            counts = np.arange(t + 1)
            to_top, to_other = counts >= certify[k], t - counts >= certify[k]
            stops = to_top | to_other | (np.maximum(counts, t - counts) <= futile[k]) | (k == len(self.looks) - 1)
            top += alive[:, to_top].sum(1)
            other += alive[:, to_other].sum(1)
            samples += t * alive[:, stops].sum(1)
            alive = np.where(stops, 0.0, alive)
            previous = t
        return top, other, samples


def guessed(p: np.ndarray, n0: int) -> np.ndarray:
    """The probability, at most, that fixed-n CERTIFY's ``n0`` selection samples pick the top
    class when the votes are of two classes (``pA``, ``1 - pA``): at least half of them for it
    (a tie counted as a right guess)."""
    return binom.sf(np.ceil(n0 / 2) - 1, n0, p)


def geometric_looks(
    first: int, n_max: int, alpha: float, decides: Callable[[int, float], bool]
) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """Looks at ``first * 2^k`` below ``n_max`` and at ``n_max``, and their levels:
    :data:`PREDICT_EARLY_SHARE` of alpha split evenly over the early looks at which unanimous
    samples ``decides(t, level)`` (a look that cannot gives its share to the others, until none
    is dropped), the rest at the last look."""
    early = _early_looks(first, n_max)
    able = list(early)
    while able:
        share = PREDICT_EARLY_SHARE * alpha / len(able)
        kept = [t for t in able if decides(t, share)]
        if kept == able:
            break
        able = kept
    share = PREDICT_EARLY_SHARE * alpha / len(able) if able else 0.0
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
    ``first / 5``, up to ``4 n``) that ``matches``; None when none does. Every tenth step is
    tried first; then the steps up to the first of those that matches, in order."""
    grid = range(n, 4 * n + 1, max(1, first // 5))
    hit = next((i for i in range(0, len(grid), 10) if matches(design(grid[i]))), None)
    last_tried = (len(grid) - 1) // 10 * 10
    for n_max in grid[max(0, hit - 9) : hit + 1] if hit is not None else grid[last_tried + 1 :]:
        candidate = design(n_max)
        if matches(candidate):
            return candidate
    return None


def power_grid(need: float) -> np.ndarray:
    """The ``pA`` values above ``need`` at which designs are compared."""
    return np.linspace(need, 1.0, POWER_GRID + 1)[1:]


@cache
def _plan(n0: int, n: int, alpha: float, need: float, first: int) -> SequentialDesign:
    check_plan(n, alpha, first)
    grid = power_grid(need)
    reference = guessed(grid, n0) * SequentialDesign.fixed(n, alpha, need).operating(grid)[0]
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
