"""The anytime-valid confidence sequence and the sequential certificate."""

import numpy as np
import pytest
import torch
from scipy.stats import norm

from mrcert.core.sequential import BetaBinomialCS
from mrcert.core.smoothing import (
    SmoothedClassifier,
    SmoothingDistribution,
    image_generator,
    lower_confidence_bound,
)
from tests.test_smoothing import Constant, tiny_sample


def test_interval_contains_the_estimate_and_shrinks():
    cs = BetaBinomialCS(0.01)
    for s, t in ((50, 100), (990, 1000), (1, 10), (10, 10)):
        assert cs.lower(s, t) <= s / t <= cs.upper(s, t)
    assert cs.lower(0, 100) == 0.0 and cs.upper(100, 100) == 1.0
    assert cs.lower(900, 1000) > cs.lower(90, 100)
    # At the threshold the martingale equals 1 / alpha.
    lo = cs.lower(900, 1000)
    assert cs.log_martingale(900, 1000, lo) == pytest.approx(np.log(100), abs=1e-8)
    # Anytime validity costs width: never tighter than the fixed-n Clopper-Pearson bound.
    assert cs.lower(990, 1000) <= lower_confidence_bound(990, 1000, 0.01)


@pytest.mark.parametrize("p", [0.6, 0.9, 0.99])
def test_coverage_holds_at_every_look_simultaneously(p):
    """Simulated Bernoulli streams: the fraction that ever leave the sequence stays below alpha."""
    alpha, streams, looks = 0.05, 400, np.arange(25, 2001, 25)
    rng = np.random.default_rng(int(p * 1000))
    cs = BetaBinomialCS(alpha)
    sums = np.cumsum(rng.random((streams, looks[-1])) < p, axis=1)[:, looks - 1]
    missed = 0
    for row in sums:
        missed += any(
            not (cs.lower(int(s), int(t)) <= p <= cs.upper(int(s), int(t))) for s, t in zip(row, looks, strict=True)
        )
    # Expected rate <= alpha; allow three binomial standard deviations of sampling error.
    assert missed / streams <= alpha + 3 * np.sqrt(alpha * (1 - alpha) / streams)


class Simulated(SmoothedClassifier):
    """The smoothed classifier with its base votes simulated: class 1 with probability ``p``
    per sample (no rendering), so the real stopping code runs on thousands of streams."""

    def __init__(self, p: float, seed: int):
        super().__init__(None, SmoothingDistribution(("tz",), (1.0,)), 2)
        self.p, self.rng = p, np.random.default_rng(seed)

    def sample_counts(self, render, n, generator, center=None):
        ones = int((self.rng.random(n) < self.p).sum())
        return np.array([n - ones, ones])


def test_sequential_decision_error_rate_on_simulated_streams():
    """Streams whose true p is just below what the radius needs: certifying it is an error."""
    alpha, radius, look, n_max = 0.05, 1.0, 50, 3000
    p_true = norm.cdf(radius) - 0.01
    certs = [
        Simulated(p_true, seed).certify_sequential(None, 100, n_max, alpha, radius, look, image_generator(0, seed))
        for seed in range(400)
    ]
    errors = sum(c.prediction == 1 and c.radius >= radius for c in certs)
    assert errors / 400 <= alpha
    assert np.mean([c.n for c in certs]) < n_max  # it does stop early when the answer is clear ("cannot be reached")


def test_sequential_certificates_follow_their_sequence_and_save_samples():
    dist = SmoothingDistribution(("tz",), (0.1,))
    smoothed, render = SmoothedClassifier(Constant(2), dist, 4, batch_size=64), tiny_sample().renderer()
    cert = smoothed.certify_sequential(render, 100, 1000, 0.01, 0.1, 100, image_generator(0, 0))
    cs = BetaBinomialCS(0.01)
    assert cert.prediction == 2 and cert.count_a == cert.n and cert.n < 1000
    assert cert.p_a_lower == cs.lower(cert.n, cert.n) and cert.radius == 0.1 * norm.ppf(cert.p_a_lower)
    assert cert.radius >= 0.1  # it stopped because the requested radius was certified
    # Batch size does not change where it stops or what it returns.
    other = SmoothedClassifier(Constant(2), dist, 4, batch_size=7)
    assert other.certify_sequential(render, 100, 1000, 0.01, 0.1, 100, image_generator(0, 0)) == cert


def test_sequential_keeps_sampling_until_a_clear_margin_is_certified():
    """Streams whose true p is clearly above what the radius needs (0.90 vs 0.84) are certified
    at that radius: it stops on the lower confidence bound, never on the point estimate (which
    clears the need at the first look while the bound does not yet)."""
    alpha, radius, look, n_max = 0.05, 1.0, 50, 3000
    certs = [
        Simulated(0.9, seed).certify_sequential(None, 100, n_max, alpha, radius, look, image_generator(0, seed))
        for seed in range(200)
    ]
    certified = [c.prediction == 1 and c.radius >= radius for c in certs]
    assert np.mean(certified) >= 0.95
    assert np.mean([c.n for c in certs]) < n_max / 2  # and still stops early


class Noisy(torch.nn.Module):
    """Votes class 1 with probability 0.6 whatever the image (its own seeded generator)."""

    def __init__(self):
        super().__init__()
        self.g = torch.Generator().manual_seed(0)

    def forward(self, x):
        out = torch.zeros(len(x), 2)
        out[torch.arange(len(x)), (torch.rand(len(x), generator=self.g) < 0.6).long()] = 1.0
        return out


def test_sequential_abstains_or_stops_when_the_radius_is_out_of_reach():
    dist = SmoothingDistribution(("tz",), (0.1,))
    smoothed = SmoothedClassifier(Noisy(), dist, 2, batch_size=100)
    cert = smoothed.certify_sequential(tiny_sample().renderer(), 100, 5000, 0.01, 0.25, 100, image_generator(0, 1))
    cs = BetaBinomialCS(0.01)
    assert cs.upper(cert.count_a, cert.n) < norm.cdf(2.5) and cert.n < 5000
    assert cert.radius < 0.25
