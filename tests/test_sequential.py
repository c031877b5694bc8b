"""Sequential CERTIFY: its exact power against fixed-n CERTIFY's, its error rate, its cost."""

import numpy as np
import pytest
import torch
from scipy.stats import binom, norm
from statsmodels.stats.proportion import proportion_confint

from mrcert.core.camera_motion import CameraMotionSmoothing
from mrcert.core.sampling import SmoothedClassifier, image_generator
from mrcert.core.sequential import TOLERANCE, PredictDesign, SequentialDesign, predict_grid
from tests.test_smoothing import Constant, tiny_sample


class Simulated(SmoothedClassifier):
    """The smoothed classifier with its base votes simulated: class 1 with probability ``p``
    per sample (no rendering), so the real CERTIFY code runs on thousands of streams."""

    def __init__(self, p: float, seed: int, sigma: float = 1.0):
        super().__init__(None, CameraMotionSmoothing(("tz",), (sigma,)), 2)
        self.p, self.rng = p, np.random.default_rng(seed)

    def sample_counts(self, render, n, generator, center=None):
        ones = int((self.rng.random(n) < self.p).sum())
        return np.array([n - ones, ones])


def fixed_power(p: np.ndarray, n: int, alpha: float, need: float) -> np.ndarray:
    """P(fixed-n CERTIFY certifies): P(Binomial(n, p) >= k) for the smallest count k whose
    Clopper-Pearson lower bound (statsmodels' exact interval, one-sided) reaches ``need``."""
    counts = np.arange(n + 1)
    lower = proportion_confint(counts, n, alpha=2 * alpha, method="beta")[0]
    k = int(counts[np.nan_to_num(lower) >= need][0])
    return binom.sf(k - 1, n, p)


@pytest.mark.parametrize(("ratio", "alpha"), [(0.5, 0.01), (1.0, 0.01), (2.0, 0.01), (1.0, 0.001)])
def test_sequential_certifies_at_least_as_often_as_fixed_n_at_every_pa(ratio, alpha):
    """Sequential CERTIFY loses no power against fixed n at any pA (an anytime-valid confidence
    sequence certifies r = sigma with probability 0.32 at pA = 0.88 where fixed n = 1000 does
    with 0.87). Exact power on a grid finer than the one the
    design was planned on; the reference is fixed-n power from statsmodels' interval."""
    need = norm.cdf(ratio)
    design = SequentialDesign.plan(1000, alpha, need, 50)
    grid = np.linspace(need, 1.0, 1999)[1:]
    sequential, samples = design.operating(grid)
    fixed = fixed_power(grid, 1000, alpha, need)
    assert (sequential >= fixed - 0.01).all(), grid[np.argmin(sequential - fixed)]
    # The exact probability of a wrong certificate at the threshold (and below it) is <= alpha.
    below = np.linspace(0.5, need, 50)
    assert (design.operating(below)[0] <= alpha).all()
    # And it is cheap where most test images are: a confident base classifier.
    assert design.operating(0.999)[1][0] <= (150 if ratio <= 1 else 600)
    assert samples.max() <= design.n_max


def test_the_exact_power_and_cost_agree_with_the_certify_code_on_simulated_streams():
    """The dynamic programme against Monte Carlo through SmoothedClassifier.certify_sequential."""
    alpha, radius, streams = 0.01, 1.0, 600
    design = SequentialDesign.plan(1000, alpha, norm.cdf(radius), 50)
    for p in (0.86, 0.9, 0.97):
        certs = [
            Simulated(p, seed).certify_sequential(None, 100, 1000, alpha, radius, 50, image_generator(0, seed))
            for seed in range(streams)
        ]
        power, cost = design.operating(p)
        certified = np.mean([c.prediction == 1 and c.radius >= radius for c in certs])
        assert abs(certified - power[0]) <= 4 * np.sqrt(power[0] * (1 - power[0]) / streams) + 1e-9
        drawn = np.array([c.n for c in certs], float)
        assert abs(drawn.mean() - cost[0]) <= 4 * drawn.std() / np.sqrt(streams) + 1e-9


def test_fixed_n_certify_matches_its_exact_power():
    """The one-look design is fixed-n CERTIFY: Monte Carlo through SmoothedClassifier.certify."""
    alpha, radius, p, streams = 0.01, 1.0, 0.86, 600
    certified = np.mean(
        [
            Simulated(p, seed).certify(None, 100, 1000, alpha, image_generator(0, seed)).radius >= radius
            for seed in range(streams)
        ]
    )
    power = SequentialDesign.fixed(1000, alpha, norm.cdf(radius)).operating(p)[0][0]
    assert power == pytest.approx(fixed_power(np.array(p), 1000, alpha, norm.cdf(radius)), abs=1e-12)
    assert abs(certified - power) <= 4 * np.sqrt(power * (1 - power) / streams)


@pytest.mark.parametrize("p", [norm.cdf(1.0), 0.9, 0.99])
def test_the_reported_bound_exceeds_the_true_pa_with_probability_at_most_alpha(p):
    """Monte Carlo type-I error: at the threshold (p = Phi(1)) certifying r = sigma is the
    error; above it, a reported pA_lower above the true pA is (the radius would be too large).
    alpha = 0.05 so that the error rate is measurable with 1,500 streams."""
    alpha, streams = 0.05, 1500
    certs = [
        Simulated(p, seed).certify_sequential(None, 100, 1000, alpha, 1.0, 50, image_generator(0, seed))
        for seed in range(streams)
    ]
    errors = np.mean([c.prediction == 1 and c.p_a_lower > p for c in certs])
    assert errors <= alpha + 3 * np.sqrt(alpha * (1 - alpha) / streams)


def test_sequential_certificates_stop_at_the_first_look_on_a_sure_image_whatever_the_batch():
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    smoothed, render = SmoothedClassifier(Constant(2), dist, 4, batch_size=64), tiny_sample().renderer()
    cert = smoothed.certify_sequential(render, 100, 1000, 0.01, 0.1, 50, image_generator(0, 0))
    design = SequentialDesign.plan(1000, 0.01, norm.cdf(1.0), 50)
    assert cert.prediction == 2 and cert.count_a == cert.n == design.looks[0] == 50
    assert cert.p_a_lower == pytest.approx(design.levels[0] ** (1 / 50), rel=1e-12)  # Clopper-Pearson at 50/50
    assert cert.radius == pytest.approx(0.1 * norm.ppf(cert.p_a_lower), rel=1e-12) and cert.radius >= 0.1
    # Batch size does not change where it stops or what it returns.
    other = SmoothedClassifier(Constant(2), dist, 4, batch_size=7)
    assert other.certify_sequential(render, 100, 1000, 0.01, 0.1, 50, image_generator(0, 0)) == cert


class Noisy(torch.nn.Module):
    """Votes class 1 with probability 0.6 whatever the image (its own seeded generator)."""

    def __init__(self):
        super().__init__()
        self.g = torch.Generator().manual_seed(0)

    def forward(self, x):
        out = torch.zeros(len(x), 2)
        out[torch.arange(len(x)), (torch.rand(len(x), generator=self.g) < 0.6).long()] = 1.0
        return out


def test_sequential_stops_early_when_the_radius_is_out_of_reach():
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    smoothed = SmoothedClassifier(Noisy(), dist, 2, batch_size=100)
    cert = smoothed.certify_sequential(tiny_sample().renderer(), 100, 1000, 0.01, 0.1, 50, image_generator(0, 1))
    assert cert.n <= 100 and cert.radius < 0.1  # pA = 0.6 is far below Phi(1) = 0.84: no need to draw 1,000


def test_a_design_refuses_looks_it_cannot_make():
    with pytest.raises(ValueError, match="first look"):
        SequentialDesign.plan(100, 0.01, 0.84, 500)


# --- sequential PREDICT ----------------------------------------------------------------------


class Voting(SmoothedClassifier):
    """The smoothed classifier with its votes simulated: classes 0, 1, 2 with probabilities
    ``pA, pB`` and the rest per sample, so the real PREDICT code runs on thousands of streams."""

    def __init__(self, pa: float, pb: float, seed: int):
        super().__init__(None, CameraMotionSmoothing(("tz",), (0.1,)), 3)
        self.p, self.rng = np.array([pa, pb, max(0.0, 1 - pa - pb)]), np.random.default_rng(seed)

    def sample_counts(self, render, n, generator, center=None):
        return self.rng.multinomial(n, self.p / self.p.sum())


def test_fixed_n_predict_as_a_design_is_cohens_test():
    """The one-look design decides exactly as Cohen's PREDICT (SciPy's two-sided binomial test
    of the top two counts), for every split of up to 30 votes."""
    design = PredictDesign.fixed(30, 0.01)
    for a in range(31):
        for b in range(31 - a):
            counts = np.array([a, b, 30 - a - b])
            assert design.decide(counts, 0) == SmoothedClassifier.decide(counts, 0.01)


@pytest.mark.parametrize(("n", "alpha"), [(100, 0.01), (100, 0.001), (200, 0.01)])
def test_sequential_predict_is_wrong_at_most_alpha_and_abstains_at_most_tolerance_more(n, alpha):
    """Exact, on the grid of top-two probabilities and on a finer one: the class returned is not
    the top class with probability at most alpha (at a tie either counts as wrong), and it
    abstains at most TOLERANCE more often than fixed-n PREDICT. The same looks each at the full
    alpha (no split) break the first: at a tie they answer more often than alpha."""
    design = PredictDesign.plan(n, alpha, 20)
    pa, pb = predict_grid()
    won, lost, abstained, _ = design.operating(pa, pb)
    fixed = PredictDesign.fixed(n, alpha).operating(pa, pb)
    tie = pa == pb  # at a tie either class returned is wrong
    assert (lost <= alpha + 1e-12).all() and (won[tie] + lost[tie] <= alpha + 1e-12).all()
    assert (abstained <= fixed[2] + TOLERANCE).all()
    assert sum(design.levels) <= alpha * (1 + 1e-12)
    fine = np.linspace(0.3, 0.5, 21)
    assert (sum(design.operating(fine, fine)[:2]) <= alpha + 1e-12).all()
    unsplit = PredictDesign(design.looks, (alpha,) * len(design.looks))
    assert sum(unsplit.operating(0.5, 0.5)[:2])[0] > alpha


def test_sequential_predict_agrees_with_its_exact_operating_characteristics_on_simulated_streams():
    """The dynamic programme against Monte Carlo through SmoothedClassifier.predict_sequential."""
    streams, design = 800, PredictDesign.plan(100, 0.01, 20)
    for pa, pb in ((0.95, 0.05), (0.6, 0.4), (0.5, 0.5)):  # two classes, as the programme models
        runs = [Voting(pa, pb, seed).predict_sequential(None, 100, 0.01, 20, None) for seed in range(streams)]
        won, lost, abstained, samples = (v[0] for v in design.operating(pa, pb))
        for value, share in (
            (won, np.mean([c == 0 for c, _ in runs])),
            (abstained, np.mean([c == -1 for c, _ in runs])),
        ):
            assert abs(share - value) <= 4 * np.sqrt(value * (1 - value) / streams) + 1e-9
        drawn = np.array([votes.sum() for _, votes in runs], float)
        assert (
            set(drawn) <= set(design.looks) and abs(drawn.mean() - samples) <= 4 * drawn.std() / np.sqrt(streams) + 0.1
        )


def test_sequential_predict_stops_at_the_first_look_on_a_sure_image_whatever_the_batch():
    """A base classifier that always answers 2: a fifth of fixed n's samples, the same answer,
    whatever the batch size."""
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    render = tiny_sample().renderer()
    answers = [
        SmoothedClassifier(Constant(2), dist, 4, batch_size=b).predict_sequential(
            render, 100, 0.01, 20, image_generator(0, 0)
        )
        for b in (7, 64)
    ]
    assert [(c, v.tolist()) for c, v in answers] == [(2, [0, 0, 20, 0])] * 2


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["task=smooth", "task.sequential=true", "task.decision=vote"],
            "task.sequential=True is not allowed: false with",
        ),
        (["task=attack", "task.sequential=true", "task.n=1000"], "task.n=1000 is not allowed: at most 400"),
        (["task=smooth", "task.sequential=true", "task.look=200"], "task.look=200 is not allowed: an integer in"),
    ],
)
def test_sequential_predict_settings_that_cannot_work_are_refused_in_one_line(overrides, message):
    from mrcert.errors import ConfigError
    from mrcert.infra.config import validate
    from tests.conftest import compose_cfg

    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        validate(compose_cfg(overrides))


def test_the_planned_predict_design_is_the_one_the_docs_describe():
    """docs/method.md §7's looks and its first row: n = 100, alpha = 0.01, looks from 20."""
    design = PredictDesign.plan(100, 0.01, 20)
    assert design.looks == (20, 40, 80, 108)
    won, _, abstained, samples = design.operating([1.0, 0.9], [0.0, 0.05])
    assert samples[0] == pytest.approx(20.0) and round(samples[1], 1) == 25.4 and (abstained <= 1e-12).all()
