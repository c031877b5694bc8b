"""The CUDA path: exact projection, certification and overlapped rendering on a GPU.

Marked ``cuda`` and skipped where no GPU exists (``make test-gpu`` runs them). How CPU and CUDA
are compared: the projection is exact float64 in one fixed order of operations, so its images
must be bit-identical. The classifier is not: cuDNN and CPU kernels add in different orders, so
logits differ by float rounding, and a sample whose top two logits are that close can vote
differently. Certify rows are therefore compared on the prediction (equal) and on the vote count
of the top class (within 1% of n); everything upstream of the model is compared bit for bit.
"""

import numpy as np
import pytest
import torch

from mrcert.core.methods.camera_motion import CameraMotionSmoothing
from mrcert.core.projection import locality_order, project
from mrcert.core.sampling import SmoothedClassifier, image_generator
from tests.conftest import PAPER_K, random_cloud, random_motions

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"),
]


@pytest.mark.parametrize("backend", ["triton", "torch"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cuda_projection_equals_the_cpu_kernel_bit_for_bit(seed, backend):
    rng = np.random.default_rng(seed)
    pts, cols = random_cloud(rng, n=200_000)
    copies = torch.from_numpy(rng.choice(len(pts), 5000, replace=False))  # exact ties
    pts, cols = torch.cat([pts, pts[copies]]), torch.cat([cols, cols[copies].flip(1)])
    motions = random_motions(rng, per_axis=10)
    cpu = project(pts, cols, PAPER_K, motions, 90, 160, backend="numba")
    order = locality_order(pts, PAPER_K, 90, 160)
    for p, c, rank in ((pts, cols, None), (pts[order], cols[order], order)):
        gpu = project(p.cuda(), c.cuda(), PAPER_K, motions.cuda(), 90, 160, backend=backend, rank=rank)
        assert torch.equal(gpu[0].cpu(), cpu[0]), "the images differ"
        depth = gpu[1].cpu()
        differ = depth != cpu[1]
        worst = float((depth - cpu[1])[differ].abs().max()) if differ.any() else 0.0
        assert not differ.any(), f"{int(differ.sum())} depths differ, by up to {worst:.3g} m"


def _classifier(num_classes: int = 5) -> torch.nn.Module:
    torch.manual_seed(0)
    from mrcert.core.models import SmallCNN

    return torch.nn.Sequential(SmallCNN(num_classes, width=8)).eval()


def test_certify_on_cuda_gives_the_cpu_rows_up_to_model_rounding():
    from mrcert.data.samples import TestSample

    rng = np.random.default_rng(3)
    pts, cols = random_cloud(rng, n=50_000)
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    rows = {}
    for device in ("cpu", "cuda"):
        sample = TestSample.build(pts.numpy(), cols.numpy(), PAPER_K, 90, 160, label=0, bound=dist.crop_bound(6.0))
        model = _classifier().to(device)
        smoothed = SmoothedClassifier(model, dist, 5, batch_size=200, device=device)
        rows[device] = [smoothed.certify(sample.renderer(), 100, 1000, 0.01, image_generator(0, i)) for i in range(3)]
    for cpu, gpu in zip(rows["cpu"], rows["cuda"], strict=True):
        assert gpu.prediction == cpu.prediction and abs(gpu.count_a - cpu.count_a) <= 10


@pytest.mark.parametrize("renders_on", ["cpu", "cuda"])
def test_overlapped_rendering_on_cuda_gives_the_same_votes(renders_on):
    """Rendering the next batch beside the model (the sample on the CPU, or on the GPU) gives the
    votes of rendering and classifying in turn."""
    from mrcert.data.samples import TestSample

    rng = np.random.default_rng(4)
    pts, cols = random_cloud(rng, n=50_000)
    dist = CameraMotionSmoothing(("rz",), (0.122173,))
    sample = TestSample.build(pts.numpy(), cols.numpy(), PAPER_K, 90, 160, label=0, bound=dist.crop_bound(6.0))
    sample = sample.to(renders_on)
    model = _classifier().cuda()
    votes = [
        SmoothedClassifier(model, dist, 5, 128, "cuda", overlap=overlap).sample_counts(
            sample.renderer(), 1000, image_generator(0, 7)
        )
        for overlap in (False, True)
    ]
    assert (votes[0] == votes[1]).all()


def test_a_sample_rendered_on_the_gpu_gets_the_votes_of_its_cpu_renders():
    """What the tasks do on a GPU (the sample moved there, the triton kernels render it) gives the
    votes of the CPU kernel's images classified on the same GPU: the images are the same bits."""
    from mrcert.data.samples import TestSample

    rng = np.random.default_rng(5)
    pts, cols = random_cloud(rng, n=50_000)
    dist = CameraMotionSmoothing(("ry",), (0.0436,))
    sample = TestSample.build(pts.numpy(), cols.numpy(), PAPER_K, 90, 160, label=0, bound=dist.crop_bound(6.0))
    smoothed = SmoothedClassifier(_classifier().cuda(), dist, 5, 200, "cuda", overlap=True)
    votes = [smoothed.sample_counts(s.renderer(), 1000, image_generator(0, 9)) for s in (sample, sample.to("cuda"))]
    assert (votes[0] == votes[1]).all()


def test_a_sample_moved_to_the_gpu_renders_motions_beyond_its_crop_exactly():
    """Motions inside the crop's bound render from the crop moved to the GPU, those beyond from
    the whole cloud, moved when first needed: every image is the CPU kernel's."""
    from mrcert.data.samples import TestSample

    rng = np.random.default_rng(6)
    pts, cols = random_cloud(rng, n=50_000)
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    sample = TestSample.build(pts.numpy(), cols.numpy(), PAPER_K, 90, 160, label=0, bound=dist.crop_bound(6.0))
    motions = torch.zeros(6, 6, dtype=torch.float64)
    motions[:, 2] = torch.tensor([0.0, 0.3, -0.5, 0.9, -1.2, 2.0])  # the bound is 0.6
    moved = sample.to("cuda")
    assert moved.crop_points.is_cuda and not moved.cloud.is_cuda  # the whole cloud stays until needed
    for chosen in (motions[:3], motions[3:], motions):  # all inside, all beyond, mixed
        images, depth = moved.render(chosen)
        expected = sample.render(chosen)
        assert images.is_cuda and torch.equal(images.cpu(), expected[0]) and torch.equal(depth.cpu(), expected[1])


def test_pixel_noise_around_a_gpu_image_is_the_cpu_noise_bit_for_bit():
    """Pixel-wise smoothing votes over noisy copies of a frame rendered where the model runs: on
    a GPU the copies are the CPU's (the noise is drawn on the CPU from the seed and moved)."""
    from mrcert.core.methods.pixelwise import PixelNoise

    image = torch.rand(3, 90, 160, generator=torch.Generator().manual_seed(0))
    noise = PixelNoise(0.5)
    indices = torch.tensor([0, 5, 17, 40])
    cpu = noise.around(image, seed=3)(indices)
    gpu = noise.around(image.cuda(), seed=3)(indices)
    assert gpu.device.type == "cuda"
    assert torch.equal(gpu.cpu(), cpu)


@pytest.mark.parametrize("axis", ["tx", "tz", "ry"])
@pytest.mark.parametrize("backend", ["triton", "torch"])
def test_images_rendered_on_the_gpu_lie_in_their_pose_boxes(axis, backend):
    """The GPU kernels may round a column differently from the CPU kernel (fused multiply-adds):
    every image they render at 2,000 poses of a piece, points on the principal axis among them
    (the column edge u = cx), lies within the piece's box."""
    from mrcert.core.verification.image_bounds import image_boxes

    rng = np.random.default_rng(8)
    pts, cols = random_cloud(rng, n=50_000)
    hair = np.column_stack([rng.choice([0.0, 1e-16, -1e-16], 300), rng.uniform(-1, 1, 300), rng.uniform(1, 3, 300)])
    pts = torch.cat([pts, torch.from_numpy(hair)])
    cols = torch.cat([cols, torch.from_numpy(rng.uniform(0, 1, (300, 3)).astype(np.float32))])
    i = ["tx", "ty", "tz", "rx", "ry", "rz"].index(axis)
    low, high = image_boxes(pts, cols, PAPER_K, axis, [-1e-4], [1e-4], 90, 160, 1.0)
    motions = torch.zeros(2000, 6, dtype=torch.float64)
    motions[:, i] = torch.linspace(-1e-4, 1e-4, 2000, dtype=torch.float64)
    images = project(pts.cuda(), cols.cuda(), PAPER_K, motions.cuda(), 90, 160, backend=backend)[0].double().cpu()
    assert ((images >= torch.from_numpy(low[0])) & (images <= torch.from_numpy(high[0]))).all()


def test_bound_propagation_on_the_gpu_gives_the_cpu_bounds():
    """Interval and backward bounds of the same box on the GPU and the CPU agree to float64 rounding."""
    from mrcert.core.verification.network import BoundNetwork

    model = _classifier()
    g = torch.Generator().manual_seed(1)
    low = torch.rand(2, 3, 90, 160, generator=g, dtype=torch.float64)
    high = low + 0.01 * (torch.rand(low.shape, generator=g, dtype=torch.float64) < 0.01)
    cpu = BoundNetwork(model).margins(low, high, 0, "crown", upto=np.inf)
    gpu = BoundNetwork(model.cuda()).margins(low.cuda(), high.cuda(), 0, "crown", upto=np.inf).cpu()
    assert torch.allclose(cpu, gpu, rtol=1e-9, atol=1e-9)


def test_cuda_enumeration_classifies_incrementally_as_the_cpu_classifies_each_image():
    """Image enumeration on a GPU: every image of a tz interval classified incrementally there has
    the logits the CPU's forward pass gives it (to float rounding), and the method's answer,
    margin and images equal the CPU's."""
    from mrcert.core.methods.base import BaseClassifier
    from mrcert.core.methods.enumeration import ImageEnumeration, _Run
    from mrcert.core.models import SmallCNN
    from tests.test_enumeration import REQUEST, sample_for
    from tests.test_incremental import randomised

    sample = sample_for("tz", 0.003)
    model = randomised(SmallCNN(3, width=8), 5)
    answers = []
    for device in ("cpu", "cuda"):
        method = ImageEnumeration("tz", 0.003)
        certifier = method.certifier(BaseClassifier(model.to(device), 3, batch_size=64, device=device))
        answers.append(certifier.certify_sample(sample.renderer(), REQUEST, torch.Generator()))
        run = _Run(certifier, sample.renderer())
        if device == "cuda":
            points, colors, rank = sample.cloud_for(run.motions([-0.003, 0.003]))
            from mrcert.core.verification.events import enumerate_images

            e = enumerate_images(points, colors, rank, PAPER_K, 90, 160, sample.background, "tz", -0.003, 0.003)
            logits = run.lanes(e, [(0, len(e))])[0]
            with torch.no_grad():
                whole = model.cpu()(torch.from_numpy(e.images(0, len(e))))
            assert (logits - whole).abs().max() <= 1e-4 * max(1.0, float(whole.abs().max()))
    cpu, gpu = answers
    assert cpu.details["outcome"] == gpu.details["outcome"] and cpu.details["images"] == gpu.details["images"]
    assert cpu.margin == pytest.approx(gpu.margin, abs=1e-4)
