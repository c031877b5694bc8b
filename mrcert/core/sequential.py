"""An anytime-valid confidence sequence for a Bernoulli mean, for sequential certification.

The beta-binomial mixture (Robbins 1970; Howard et al. 2021): with a Beta(a, b) mixing
distribution,

    M_t(p) = B(a + S_t, b + t - S_t) / B(a, b) / (p^S_t (1 - p)^(t - S_t))

is a nonnegative martingale with mean 1 under the true mean p, so by Ville's inequality
``P(exists t: M_t(p) >= 1 / alpha) <= alpha``. The set ``{p: M_t(p) < 1 / alpha}`` is an
interval that contains p at *every* t simultaneously with probability >= 1 - alpha; its ends
are valid bounds at any data-dependent stopping time. (Recomputing a fixed-n Clopper-Pearson
bound after every batch has no such guarantee; docs/method.md §6.)
"""

from __future__ import annotations

import math

from scipy.optimize import brentq
from scipy.special import betaln


class BetaBinomialCS:
    """Confidence sequence ``{p : log M_t(p) < log(1 / alpha)}`` for successes ``s`` in ``t`` trials."""

    def __init__(self, alpha: float, a: float = 1.0, b: float = 1.0):
        if not 0 < alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {alpha}")
        self.alpha, self.a, self.b = alpha, a, b
        self.threshold = math.log(1.0 / alpha)

    def log_martingale(self, s: int, t: int, p: float) -> float:
        """``log M_t(p)``."""
        mix = betaln(self.a + s, self.b + t - s) - betaln(self.a, self.b)
        like = (s * math.log(p) if s else 0.0) + ((t - s) * math.log1p(-p) if t - s else 0.0)
        return mix - like

    def _edge(self, s: int, t: int, lo: float, hi: float) -> float:
        """The p in [lo, hi] where log M_t crosses the threshold (``f(lo)`` and ``f(hi)`` differ in sign)."""
        return brentq(lambda p: self.log_martingale(s, t, p) - self.threshold, lo, hi, xtol=1e-14, rtol=1e-14)

    def lower(self, s: int, t: int) -> float:
        """Lower end of the interval at time ``t`` (0 when no p below the estimate is excluded)."""
        if t == 0 or s == 0:
            return 0.0
        p_hat = s / t
        tiny = 1e-300
        if self.log_martingale(s, t, tiny) < self.threshold:
            return 0.0
        # M_t is smallest (<= 1) at the estimate, so the edge lies between 0 and it.
        return self._edge(s, t, tiny, min(p_hat, 1 - 1e-16))

    def upper(self, s: int, t: int) -> float:
        """Upper end of the interval at time ``t``."""
        return 1.0 - self.lower(t - s, t)
