"""Certificates only where Theorem 1 licenses them: multi-axis smoothing around a moved camera.

The oracle is the exact composition of motions (Lemma 1) and a simulated base classifier that
reads the camera's pose: the smoothed classifier's true top-class probability at a moved
camera ``alpha`` is ``P_eps[h(alpha o eps) = A]``, estimated by Monte Carlo with many samples.
Theorem 1 claims ``p_A(alpha) >= Phi(Phi^-1(p_A(0)) - |alpha|_sigma)``; for a licensed
combination this holds, for a refused one it fails by far.
"""

import pytest
import torch
from scipy.stats import norm

from mrcert.core.axes import axis_index
from mrcert.core.geometry import compose
from mrcert.core.methods.camera_motion import CameraMotionSmoothing
from mrcert.errors import ConfigError, MrcertError
from mrcert.infra.config import validate
from tests.conftest import compose_cfg

N = 400_000


def noise(axes, sigmas, n=N, seed=0) -> torch.Tensor:
    """Gaussian motions on ``axes`` (built directly, so refused combinations can be studied too)."""
    g = torch.Generator().manual_seed(seed)
    m = torch.zeros(n, 6, dtype=torch.float64)
    for a, s in zip(axes, sigmas, strict=True):
        m[:, axis_index(a)] = torch.randn(n, generator=g, dtype=torch.float64) * s
    return m


def p_top(h, alpha: torch.Tensor, eps: torch.Tensor) -> float:
    """P[h(alpha o eps) = 0], the smoothed classifier's top-class probability at ``alpha``."""
    return float((h(compose(alpha.expand(len(eps), 6), eps)) == 0).double().mean())


def sigma_norm(alpha: torch.Tensor, axes, sigmas) -> float:
    return float(sum((alpha[axis_index(a)] / s) ** 2 for a, s in zip(axes, sigmas, strict=True)) ** 0.5)


def motion(**values) -> torch.Tensor:
    m = torch.zeros(6, dtype=torch.float64)
    for a, v in values.items():
        m[axis_index(a)] = v
    return m


# Base classifiers that read the camera's position: class 0 on one side of a plane.
READS_TY = lambda m: (m[:, 1] > 0.03).long()  # noqa: E731
READS_TX = lambda m: (m[:, 0] > 0.02).long()  # noqa: E731
READS_TY_EXACTLY = lambda m: (m[:, 1].abs() > 1e-3).long()  # noqa: E731


@pytest.mark.parametrize(
    "axes,sigmas",
    [(("tx", "ty", "rz"), (0.05, 0.05, 0.122173)), (("tx", "ty", "tz", "rz"), (0.05, 0.05, 0.1, 0.122173))],
)
@pytest.mark.parametrize("h", [READS_TY, READS_TX])
def test_a_licensed_combination_keeps_the_theorem_1_bound_at_moved_cameras(axes, sigmas, h):
    CameraMotionSmoothing(axes, sigmas)  # accepted
    eps = noise(axes, sigmas)
    p0 = p_top(h, motion(), eps)
    assert 0.6 < p0 < 0.9
    for alpha in (motion(rz=0.15), motion(rz=-0.2, tx=0.02), motion(rz=0.1, ty=-0.03), motion(rz=0.25)):
        bound = norm.cdf(norm.ppf(p0) - sigma_norm(alpha, axes, sigmas))
        assert p_top(h, alpha, eps) >= bound - 0.004  # Monte Carlo error ~ 0.001
    # The law of alpha o eps is the Gaussian shifted by alpha: the same as alpha + eps.
    alpha = motion(rz=0.2, tx=0.03)
    assert p_top(h, alpha, eps) == pytest.approx(float((h(alpha + eps) == 0).double().mean()), abs=0.004)


def test_the_refused_counterexample_breaks_the_certificate_it_would_issue():
    axes, sigmas = ("tx", "rz"), (0.05, 0.122173)
    with pytest.raises(MrcertError, match="tx and ty must both be smoothed with equal sigma, or neither"):
        CameraMotionSmoothing(axes, sigmas)
    eps = noise(axes, sigmas, n=100_000)
    assert p_top(READS_TY_EXACTLY, motion(), eps) == 1.0  # CERTIFY would give nA = n: radius 2.605
    alpha = motion(rz=0.122173)  # |alpha|_sigma = 1, well inside that radius
    assert sigma_norm(alpha, axes, sigmas) == pytest.approx(1.0)
    assert p_top(READS_TY_EXACTLY, alpha, eps) < 0.2  # the claimed top class is not even the majority


@pytest.mark.parametrize(
    "axes,sigmas,allowed",
    [
        (("tx", "rz"), (0.05, 0.122), False),
        (("tx", "ty", "tz", "rz"), (0.05, 0.06, 0.1, 0.122), False),
        (("tx", "ty", "tz", "rx"), (0.05, 0.05, 0.1, 0.0436), False),  # the paper's sigmas: sigma_y != sigma_z
        (("ty", "rx"), (0.05, 0.0436), False),
        (("rx", "rz"), (0.04, 0.1), False),
        (("tx", "tx"), (0.05, 0.05), False),
        (("tx", "ty", "tz", "rz"), (0.05, 0.05, 0.1, 0.122), True),
        (("tz", "rz"), (0.1, 0.122), True),
        (("tx", "ry"), (0.05, 0.04), False),
        (("ty", "ry"), (0.05, 0.04), True),  # ty is the axis of the rotation: never mixed
        (("tx", "tz", "ry"), (0.05, 0.05, 0.04), True),
        (("tx", "ty", "tz"), (0.05, 0.06, 0.1), True),  # translations only: any sigmas
    ],
)
def test_the_licensing_rule(axes, sigmas, allowed):
    if allowed:
        CameraMotionSmoothing(axes, sigmas)
    else:
        with pytest.raises(MrcertError, match="not licensed by Theorem 1"):
            CameraMotionSmoothing(axes, sigmas)


def test_a_refused_motion_config_stops_before_any_work():
    validate(compose_cfg(["motion=txyz_rz"]))  # the shipped multi-axis config is licensed
    cfg = compose_cfg(["motion=txyz_rz", "motion.sigmas=[0.05,0.06,0.1,0.122173]"])
    with pytest.raises(ConfigError, match=r"motion.axes=.*sigma_x=0.05, sigma_y=0.06.*equal sigma, or neither"):
        validate(cfg)


def test_a_smoothed_prediction_at_a_moved_camera_draws_the_composition_not_the_sum():
    """PREDICT at a camera moved by ``alpha`` renders ``alpha o eps`` (Lemma 1): on the one smoothed
    axis that is ``alpha + eps`` bit for bit; with a rotation it is the composition, never the sum."""
    from mrcert.core.sampling import SmoothedClassifier, image_generator

    seen = []

    def render(motions):  # records what the classifier asks to see
        seen.append(motions.clone())
        return torch.zeros(len(motions), 3, 2, 2)

    class Zero(torch.nn.Module):
        def forward(self, x):
            return torch.zeros(len(x), 2)

    for axes, sigmas, alpha in [
        (("tx", "ty", "tz", "rz"), (0.05, 0.05, 0.1, 0.122173), motion(tx=0.03, rz=0.2)),
        (("rz",), (0.122173,), motion(rz=0.2)),
    ]:
        dist = CameraMotionSmoothing(axes, sigmas)
        seen.clear()
        SmoothedClassifier(Zero(), dist, 2, batch_size=1000).sample_counts(render, 500, image_generator(0, 1), alpha)
        eps = dist.sample(500, image_generator(0, 1))
        expected = alpha + eps if len(axes) == 1 else compose(alpha.expand(500, 6), eps)
        assert torch.equal(seen[0], expected)
        if len(axes) > 1:
            assert not torch.allclose(seen[0], alpha + eps)  # the sum would be another distribution
