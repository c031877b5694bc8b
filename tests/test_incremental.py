"""Classifying an enumeration's images incrementally (each recomputed where its changed pixels
reach): checked against the network's own forward pass on every image, one sequence at a time
and many at once, on a plain CNN, a residual network and one with a non-linear head; the
interval bound over a few pixels checked by sampling, and the bound it keeps across steps against
the bound computed afresh."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

import mrcert.core.methods.enumeration as enumeration_method
from mrcert.core.methods.base import BaseClassifier
from mrcert.core.methods.enumeration import (
    VARIANTS,
    ImageEnumeration,
    _Box,
    _change,
    _groups,
    _low_variants,
    _open_images,
    _point_groups,
    _split,
)
from mrcert.core.models import Normalize, SmallCNN, class_margins
from mrcert.core.verification.events import enumerate_images
from mrcert.core.verification.incremental import IncrementalNetwork
from mrcert.data.samples import TestSample
from tests.conftest import PAPER_K
from tests.test_enumeration import REQUEST, sample_for
from tests.test_pixelwise import occluding_scene

H, W = 24, 40
K = torch.tensor([[40.0, 0.0, 20.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def randomised(net: nn.Module, seed: int) -> nn.Module:
    """``net`` behind the normaliser, its batch norms given statistics of their own, in evaluation mode."""
    g = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.copy_(torch.rand(m.num_features, generator=g) * 0.2 - 0.1)
            m.running_var.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.bias.data.copy_(torch.rand(m.num_features, generator=g) * 0.4 - 0.2)
    return nn.Sequential(Normalize(), net).eval()


class Residual(nn.Module):
    """Strided and 1x1 convolutions, a padded max pooling after a ReLU, and two residual sums."""

    def __init__(self):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.BatchNorm2d(8), nn.ReLU(), nn.MaxPool2d(3, 2, 1))
        self.a = nn.Sequential(
            nn.Conv2d(8, 8, 3, padding=1), nn.BatchNorm2d(8), nn.ReLU(), nn.Conv2d(8, 8, 3, padding=1)
        )
        self.down = nn.Conv2d(8, 16, 1, stride=2)
        self.b = nn.Conv2d(8, 16, 3, stride=2, padding=1)
        self.head = nn.Linear(16, 3)

    def forward(self, x):
        x = self.stem(x)
        x = torch.relu(x + self.a(x))
        x = torch.relu(self.down(x) + self.b(x))
        return self.head(torch.flatten(F.adaptive_avg_pool2d(x, 1), 1))


class MlpHead(nn.Module):
    """A convolution, then a head that is not affine (Linear, ReLU, Linear)."""

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, 6, 3, stride=2, padding=1)
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(6 * 12 * 20, 16), nn.ReLU(), nn.Linear(16, 4))

    def forward(self, x):
        return self.head(torch.relu(self.conv(x)))


def models():
    torch.manual_seed(0)
    return {
        "small_cnn": randomised(SmallCNN(5, width=6), 1),
        "residual": randomised(Residual(), 2),
        "mlp_head": randomised(MlpHead(), 3),
    }


def enumeration(seed: int = 0, a: float = 0.02, scale: int = 1):
    """A random cloud along tz; ``scale`` times the image size (and focal length)."""
    rng = np.random.default_rng(seed)
    n = 3000 * scale * scale
    z = rng.uniform(0.8, 3.0, n)
    xy = rng.uniform(-1, 1, (n, 2)) * np.array([0.55, 0.35]) * z[:, None]
    colors = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    k = K.clone()
    k[:2] *= scale
    return enumerate_images(np.column_stack([xy, z]), colors, None, k, H * scale, W * scale, 0.0, "tz", -a, a)


def full(model, e):
    with torch.no_grad():
        return model(torch.from_numpy(e.images(0, len(e))))


@pytest.mark.parametrize("name", ["small_cnn", "residual", "mlp_head"])
def test_each_image_is_classified_as_the_network_classifies_it_whole_one_sequence_and_many(name):
    model = models()[name]
    e = enumeration()
    assert len(e) > 150
    net = IncrementalNetwork.of(model)
    assert net is not None
    expected = full(model, e)
    tol = 1e-5 * max(1.0, float(expected.abs().max()))
    table = torch.from_numpy(e.table())
    bounds = np.searchsorted(e.change_image, np.arange(len(e) + 1), side="left")
    with torch.inference_mode():
        rows = [net.start(torch.from_numpy(e.images(0, 1))).clone()]
        for k in range(1, len(e)):
            lo, hi = bounds[k], bounds[k + 1]
            rows.append(net.step(e.change_pixel[lo:hi], table[e.change_winner[lo:hi]].T).clone())
    assert (torch.cat(rows) - expected).abs().max() <= tol
    # many sequences at once: six pieces, one changed pixel per step each
    cuts = np.linspace(0, len(e), 7).round().astype(int)
    spans = [np.searchsorted(e.change_image, [a + 1, b], side="left") for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    steps = max(int(hi - lo) for lo, hi in spans)
    pixels = np.full((6, steps), -1)
    colours = torch.zeros(6, steps, 3)
    shown = np.zeros((6, steps), bool)
    for r, (lo, hi) in enumerate(spans):
        n = int(hi - lo)
        pixels[r, :n] = e.change_pixel[lo:hi]
        colours[r, :n] = table[e.change_winner[lo:hi]]
        images = e.change_image[lo:hi]
        shown[r, :n] = np.r_[images[1:] != images[:-1], True]
    firsts = torch.from_numpy(np.concatenate([e.images(a, a + 1) for a in cuts[:-1]]))
    lanes = net.lanes(firsts, pixels, colours, shown)
    assert lanes.shape == expected.shape and (lanes - expected).abs().max() <= tol


def margin(model, image, c):
    with torch.no_grad():
        return class_margins(model(image), c)


@pytest.mark.parametrize("name", ["small_cnn", "residual", "mlp_head"])
def test_the_bound_over_a_few_pixels_holds_for_every_sampled_image_and_is_exact_on_a_point(name):
    model = models()[name]
    e = enumeration(1)
    image = torch.from_numpy(e.images(len(e) // 2, len(e) // 2 + 1))
    c = int(model(image).argmax())
    net = IncrementalNetwork.of(model)
    rng = np.random.default_rng(0)
    g = torch.Generator().manual_seed(0)
    with torch.inference_mode():
        net.start(image)
        for trial in range(12):
            near = rng.integers(0, H * W)
            pixels = np.unique(np.clip(near + rng.integers(-2, 3, rng.integers(1, 5)) * (1 + W * (trial % 2)), 0,
                                       H * W - 1))  # fmt: skip
            nominal = image.reshape(3, -1)[:, pixels]
            other = torch.rand(3, len(pixels), generator=g)
            low, high = torch.minimum(nominal, other), torch.maximum(nominal, other)
            bound = net.bound(pixels, low, high, c)
            samples = image.repeat(300, 1, 1, 1).reshape(300, 3, -1)
            samples[:, :, pixels] = low + torch.rand(300, 3, len(pixels), generator=g) * (high - low)
            worst = margin(model, samples.reshape(300, 3, H, W), c).min()
            assert bound <= worst + 1e-5, (trial, bound, worst)
            point = net.bound(pixels, nominal, nominal, c)  # a box of one image: its own margin
            assert point == pytest.approx(float(margin(model, image, c)[0]), abs=1e-5)


def test_a_bound_and_a_variant_kept_across_steps_equal_those_computed_afresh():
    """The bound over the same few pixels, and the logits of the image changed there, are kept
    while the steps change pixels they did not read (the head is affine): at every step of an
    enumeration they equal a fresh network's bound and the network's own logits."""
    model = models()["small_cnn"]
    e = enumeration(2, 0.002, scale=4)
    net = IncrementalNetwork.of(model)
    assert net.boundary is not None  # the affine head: bounds are kept
    table = torch.from_numpy(e.table())
    bounds = np.searchsorted(e.change_image, np.arange(len(e) + 1), side="left")
    pixels = np.array([40 * 4 * W + 72, 40 * 4 * W + 73, 41 * 4 * W + 72])
    computed = []
    offsets = net._offsets
    net._offsets = lambda *args: computed.append(1) or offsets(*args)
    steps = min(len(e), 160) - 1
    with torch.inference_mode():
        net.start(torch.from_numpy(e.images(0, 1)))
        c = int(net.values[net.output].argmax())
        for k in range(1, min(len(e), 160)):
            lo, hi = bounds[k], bounds[k + 1]
            net.step(e.change_pixel[lo:hi], table[e.change_winner[lo:hi]].T)
            nominal = net.values[0].reshape(3, -1)[:, pixels].clone()
            assert len(e) > 160
            low, high = nominal - 0.3 * torch.rand(3, 3, generator=torch.Generator().manual_seed(0)), nominal
            bound = net.bound(pixels, low, high, c)
            fresh = IncrementalNetwork.of(model)
            fresh.start(net.values[0].clone())
            assert bound == pytest.approx(fresh.bound(pixels, low, high, c), abs=1e-5), k
            variant = net.values[0].clone()  # the image with the pixels given their lower colours
            variant.view(3, -1)[:, pixels] = low
            assert torch.allclose(net.variant(pixels, low), model(variant), atol=1e-5), k
            assert torch.equal(net.values[0].view(3, -1)[:, pixels], nominal)  # left as it was
    assert len(computed) < steps / 2  # most steps kept it


@pytest.mark.parametrize(
    "layer",
    [nn.Conv2d(3, 4, 3, padding=2, dilation=2), nn.Upsample(scale_factor=2), nn.MaxPool2d(2, ceil_mode=True)],
    ids=["dilated", "upsample", "ceil_pool"],
)
def test_a_graph_with_a_layer_it_cannot_update_by_window_is_refused(layer):
    model = nn.Sequential(layer, nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.LazyLinear(2))
    model(torch.zeros(1, 3, H, W))
    assert IncrementalNetwork.of(model.eval()) is None


def test_the_method_answers_the_same_with_and_without_incremental_classification():
    """On the 90 x 160 test scene along tz, a small CNN: outcome, least margin and the images
    classified agree whether images are classified whole or incrementally."""
    sample = sample_for("tz", 0.003)
    model = randomised(SmallCNN(3, width=4), 4)
    answers = []
    for incremental in (True, False):
        method = ImageEnumeration("tz", 0.003, incremental=incremental)
        cert = method.certifier(BaseClassifier(model, 3, batch_size=64)).certify_sample(
            sample.renderer(), REQUEST, torch.Generator()
        )
        answers.append(cert)
    a, b = answers
    assert a.details["outcome"] == b.details["outcome"] and a.prediction == b.prediction
    assert a.details["images"] == b.details["images"] > 100
    assert a.margin == pytest.approx(b.margin, abs=1e-5)


def test_images_rounding_may_render_are_decided_alike_incrementally_and_whole():
    """A wall with a second point one float spacing behind a third of its points (records where
    the farther one has the lower rank): the variants those records allow are decided by the
    incremental path (nominal logits many at a time, each variant's change kept near its pixels)
    as by the whole-image path, on models that verify and models that do not."""
    points, colors = occluding_scene(1)
    points, colors = points.numpy(), colors.numpy()
    rng = np.random.default_rng(5)
    twins = rng.choice(np.nonzero(points[:, 2] == 3.0)[0], 300, replace=False)
    behind = points[twins].copy()
    behind[:, 2] = np.nextafter(behind[:, 2], 4.0)
    points = np.concatenate([behind, points])  # first: the lower rank, which wins a tie
    colors = np.concatenate([rng.uniform(0, 1, (len(twins), 3)).astype(np.float32), colors])
    a = 0.002
    bound = ImageEnumeration("tz", a).crop_bound(1.0)
    sample = TestSample.build(points, colors, PAPER_K, 90, 160, label=0, bound=bound)
    cloud = sample.cloud_for(torch.tensor([[0, 0, -a, 0, 0, 0], [0, 0, a, 0, 0, 0]], dtype=torch.float64))
    e = enumerate_images(*cloud, PAPER_K, 90, 160, sample.background, "tz", -a, a)
    assert len(e.fragile) > 3  # the records this test is about
    outcomes = []
    for seed in range(4):
        torch.manual_seed(seed)  # the weights
        model = randomised(SmallCNN(3, width=4), 10 + seed)
        answers = [
            ImageEnumeration("tz", a, incremental=incremental)
            .certifier(BaseClassifier(model, 3, batch_size=64))
            .certify_sample(sample.renderer(), REQUEST, torch.Generator())
            for incremental in (True, False)
        ]
        mine, whole = answers
        assert mine.details["outcome"] == whole.details["outcome"], seed
        outcomes.append(mine.details["outcome"])
    assert {"verified", "unknown"} <= set(outcomes)  # a variant classified otherwise: unknown, on both paths


class Local(nn.Module):
    """Two 3x3 convolutions with ReLUs and an affine head: a pixel reaches its 5x5 neighbourhood."""

    def __init__(self):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.Conv2d(8, 8, 3, padding=1), nn.ReLU())
        self.head = nn.Linear(8, 4)

    def forward(self, x):
        return self.head(torch.flatten(F.adaptive_avg_pool2d(self.body(x), 1), 1))


def every_image(image: torch.Tensor, pixels: np.ndarray, options: list) -> torch.Tensor:
    """Every image (V, 3, H, W) beside ``image`` (1, 3, H, W) with each of ``pixels`` its own
    colour or one of its ``options``, not all their own."""
    every = []
    for combo in itertools.product(*([None, *o] for o in options)):
        if any(colour is not None for colour in combo):
            variant = image.clone()
            for p, colour in zip(pixels, combo, strict=True):
                if colour is not None:
                    variant.view(3, -1)[:, p] = colour
            every.append(variant)
    return torch.cat(every)


@pytest.mark.parametrize("name", ["local", "residual"])
def test_the_variants_of_fragile_pixels_found_group_by_group_are_exactly_those_below_the_margin(name):
    """Fragile pixels (neighbours and loners far apart, each its colour or one of two others):
    grouped by the windows of the affine tail's first layer they reach, the images whose margin is
    at most a threshold are found from one change of the logits per group's image, and they are
    exactly the images (of all 3^7 - 1, each classified whole) below that threshold."""
    torch.manual_seed(4)
    model = randomised(Local(), 4) if name == "local" else models()[name]
    e = enumeration(3)
    image = torch.from_numpy(e.images(len(e) // 2, len(e) // 2 + 1))
    pixels = np.array([5 * W + 5, 6 * W + 5, 7 * W + 6, 12 * W + 20, 12 * W + 21, 21 * W + 36, 2 * W + 38])
    g = torch.Generator().manual_seed(1)
    options = [[torch.rand(3, generator=g), torch.rand(3, generator=g)] for _ in pixels]
    net = IncrementalNetwork.of(model)
    with torch.inference_mode():
        logits = net.start(image)[0].clone()
        c = int(logits.argmax())
        groups = _groups(net, pixels, options)
        assert 1 < len(groups) < len(pixels)  # neighbours share a group, loners do not
        changes = [_change(net, choices, c) for choices in groups]
        margins = np.sort(margin(model, every_image(image, pixels, options), c))  # each classified whole
    rounding = 1e-6 * max(1.0, float(np.abs(logits).max()))  # float32 sums in another order
    gaps = np.nonzero(np.diff(margins) > 2 * rounding)[0] + 1  # thresholds far from any margin
    for least in (1, 7, 40):
        count = int(gaps[gaps >= least][0])
        assert count <= VARIANTS
        scale = float(margins[count - 1] + margins[count]) / 2
        found, open_ = _low_variants(logits, changes, c, scale)
        assert found is not None and not open_ and len(found) == count, (count, found)
        with torch.inference_mode():
            for combo in found:
                variant = image.clone()
                for choices, r in zip(groups, combo, strict=True):
                    if r >= 0:
                        where, values = choices[r]
                        variant.view(3, -1)[:, where] = values
                assert margin(model, variant, c)[0] <= scale + rounding
    assert _low_variants(logits, changes, c, float(margins[70]))[0] is None  # more than VARIANTS


def test_a_group_with_too_many_images_is_boxed_and_no_image_below_the_margin_is_missed():
    """Beside four fragile pixels (each its colour or one of two others), a block of twelve
    neighbours, each its colour or one a little off it (4,095 images, more than a group's changes
    are computed for), is one box bounded as a whole: at a threshold above the margin of any of
    the few pixels' 81 images, that image with the block changed may be below it too, so the
    box is open, never left out of a list of images; below the bound of every
    image, nothing is open, and none of 4,000 images sampled over all sixteen pixels' choices
    (each classified whole) is below it."""
    torch.manual_seed(4)
    model = randomised(Local(), 4)
    e = enumeration(3)
    image = torch.from_numpy(e.images(len(e) // 2, len(e) // 2 + 1))
    few = [5 * W + 5, 6 * W + 5, 7 * W + 6, 21 * W + 36]
    block = [r * W + col for r in (14, 15, 16) for col in (20, 21, 22, 23)]
    pixels = np.array(few + block)
    g = torch.Generator().manual_seed(1)
    flat = image.view(3, -1)
    options = [[torch.rand(3, generator=g) for _ in range(2)] for _ in few]
    options += [[(flat[:, p] + 0.0004 * torch.rand(3, generator=g) - 0.0002).clamp(0, 1)] for p in block]
    net = IncrementalNetwork.of(model)
    rng = np.random.default_rng(0)
    with torch.inference_mode():
        logits = net.start(image)[0].clone()
        c = int(logits.argmax())
        assert net.affine()
        groups = _groups(net, pixels, options)
        boxed = [g for g, x in enumerate(groups) if isinstance(x[0], _Box)]
        assert len(boxed) == 1 and sorted(groups[boxed[0]][0].pixels.tolist()) == block
        changes = [_change(net, x, c) for x in groups]
        picks = [rng.integers(0, len(o) + 1, 4000) for o in options]  # 0: the current colour
        samples = image.repeat(4000, 1, 1, 1)
        for p, o, pick in zip(pixels.tolist(), options, picks, strict=True):
            for r, colour in enumerate(o, 1):
                samples.view(4000, 3, -1)[torch.from_numpy(pick == r), :, p] = colour
        margins = margin(model, samples, c)
        exact = image.repeat(81, 1, 1, 1)  # the few pixels' images, the block as it is
        for x, combo in enumerate(itertools.product(*([None, *o] for o in options[:4]))):
            for p, colour in zip(few, combo, strict=True):
                if colour is not None:
                    exact[x].view(3, -1)[:, p] = colour
        levels = np.sort(margin(model, exact, c))
    rounding = 1e-6 * max(1.0, float(logits.abs().max()))  # float32 sums in another order
    for n in (1, 5, 10, 40):  # an image below: one the box's bound leaves open
        scale = float(levels[n - 1] + levels[n]) / 2
        assert _low_variants(logits, changes, c, scale)[1] == {(boxed[0], 0)}
    box = float(-changes[boxed[0]][0].min())
    scale = float(levels[0]) - box - (float(levels[-1]) - float(levels[0])) - rounding
    assert _low_variants(logits, changes, c, scale) == ([], set())  # below every bound: nothing open
    assert (margins > scale + rounding).all()  # and no sampled image below it


def test_a_box_split_until_its_bound_holds_gives_exactly_the_images_below_the_margin(monkeypatch):
    """Beside two fragile pixels (each its colour or one of two others), a block of five
    neighbours, each its colour or one of two others (242 images, a box where a group's changes
    are computed for at most 64, whose bound over them all says little): the box split where its
    bound leaves an image open, the images whose margin may be at most a threshold are those of
    all 2,186 (each classified whole) below it, from none to dozens, up to float rounding; and a
    box's parts hold its images between them, each once."""
    monkeypatch.setattr(enumeration_method, "GROUP_VARIANTS", 64)
    torch.manual_seed(4)
    model = randomised(Local(), 4)
    e = enumeration(3)
    image = torch.from_numpy(e.images(len(e) // 2, len(e) // 2 + 1))
    few = [5 * W + 5, 21 * W + 36]
    block = [r * W + col for r in (14, 15) for col in (20, 21)] + [16 * W + 21]
    pixels = np.array(few + block)
    g = torch.Generator().manual_seed(1)
    options = [[torch.rand(3, generator=g), torch.rand(3, generator=g)] for _ in pixels]
    net = IncrementalNetwork.of(model)
    with torch.inference_mode():
        logits = net.start(image)[0].clone()
        c = int(logits.argmax())
        assert net.affine()
        flat = image.view(3, -1)
        margins = np.sort(margin(model, every_image(image, pixels, options), c))  # each classified whole
        groups = _groups(net, pixels, options)
        box = next(x[0] for x in groups if isinstance(x[0], _Box))
        assert sorted(box.pixels.tolist()) == block and box.count() == 3**5
        parts, leaves = [box], []
        while parts:
            part = parts.pop()
            made = _split(flat, part)
            assert not (len(made) == 1 and made[0] is part)  # a box is always split
            parts += [x for x in made if isinstance(x, _Box)]
            leaves += [x for x in made if not isinstance(x, _Box)]
        held = [tuple(flat[:, box.pixels].T.reshape(-1).tolist())]  # the current image
        for where, values in leaves:
            variant = flat[:, box.pixels].clone()
            variant[:, np.searchsorted(box.pixels, where)] = values
            held.append(tuple(variant.T.reshape(-1).tolist()))
        assert len(held) == len(set(held)) == 3**5
        rounding = 1e-6 * max(1.0, float(logits.abs().max()))  # float32 sums in another order
        unsplit = _low_variants(logits, [_change(net, x, c) for x in groups], c, float(margins[0]) - 2 * rounding)
        assert unsplit[1]  # the box's bound alone leaves an image open
        for count in (0, 1, 5, 30):
            scale = float(margins[count]) - 2 * rounding
            found = _open_images(net, _groups(net, pixels, options), logits, c, scale)[0]
            assert found is not None
            alone = []
            for where, values in found:
                variant = image.clone()
                variant.view(3, -1)[:, where] = values
                alone.append(float(margin(model, variant, c)[0]))
            assert len(set(map(tuple, (w.tolist() + v.reshape(-1).tolist() for w, v in found)))) == len(found)
            assert (np.array(alone) <= scale + rounding).all()  # none above the threshold
            assert len(found) >= int((margins < scale - rounding).sum())  # none below it missed


def test_a_window_s_images_found_unit_by_unit_are_exactly_those_of_every_choice_of_its_units():
    """Free points, each in one of two or three pixels or off the image, some sharing pixels, two
    of them twins (in their r-th pixels together), and per pixel the points that may show there
    nearest first (a point held throughout, or the background): the images found unit by unit,
    equal ones kept once and grouped by the windows their pixels reach, are exactly the distinct
    images of every choice of every unit (brute force), each pixel showing the nearest point there."""
    torch.manual_seed(4)
    model = randomised(Local(), 4)
    e = enumeration(3)
    image = torch.from_numpy(e.images(len(e) // 2, len(e) // 2 + 1))
    near, far = [5 * W + 5, 5 * W + 6, 6 * W + 5, 6 * W + 6], [18 * W + 30, 19 * W + 30]
    pixels = {0: [near[0], near[1]], 1: [near[1], near[3]], 2: [near[2], -1], 3: [near[0], near[2], near[3]],
              4: [near[3], near[1]], 5: [far[0], far[1]], 6: [far[1], -1], 7: [-1, -1]}  # fmt: skip
    units = {0: [0], -2: [1, 4], 2: [2], 3: [3], 5: [5], 6: [6], 7: [7]}  # 1 and 4 twins: r-th pixels together
    rng = np.random.default_rng(2)
    ranked = {}
    for p in near + far:
        there = [q for q, ps in pixels.items() if p in ps]
        held = int(rng.choice([-1, 10 + p % 7]))  # the point there throughout, or the background
        order = list(rng.permutation([*there, held]))
        if held == -1:  # the background is the farthest
            order.remove(-1)
            order.append(-1)
        ranked[p] = [int(q) for q in order]
    table = torch.from_numpy(rng.uniform(0, 1, (30, 3)).astype(np.float32))
    net = IncrementalNetwork.of(model)
    with torch.inference_mode():
        net.start(image)
        groups = _point_groups(net, pixels, ranked, units, table)
    assert groups is not None and len(groups) == 2  # the near pixels and the far ones
    brute = set()
    for combo in itertools.product(*[range(len(pixels[qs[0]])) for qs in units.values()]):
        chosen = {q: pixels[q][r] for qs, r in zip(units.values(), combo, strict=True) for q in qs}
        variant = image.clone().view(3, -1)
        for p, order in ranked.items():
            variant[:, p] = table[next(q for q in order if q not in pixels or chosen[q] == p)]
        brute.add(variant.numpy().tobytes())
    found = set()
    for picked in itertools.product(*groups):
        variant = image.clone().view(3, -1)
        for where, values in picked:
            variant[:, torch.from_numpy(where)] = values
        found.add(variant.numpy().tobytes())
    assert found == brute and len(brute) > 8
    assert np.prod([len(choices) for choices in groups]) == len(brute)  # each image once
    assert sum(len(choices) for choices in groups) < np.prod([len(ps) for ps in pixels.values()])  # kept once
