"""Sequential CERTIFY: its exact power against fixed-n CERTIFY's, its error rate, its cost."""

import numpy as np
import pytest
import torch
from scipy.stats import binom, norm
from statsmodels.stats.proportion import proportion_confint

from mrcert.core.methods.base import ABSTAIN
from mrcert.core.methods.camera_motion import CameraMotionSmoothing
from mrcert.core.sampling import SmoothedClassifier, VoteCounter, image_generator
from mrcert.core.sequential import TOLERANCE, PredictDesign, SequentialDesign, predict_grid
from tests.test_smoothing import Constant, tiny_sample


class SimulatedVotes:
    """Votes drawn from class probabilities ``p`` (no model, no rendering)."""

    def __init__(self, p, seed: int):
        self.p, self.num_classes = np.asarray(p, float), len(p)
        self.rng = np.random.default_rng(seed)

    def __call__(self, render, inputs) -> np.ndarray:
        return self.rng.multinomial(len(inputs), self.p / self.p.sum())


class Simulated(SmoothedClassifier):
    """The smoothed classifier with its base votes simulated -- class 1 with probability ``p``
    per sample and class 0 otherwise, or the classes of a list ``p`` -- so the real CERTIFY code
    runs on thousands of streams."""

    def __init__(self, p, seed: int, sigma: float = 1.0):
        probs = [1 - p, p] if np.isscalar(p) else list(p)
        super().__init__(None, CameraMotionSmoothing(("tz",), (sigma,)), len(probs))
        self.votes = SimulatedVotes(probs, seed)


def fixed_power(p: np.ndarray, n: int, alpha: float, need: float) -> np.ndarray:
    """P(fixed-n CERTIFY certifies) with a right guess: P(Binomial(n, p) >= k) for the smallest
    count k whose Clopper-Pearson lower bound (statsmodels' exact interval, one-sided) reaches
    ``need``."""
    counts = np.arange(n + 1)
    lower = proportion_confint(counts, n, alpha=2 * alpha, method="beta")[0]
    k = int(counts[np.nan_to_num(lower) >= need][0])
    return binom.sf(k - 1, n, p)


@pytest.mark.parametrize(("ratio", "alpha"), [(0.5, 0.01), (1.0, 0.01), (2.0, 0.01), (1.0, 0.001)])
def test_sequential_certifies_at_least_as_often_as_fixed_n_and_is_wrong_at_most_alpha(ratio, alpha):
    """Exact, for votes of two classes, on a grid finer than the one the design was planned on:
    the top class is certified at least as often as by fixed-n CERTIFY (its guess on n0 = 100
    votes, at least half of them for the top class, times statsmodels' power), less the
    tolerance; below the threshold every certificate is wrong, and there are at most alpha of
    them; and a clear image costs the first look, a 27th of fixed n's 1,100 samples."""
    need = norm.cdf(ratio)
    design = SequentialDesign.plan(100, 1000, alpha, need, 40)
    grid = np.linspace(need, 1.0, 1999)[1:]
    top, _, samples = design.operating(grid)
    fixed = binom.sf(49, 100, grid) * fixed_power(grid, 1000, alpha, need)
    assert (top >= fixed - 0.01).all(), grid[np.argmin(top - fixed)]
    below = np.linspace(0.5, need, 50)
    wrong = sum(design.operating(below)[:2])
    assert (wrong <= alpha).all() and design.error_bound() <= alpha * (1 + 1e-12)
    first = design.looks[int(np.flatnonzero(np.array(design.levels) > 0)[0])]  # the first that can certify
    assert design.operating(1.0)[2][0] == pytest.approx(first) and (first == 40 or (ratio, alpha) != (1.0, 0.01))
    assert samples.max() <= design.n_max


def test_certifying_the_class_the_same_votes_pick_needs_the_scaled_levels():
    """At r = 0 (pA must exceed 1/2) two classes of 1/2 each are the worst case: either one
    certified is wrong. The planned design's levels are scaled for it and stay within alpha;
    the same looks with their levels summing to alpha (no scaling) do not."""
    alpha = 0.01
    design = SequentialDesign.plan(100, 1000, alpha, 0.5, 40)
    assert sum(design.operating(0.5)[:2])[0] <= alpha
    unscaled = SequentialDesign(design.looks, tuple(np.array(design.levels) * alpha / sum(design.levels)), 0.05, 0.5)
    assert sum(unscaled.operating(0.5)[:2])[0] > alpha


def test_the_exact_power_and_cost_agree_with_the_certify_code_on_simulated_streams():
    """The dynamic programme against Monte Carlo through SmoothedClassifier.certify_sequential:
    the top class certified, the other one certified (at r = 0, where it can be), the samples."""
    streams = 600
    for p, radius, alpha in ((0.86, 1.0, 0.01), (0.9, 1.0, 0.01), (0.97, 1.0, 0.01), (0.5, 0.0, 0.05)):
        design = SequentialDesign.plan(100, 1000, alpha, max(norm.cdf(radius), 0.5), 40)
        certs = [
            Simulated(p, seed).certify_sequential(None, 100, 1000, alpha, radius, 40, image_generator(0, seed))
            for seed in range(streams)
        ]
        top, other, cost = (v[0] for v in design.operating(p))
        for value, share in (
            (top, np.mean([c.prediction == 1 and c.radius >= radius for c in certs])),
            (other, np.mean([c.prediction == 0 for c in certs])),
        ):
            assert abs(share - value) <= 4 * np.sqrt(value * (1 - value) / streams) + 1e-9
        drawn = np.array([c.n for c in certs], float)
        assert abs(drawn.mean() - cost) <= 4 * drawn.std() / np.sqrt(streams) + 1e-9


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


@pytest.mark.parametrize(
    ("p", "radius"),
    [(norm.cdf(1.0), 1.0), (0.9, 1.0), (0.99, 1.0), ((0.5, 0.5), 0.0), ((0.4, 0.3, 0.3), 0.0)],
)
def test_the_reported_bound_exceeds_the_certified_class_probability_at_most_alpha(p, radius):
    """Monte Carlo error rate through the real code: a certificate whose pA_lower exceeds the
    certified class's true probability is wrong (at the threshold p = Phi(1), any certificate
    of r = sigma; at r = 0 with no class above 1/2, any certificate at all). alpha = 0.05 so
    that the error rate is measurable with 1,500 streams."""
    alpha, streams = 0.05, 1500
    probs = np.array([1 - p, p] if np.isscalar(p) else p)
    certs = [
        Simulated(p, seed).certify_sequential(None, 100, 1000, alpha, radius, 40, image_generator(0, seed))
        for seed in range(streams)
    ]
    errors = np.mean([c.prediction != ABSTAIN and c.p_a_lower > probs[c.prediction] for c in certs])
    assert errors <= alpha + 3 * np.sqrt(alpha * (1 - alpha) / streams)


def test_sequential_certificates_stop_at_the_first_look_on_a_sure_image_whatever_the_batch():
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    smoothed, render = SmoothedClassifier(Constant(2), dist, 4, batch_size=64), tiny_sample().renderer()
    cert = smoothed.certify_sequential(render, 100, 1000, 0.01, 0.1, 40, image_generator(0, 0))
    design = SequentialDesign.plan(100, 1000, 0.01, norm.cdf(1.0), 40)
    assert cert.prediction == 2 and cert.count_a == cert.n == design.looks[0] == 40
    assert cert.p_a_lower == pytest.approx(design.levels[0] ** (1 / 40), rel=1e-12)  # Clopper-Pearson at 40/40
    assert cert.radius == pytest.approx(0.1 * norm.ppf(cert.p_a_lower), rel=1e-12) and cert.radius >= 0.1
    # Batch size does not change where it stops or what it returns.
    other = SmoothedClassifier(Constant(2), dist, 4, batch_size=7)
    assert other.certify_sequential(render, 100, 1000, 0.01, 0.1, 40, image_generator(0, 0)) == cert


class Noisy(torch.nn.Module):
    """Votes class 1 with probability ``p`` whatever the image (its own seeded generator)."""

    def __init__(self, p: float = 0.6):
        super().__init__()
        self.p, self.g = p, torch.Generator().manual_seed(0)

    def forward(self, x):
        out = torch.zeros(len(x), 2)
        out[torch.arange(len(x)), (torch.rand(len(x), generator=self.g) < self.p).long()] = 1.0
        return out


class Recording(VoteCounter):
    """A vote counter that keeps every input it classifies, in order."""

    def __call__(self, render, inputs):
        self.seen = [*getattr(self, "seen", []), inputs]
        return super().__call__(render, inputs)


def test_sequential_certify_classifies_the_samples_fixed_n_estimates_with():
    """The two procedures see the same samples of an image: sequential CERTIFY's stream is fixed
    n's n = 1,000 estimation samples (its n0 selection samples drawn and skipped), then fresh
    ones up to the last look."""
    dist, render = CameraMotionSmoothing(("tz",), (0.1,)), tiny_sample().renderer()
    streams = {}
    for name in ("fixed", "sequential"):
        smoothed = SmoothedClassifier(Noisy(0.86), dist, 2, batch_size=100)
        smoothed.votes = Recording(smoothed.votes.base, 2, batch_size=100)
        if name == "fixed":
            smoothed.certify(render, 100, 1000, 0.01, image_generator(0, 3))
        else:
            cert = smoothed.certify_sequential(render, 100, 1000, 0.01, 0.1, 40, image_generator(0, 3))
        streams[name] = torch.cat(smoothed.votes.seen)
    fixed, sequential = streams["fixed"], streams["sequential"]
    assert len(fixed) == 1100 and len(sequential) == cert.n > 1000  # borderline: it reaches the last look
    assert torch.equal(sequential[:1000], fixed[100:]) and not torch.equal(sequential[:100], fixed[:100])


def test_sequential_stops_early_when_the_radius_is_out_of_reach():
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    smoothed = SmoothedClassifier(Noisy(), dist, 2, batch_size=100)
    cert = smoothed.certify_sequential(tiny_sample().renderer(), 100, 1000, 0.01, 0.1, 40, image_generator(0, 1))
    # pA = 0.6 is far below Phi(1) = 0.84: no need to draw 1,000, and nothing is claimed
    assert cert.n <= 80 and cert.prediction == ABSTAIN and cert.radius == 0.0


def test_a_design_refuses_looks_it_cannot_make():
    with pytest.raises(ValueError, match="first look"):
        SequentialDesign.plan(100, 100, 0.01, 0.84, 500)


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
