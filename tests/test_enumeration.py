"""Exact enumeration of the images a translation interval renders, and the complete certifier on it:
checked against an independent z-buffer (NumPy, the projection rule of docs/method.md §2 written
again) and mrcert's own renderer at thousands of poses per interval and at both float neighbours
of every enumerated change; no sampled image is missing, and no interval is verified that a
sampled pose classifies otherwise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mrcert.core.methods.base import BaseClassifier
from mrcert.core.methods.enumeration import ImageEnumeration, _point_groups
from mrcert.core.projection import project
from mrcert.core.verification.events import enumerate_images, record_options
from mrcert.core.verification.incremental import IncrementalNetwork
from mrcert.data.samples import TestSample
from mrcert.errors import ConfigError
from tests.conftest import PAPER_K, compose_cfg
from tests.test_pixelwise import occluding_scene
from tests.test_verification import REQUEST, Brightness, piece_poses

# rx and ry move the depths too: their sweeps are long on 2 cores, checked by ``make test-full``
ROTATION_AXES = ["rz", *(pytest.param(a, marks=pytest.mark.slow) for a in ("rx", "ry"))]

SMALL_H, SMALL_W = 12, 16
SMALL_K = torch.tensor([[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def zbuffer(points: np.ndarray, colors: np.ndarray, rank: np.ndarray, K, axis: int, t: float, h: int, w: int, bg):
    """The projection rule as NumPy computes it: P - t, then column and row by floor, the nearest
    point (lowest rank among equal depths) per pixel, the background elsewhere."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    moved = points.copy()
    moved[:, axis] = points[:, axis] - t
    z = moved[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * (moved[:, 0] / z) + cx
        v = fy * (moved[:, 1] / z) + cy
    ok = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    image = np.full((h * w, colors.shape[1]), bg, colors.dtype)
    idx = np.nonzero(ok)[0]
    pix = np.floor(v[idx]).astype(np.int64) * w + np.floor(u[idx]).astype(np.int64)
    order = np.lexsort((rank[idx], z[idx], pix))
    pix, idx = pix[order], idx[order]
    first = np.r_[True, pix[1:] != pix[:-1]]
    image[pix[first]] = colors[idx[first]]
    return image.reshape(h, w, -1).transpose(2, 0, 1)


def tiny_cloud(seed: int, n: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A few hundred points at 0.3-3 m, some at exactly one depth (ties), some crossing the camera plane on tz."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.3, 3.0, n)
    z[: n // 4] = 1.0  # a wall facing the camera: equal depths, the rank decides
    z[n // 4 : n // 4 + 5] = rng.uniform(0.001, 0.004, 5)  # close enough to cross the camera plane
    xy = rng.uniform(-0.5, 0.5, (n, 2)) * z[:, None]
    points = np.column_stack([xy, z])
    colors = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    return points, colors, rng.permutation(n)


@pytest.mark.parametrize("axis", ["tx", "ty", "tz"])
@pytest.mark.parametrize("seed", [0, 1])
def test_every_image_a_dense_sampling_finds_is_enumerated_at_its_pose(axis, seed):
    points, colors, rank = tiny_cloud(seed)
    a = 0.02
    e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 1.0, axis, -a, a)
    assert len(e) > 20 and e.events >= len(e) - 1
    k = ["tx", "ty", "tz"].index(axis)
    rng = np.random.default_rng(seed)
    poses = np.concatenate([rng.uniform(-a, a, 3000), [-a, a, 0.0]])
    # both float neighbours of every change the enumeration found
    poses = np.concatenate([poses, e.starts[1:], np.nextafter(e.starts[1:], -np.inf)])
    which = np.searchsorted(e.starts, poses, side="right") - 1
    images = e.images(0, len(e))
    motions = torch.zeros(len(poses), 6, dtype=torch.float64)
    motions[:, k] = torch.from_numpy(poses)
    rendered = project(torch.from_numpy(points), torch.from_numpy(colors), SMALL_K, motions, SMALL_H, SMALL_W, 1.0,
                       rank=torch.from_numpy(rank))[0].numpy()  # fmt: skip
    for j, t in enumerate(poses):
        mine = zbuffer(points, colors, rank, SMALL_K, k, float(t), SMALL_H, SMALL_W, 1.0)
        assert np.array_equal(mine, rendered[j]), t  # the two renderers agree
        assert np.array_equal(images[which[j]], mine), (t, which[j])
    for i in range(1, len(e)):  # each image differs from the one before it
        assert not np.array_equal(images[i], images[i - 1])


def test_the_test_scene_is_enumerated_as_the_renderer_draws_it_at_every_change():
    """On a scene of 70,000 points and 90 x 160 pixels, tz over +-5 mm: at every enumerated
    change and the float before it, the renderer draws exactly the enumerated image."""
    points, colors = occluding_scene()
    a = 0.005
    e = enumerate_images(points, colors, None, PAPER_K, 90, 160, 1.0, "tz", -a, a)
    assert len(e) > 100 and len(e.fragile) == 0
    rng = np.random.default_rng(0)
    picks = rng.choice(np.arange(1, len(e)), 150, replace=False)
    poses = np.concatenate([e.starts[picks], np.nextafter(e.starts[picks], -np.inf), rng.uniform(-a, a, 100)])
    motions = torch.zeros(len(poses), 6, dtype=torch.float64)
    motions[:, 2] = torch.from_numpy(poses)
    rendered = project(points, colors, PAPER_K, motions, 90, 160, 1.0)[0].numpy()
    which = np.searchsorted(e.starts, poses, side="right") - 1
    for j in range(len(poses)):
        assert np.array_equal(e.images(int(which[j]), int(which[j]) + 1)[0], rendered[j]), poses[j]


def test_depths_a_unit_in_the_last_place_apart_are_recorded_as_a_pixel_rounding_may_hand_over():
    """Two points on the optical axis, depths 1 and the next float above, the farther of lower
    rank: at some poses ``1 - t`` and ``next(1) - t`` round to one value and the farther point
    wins the tie. The enumeration records it, its hull holds both colours, and every sampled pose
    shows the nominal image or the one the record allows."""
    z = np.array([1.0, np.nextafter(1.0, 2.0)])
    points = np.column_stack([[0.0, 0.0], [0.0, 0.0], z])
    colors = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.25]], np.float32)
    rank = np.array([1, 0])
    e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 0.5, "tz", -0.01, 0.01)
    pixel = 6 * SMALL_W + 8
    assert [tuple(r) for r in e.alternates(0, len(e))[:, 2:]] == [(pixel, 1)]
    low, high = e.hull(0, len(e))
    assert low[:, 6, 8].tolist() == [0.0, 0.0, 0.0] and high[:, 6, 8].tolist() == [1.0, 0.5, 0.25]
    (k,) = {int(r[0]) for r in e.alternates(0, len(e))} & {0}
    (variant,) = e.variants(k, 64)  # the nominal image with the pixel handed to the farther point
    assert variant[:, 6, 8].tolist() == [1.0, 0.5, 0.25] and np.array_equal(
        np.delete(variant.reshape(3, -1), pixel, 1), np.delete(e.images(k, k + 1)[0].reshape(3, -1), pixel, 1)
    )
    shown = set()
    for t in np.random.default_rng(0).uniform(-0.01, 0.01, 2000):
        shown.add(tuple(zbuffer(points, colors, rank, SMALL_K, 2, float(t), SMALL_H, SMALL_W, 0.5)[:, 6, 8]))
    assert shown == {(0.0, 0.0, 0.0), (1.0, 0.5, 0.25)}  # rounding does hand the pixel over


def test_depths_two_spacings_apart_never_tie_and_are_not_recorded():
    """Depths 1.5 and two floats above it: ``fl(Z - t)`` of the two never coincide (each rounds by
    at most half a spacing), so the nearer point shows at every sampled pose and no record is made;
    one spacing apart they are recorded."""
    near = 1.5
    for steps, recorded in ((2, False), (1, True)):
        far = near
        for _ in range(steps):
            far = np.nextafter(far, 2.0)
        points = np.column_stack([[0.0, 0.0], [0.0, 0.0], [near, far]])
        colors = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.25]], np.float32)
        rank = np.array([1, 0])
        e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 0.5, "tz", -0.01, 0.01)
        assert (len(e.alternates(0, len(e))) > 0) == recorded
        if not recorded:
            for t in np.random.default_rng(1).uniform(-0.01, 0.01, 3000):
                shown = zbuffer(points, colors, rank, SMALL_K, 2, float(t), SMALL_H, SMALL_W, 0.5)[:, 6, 8]
                assert shown.tolist() == [0.0, 0.0, 0.0]


def sample_for(axis: str, half_width: float) -> TestSample:
    points, colors = occluding_scene(0)
    bound = ImageEnumeration(axis, half_width).crop_bound(1.0)
    return TestSample.build(points.numpy(), colors.numpy(), PAPER_K, 90, 160, label=0, bound=bound)


@pytest.mark.parametrize(("axis", "half_width"), [("tx", 0.001), ("tz", 0.005)])
def test_every_interval_is_decided_and_none_verified_that_a_sampled_pose_classifies_otherwise(axis, half_width):
    """Thresholds from easy to impossible: every answer is verified or falsified (never unknown);
    verified means 3,000 sampled poses are all classified as predicted, and agrees with
    classifying every enumerated image; a falsified interval's logged pose is inside it and
    classified otherwise on its own."""
    sample = sample_for(axis, half_width)
    probe = sample.renderer()(piece_poses(axis, -half_width, half_width, 3000))
    window = probe[:, :, 30:60, 60:100].double().mean((1, 2, 3))
    centre = float(window[-3])
    outcomes = set()
    for threshold in np.quantile(window.numpy(), [0.0, 0.3, 0.7, 1.0]).tolist() + [centre - 0.2, centre + 0.2]:
        model = Brightness(threshold).eval()
        method = ImageEnumeration(axis, half_width, run_images=64)
        cert = method.certifier(BaseClassifier(model, 2, batch_size=64)).certify_sample(
            sample.renderer(), REQUEST, torch.Generator()
        )
        outcome = cert.details["outcome"]
        outcomes.add(outcome)
        assert outcome in ("verified", "falsified")
        with torch.no_grad():
            probed = model(probe)
        seen = probed.argmax(1)[(probed[:, 0] - probed[:, 1]).abs() > 1e-4]  # beyond a batch's rounding
        points, colors, rank = sample.cloud_for(piece_poses(axis, -half_width, half_width, 0)[:2])
        e = enumerate_images(points, colors, rank, PAPER_K, 90, 160, 1.0, axis, -half_width, half_width)
        with torch.no_grad():  # every image of the interval, 512 at a time
            logits = torch.cat(
                [model(torch.from_numpy(e.images(s, min(s + 512, len(e))))) for s in range(0, len(e), 512)]
            )
        every = logits.argmax(1)
        clear = (logits[:, 0] - logits[:, 1]).abs() > 1e-4  # beyond what a batch's rounding decides
        if outcome == "verified":
            assert cert.radius == half_width and (seen == cert.prediction).all()
            assert (every[clear] == cert.prediction).all()
        else:
            assert (every != cert.prediction).any() or not clear.all()  # otherwise only at rounding level
            pose = cert.details["counterexample"]
            assert abs(pose) <= half_width and cert.radius == 0.0
            with torch.no_grad():
                assert int(model(sample.renderer()(piece_poses(axis, pose, pose, 0)[:1])).argmax()) != cert.prediction
    assert outcomes == {"verified", "falsified"}


def test_a_rotation_beyond_one_radian_is_refused_before_any_run():
    from mrcert.infra.config import validate

    validate(compose_cfg(["task=certify", "method=enumeration", "motion=rx"]))  # every axis is enumerated
    with pytest.raises(ConfigError, match=r"method.half_width=1.5 is not allowed: at most 1 rad on rx"):
        validate(compose_cfg(["task=certify", "method=enumeration", "motion=rx", "method.half_width=1.5"]))


def rotation_check(
    points, colors, rank, lo: float, hi: float, axis: str = "rz", combinations: bool = True
) -> tuple[int, int]:
    """Render the rotation ``axis`` at thousands of poses (random, every image's start and its
    float neighbours, every band's ends and inside -- a depth order's too): each image is the
    enumerated image of its pose, or inside a band the image before or after it, or one its
    records allow: one of their combinations, and one of a window's images point by point
    (``combinations``), or else at each pixel one of the colours they allow there (what the hull
    holds). Returns (poses, poses inside bands)."""
    from mrcert.core.verification.rotation_events import ROTATIONS, rotation_bands

    e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 1.0, axis, lo, hi)
    bands = rotation_bands(points, SMALL_K, axis, lo, hi, SMALL_H, SMALL_W)[0][:, :2]
    inside = np.concatenate([np.linspace(x, y, 7)[1:-1] for x, y in bands]) if len(bands) else np.empty(0)
    rng = np.random.default_rng(1)
    poses = np.r_[rng.uniform(lo, hi, 3000), e.starts, np.nextafter(e.starts, -np.inf), np.nextafter(e.starts, np.inf)]
    poses = np.sort(np.r_[poses, bands.ravel(), inside])
    poses = poses[(poses >= lo) & (poses <= hi)]
    motions = torch.zeros(len(poses), 6, dtype=torch.float64)
    motions[:, ROTATIONS[axis]] = torch.from_numpy(poses)
    drawn = project(torch.from_numpy(points), torch.from_numpy(colors), SMALL_K, motions, SMALL_H, SMALL_W, 1.0,
                    rank=torch.from_numpy(rank))[0].numpy()  # fmt: skip
    images = e.images(0, len(e))
    k = np.searchsorted(e.starts, poses, side="right") - 1
    in_band = ((poses[:, None] > bands[None, :, 0]) & (poses[:, None] < bands[None, :, 1])).any(1)
    assert np.array_equal(images[0], drawn[0])  # the interval's start exactly as the renderer draws it
    for j in range(len(poses)):
        if np.array_equal(images[k[j]], drawn[j]):
            continue
        near = (k[j] - 1, k[j] + 1) if in_band[j] else ()
        if any(np.array_equal(images[q], drawn[j]) for q in near if 0 <= q < len(e)):
            continue
        if not combinations:
            options = record_options(e.alternates(int(k[j]), int(k[j]) + 1))
            want, table = drawn[j].reshape(len(colors[0]), -1), e.table()
            differ = np.nonzero((images[k[j]].reshape(want.shape) != want).any(0))[0]
            assert all(any(np.array_equal(table[q], want[:, p]) for q in options.get(p, [])) for p in differ), (
                f"{axis}={poses[j]!r} draws a colour no record allows (image {k[j]})"
            )
            continue
        variants = e.variants(int(k[j]), 100000)
        assert variants is not None and any(np.array_equal(v, drawn[j]) for v in variants), (
            f"{axis}={poses[j]!r} draws an image the enumeration does not hold (image {k[j]})"
        )
        windows = e.windows_at(int(k[j]))
        if sum(e.window_records[w + 1] - e.window_records[w] for w in windows) == len(e.alternates(k[j], k[j] + 1)):
            # all the image's records are its windows' (else the method classifies their combinations)
            assert point_by_point(e, int(k[j]), drawn[j]), f"{axis}={poses[j]!r}: not a window's image, point by point"
    return len(poses), int(in_band.sum())


def point_by_point(e, k: int, drawn: np.ndarray) -> bool:
    """Whether ``drawn`` is an image one of the windows holding image ``k`` allows, point by point
    (:func:`mrcert.core.methods.enumeration._point_groups`, the images the method classifies on
    rz): image ``k`` with each group of free points' pixels as it is or as one of its choices sets them."""
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, padding=1), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(1),
                                torch.nn.Flatten(), torch.nn.Linear(4, 3)).eval()  # fmt: skip
    net = IncrementalNetwork.of(model)
    image = e.images(k, k + 1)
    with torch.inference_mode():
        net.start(torch.from_numpy(image))
    table = torch.from_numpy(e.table())
    current, want = image[0].reshape(3, -1), drawn.reshape(3, -1)
    for w in e.windows_at(k):
        groups = _point_groups(net, *e.free_points(w), table)
        assert groups is not None
        covered = np.zeros(current.shape[1], bool)
        ok = True
        for choices in groups:
            where = choices[0][0]
            covered[where] = True
            ok &= np.array_equal(want[:, where], current[:, where]) or any(
                np.array_equal(want[:, where], values.numpy()) for _, values in choices
            )
        if ok and np.array_equal(want[:, ~covered], current[:, ~covered]):
            return True
    return False


@pytest.mark.parametrize("axis", ROTATION_AXES)
@pytest.mark.parametrize("seed", [0, 1])
def test_every_image_a_dense_sampling_finds_on_a_rotation_is_enumerated(axis, seed):
    """A quarter of the cloud on a wall facing the camera: on rx and ry its points' depths all
    cross at 0, each pair of one pixel within rounding there."""
    points, colors, rank = tiny_cloud(seed)
    count, in_band = rotation_check(points, colors, rank, -0.3, 0.3, axis)
    assert count > 8000 and in_band > 3000  # the bands' insides were sampled, not only their outsides


@pytest.mark.parametrize("axis", ROTATION_AXES)
def test_rotation_bands_that_overlap_or_hold_an_end_are_recorded_and_every_drawn_image_allowed(axis):
    from mrcert.core.verification.rotation_events import ROTATIONS, _bands

    points, colors, rank = tiny_cloud(0, 200)
    points = np.r_[points, points[:40]]  # the same positions twice: their bands coincide
    colors = np.r_[colors, np.random.default_rng(5).uniform(0, 1, (40, 3)).astype(np.float32)]
    rank = np.random.default_rng(3).permutation(len(points))
    bands, owners = _bands(points, ROTATIONS[axis], -0.3, 0.3, 20.0, 20.0, 8.0, 6.0, SMALL_H, SMALL_W)
    inside = (bands[:, 4] == 0) & (np.minimum(bands[:, 2], bands[:, 3]) >= 0) & (bands[:, 3] < SMALL_W)
    band = bands[np.nonzero(inside & (np.abs(points[owners, 1] / points[owners, 2]) < 0.1))[0][10]]
    lo = 0.5 * (band[0] + band[1])  # the interval starts inside a band of a point on the image
    e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 1.0, axis, lo, lo + 0.2)
    assert len(e.fragile) > 0
    rotation_check(points, colors, rank, lo, lo + 0.2, axis)


@pytest.mark.parametrize("axis", ROTATION_AXES)
def test_points_a_unit_in_the_last_place_apart_may_each_be_either_side_while_their_bands_overlap(axis):
    """Two points one float apart cross each edge within rounding of one another, in an order
    only the renderer's arithmetic decides: while both bands hold, each point is in either pixel,
    and every image a dense sampling draws there is one the records allow."""
    points, colors, rank = tiny_cloud(2, 150)
    near = points.copy()
    near[:, 0] = np.nextafter(near[:, 0], np.inf)
    near[:, 1] = np.nextafter(near[:, 1], -np.inf)
    points = np.r_[points, near]
    colors = np.r_[colors, np.random.default_rng(6).uniform(0, 1, (len(near), 3)).astype(np.float32)]
    rank = np.random.default_rng(7).permutation(len(points))
    e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 1.0, axis, -0.3, 0.3)
    records = e.fragile
    pairs = {(a, b): set() for a, b, _, _ in records.tolist()}
    for a, b, _, q in records.tolist():
        pairs[(a, b)].add(q)
    assert max(len(q) for q in pairs.values()) >= 2  # windows where two such points are free at once
    # on rx and ry two such points' depths are within rounding of each other at every pose: their
    # order is the renderer's alone throughout, too many combinations to list (the hull holds them)
    rotation_check(points, colors, rank, -0.3, 0.3, axis, combinations=axis == "rz")


@pytest.mark.slow
@pytest.mark.parametrize("axis", ["rx", "ry"])
def test_points_on_a_line_along_the_rotation_axis_cross_together_and_their_depths_never_tie_ambiguously(axis):
    """A grid's line along the rotation's own axis (rx: equal Y and Z, X apart): the renderer
    computes one row (ry: column) and one depth for all its points at every pose, so their
    crossings coincide without a recorded window, their equal depths always hand a shared pixel
    to the lower rank, and every sampled pose draws an enumerated image."""
    rng = np.random.default_rng(8)
    lines = []
    for _ in range(12):
        y, z = rng.uniform(-0.3, 0.3), rng.uniform(1.0, 3.0)
        along = (np.linspace(-0.4, 0.4, 17) + 0.013) * z  # off the column edges at rx = 0
        lines.append(np.column_stack([along, np.full(17, y * z), np.full(17, z)]))
    points = np.concatenate(lines)
    if axis == "ry":
        points = points[:, [1, 0, 2]]
    colors = rng.uniform(0, 1, (len(points), 3)).astype(np.float32)
    rank = rng.permutation(len(points))
    e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 1.0, axis, -0.3, 0.3)
    assert len(e.fragile) == 0 and len(e.window_records) == 1  # no window, no near-equal depths
    count, _ = rotation_check(points, colors, rank, -0.3, 0.3, axis)
    assert count > 3000


def test_a_column_of_points_on_the_optical_axis_is_resolved_point_by_point_near_rz_0():
    """Points a scan puts on the camera's principal column (X a rounding error from 0) all cross
    it within 1e-12 rad of rz = 0, far closer than the arithmetic's error in the column: the
    renderer's own operations order them, so the enumeration holds one image per crossing and
    no fragile record (a position held twice is one point), and every pose sampled there draws
    an enumerated image."""
    rng = np.random.default_rng(4)
    n = 40
    z = rng.uniform(1.0, 3.0, n)
    y = np.linspace(-0.243, 0.247, n) * z  # no row edge within rounding
    x = rng.uniform(1e-15, 5e-15, n) * z  # the principal column, up to rounding
    points = np.column_stack([x, y, z])
    points = np.r_[points, points]  # each position twice, in other colours: the lower rank shows
    colors = rng.uniform(0, 1, (2 * n, 3)).astype(np.float32)
    rank = rng.permutation(2 * n)
    lo, hi = -2e-11, 2e-11
    e = enumerate_images(points, colors, rank, SMALL_K, SMALL_H, SMALL_W, 1.0, "rz", lo, hi)
    assert len(e.fragile) == 0 and len(e) > n // 2  # each point's own crossing, not one blur of all
    count, _ = rotation_check(points, colors, rank, lo, hi)
    assert count > 3000


def test_the_rotation_s_cos_and_sin_are_within_one_unit_in_the_last_place():
    """The rz bands assume the renderer's float64 cos and sin within a few units in the last
    place of the exact value (mpmath at 40 digits)."""
    import mpmath

    from mrcert.core.verification.rotation_events import LIBM_ULPS

    mpmath.mp.dps = 40
    theta = np.r_[np.random.default_rng(0).uniform(-1, 1, 4000), np.geomspace(1e-12, 1, 200)]
    motions = torch.zeros(len(theta), 6, dtype=torch.float64)
    motions[:, 5] = torch.from_numpy(theta)
    from mrcert.core.projection import rotations

    R = rotations(motions).numpy()
    for t, r in zip(theta, R, strict=True):
        c, s = float(mpmath.cos(mpmath.mpf(abs(t)))), float(mpmath.sin(mpmath.mpf(t)))
        assert abs(r[0, 0] - c) <= np.spacing(c) <= LIBM_ULPS * np.spacing(c)
        assert abs(r[1, 0] - s) <= np.spacing(abs(s))
        assert r[2, 2] == 1.0 and r[0, 2] == r[2, 0] == r[1, 2] == r[2, 1] == 0.0 and r[0, 1] == -r[1, 0]
