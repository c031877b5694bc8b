"""Deterministic certification by bound propagation: every image of a pose piece inside its box,
every logit inside its bounds, exact where it must be, and no verified image that a sampled
pose gets wrong (docs/method.md §9)."""

import itertools

import numpy as np
import pytest
import torch
import torchvision
from torch import nn

from mrcert.core.methods.base import BaseClassifier, CertifyRequest
from mrcert.core.methods.bound_propagation import BoundPropagation, IntervalVerifier
from mrcert.core.models import Normalize, SmallCNN
from mrcert.core.verification.image_bounds import image_boxes
from mrcert.core.verification.network import BoundNetwork
from mrcert.data.samples import TestSample
from mrcert.errors import ConfigError, MrcertError
from tests.conftest import PAPER_K, compose_cfg
from tests.test_pixelwise import H, W, _tied_occluding_scene, occluding_scene, render, striped_wall

AXES_AND_WIDTHS = [("tx", 0.002, False), ("ty", 0.002, False), ("tz", 0.002, False), ("tz", 0.006, True)] + [
    (axis, 0.001, False) for axis in ("rx", "ry", "rz")
]


def piece_poses(axis: str, start: float, end: float, count: int, seed: int = 0) -> torch.Tensor:
    """``count`` motions drawn uniformly in the piece, plus its ends, its middle and poses just inside."""
    rng = np.random.default_rng(seed)
    values = np.concatenate(
        [rng.uniform(start, end, count), [start, end, 0.5 * (start + end), start + 1e-12, end - 1e-12]]
    )
    motions = torch.zeros(len(values), 6, dtype=torch.float64)
    motions[:, ["tx", "ty", "tz", "rx", "ry", "rz"].index(axis)] = torch.from_numpy(values)
    return motions


def outside(views: torch.Tensor, low: np.ndarray, high: np.ndarray) -> int:
    """How many pixel values of ``views`` (B, C, H, W) fall outside ``[low, high]`` (C, H, W)."""
    v = views.double()
    return int(((v < torch.from_numpy(low)) | (v > torch.from_numpy(high))).sum())


@pytest.mark.parametrize(("axis", "half_width", "near_plane"), AXES_AND_WIDTHS)
def test_every_image_of_a_piece_lies_in_its_box_on_every_axis(axis, half_width, near_plane):
    """The certifying path (a test sample cropped for the interval, rendered by its renderer,
    bounded from ``cloud_for`` with its ranks), exact ties and points crossing the camera plane:
    over 1,000 poses per piece, every pixel and channel of every image inside the piece's box."""
    points, colors = _tied_occluding_scene(near_plane)
    method = BoundPropagation(axis, half_width)
    sample = TestSample.build(points.numpy(), colors.numpy(), PAPER_K, H, W, label=0, bound=method.crop_bound(1.0))
    render = sample.renderer()
    edges = np.linspace(-half_width, half_width, 4)
    crop, crop_colors, rank = sample.cloud_for(piece_poses(axis, -half_width, half_width, 0))
    assert len(crop) < len(points)
    low, high = image_boxes(crop, crop_colors, sample.K, axis, edges[:-1], edges[1:], H, W, sample.background, rank)
    for k in range(3):
        views = render(piece_poses(axis, edges[k], edges[k + 1], 1000, seed=k))
        assert outside(views, low[k], high[k]) == 0
    # Not vacuous: most pixels of a millimetre piece keep one value (unless points may cross the
    # camera plane, which may put them anywhere).
    assert ((high - low).max(1) == 0).mean() > (0.2 if near_plane else 0.5)


@pytest.mark.parametrize("axis", ["tz", "rz"])
def test_a_roll_keeps_depth_ties_as_a_translation_does(axis):
    """Along a roll, as along a translation, every depth stays its reference depth, so exact
    copies of points in other colours never show (the staying point of lower rank wins each
    tie): micro-radian pieces on either side of no motion keep every pixel to one value, and
    every sampled pose's image lies inside its piece's box."""
    points, colors = _tied_occluding_scene(False)
    sample = TestSample.build(
        points.numpy(), colors.numpy(), PAPER_K, H, W, label=0, bound=BoundPropagation(axis, 1e-6).crop_bound(1.0)
    )
    edges = np.array([-1e-6, 0.0, 1e-6])
    crop, crop_colors, rank = sample.cloud_for(piece_poses(axis, -1e-6, 1e-6, 0))
    low, high = image_boxes(crop, crop_colors, sample.K, axis, edges[:-1], edges[1:], H, W, sample.background, rank)
    render = sample.renderer()
    for k in range(2):
        assert outside(render(piece_poses(axis, edges[k], edges[k + 1], 300, seed=k)), low[k], high[k]) == 0
    assert ((high - low).max(1) == 0).all()


def row_sampled_wall() -> tuple[torch.Tensor, torch.Tensor]:
    """A wall sampled in rows along x, as synthetic scenes are: each row's points share their
    height and depth exactly (the wall leans back, so rows lie at different depths), several to a
    pixel, each of its own colour."""
    x, y = np.meshgrid((np.arange(-200, 200) + 0.5) * 0.003, (np.arange(-100, 100) + 0.5) * 0.003)  # none on an axis
    points = np.column_stack([x.ravel(), y.ravel(), 3.0 + 0.3 * y.ravel()])
    colors = np.random.default_rng(5).uniform(0, 1, (len(points), 3)).astype(np.float32)
    return torch.from_numpy(points), torch.from_numpy(colors)


def test_a_pitch_keeps_a_rows_ties_and_a_yaw_breaks_them():
    """Along a pitch the points of a row keep one depth (their height and depth are equal), so
    the row's first point holds its pixels: micro-radian pieces keep almost every pixel to one
    value. Along a yaw their depths part at any angle, however small, and on one side of no
    rotation the image changes in most pixels. Either way a box is wide only where the piece's
    images change (sound, and as tight as the images allow)."""
    points, colors = row_sampled_wall()
    edges = np.array([-1e-6, 0.0, 1e-6])
    reference = render(points, colors, torch.zeros(1, 6, dtype=torch.float64))
    for axis in ("rx", "ry"):
        low, high = image_boxes(points, colors, PAPER_K, axis, edges[:-1], edges[1:], H, W, 1.0)
        changed = []
        for k in range(2):
            views = render(points, colors, piece_poses(axis, edges[k], edges[k + 1], 300, seed=k))
            assert outside(views, low[k], high[k]) == 0
            changed.append(((views - reference).abs().amax(1) > 0).any(0).double().mean().item())
            wide = ((high[k] - low[k]).max(0) > 0).mean()
            assert wide <= changed[k] + 0.01, (axis, k, wide, changed[k])
            if axis == "rx":
                assert wide < 0.02
        if axis == "ry":
            assert max(changed) > 0.5


def twinned_wall() -> tuple[torch.Tensor, torch.Tensor]:
    """A wall of points, each with a twin of the other colour and a higher rank a hair away:
    within a millimetre across and 1e-7 m in depth, so that pitches and yaws of a fraction of a
    milliradian reorder the pairs one way or the other."""
    rng = np.random.default_rng(11)
    base = np.column_stack([rng.uniform(-1.5, 1.5, 20000), rng.uniform(-0.8, 0.8, 20000), np.full(20000, 3.0)])
    twins = base + np.column_stack([rng.uniform(-1e-3, 1e-3, (20000, 2)), rng.uniform(-1e-7, 1e-7, 20000)])
    colors = rng.uniform(0, 1, (20000, 3)).astype(np.float32)
    return torch.from_numpy(np.concatenate([base, twins])), torch.from_numpy(np.concatenate([colors, 1 - colors]))


@pytest.mark.parametrize("axis", ["rx", "ry"])
def test_pitch_and_yaw_pieces_on_either_side_of_no_rotation_hide_only_what_stays_hidden(axis):
    """On a piece on one side of no rotation a twin stays behind its point when it is no nearer
    and on the side the rotation turns away (a pitch's height, a yaw's abscissa): every sampled
    pose of pieces on either side and across, dense enough to see pairs swap, lies in its box,
    and the side rule hides twins there (not vacuous)."""
    points, colors = twinned_wall()
    edges = np.array([-1e-3, -2e-4, 0.0, 2e-4, 1e-3])
    starts, ends = np.concatenate([edges[:-1], [-2e-4]]), np.concatenate([edges[1:], [2e-4]])
    low, high = image_boxes(points, colors, PAPER_K, axis, starts, ends, H, W, 1.0)
    for k in range(len(starts)):
        views = render(points, colors, piece_poses(axis, starts[k], ends[k], 400, seed=k))
        assert outside(views, low[k], high[k]) == 0
    one_side, across = ((high - low).max(1) == 0).mean((1, 2))[[1, 4]]
    assert one_side > across + 0.05


@pytest.mark.parametrize("x", [1e-12, 0.0, -1e-12])
def test_points_on_the_principal_axis_keep_their_box(x):
    """Points a hair off the principal axis (or on it) project onto the column edge u = cx for
    every translation along z: every rendered pose agrees with the box, and the widening for
    rounding keeps the points just off it in one column (so those pixels keep one value)."""
    rng = np.random.default_rng(3)
    wall = np.column_stack([rng.uniform(-2, 2, 30000), rng.uniform(-1.2, 1.2, 30000), np.full(30000, 3.0)])
    axis_points = np.column_stack([np.full(400, x), np.linspace(-1.1, 1.1, 400), np.full(400, 2.0)])
    points = torch.from_numpy(np.concatenate([wall, axis_points]))
    colors = torch.from_numpy(rng.uniform(0, 1, (len(points), 3)).astype(np.float32))
    low, high = image_boxes(points, colors, PAPER_K, "tz", [-1e-6], [1e-6], H, W, 1.0)
    views = render(points, colors, piece_poses("tz", -1e-6, 1e-6, 300))
    assert outside(views, low[0], high[0]) == 0
    column = int(PAPER_K[0, 2]) - (x < 0)
    rows = np.unique(np.floor(PAPER_K[1, 1].item() * axis_points[:, 1] / 2.0 + PAPER_K[1, 2].item()))
    rows = rows[(rows >= 0) & (rows < H)].astype(int)
    if x != 0.0:  # one point, one value throughout
        assert (high[0, :, rows, column] - low[0, :, rows, column]).max() == 0


def test_a_box_from_the_end_images_alone_fails_the_dense_check():
    """The deliberate break: take each pixel's range over the piece's two end images only (as if
    nothing between them could differ). Stripes half a period apart look alike at both ends and
    inverted half-way: the dense check catches it, where the real box holds."""
    points, colors = striped_wall(0.05)
    ends = piece_poses("tx", 0.0, 0.05, 0)[:2]
    images = render(points, colors, ends).double()
    naive_low, naive_high = images.min(0).values.numpy(), images.max(0).values.numpy()
    views = render(points, colors, piece_poses("tx", 0.0, 0.05, 200))
    assert outside(views, naive_low, naive_high) > 0
    low, high = image_boxes(points, colors, PAPER_K, "tx", [0.0], [0.05], H, W, 1.0)
    assert outside(views, low[0], high[0]) == 0


# --- bound propagation ---------------------------------------------------------------------------
def random_box(shape, width: float, seed: int, zero_share: float = 0.0):
    g = torch.Generator().manual_seed(seed)
    centre = torch.rand((1, *shape), generator=g, dtype=torch.float64)
    radius = width * torch.rand((1, *shape), generator=g, dtype=torch.float64)
    radius[torch.rand((1, *shape), generator=g) < zero_share] = 0.0
    return centre - radius, centre + radius


def sampled(model: nn.Module, low, high, count: int, seed: int = 0) -> torch.Tensor:
    """Outputs at ``count`` points of the box: its corners' extremes in every coordinate and uniform draws."""
    g = torch.Generator().manual_seed(seed)
    t = torch.rand((count, *low.shape[1:]), generator=g, dtype=torch.float64)
    t[: count // 4] = t[: count // 4].round()  # vertices
    with torch.no_grad():
        return model.double()(low + (high - low) * t)


def margins_seen(outputs: torch.Tensor, target: int) -> torch.Tensor:
    seen = (outputs[:, target : target + 1] - outputs).min(0).values
    seen[target] = torch.inf
    return seen


def test_the_propagation_is_exact_on_a_linear_network():
    """For ``y = A x + b`` the least margin over a box has a closed form, attained at a vertex:
    ``(a_c - a_j) . centre + (b_c - b_j) - |a_c - a_j| . radius``. The backward relaxation
    reaches it (to float64 rounding); interval bounds of the two logits separately do not."""
    torch.manual_seed(0)
    net = nn.Sequential(nn.Flatten(), nn.Linear(24, 10), nn.Linear(10, 5)).double()
    low, high = random_box((2, 3, 4), 0.1, seed=1)
    a = (net[2].weight @ net[1].weight).detach()
    b = (net[2].weight @ net[1].bias + net[2].bias).detach()
    c, r = ((low + high) / 2).flatten(), ((high - low) / 2).flatten()
    for target in range(5):
        diff = a[target] - a
        exact = diff @ c + (b[target] - b) - diff.abs() @ r
        exact[target] = torch.inf
        crown = BoundNetwork(net).margins(low, high, target, "crown", upto=np.inf)[0]
        interval = BoundNetwork(net).margins(low, high, target, "interval")[0]
        assert torch.allclose(crown, exact, rtol=1e-12, atol=1e-12)
        assert (interval <= exact + 1e-12).all() and (interval < exact - 1e-6).any()


def test_a_tiny_relu_network_against_brute_force():
    """Two inputs, six ReLUs, three classes: the least margin over a 601 x 601 grid of the box
    (the truth, to the grid's resolution) is never below a bound, the backward relaxation is
    never looser than interval bounds, and where every ReLU is stable on the box it is exact."""
    torch.manual_seed(4)
    net = nn.Sequential(nn.Linear(2, 6), nn.ReLU(), nn.Linear(6, 3)).double()
    grid = torch.stack(torch.meshgrid(torch.linspace(0, 1, 601), torch.linspace(0, 1, 601), indexing="ij"), -1)
    for seed, width in itertools.product(range(4), (0.02, 0.3)):
        low, high = random_box((2,), width, seed)
        points = (low + (high - low) * grid.reshape(-1, 2).double()).detach()
        with torch.no_grad():
            outputs = net(points)
        for target in range(3):
            truth = margins_seen(outputs, target)
            crown = BoundNetwork(net).margins(low, high, target, "crown", upto=np.inf)[0]
            interval = BoundNetwork(net).margins(low, high, target, "interval")[0]
            assert (crown <= truth + 1e-12).all() and (interval <= truth + 1e-12).all()
            assert (crown >= interval - 1e-12).all()
            with torch.no_grad():
                pre = net[0](torch.cat([low, high, points]))
            if ((pre > 0).all(0) | (pre < 0).all(0)).all():  # stable: the network is affine on the box
                corners = torch.tensor(list(itertools.product(*zip(low[0].tolist(), high[0].tolist(), strict=True))))
                with torch.no_grad():
                    exact = margins_seen(net(corners.double()), target)
                assert torch.allclose(crown, exact, atol=1e-9)


def perturbed(model: nn.Module) -> nn.Module:
    """``model`` in evaluation mode with batch-norm statistics and affine terms drawn away from
    the identity (so that they matter)."""
    g = torch.Generator().manual_seed(0)
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.copy_(torch.rand(m.running_mean.shape, generator=g) - 0.5)
            m.running_var.copy_(torch.rand(m.running_var.shape, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(m.weight.shape, generator=g) + 0.5)
            m.bias.data.copy_(torch.rand(m.bias.shape, generator=g) * 0.4 - 0.2)
    return model.eval()


@pytest.mark.parametrize(
    ("name", "build", "width"),
    [
        ("small_cnn", lambda: SmallCNN(6, 8), 0.003),
        ("resnet18", lambda: torchvision.models.resnet18(num_classes=6), 0.0005),
        pytest.param("resnet50", lambda: torchvision.models.resnet50(num_classes=6), 0.0002, marks=pytest.mark.slow),
    ],
)
def test_every_layer_of_our_architectures_is_bounded_soundly(name, build, width):
    """Convolution, batch norm, ReLU, max pooling (the ResNets' overlapping windows), residual
    additions, average pooling and flattening, behind our normaliser: the layers' forward pass is
    the module's, and every output of 256 points of a box (vertices among them) lies within the
    interval bounds and above every margin bound."""
    torch.manual_seed(1)
    model = perturbed(nn.Sequential(Normalize(), build()))
    network = BoundNetwork(model)
    low, high = random_box((3, 24, 40), width, seed=2, zero_share=0.9)
    with torch.no_grad():
        assert torch.allclose(network.forward(low), model.double()(low), atol=1e-10)
    outputs = sampled(model, low, high, 256)
    l_out, u_out = network.interval(low, high)[network.output]
    assert (outputs >= l_out - 1e-9).all() and (outputs <= u_out + 1e-9).all()
    target = int(outputs[0].argmax())
    crown = network.margins(low, high, target, "crown", upto=np.inf)[0]
    assert (crown <= margins_seen(outputs, target) + 1e-9).all()


@pytest.mark.parametrize(
    ("name", "build", "width"),
    [
        ("small_cnn", lambda: SmallCNN(6, 8), 0.02),
        ("resnet18", lambda: torchvision.models.resnet18(num_classes=6), 0.002),
    ],
)
def test_linear_bounds_carried_forwards_hold_on_every_layer(name, build, width):
    """Boxes that perturb a few inputs (two boxes of a batch, each its own few, the rest fixed):
    the bounds carried forwards in those inputs hold every layer's value at 256 points of each
    box, are never looser than interval bounds, and the margins they give hold too; somewhere
    they are tighter than interval bounds."""
    torch.manual_seed(1)
    model = perturbed(nn.Sequential(Normalize(), build()))
    carried, plain = BoundNetwork(model, forward_inputs=64), BoundNetwork(model)
    boxes = [random_box((3, 24, 40), width, seed=s, zero_share=0.995) for s in (3, 4)]
    low, high = torch.cat([b[0] for b in boxes]), torch.cat([b[1] for b in boxes])
    free = int((high > low).flatten(1).any(0).sum())
    assert 0 < free <= 64
    bounds = carried.interval(low, high, tighten=True)
    intervals = plain.interval(low, high)
    for b in range(2):
        points = low[b : b + 1] + (high - low)[b : b + 1] * torch.rand((256, 3, 24, 40), dtype=torch.float64)
        points[:2] = torch.cat([low[b : b + 1], high[b : b + 1]])
        with torch.no_grad():
            values = carried.forward(points, every=True)
        for k, (lo, up) in enumerate(bounds):
            assert (values[k] >= lo[b : b + 1] - 1e-9).all() and (values[k] <= up[b : b + 1] + 1e-9).all(), k
            assert (lo[b] >= intervals[k][0][b] - 1e-12).all() and (up[b] <= intervals[k][1][b] + 1e-12).all()
        outputs = values[carried.output]
        target = int(outputs[0].argmax())
        crown = carried.margins(low[b : b + 1], high[b : b + 1], target, "crown", upto=np.inf)[0]
        assert (crown <= margins_seen(outputs, target) + 1e-9).all()
    gained = [(i[1] - i[0]).sum() - (c[1] - c[0]).sum() for c, i in zip(bounds, intervals, strict=True)]
    assert max(gained) > 0


def two_input_boxes():
    """A ReLU network of two inputs (two ReLU layers, three classes), and three boxes of it, each
    with a 401 x 401 grid of its points, every layer's value there, the centre's class and the
    margins' specification (the other classes' rows)."""
    torch.manual_seed(4)
    net = nn.Sequential(nn.Linear(2, 8), nn.ReLU(), nn.Linear(8, 8), nn.ReLU(), nn.Linear(8, 3)).double()
    network = BoundNetwork(net, forward_inputs=16)
    grid = torch.stack(torch.meshgrid(torch.linspace(0, 1, 401), torch.linspace(0, 1, 401), indexing="ij"), -1)
    for seed in range(3):
        low, high = random_box((2,), 0.3, seed)
        points = (low + (high - low) * grid.reshape(-1, 2).double()).detach()
        with torch.no_grad():
            values = network.forward(points, every=True)
        target = int(values[network.output][len(points) // 2].argmax())
        spec = -torch.eye(3, dtype=torch.float64)
        spec[:, target] += 1.0
        yield network, low, high, points, values, target, spec[[j for j in range(3) if j != target]]


def test_bounds_on_the_parts_of_a_relu_split_hold_there_and_the_parts_cover_the_box():
    """Two inputs, two ReLU layers, three classes, a 401 x 401 grid of each box: for each of its
    unstable neurons assumed active and then inactive, the margins bounded on that part are never
    above the least margin over the grid's points in it (an empty part: +inf), and on at least
    one split both parts' bounds beat the unsplit box's."""
    gained = False
    for seed, (network, low, high, _, values, target, spec) in enumerate(two_input_boxes()):
        whole, scores = network.split_lower(low, high, spec, {})
        for k, score in scores[0].items():
            pre = values[network.layers[k].inputs[0]].flatten(1)
            for i in torch.nonzero(score.flatten() > 0)[:, 0].tolist():
                parts = []
                for active in (True, False):
                    mask = torch.zeros((1, *score.shape[1:]), dtype=torch.bool)
                    mask.view(-1)[i] = True
                    splits = {k: (mask, torch.zeros_like(mask)) if active else (torch.zeros_like(mask), mask)}
                    bound = network.split_lower(low, high, spec, splits)[0][0]
                    inside = pre[:, i] >= 0 if active else pre[:, i] <= 0
                    y = values[network.output][inside]
                    truth = (y[:, target : target + 1] - y).min(0).values if len(y) else torch.full((3,), torch.inf)
                    seen = torch.stack([truth[j] for j in range(3) if j != target])
                    assert (bound <= seen + 1e-9).all(), (seed, k, i, active)
                    parts.append(bound)
                gained |= bool(((parts[0] > whole[0] + 1e-9) & (parts[1] > whole[0] + 1e-9)).any())
    assert gained


def test_optimised_slopes_and_split_multipliers_hold_on_the_part_and_never_loosen():
    """The same grid and network: on parts split on two unstable neurons at once (each sign of
    each), the bounds with optimised ReLU slopes and split multipliers (alpha- and beta-CROWN)
    are never above the least margin over the grid's points in the part, never below the bounds
    without them, and on some part strictly above."""
    gained = 0.0
    for seed, (network, low, high, points, values, target, spec) in enumerate(two_input_boxes()):
        _, scores = network.split_lower(low, high, spec, {})
        unstable = [(k, i) for k, score in scores[0].items() for i in torch.nonzero(score.flatten() > 0)[:, 0].tolist()]
        for (k1, i1), (k2, i2) in itertools.combinations(unstable[:5], 2):
            for signs in itertools.product((True, False), repeat=2):
                splits, inside = {}, torch.ones(len(points), dtype=torch.bool)
                for (k, i), active in zip(((k1, i1), (k2, i2)), signs, strict=True):
                    shape = scores[0][k].shape[1:]
                    on, off = splits.get(k, (torch.zeros((1, *shape), dtype=torch.bool),) * 2)
                    on, off = on.clone(), off.clone()
                    (on if active else off).view(-1)[i] = True
                    splits[k] = (on, off)
                    pre = values[network.layers[k].inputs[0]].flatten(1)[:, i]
                    inside &= pre >= 0 if active else pre <= 0
                plain = network.split_lower(low, high, spec, splits)[0][0]
                optimised = network.split_lower(low, high, spec, splits, steps=30)[0][0]
                y = values[network.output][inside]
                truth = (y[:, target : target + 1] - y).min(0).values if len(y) else torch.full((3,), torch.inf)
                seen = torch.stack([truth[j] for j in range(3) if j != target])
                assert (optimised <= seen + 1e-9).all(), (seed, k1, i1, k2, i2, signs)
                assert (optimised >= plain - 1e-12).all()
                finite = torch.isfinite(plain)
                gained = max(gained, float((optimised - plain)[finite].max()) if finite.any() else 0.0)
    assert gained > 1e-6


def test_a_layer_it_cannot_bound_is_refused_in_one_line():
    class Squares(nn.Module):
        def forward(self, x):
            return (x * x).flatten(1)

    with pytest.raises(MrcertError, match="bound propagation does not support"):
        BoundNetwork(Squares())
    with pytest.raises(MrcertError, match="does not support Sigmoid"):
        BoundNetwork(nn.Sequential(nn.Flatten(), nn.Sigmoid()))


# --- the method --------------------------------------------------------------------------------
def Brightness(threshold: float, rows=slice(30, 60), cols=slice(60, 100)) -> nn.Module:
    """Two classes by the mean brightness of a window of the image (ten times its excess over
    ``threshold``, and the opposite): linear, so its bounds are exactly the box's, and a motion
    that carries an edge through the window flips it."""
    mask = torch.zeros(3, H, W)
    mask[:, rows, cols] = 1.0 / (3 * (rows.stop - rows.start) * (cols.stop - cols.start))
    head = nn.Linear(3 * H * W, 2)
    with torch.no_grad():
        head.weight.copy_(torch.stack([10 * mask.flatten(), -10 * mask.flatten()]))
        head.bias.copy_(torch.tensor([-10 * threshold, 10 * threshold]))
    return nn.Sequential(nn.Flatten(), head)


def verifier(model: nn.Module, axis: str, half_width: float, **kwargs) -> IntervalVerifier:
    method = BoundPropagation(axis, half_width, **kwargs)
    return method.certifier(BaseClassifier(model.eval(), 2, batch_size=64))


def sample_for(axis: str, half_width: float, seed: int = 0) -> TestSample:
    points, colors = occluding_scene(seed)
    bound = BoundPropagation(axis, half_width).crop_bound(1.0)
    return TestSample.build(points.numpy(), colors.numpy(), PAPER_K, H, W, label=0, bound=bound)


REQUEST = CertifyRequest(0, 0, 0.01, 0.0)


@pytest.mark.parametrize(("axis", "half_width"), [("tx", 0.004), ("tz", 0.02), ("ry", 0.003), ("rz", 0.01)])
def test_no_verified_interval_has_a_sampled_pose_classified_otherwise(axis, half_width):
    """Soundness of the whole method: thresholds from easy to impossible; wherever the interval
    is verified, 3,000 sampled poses are all classified as the prediction; wherever it is
    falsified, the logged pose is inside the interval and classified otherwise."""
    sample = sample_for(axis, half_width)
    probe = sample.renderer()(piece_poses(axis, -half_width, half_width, 3000))
    window = (probe[:, :, 30:60, 60:100]).double().mean((1, 2, 3))
    centre = float(window[-3])  # the middle pose: 0
    outcomes = set()
    for threshold in np.quantile(window.numpy(), [0.0, 0.3, 0.7, 1.0]).tolist() + [centre - 0.2, centre + 0.2]:
        model = Brightness(threshold)
        cert = verifier(model, axis, half_width, seconds=60, max_pieces=64).certify_sample(
            sample.renderer(), REQUEST, torch.Generator()
        )
        outcomes.add(cert.details["outcome"])
        with torch.no_grad():
            seen = model(probe).argmax(1)
        if cert.details["outcome"] == "verified":
            assert cert.radius == half_width and (seen == cert.prediction).all() and cert.margin > 0
        elif cert.details["outcome"] == "falsified":
            pose = cert.details["counterexample"]
            assert abs(pose) <= half_width and cert.radius == 0.0
            motion = piece_poses(axis, pose, pose, 0)[:1]
            with torch.no_grad():
                assert int(model(sample.renderer()(motion)).argmax()) != cert.prediction
    assert {"verified", "falsified"} <= outcomes


@pytest.mark.slow
def test_every_logit_of_a_sampled_pose_lies_within_the_bounds_of_its_piece():
    """A convolutional classifier on the occluding scene: per piece, the logits of 500 sampled
    poses lie within the interval bounds of the piece's box pushed through the network, and
    every margin above its bound."""
    torch.manual_seed(2)
    model = perturbed(nn.Sequential(Normalize(), SmallCNN(4, 8)))
    sample = sample_for("tz", 0.01)
    render = sample.renderer()
    network = BoundNetwork(model)
    edges = np.linspace(-0.01, 0.01, 5)
    crop, crop_colors, rank = sample.cloud_for(piece_poses("tz", -0.01, 0.01, 0))
    low, high = image_boxes(crop, crop_colors, sample.K, "tz", edges[:-1], edges[1:], H, W, 1.0, rank)
    low, high = torch.from_numpy(low), torch.from_numpy(high)
    l_out, u_out = network.interval(low, high)[network.output]
    margins = network.margins(low, high, 0, "crown", upto=np.inf)
    for k in range(4):
        with torch.no_grad():
            logits = model.double()(render(piece_poses("tz", edges[k], edges[k + 1], 500, seed=k)).double())
        assert (logits >= l_out[k] - 1e-9).all() and (logits <= u_out[k] + 1e-9).all()
        assert (margins_seen(logits, 0) >= margins[k] - 1e-9).all()


def test_a_budget_spent_leaves_the_image_unknown_with_its_counts():
    """A threshold at the window's value at the test pose cannot be decided away from it: with a
    budget of 4 pieces the answer is unknown, after exactly 4 bound passes, and not certified."""
    sample = sample_for("tz", 0.02)
    with torch.no_grad():
        centre = float(sample.renderer()(piece_poses("tz", 0, 0, 0)[:1])[:, :, 30:60, 60:100].double().mean())
    cert = verifier(Brightness(centre + 1e-4), "tz", 0.02, max_pieces=4, samples=2).certify_sample(
        sample.renderer(), REQUEST, torch.Generator()
    )
    if cert.details["outcome"] != "falsified":
        assert cert.details["outcome"] == "unknown" and cert.details["bound_passes"] == 4 and cert.radius == 0.0


def test_the_profiles_budget_is_pieces_so_a_slow_machine_gets_the_same_answer(monkeypatch):
    """An image the quick profile cannot decide (its class holds at 3,000 sampled poses, a hair
    above the threshold, beyond what the bounds resolve) uses up its budget of pieces: the same
    answer, bound passes and pieces with the machine's clock running a million times slower."""
    from types import SimpleNamespace

    from mrcert.core.methods import bound_propagation

    sample = sample_for("tz", 0.02)
    with torch.no_grad():
        window = sample.renderer()(piece_poses("tz", -0.02, 0.02, 3000))[:, :, 30:60, 60:100].double().mean((1, 2, 3))
    lowest = float(window.min())
    for profile in ("quick", "paper"):
        assert compose_cfg([f"profile={profile}", "method=bound_propagation"]).method.seconds == float("inf")
    m = compose_cfg(["profile=quick", "method=bound_propagation"]).method

    def answer() -> dict:
        made = verifier(Brightness(lowest - 1e-6), "tz", 0.02, max_pieces=m.max_pieces, seconds=m.seconds, samples=2)
        cert = made.certify_sample(sample.renderer(), REQUEST, torch.Generator())
        return {k: cert.details[k] for k in ("outcome", "bound_passes", "pieces")}

    here = answer()
    clock = iter(itertools.count(step=1e6))
    monkeypatch.setattr(bound_propagation, "time", SimpleNamespace(perf_counter=lambda: float(next(clock))))
    assert answer() == here and here["outcome"] == "unknown" and here["bound_passes"] == m.max_pieces


def test_tasks_it_cannot_serve_are_refused_naming_what_it_serves():
    from mrcert.infra.config import validate

    base = ["method=bound_propagation", "model=small_cnn"]
    for overrides, key in (
        (["task=smooth"], "task"),
        (["task=attack"], "task"),
        (["task=certify", "task.sequential=true"], "task.sequential"),
        (["task=train", "model.variant=augmented"], "model.variant"),
    ):
        with pytest.raises(ConfigError, match="method=bound_propagation serves: task=certify$") as err:
            validate(compose_cfg([*base, *overrides]))
        assert err.value.key == key
    validate(compose_cfg([*base, "task=certify"]))
    validate(compose_cfg([*base, "task=attack", "task.smoothed=false"]))  # the base model alone
    with pytest.raises(ConfigError, match="method.relaxation"):
        validate(compose_cfg([*base, "task=certify", "method.relaxation=alpha"]))


def test_a_piece_down_to_two_float_poses_is_decided_by_classifying_them():
    """A dark point crosses from column 80 into column 79 at tx = 1 mm. Any piece holding that pose
    has both pixels free in its box, whose corner with both dark fails the classifier (dark pixels
    of the two, fewer than one white); no rendered image has both dark. Bisection reaches pieces
    of at most 1,024 float64 poses around the crossing, each decided by classifying every one of
    its poses: verified, and every pose sampled is classified right."""
    points = torch.tensor([[1e-3, 0.0005, 1.0]], dtype=torch.float64)
    colors = torch.zeros(1, 3)
    row = int(PAPER_K[1, 1].item() * 0.0005 + PAPER_K[1, 2].item())
    mask = torch.zeros(3, H, W)
    mask[:, row, 79:81] = 1.0 / 3
    head = nn.Linear(3 * H * W, 2)
    with torch.no_grad():
        head.weight.copy_(torch.stack([10 * mask.flatten(), -10 * mask.flatten()]))
        head.bias.copy_(torch.tensor([-5.0, 5.0]))  # white pixels among the two, less a half
    model = nn.Sequential(nn.Flatten(), head)
    sample = TestSample.build(points.numpy(), colors.numpy(), PAPER_K, H, W, label=0)
    cert = verifier(model, "tx", 2e-3, samples=3, max_pieces=400, seconds=120).certify_sample(
        sample.renderer(), REQUEST, torch.Generator()
    )
    assert cert.details["outcome"] == "verified" and cert.radius == 2e-3
    assert cert.details["bound_passes"] > 40  # it went down to float resolution around the crossing
    with torch.no_grad():
        seen = model(sample.renderer()(piece_poses("tx", -2e-3, 2e-3, 2000))).argmax(1)
    assert (seen == 0).all()
