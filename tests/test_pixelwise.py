"""Pixel-wise smoothing: the bound between frames is sound for every pose, occlusion included,
and the interval rule, the noise and the frames behave as documented (docs/method.md §8)."""

import mlflow
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy.stats import norm

from mrcert.__main__ import run_task
from mrcert.core.methods import build_method
from mrcert.core.methods.pixelwise import PixelNoise, PixelwiseSmoothing, frame_motions, interval_certified
from mrcert.core.projection import project
from mrcert.core.verification.image_bounds import piece_bounds
from mrcert.data.sources import load
from mrcert.errors import ConfigError, MrcertError
from mrcert.infra.checkpoints import load_classifier
from mrcert.infra.config import validate
from mrcert.infra.identity import identify
from mrcert.infra.resolver import train_key
from mrcert.infra.tasks import TASKS
from mrcert.reporting.certify_log import read_log
from mrcert.tasks.train import accuracy, as_tensors, evaluate
from tests.conftest import PAPER_K, TINY, TINY_CLASSES, compose_cfg

H, W = 90, 160


def occluding_scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A wall of random colours at 3 m with a hole showing the background, and a nearer
    square at 1.5 m in front of it: edges, occlusion and disocclusion under any motion."""
    rng = np.random.default_rng(seed)
    wall = np.column_stack([rng.uniform(-2.2, 2.2, 60000), rng.uniform(-1.3, 1.3, 60000), np.full(60000, 3.0)])
    hole = (np.abs(wall[:, 0] - 0.9) < 0.25) & (np.abs(wall[:, 1] + 0.3) < 0.2)
    near = np.column_stack([rng.uniform(-0.5, 0.2, 12000), rng.uniform(-0.4, 0.3, 12000), np.full(12000, 1.5)])
    near[:, 2] += rng.uniform(-0.02, 0.02, len(near))  # a rough surface, black in front, white behind
    colors = np.concatenate([rng.uniform(0, 1, (int((~hole).sum()), 3)), np.repeat((near[:, 2:] > 1.5) * 1.0, 3, 1)])
    return torch.from_numpy(np.concatenate([wall[~hole], near])), torch.from_numpy(colors.astype(np.float32))


def render(points, colors, motions) -> torch.Tensor:
    return project(points, colors, PAPER_K, motions, H, W, 1.0)[0]


def dense_views(frames: torch.Tensor, per_piece: int, seed: int = 0):
    """Per piece: ``per_piece`` poses drawn uniformly inside it, plus its middle and poses just
    inside each end, as motions (its index, motions)."""
    rng = np.random.default_rng(seed)
    axis = int(torch.nonzero(frames[-1]).flatten()[0])
    for k in range(len(frames) - 1):
        a0, a1 = float(frames[k, axis]), float(frames[k + 1, axis])
        inside = np.concatenate([rng.uniform(a0, a1, per_piece), [a0 + 1e-9, a1 - 1e-9, 0.5 * (a0 + a1)]])
        motions = torch.zeros(len(inside), 6, dtype=torch.float64)
        motions[:, axis] = torch.from_numpy(inside)
        yield k, motions


def worst_distances(points, colors, frames, images, per_piece: int) -> tuple[np.ndarray, np.ndarray]:
    """The largest l2 distance to each piece's left and right frame over its dense poses."""
    left, right = [], []
    for k, motions in dense_views(frames, per_piece):
        views = render(points, colors, motions)
        left.append(float((views - images[k]).flatten(1).norm(dim=1).max()))
        right.append(float((views - images[k + 1]).flatten(1).norm(dim=1).max()))
    return np.array(left), np.array(right)


@pytest.mark.parametrize(("axis", "half_width"), [("tz", 0.02), ("tx", 0.01), ("ry", 0.004), ("rz", 0.01), ("rz", 0.4)])
def test_every_pose_between_two_frames_is_within_the_bound_of_both(axis, half_width):
    points, colors = occluding_scene()
    frames = frame_motions(axis, half_width, 5)
    images = render(points, colors, frames)
    left, right, left_map, right_map = piece_bounds(points, colors, PAPER_K, axis, frames, images, 1.0, per_pixel=True)
    # Pixel by pixel, every dense pose's colour is within the bound of that pixel ...
    for k, motions in dense_views(frames, per_piece=60):
        views, frame = render(points, colors, motions).double(), images.double()
        assert (((views - frame[k]) ** 2).sum(1) <= torch.from_numpy(left_map[k]) + 1e-12).all()
        assert (((views - frame[k + 1]) ** 2).sum(1) <= torch.from_numpy(right_map[k]) + 1e-12).all()
    # ... and so each image is within the piece's l2 bound of both its frames.
    assert np.allclose(left**2, left_map.reshape(len(left), -1).sum(1), rtol=1e-6)
    seen_left, seen_right = worst_distances(points, colors, frames, images, per_piece=60)
    assert (seen_left <= left).all() and (seen_right <= right).all()
    # The frames' own images are what the bound is measured against: a piece's far end is
    # one of its poses, so its bound is at least the distance between the two frames.
    between = (images[1:] - images[:-1]).flatten(1).norm(dim=1).numpy()
    assert (left >= between - 1e-6).all() and (right >= between - 1e-6).all()
    # Not vacuous: close to the largest distance the dense poses show (1.09-1.14x measured;
    # 1.7x for pieces of 0.2 rad, where points sweep many pixels).
    assert (left <= 2 * seen_left).all() and (right <= 2 * seen_right).all()


def striped_wall(period: float, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A wall at 3 m of black and white vertical stripes ``period`` metres apart, densely sampled."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-2.2, 2.2, 150000), rng.uniform(-1.3, 1.3, 150000), np.full(150000, 3.0)])
    white = np.floor(pts[:, 0] / (period / 2)) % 2 == 1
    return torch.from_numpy(pts), torch.from_numpy(np.repeat(white[:, None], 3, axis=1).astype(np.float32))


def test_a_bound_from_the_frames_alone_fails_the_dense_check_where_the_real_one_holds():
    """The deliberate break: bound each piece by the distance between its two frames (as if
    images changed no more between frames than across them). Stripes one piece's motion
    apart look the same at both frames and inverted half-way: the dense check catches the
    break, and the real bound still covers every pose."""
    points, colors = striped_wall(period=0.05)
    frames = frame_motions("tx", 0.1, 5)  # pieces of 0.05 m: one stripe period
    images = render(points, colors, frames)
    seen_left, seen_right = worst_distances(points, colors, frames, images, per_piece=40)
    naive = (images[1:] - images[:-1]).flatten(1).norm(dim=1).numpy()
    assert (seen_left > naive + 1e-6).any() and (seen_right > naive + 1e-6).any()
    left, right = piece_bounds(points, colors, PAPER_K, "tx", frames, images, 1.0)
    assert (seen_left <= left).all() and (seen_right <= right).all()


def test_a_rotation_piece_of_pi_or_more_is_refused_where_its_bound_would_not_hold():
    """The bound of a rotation piece places its arc in the triangle of its ends and their
    tangents' meeting point, which exists only for arcs narrower than pi. Two frames at -pi and
    pi about rz are the same image, so a 'bound' over that piece would read 0 while the image
    at 0 lies far from both: such a piece is refused, by the method and by the bound itself."""
    points, colors = occluding_scene()
    frames = frame_motions("rz", np.pi - 1e-9, 2)
    images = render(points, colors, frames)
    middle = render(points, colors, torch.zeros(1, 6, dtype=torch.float64))[0]
    assert float((images[0] - images[1]).norm()) < 1e-3 < float((middle - images[0]).norm())
    with pytest.raises(ValueError, match="narrower than pi"):
        piece_bounds(points, colors, PAPER_K, "rz", frames, images, 1.0)
    method = ["method=pixelwise", f"method.certify.half_width={np.pi - 1e-9!r}"]
    with pytest.raises(ConfigError, match="at least 3 for half_width"):
        validate(compose_cfg([*method, "motion=rz", "method.certify.frames=2"]))
    validate(compose_cfg([*method, "motion=rz", "method.certify.frames=3"]))  # pieces just under pi: bounded
    validate(compose_cfg(["method=pixelwise", "motion=tz", "method.certify.half_width=9", "method.certify.frames=2"]))


def test_more_frames_give_smaller_bounds():
    points, colors = occluding_scene()
    worst = []
    for count in (3, 9, 33):
        frames = frame_motions("tz", 0.02, count)
        left, _ = piece_bounds(points, colors, PAPER_K, "tz", frames, render(points, colors, frames), 1.0)
        worst.append(left.max())
    assert worst[0] > worst[1] > worst[2]


def test_the_interval_needs_one_class_and_a_covering_frame_in_every_piece():
    left, right = np.array([0.3, 0.5]), np.array([0.4, 0.2])
    assert interval_certified(np.array([1, 1, 1]), np.array([0.35, 0.1, 0.25]), left, right)
    assert not interval_certified(np.array([1, 1, 1]), np.array([0.35, 0.1, 0.15]), left, right)  # piece 2 open
    assert not interval_certified(np.array([1, 2, 1]), np.array([1.0, 1.0, 1.0]), left, right)  # two classes
    assert not interval_certified(np.array([1, -1, 1]), np.array([1.0, 0.0, 1.0]), left, right)  # abstention
    assert not interval_certified(np.array([1, 1, 1]), np.array([0.3, 0.1, 0.2]), left, right)  # radius == bound


def test_pixel_noise_is_the_same_whatever_the_batches():
    image = torch.rand(3, H, W, generator=torch.Generator().manual_seed(0))
    noisy = PixelNoise(0.25).around(image, seed=7)
    whole = noisy(torch.arange(50))
    pieces = torch.cat([noisy(torch.arange(s, min(s + 7, 50))) for s in range(0, 50, 7)])
    assert torch.equal(whole, pieces)
    noise = (whole - image).flatten()
    assert abs(float(noise.std()) - 0.25) < 0.01 and abs(float(noise.mean())) < 0.01
    assert not torch.equal(noisy(torch.arange(3)), PixelNoise(0.25).around(image, seed=8)(torch.arange(3)))


@pytest.mark.parametrize(("count", "half_width"), [(1, 0.1), (3, 0.0)])
def test_bad_frames_are_refused(count, half_width):
    with pytest.raises(ValueError, match="frames|half-width"):
        frame_motions("tz", half_width, count)


PIXELWISE = ["method=pixelwise", "method.certify.frames=3", "method.certify.half_width=0.01", "method.sigma=0.25"]
RECIPE = ["train.epochs=2", "train.batch_size=8"]


def test_a_pixel_noise_model_s_test_accuracy_is_read_on_noisy_and_on_clean_images(tmp_path, monkeypatch):
    """``test_acc`` on the images as the model is used (with its method's pixel noise),
    ``test_acc_clean`` on the clean ones. On tiny data both read chance, so the images each metric
    was measured on are told apart by their mean: noise of sigma 0.25 leaves it, but not each pixel."""
    import mrcert.tasks.train as train_task

    seen_means = []

    def measured(model, images, labels, device, batch, seen=None, seed=0):
        clean = train_task.to_device(images, torch.device("cpu"))
        x = (
            clean
            if seen is None
            else torch.cat([seen.perturb(clean[i : i + 1], torch.Generator()) for i in range(len(clean))])
        )
        seen_means.append(float((x - clean).abs().mean()))
        return float(len(seen_means))  # the n-th measurement reads n

    cfg = compose_cfg([*TINY, *RECIPE, *PIXELWISE, "task=train", "model.variant=augmented", "train.epochs=1"], tmp_path)
    monkeypatch.setattr(train_task, "accuracy", measured)
    result = run_task(cfg, tmp_path / "t")
    # The last two measurements: test_acc (noisy images: they differ from the clean ones by about
    # 0.25 * sqrt(2 / pi) per pixel), then test_acc_clean (the images themselves).
    assert (result["test_acc"], result["test_acc_clean"]) == (len(seen_means) - 1, len(seen_means))
    assert seen_means[-2] == pytest.approx(0.25 * np.sqrt(2 / np.pi), rel=0.05) and seen_means[-1] == 0.0


def test_certify_with_pixelwise_smoothing_lands_in_mlflow_like_a_motion_run(tmp_path):
    """``mrcert task=certify method=pixelwise motion=tz``: its own augmented model (pixel noise),
    one certificate per image for the whole interval, a finished MLflow run keyed by the method."""
    train = compose_cfg([*TINY, *RECIPE, *PIXELWISE, "task=train", "model.variant=augmented"], tmp_path)
    result = run_task(train, tmp_path / "t")
    # The model is selected and measured on images as it will see them: with pixel noise.
    bundle = load(train.data)
    model = load_classifier(
        OmegaConf.merge(train, {"model": {"checkpoint": result["checkpoint"]}}), TINY_CLASSES, "cpu"
    )
    test_x, test_y = as_tensors(bundle.test())
    assert accuracy(model, test_x, test_y, "cpu", 64, build_method(train)) == result["test_acc"]
    assert accuracy(model, test_x, test_y, "cpu", 64) == result["test_acc_clean"]  # and without the noise
    cfg = compose_cfg(
        [*TINY, *RECIPE, *PIXELWISE, "task=certify", "model.variant=augmented", "task.n0=8", "task.n=40", "task.max=2"],
        tmp_path,
    )
    metrics = run_task(cfg, tmp_path / "c")
    log = read_log(tmp_path / "c" / "certify.tsv")
    # With pixel sigma 0.25 and n = 40 no frame's radius can cover a 1 cm piece of tz: each image
    # stops after its first frame (n = 40 estimation samples), and nothing is certified.
    assert len(log) == 2 and set(log.radius) == {0.0} and (log.n == 40).all() and (log.margin < 0).all()
    assert (log.projected == 3).all()  # each frame rendered once, for the bounds and the votes
    # The interval's half-width is in metres, the pixel noise in units of the [0, 1] image.
    assert set(log.radius_unit) == {"m"} and set(log.sigma_unit) == {"intensity"}
    assert metrics["mean_samples"] == 8 + 40  # the class guess and the estimation samples
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = mlflow.search_runs(search_all_experiments=True, filter_string="attributes.status = 'FINISHED'")
    certify = runs[runs["tags.mrcert.task"] == "certify"]
    assert len(certify) == 1 and certify.iloc[0]["params.method.name"] == "pixelwise"
    trained = runs[runs["tags.mrcert.task"] == "train"].iloc[0]
    assert certify.iloc[0]["tags.mrcert.train_run"] == trained["run_id"]  # bound to the pixel-noise model
    # Camera motion smoothing on that same pixel-noise model (the authors' like-for-like reference):
    # model.trained_for names the method it was trained for; nothing is trained again.
    noise = "model.trained_for={name:pixelwise,sigma:0.25}"
    motion = [*TINY, *RECIPE, "task=certify", "model.variant=augmented", noise, "task.n0=8", "task.n=40", "task.max=2"]
    run_task(compose_cfg(motion, tmp_path), tmp_path / "m")
    runs = mlflow.search_runs(search_all_experiments=True, filter_string="attributes.status = 'FINISHED'")
    (same_model,) = runs[(runs["tags.mrcert.task"] == "certify") & (runs["params.method.name"] == "camera_motion")].iloc
    assert (
        same_model["tags.mrcert.train_run"] == trained["run_id"] and len(runs[runs["tags.mrcert.task"] == "train"]) == 1
    )
    assert same_model["tags.mrcert.checkpoint"] == certify.iloc[0]["tags.mrcert.checkpoint"]
    assert set(read_log(tmp_path / "m" / "certify.tsv").sigma_unit) == {"m"}  # smoothed over motions
    # Without it, the motion-augmented model is asked for, which was never trained: the error
    # names the command that trains it.
    with pytest.raises(MrcertError, match="mrcert task=train .*model.variant=augmented"):
        run_task(compose_cfg([m for m in motion if m != noise], tmp_path), tmp_path / "n")


def test_the_method_keys_its_runs_and_motion_smoothing_keeps_the_old_keys(tmp_path):
    def key(overrides):
        return identify(compose_cfg(["task=train", *overrides], tmp_path), TASKS["train"].identity).key

    motion = key(["model.variant=augmented"])
    assert key(["model.variant=augmented", "method=pixelwise"]) != motion
    assert key(["model.variant=augmented", "method=camera_motion"]) == motion
    assert key(["model.variant=vanilla", "method=pixelwise"]) == key(["model.variant=vanilla"])  # one vanilla model
    pixelwise = key(["model.variant=augmented", "method=pixelwise"])
    # An evaluation's model trained for another method: that method's train run.
    noise = compose_cfg(["task=certify", "model.variant=augmented", "model.trained_for={name:pixelwise,sigma:0.25}"])
    assert train_key(noise) == pixelwise != train_key(compose_cfg(["task=certify", "model.variant=augmented"]))
    assert key(["model.variant=augmented", "method=pixelwise", "method.certify.frames=5"]) == pixelwise
    assert key(["model.variant=augmented", "method=pixelwise", "method.sigma=0.5"]) != pixelwise
    # Pixel noise never sees the motion: one pixel-noise model serves every axis.
    assert key(["model.variant=augmented", "method=pixelwise", "motion=rx"]) == pixelwise
    assert key(["model.variant=augmented", "motion=rx"]) != motion
    # The key of method=camera_motion runs is the one they had before methods existed: no method.* in it.
    values = identify(compose_cfg(["task=train", "model.variant=augmented"], tmp_path), TASKS["train"].identity).values
    assert not any(k.startswith("method") for k in values)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["method.name=bogus"], "method.name"),
        (["task=certify", "task.sequential=true", "method=pixelwise"], "task.sequential"),
        (["method=pixelwise", "motion=txyz_rz"], "motion"),
        (["method=pixelwise", "motion=rx", "motion.axis=rx+ry"], "motion.axis"),  # several axes joined: one line
        (["method=bound_propagation", "motion=rx", "motion.axis=rx+ry"], "motion.axis"),
        (["method=pixelwise", "method.certify.frames=1"], "method.certify.frames"),
        (["method=pixelwise", "method.certify.half_width=0"], "method.certify.half_width"),
        (
            ["method=pixelwise", "motion=rz", "method.certify.half_width=3.14159", "method.certify.frames=2"],
            "method.certify.frames",
        ),  # a piece of 2 pi: its arc does not fit the tangent triangle
    ],
)
def test_bad_method_settings_are_refused_naming_the_key(overrides, key, tmp_path):
    with pytest.raises(ConfigError) as err:
        validate(compose_cfg(overrides, tmp_path))
    assert err.value.key == key


class NoiseDetector(torch.nn.Module):
    """Class 0 when the image varies (noise), class 1 when it is flat."""

    def forward(self, x):
        spread = x.flatten(1).std(dim=1)
        return torch.stack([spread, torch.full_like(spread, 0.1)], dim=1)


def test_a_pixel_noise_model_is_validated_and_tested_on_noisy_images():
    flat = torch.full((8, 3, H, W), 128, dtype=torch.uint8)
    labels = torch.zeros(8, dtype=torch.long)
    method = PixelwiseSmoothing("tz", 0.25, 0.01, 3)
    assert accuracy(NoiseDetector(), flat, labels, "cpu", 3, method) == 1.0  # it sees noise, in any batches
    assert accuracy(NoiseDetector(), flat, labels, "cpu", 3) == 0.0
    noisy = [evaluate(NoiseDetector(), flat, labels, "cpu", size, method) for size in (3, 8)]
    assert noisy[0] == pytest.approx(noisy[1], rel=1e-6)


def test_a_pixelwise_run_reports_certified_accuracy_for_its_interval():
    """A pixel-wise certificate covers [-a, a] and nothing beyond: the run's headline certified
    accuracy is at a, not at motion.radius (where no pixel-wise certificate can reach)."""
    import pandas as pd

    cfg = compose_cfg(["task=certify", "method=pixelwise", "method.certify.half_width=0.001"])
    assert float(cfg.motion.radius) > 0.001
    log = pd.DataFrame({"idx": [0, 1, 2, 3], "predict": [0, 1, -1, 2], "correct": [1, 1, 0, 0],
                        "radius": [0.001, 0.0, 0.0, 0.001], "n": 4000, "seconds": 1.0})  # fmt: skip
    assert TASKS["certify"].summarize(log, cfg)["certified_accuracy"] == 0.25
    motion = compose_cfg(["task=certify"])
    log["radius"] = [float(motion.motion.radius)] * 2 + [0.0, 0.0]
    assert TASKS["certify"].summarize(log, motion)["certified_accuracy"] == 0.5  # motion smoothing: at motion.radius


class ScriptedFrames:
    """Stands in for the smoothed classifier: frame k certifies ``script[k]`` (class, radius)."""

    def __init__(self, script):
        self.script, self.calls = script, 0

    def certify_view(self, view, n0, n, alpha, generator, center=None):
        from mrcert.core.methods.base import Certificate

        prediction, radius = self.script[self.calls]
        self.calls += 1
        return Certificate(prediction, radius, n, 0.99, n)


def _scene_render(half_width):
    from mrcert.data.samples import TestSample

    points, colors = occluding_scene()
    bound = PixelwiseSmoothing("tz", 0.25, half_width, 3).crop_bound(1.0)
    return TestSample.build(points.numpy(), colors.numpy(), PAPER_K, H, W, label=0, bound=bound).renderer()


@pytest.mark.parametrize(
    ("sigma", "script", "frames_run", "radius", "prediction"),
    [
        (0.25, [(0, 1e9)] * 5, 1, 0.0, 0),  # no frame's radius (at most ~0.28) can cover a piece: stop at once
        (1000.0, [(0, 1e9)] * 5, 5, 0.02, 0),  # every frame certifies: the interval
        (1000.0, [(0, 1e9), (1, 1e9)] + [(0, 1e9)] * 3, 2, 0.0, -1),  # two classes: stop at the second frame
        (1000.0, [(0, 1e9), (-1, 0.0)] + [(0, 1e9)] * 3, 2, 0.0, -1),  # an abstention: stop there
    ],
)
def test_frames_are_spent_only_while_the_interval_can_still_be_certified(sigma, script, frames_run, radius, prediction):
    """The bounds come first; each frame is certified only while the interval can still be (one
    class so far, and every piece coverable with the largest radius n allows at the frames not
    yet certified); the log's n counts the frames actually certified."""
    method = PixelwiseSmoothing("tz", sigma, 0.02, 5)
    frames = ScriptedFrames(script)
    cert = method.certify_smoothed(frames, _scene_render(0.02), 8, 40, 0.01, torch.Generator().manual_seed(0))
    assert frames.calls == frames_run and cert.n == 40 * frames_run
    assert cert.radius == radius and cert.prediction == prediction
    # The log's margin: the worst piece's better end, its radius (the reach for frames not
    # certified) less its bound; negative exactly when some piece cannot be covered.
    render = _scene_render(0.02)
    motions = frame_motions("tz", 0.02, 5)
    points, colors, rank = render.cloud_for(motions)
    left, right = piece_bounds(points, colors, PAPER_K, "tz", motions, render(motions), 1.0, rank=rank)
    radii = np.array([r for _, r in script[:frames_run]] + [method.reach(40, 0.01)] * (5 - frames_run))
    assert cert.margin == pytest.approx(np.min(np.maximum(radii[:-1] - left, radii[1:] - right)))
    assert (cert.margin > 0) == (sigma > 1)
    # All n votes for one class: the one-sided Clopper-Pearson bound is (alpha / frames) ** (1 / n).
    closed_form = 0.25 * norm.ppf((0.01 / 5) ** (1 / 40))
    assert PixelwiseSmoothing("tz", 0.25, 0.02, 5).reach(40, 0.01) == pytest.approx(closed_form, rel=1e-9)


def _tied_occluding_scene(near_plane: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The occluding scene plus exact copies of some points in other colours (the tie rule
    decides which shows) and, with ``near_plane``, points a few millimetres in front of the
    camera that a motion along z carries across the camera plane."""
    rng = np.random.default_rng(7)
    points, colors = occluding_scene()
    copies = torch.from_numpy(rng.choice(len(points), 5000, replace=False))
    points, colors = torch.cat([points, points[copies]]), torch.cat([colors, 1 - colors[copies]])
    if near_plane:
        z = rng.uniform(0.0005, 0.004, 12)
        near = np.column_stack([rng.uniform(-0.15, 0.15, 12) * z, rng.uniform(-0.1, 0.1, 12) * z, z])
        points = torch.cat([points, torch.from_numpy(near)])
        colors = torch.cat([colors, torch.from_numpy(rng.uniform(0, 1, (12, 3)).astype(np.float32))])
    return points, colors


@pytest.mark.parametrize(
    ("axis", "half_width", "near_plane"),
    [("tx", 0.002, False), ("ty", 0.002, False), ("tz", 0.002, False), ("tz", 0.006, True)]
    + [(axis, 0.001, False) for axis in ("rx", "ry", "rz")],
)
def test_the_certifying_path_bounds_every_pose_of_small_pieces_on_every_axis(axis, half_width, near_plane):
    """What certification renders and bounds -- a test sample cropped for the interval, its frames
    drawn by its renderer (the crop, its points' ranks in the whole cloud), the bounds from
    ``cloud_for`` -- on millimetre pieces of all six axes, with exact ties, and points crossing
    the camera plane: every dense pose, rendered the same way, lies within both of its piece's
    bounds."""
    from mrcert.data.samples import TestSample

    points, colors = _tied_occluding_scene(near_plane)
    method = PixelwiseSmoothing(axis, 0.25, half_width, 4)
    sample = TestSample.build(points.numpy(), colors.numpy(), PAPER_K, H, W, label=0, bound=method.crop_bound(1.0))
    render = sample.renderer()
    frames = frame_motions(axis, half_width, 4)
    images = render(frames).double()
    crop, crop_colors, rank = sample.cloud_for(frames)
    assert len(crop) < len(points)  # the crop is what is rendered and bounded
    left, right, left_map, right_map = piece_bounds(
        crop, crop_colors, sample.K, axis, frames, images, sample.background, per_pixel=True, rank=rank
    )
    for k, motions in dense_views(frames, per_piece=40):
        views = render(motions).double()
        # pixel by pixel (a pixel the bound misses shows even where the l2 sum has room) ...
        assert (((views - images[k]) ** 2).sum(1) <= torch.from_numpy(left_map[k]) + 1e-12).all()
        assert (((views - images[k + 1]) ** 2).sum(1) <= torch.from_numpy(right_map[k]) + 1e-12).all()
        # ... and as the l2 distances certification compares with the frames' radii
        assert ((views - images[k]).flatten(1).norm(dim=1) <= left[k]).all()
        assert ((views - images[k + 1]).flatten(1).norm(dim=1) <= right[k]).all()
    if near_plane:  # the points in front of the camera do cross its plane within the interval
        assert ((points[:, 2] > 0) & (points[:, 2] < half_width)).sum() == 12
