"""The projection O(V, alpha) against Open3D, the paper's closed forms and Lemma 1."""

import numpy as np
import pytest
import torch

from mrcert.core import projection
from mrcert.core.axes import AXES, axis_index
from mrcert.core.geometry import compose, motion_to_matrix, rotvec_to_matrix
from mrcert.core.projection import camera_points, project
from tests.conftest import PAPER_K, random_cloud, random_motions

H, W = 90, 160
BACKENDS = ["numba", "torch"]


def move_cloud(points: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """Camera coordinates R^T (P - t) of points after the camera moves by ``motion``."""
    R = rotvec_to_matrix(motion[3:])
    return (points - motion[:3]) @ R


def open3d_depth(points: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """Open3D's depth image (0 = empty) of float32 ``points``, with cx - 0.5, cy - 0.5 (docs/method.md §2)."""
    import open3d as o3d

    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(np.float32)))
    pcd.point.colors = o3d.core.Tensor(np.ones((len(points), 3), np.float32))
    K = PAPER_K.clone()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    rgbd = pcd.project_to_rgbd_image(
        W, H, o3d.core.Tensor(K.numpy()), o3d.core.Tensor(extrinsic), depth_scale=1.0, depth_max=1e6
    )
    return np.asarray(rgbd.depth.as_tensor().numpy())[..., 0]


def unambiguous(camera_points: np.ndarray, margin: float = 1e-3) -> np.ndarray:
    """Mask of points whose pixel coordinates lie more than ``margin`` px from a pixel edge.

    Open3D computes in float32 (~1e-5 px of error), so points closer to an edge than that may
    legitimately land on either side; they are left out of the comparison.
    """
    X, Y, Z = camera_points.T.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 386.274 * (X / Z) + 80.0
        v = 386.274 * (Y / Z) + 45.0
    frac = lambda a: np.abs(a - np.round(a))  # noqa: E731
    return (Z <= 0) | ((frac(u) > margin) & (frac(v) > margin))


def as_depth_image(depth: torch.Tensor) -> np.ndarray:
    return torch.where(torch.isinf(depth), 0.0, depth).float().numpy()


@pytest.mark.parametrize("backend", BACKENDS)
def test_pixel_rule_and_zbuffer_equal_open3d_exactly(backend, rng):
    """Clouds moved by random motions, projected by both: identical float32 depth images."""
    points, colors = random_cloud(rng)
    for motion in random_motions(rng):
        moved = move_cloud(points, motion).numpy().astype(np.float32)
        moved = moved[unambiguous(moved)]
        _, depth = project(
            torch.from_numpy(moved.astype(np.float64)),
            colors[: len(moved)],
            PAPER_K,
            torch.zeros(1, 6, dtype=torch.float64),
            H,
            W,
            backend=backend,
        )
        theirs = open3d_depth(moved, np.eye(4))
        assert (theirs > 0).sum() > 1000
        np.testing.assert_array_equal(as_depth_image(depth[0]), theirs, err_msg=f"motion {motion.tolist()}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_motions_match_open3d_extrinsics(backend, rng):
    """Our motion = Open3D extrinsic inv([[R, t], [0, 1]]): same pixels filled, same depths to float32."""
    points, colors = random_cloud(rng)
    points = points.float().double()  # the float32 cloud Open3D sees
    for motion in random_motions(rng):
        keep = torch.from_numpy(unambiguous(move_cloud(points, motion).numpy(), margin=1e-2))
        pts = points[keep]
        _, depth = project(pts, colors[keep], PAPER_K, motion[None], H, W, backend=backend)
        extrinsic = torch.linalg.inv(motion_to_matrix(motion)).numpy()
        theirs = open3d_depth(pts.numpy(), extrinsic)
        ours = as_depth_image(depth[0])
        np.testing.assert_array_equal(ours > 0, theirs > 0, err_msg=f"motion {motion.tolist()}")
        np.testing.assert_allclose(ours, theirs, rtol=1e-6)


def closed_form(P: np.ndarray, axis: str, a: float) -> tuple[float, float, float]:
    """Appendix A.2's pixel (u, v) and depth of a point under a one-axis motion.

    The paper's R_z row coordinate has a sign typo (docs/method.md §1); this uses R^{-1} P.
    """
    X, Y, Z = P
    fx, fy, cx, cy = 386.274, 386.274, 80.0, 45.0
    c, s = np.cos(a), np.sin(a)
    if axis == "tz":
        return (fx * X + cx * (Z - a)) / (Z - a), (fy * Y + cy * (Z - a)) / (Z - a), Z - a
    if axis == "tx":
        return (fx * (X - a) + cx * Z) / Z, (fy * Y + cy * Z) / Z, Z
    if axis == "ty":
        return (fx * X + cx * Z) / Z, (fy * (Y - a) + cy * Z) / Z, Z
    if axis == "rz":
        return (fx * c * X + fx * s * Y) / Z + cx, (fy * c * Y - fy * s * X) / Z + cy, Z
    if axis == "rx":
        D = -s * Y + c * Z
        return fx * X / D + cx, (Y * c + Z * s) / D * fy + cy, D
    D = s * X + c * Z  # ry
    return (X * c - Z * s) / D * fx + cx, fy * Y / D + cy, D


@pytest.mark.parametrize("axis", AXES)
def test_single_points_follow_the_closed_forms(axis, rng):
    for _ in range(40):
        P = np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.4, 0.4), rng.uniform(1.5, 4.0)])
        a = rng.uniform(-0.1, 0.1)
        u, v, D = closed_form(P, axis, a)
        motion = torch.zeros(1, 6, dtype=torch.float64)
        motion[0, axis_index(axis)] = a
        img, depth = project(torch.from_numpy(P[None]), torch.tensor([[0.2, 0.4, 0.6]]), PAPER_K, motion, H, W)
        hit = torch.nonzero(torch.isfinite(depth[0]))
        if not (0 <= u < W and 0 <= v < H):
            assert len(hit) == 0
            continue
        assert hit.tolist() == [[int(np.floor(v)), int(np.floor(u))]]
        assert depth[0, int(v), int(u)].item() == pytest.approx(D, rel=1e-12)
        assert img[0, :, int(v), int(u)].tolist() == pytest.approx([0.2, 0.4, 0.6])


@pytest.mark.parametrize("backend", BACKENDS)
def test_lemma_1_moving_the_scene_then_rendering_equals_rendering_the_composition(backend, rng):
    points, colors = random_cloud(rng, n=30000)
    a1 = random_motions(rng, per_axis=2)
    a2 = random_motions(rng, per_axis=2)
    for m1, m2 in zip(a1, a2, strict=True):
        moved = move_cloud(points, m1)
        img_a, dep_a = project(moved, colors, PAPER_K, m2[None], H, W, backend=backend)
        img_b, dep_b = project(points, colors, PAPER_K, compose(m1[None], m2[None]), H, W, backend=backend)
        assert torch.equal(img_a, img_b)
        assert torch.equal(torch.isinf(dep_a), torch.isinf(dep_b))


@pytest.mark.parametrize("axis", AXES)
def test_one_axis_composition_is_addition_in_images(axis, rng):
    points, colors = random_cloud(rng, n=30000)
    i = axis_index(axis)
    for _ in range(3):
        m1, m2 = torch.zeros(6, dtype=torch.float64), torch.zeros(6, dtype=torch.float64)
        m1[i], m2[i] = rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)
        img_a, _ = project(move_cloud(points, m1), colors, PAPER_K, m2[None], H, W)
        img_b, _ = project(points, colors, PAPER_K, (m1 + m2)[None], H, W)
        assert torch.equal(img_a, img_b)


@pytest.mark.parametrize("backend", BACKENDS)
def test_nearer_point_wins_and_equal_depths_break_to_the_lowest_index(backend):
    K = torch.tensor([[64.0, 0, 80], [0, 64.0, 45], [0, 0, 1]], dtype=torch.float64)
    zero = torch.zeros(1, 6, dtype=torch.float64)
    near, far = [0.01, 0.01, 1.0], [0.02, 0.02, 2.0]  # both on pixel (45, 80)
    red, blue = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]
    for pts, cols in (([near, far], [red, blue]), ([far, near], [blue, red])):
        img, depth = project(torch.tensor(pts), torch.tensor(cols), K, zero, H, W, backend=backend)
        assert img[0, :, 45, 80].tolist() == red
        assert depth[0, 45, 80].item() == 1.0
    same = [[0.01, 0.01, 1.0], [0.015, 0.015, 1.0], [0.012, 0.012, 1.0]]
    for _ in range(5):
        img, _ = project(torch.tensor(same), torch.tensor([red, blue, [0.0, 1.0, 0.0]]), K, zero, H, W, backend=backend)
        assert img[0, :, 45, 80].tolist() == red
    img, _ = project(torch.tensor(same), torch.tensor([blue, red, red]), K, zero, H, W, backend=backend)
    assert img[0, :, 45, 80].tolist() == blue


@pytest.mark.parametrize("backend", BACKENDS)
def test_points_behind_the_camera_and_on_the_borders(backend):
    # fx = 64, cx = 80, Z = 1: u = 64 X + 80 exactly in binary floating point.
    K = torch.tensor([[64.0, 0, 80], [0, 64.0, 45], [0, 0, 1]], dtype=torch.float64)
    pts = torch.tensor(
        [
            [0.0, 0.0, -1.0],  # behind the camera
            [0.0, 0.0, 0.0],  # at the camera centre (Z = 0)
            [-1.25, 0.0, 1.0],  # u = 0 exactly: column 0
            [1.25, 0.1, 1.0],  # u = 160 = W exactly: outside
            [1.25 - 2**-20, 0.2, 1.0],  # u just below W: column 159
            [0.3, -45 / 64, 1.0],  # v = 0 exactly: row 0
            [0.4, 45 / 64, 1.0],  # v = 90 = H exactly: outside
        ],
        dtype=torch.float64,
    )
    cols = torch.linspace(0, 1, len(pts), dtype=torch.float32)[:, None].repeat(1, 3)
    img, depth = project(pts, cols, K, torch.zeros(1, 6, dtype=torch.float64), H, W, background=0.5, backend=backend)
    hits = {tuple(x) for x in torch.nonzero(torch.isfinite(depth[0])).tolist()}
    assert hits == {(45, 0), (int(np.floor(45 + 0.2 * 64)), 159), (0, int(np.floor(80 + 0.3 * 64)))}
    assert (img[0][:, torch.isinf(depth[0])] == 0.5).all()


def test_camera_points_are_the_pose_frame_and_render_exactly(rng):
    """camera_points(P, m) = inv(pose)[:3] @ [P; 1] for pose = [[R, t], [0, 1]], and rendering them
    without motion equals rendering P under m, bit for bit; +tx moves points left."""
    points, colors = random_cloud(rng, n=20000)
    for motion in random_motions(rng, per_axis=1):
        cam = camera_points(points, motion)
        pose = motion_to_matrix(motion)
        expected = torch.linalg.inv(pose) @ torch.cat([points, torch.ones(len(points), 1, dtype=torch.float64)], 1).T
        torch.testing.assert_close(cam, expected[:3].T, atol=1e-12, rtol=0)
        a, _ = project(cam, colors, PAPER_K, torch.zeros(1, 6, dtype=torch.float64), H, W)
        b, _ = project(points, colors, PAPER_K, motion[None], H, W)
        assert torch.equal(a, b)
    # The compiled CPU kernel and the torch expression give the same bits.
    motion = random_motions(rng, per_axis=1)[-1]
    via_torch = projection._camera_coordinate  # the torch formula, used on non-CPU devices
    r = rotvec_to_matrix(motion[None, 3:])
    d = [points[:, i][None, :] - motion[i] for i in range(3)]
    expected = torch.stack([via_torch(r, j, *d)[0] for j in range(3)], dim=1)
    assert torch.equal(camera_points(points, motion), expected)
    moved = camera_points(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([0.1, 0, 0, 0, 0, 0.0]))
    assert moved[0, 0] < 0


def test_backends_and_chunking_give_identical_images(rng):
    points, colors = random_cloud(rng, n=50000)
    motions = random_motions(rng, per_axis=4)
    ref_img, ref_depth = project(points, colors, PAPER_K, motions, H, W, backend="numba")
    for kwargs in (
        {"backend": "torch"},
        {"backend": "torch", "chunk_elements": 1},
        {"backend": "torch", "chunk_elements": 120_001},
    ):
        img, depth = project(points, colors, PAPER_K, motions, H, W, **kwargs)
        assert torch.equal(img, ref_img) and torch.equal(depth, ref_depth)
    # Rendering motions one by one equals rendering them in one batch.
    for b in (0, 7, len(motions) - 1):
        img, _ = project(points, colors, PAPER_K, motions[b : b + 1], H, W)
        assert torch.equal(img[0], ref_img[b])


def test_bad_shapes_are_reported():
    pts = torch.zeros(4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        project(torch.zeros(4, 2), torch.zeros(4, 3), PAPER_K, torch.zeros(1, 6), H, W)
    with pytest.raises(ValueError, match=r"motions must have shape \(B, 6\)"):
        project(pts, torch.zeros(4, 3), PAPER_K, torch.zeros(1, 3), H, W)
    with pytest.raises(ValueError, match="height must be a positive integer, got 0"):
        project(pts, torch.zeros(4, 3), PAPER_K, torch.zeros(1, 6), 0, W)
    with pytest.raises(ValueError, match="height x width must be under 2\\*\\*31 pixels, got 65536 x 32768"):
        project(pts, torch.zeros(4, 3), PAPER_K, torch.zeros(1, 6), 65536, 32768)
    with pytest.raises(ValueError, match="unknown projection backend 'cuda'"):
        project(pts, torch.zeros(4, 3), PAPER_K, torch.zeros(1, 6), H, W, backend="cuda")


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_any_point_order_renders_the_images_of_the_original_order(backend, rng):
    pts, cols = random_cloud(rng, n=20000)
    # Exact ties: copies of 3000 points with other colours, so the tie rule decides those pixels.
    copies = torch.from_numpy(rng.choice(len(pts), 3000, replace=False))
    pts = torch.cat([pts, pts[copies]])
    cols = torch.cat([cols, torch.from_numpy(rng.uniform(0, 1, (3000, 3)).astype(np.float32))])
    motions = random_motions(rng)
    reference = project(pts, cols, PAPER_K, motions, 90, 160, backend=backend)
    shuffle = torch.from_numpy(rng.permutation(len(pts)))
    local = projection.locality_order(pts, PAPER_K, 90, 160)
    assert not torch.equal(local, torch.arange(len(pts)))
    for perm in (shuffle, local):
        for locality in (True, False):  # numba: sorted into locality order inside, or rendered as stored
            images, depth = project(
                pts[perm], cols[perm], PAPER_K, motions, 90, 160, backend=backend, rank=perm, locality=locality
            )
            assert torch.equal(images, reference[0]) and torch.equal(depth, reference[1])
    # Without the ranks the copies would win by storage order: the rule is what keeps the images.
    plain, _ = project(pts[shuffle], cols[shuffle], PAPER_K, motions, 90, 160, backend=backend)
    assert not torch.equal(plain, reference[0])


def test_a_cloud_changed_between_renders_is_never_rendered_stale(rng):
    """project() keeps each cloud's locality order for the next calls: changing the points, the
    colours or the ranks in place, or passing other tensors, must give the new images."""
    pts, cols = random_cloud(rng, n=5000)
    motions = random_motions(rng, per_axis=2)
    project(pts, cols, PAPER_K, motions, 90, 160)  # prepared and kept
    pts.mul_(1.1)
    assert torch.equal(
        project(pts, cols, PAPER_K, motions, 90, 160)[1], project(pts.clone(), cols, PAPER_K, motions, 90, 160)[1]
    )
    cols.mul_(0.5)
    assert torch.equal(
        project(pts, cols, PAPER_K, motions, 90, 160)[0], project(pts, cols.clone(), PAPER_K, motions, 90, 160)[0]
    )
    rank = torch.arange(len(pts))
    project(pts, cols, PAPER_K, motions, 90, 160, rank=rank)
    rank.copy_(rank.flip(0))
    fresh = project(pts, cols, PAPER_K, motions, 90, 160, rank=rank.clone())
    assert torch.equal(project(pts, cols, PAPER_K, motions, 90, 160, rank=rank)[0], fresh[0])
    # Tensors made under inference mode have no version counter: rendered afresh, never stale.
    with torch.inference_mode():
        frozen = pts.clone()
        first = project(frozen, cols, PAPER_K, motions, 90, 160)
        frozen.mul_(0.9)
        assert not torch.equal(project(frozen, cols, PAPER_K, motions, 90, 160)[1], first[1])
    # Another camera, the same tensors.
    other_k = PAPER_K.clone()
    other_k[0, 0] *= 0.8
    assert torch.equal(
        project(pts, cols, other_k, motions, 90, 160)[1], project(pts.clone(), cols, other_k, motions, 90, 160)[1]
    )


def test_a_test_sample_renders_the_images_of_its_cloud_as_given(rng):
    from mrcert.core.crop import CropBound
    from mrcert.data.samples import TestSample

    pts, cols = random_cloud(rng, n=20000)
    shuffled = torch.from_numpy(rng.permutation(len(pts)))
    pts, cols = pts[shuffled], cols[shuffled]
    motions = random_motions(rng)
    reference = project(pts, cols, PAPER_K, motions, 90, 160)
    for bound in (None, CropBound((0.5, 0.5, 0.5), 0.5, roll_only=False)):
        sample = TestSample.build(pts.numpy(), cols.numpy(), PAPER_K, 90, 160, label=0, bound=bound)
        images, depth = sample.render(motions)
        assert torch.equal(images, reference[0]) and torch.equal(depth, reference[1])


def test_the_locality_order_meets_each_pixels_nearest_point_first(rng):
    """What makes the z-test cheap: in locality order, points come tile by tile (32x32 pixels at
    the unmoved camera) and nearest first within a tile, so that a pixel rarely replaces its
    winner. Tiles and depths recomputed here with NumPy."""
    pts, _ = random_cloud(rng, n=30000, behind=0)
    order = projection.locality_order(pts, PAPER_K, 90, 160).numpy()
    p = pts.numpy()[order]
    fx, fy, cx, cy = (float(v) for v in (PAPER_K[0, 0], PAPER_K[1, 1], PAPER_K[0, 2], PAPER_K[1, 2]))
    # pixels on the image plane extended by 4 images on each side, beyond which they are clamped
    u = np.clip(np.floor(fx * (p[:, 0] / p[:, 2]) + cx), -4 * 160, 5 * 160 - 1) + 4 * 160
    v = np.clip(np.floor(fy * (p[:, 1] / p[:, 2]) + cy), -4 * 90, 5 * 90 - 1) + 4 * 90
    tile = (v // 32) * -(-9 * 160 // 32) + u // 32
    assert (np.diff(tile) >= 0).all()
    same_tile = np.diff(tile) == 0
    assert same_tile.mean() > 0.9
    assert (np.diff(p[:, 2])[same_tile] >= 0).all()


def test_the_locality_order_does_not_depend_on_the_order_points_come_in(rng):
    """``project()`` renders a cloud in its locality order, so a shuffled cloud costs what the
    ordered one does only if both end up in the same order: also for points at one depth (a wall
    facing the camera, one point per pixel, 1 cm apart at 3 m), which the depth cannot order."""
    gx, gy = np.meshgrid(np.arange(-1.5, 1.5, 0.01), np.arange(-0.8, 0.8, 0.01))
    wall = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 3.0)])
    pts = torch.from_numpy(np.concatenate([wall, random_cloud(rng, n=5000, behind=0)[0].numpy()]))
    order = projection.locality_order(pts, PAPER_K, 90, 160)
    shuffle = torch.from_numpy(rng.permutation(len(pts)))
    assert torch.equal(shuffle[projection.locality_order(pts[shuffle], PAPER_K, 90, 160)], order)


@pytest.mark.parametrize("spread", [5.0, 20.0])
def test_culled_blocks_change_no_pixel(spread, rng):
    """Mostly off-screen clouds in locality order (so whole blocks are skipped): the numba
    kernel still equals the torch back end, which skips nothing, bit for bit."""
    n = 60000
    pts = torch.from_numpy(
        np.column_stack([rng.uniform(-spread, spread, n), rng.uniform(-spread, spread, n), rng.uniform(-2, 6, n)])
    )
    cols = torch.from_numpy(rng.uniform(0, 1, (n, 3)).astype(np.float32))
    order = projection.locality_order(pts, PAPER_K, 90, 160)
    motions = random_motions(rng, per_axis=4) * 3
    p, c = pts[order].contiguous(), cols[order].contiguous()
    numba_out = project(p, c, PAPER_K, motions, 90, 160, backend="numba", rank=order)
    torch_out = project(pts, cols, PAPER_K, motions, 90, 160, backend="torch")
    assert torch.equal(numba_out[0], torch_out[0]) and torch.equal(numba_out[1], torch_out[1])
    assert (numba_out[1] < torch.inf).any()  # some points do land


# The triton back end: on a GPU its compiled kernels, elsewhere the same kernels under Triton's
# interpreter (tests/conftest.py sets TRITON_INTERPRET=1 where there is no GPU).
TRITON_DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def _tied_cloud(rng, n):
    """A random cloud (some points behind the camera) with 10% exact copies in other colours."""
    pts, cols = random_cloud(rng, n=n, behind=n // 20)
    copies = torch.from_numpy(rng.choice(len(pts), len(pts) // 10, replace=False))
    return torch.cat([pts, pts[copies]]), torch.cat([cols, cols[copies].flip(1)])


@pytest.mark.parametrize("given_order", ["rows", "locality order with ranks", "shuffled with ranks"])
def test_triton_kernels_give_the_cpu_kernels_images_and_depths_bit_for_bit(given_order, rng, monkeypatch):
    """Exact ties (copies of points in other colours: the lower rank must win), points behind the
    camera, motions on every axis and large ones that move whole blocks out of view, launches
    split over motions: every pixel and depth equals the numba kernel's."""
    from mrcert.core import projection_cuda

    pts, cols = _tied_cloud(rng, 1500)
    motions = torch.cat([random_motions(rng, per_axis=1), random_motions(rng, per_axis=1)[-2:] * 12])
    expected = project(pts, cols, PAPER_K, motions, 90, 160, backend="numba")
    order = {
        "rows": None,
        "locality order with ranks": projection.locality_order(pts, PAPER_K, 90, 160),
        "shuffled with ranks": torch.from_numpy(rng.permutation(len(pts))),
    }[given_order]
    p, c = (pts, cols) if order is None else (pts[order].contiguous(), cols[order].contiguous())
    monkeypatch.setattr(projection_cuda, "MAX_PIXELS", 3 * 90 * 160)  # three motions per launch
    images, depth = project(
        p.to(TRITON_DEVICE), c.to(TRITON_DEVICE), PAPER_K, motions, 90, 160, backend="triton", rank=order
    )
    assert images.device.type == TRITON_DEVICE and images.dtype == torch.float32
    assert torch.equal(depth.cpu(), expected[1]), "depths differ"
    assert torch.equal(images.cpu(), expected[0]), "images differ"
    assert (expected[1] < torch.inf).sum() > 1000  # the scene does land
    reversed_ranks = project(pts, cols, PAPER_K, motions, 90, 160, backend="numba", rank=-torch.arange(len(pts)))
    assert not torch.equal(reversed_ranks[0], expected[0])  # and the tie rule decides pixels


def test_the_triton_back_end_wants_a_gpu_or_triton_s_interpreter(monkeypatch):
    pts, cols = random_cloud(np.random.default_rng(0), n=10)
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    with pytest.raises(ValueError, match="triton projection backend needs CUDA tensors, got device cpu"):
        project(pts, cols, PAPER_K, torch.zeros(1, 6), 90, 160, backend="triton")


@pytest.mark.parametrize("locality", [True, False])
def test_a_cloud_prepared_where_it_renders_is_the_cpu_path_s_cloud(locality, rng):
    """A sample rendering on a GPU is put in locality order and boxed by tensor operations on its
    device: the same keys, permutation, colours, ranks and boxes as the CPU path, array for array
    (here on the CPU: exact copies, points behind the camera and a rank order given)."""
    points, colors = random_cloud(rng, 30_011)
    points[:500] = points[500:1000]  # exact copies: ties in the sort keys (the last 500 are behind the camera)
    rank = torch.from_numpy(rng.permutation(len(points)))
    K = torch.as_tensor(PAPER_K, dtype=torch.float64)
    for given in (None, rank):
        cpu = projection._prepare(points, colors, given, K, 90, 160, locality, 512, None)
        there = projection._prepare(points, colors, given, K, 90, 160, locality, 512, "cpu")
        for field in ("points", "rank", "colors", "center", "half"):
            assert np.array_equal(np.asarray(getattr(cpu, field)), getattr(there, field).numpy()), field
