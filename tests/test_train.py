"""Training: loss goes down and is tracked, resume is exact, checkpoints are found, augmentation is real."""

from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch

from mrcert.__main__ import bind, run_task
from mrcert.core.geometry import matrix_to_motion
from mrcert.core.methods.camera_motion import CameraMotionSmoothing
from mrcert.core.models import build_model
from mrcert.core.projection import camera_points, project
from mrcert.data.holdout import validation_split
from mrcert.data.sources import load
from mrcert.errors import MrcertError
from mrcert.infra.checkpoints import load_classifier, local_checkpoint
from mrcert.tasks.train import as_tensors, better, evaluate
from tests.conftest import TINY, TINY_CLASSES, compose_cfg, kill_when, run_cli

ROOT = Path(__file__).resolve().parent.parent
RECIPE = [*TINY, "train.batch_size=8", "train.lr=0.02"]
TINY_TRAIN = [*RECIPE, "task=train"]


def train_in_process(overrides, outputs, name):
    cfg = compose_cfg(overrides, outputs)
    return run_task(cfg, outputs / "runs" / name), cfg


def store(outputs):
    mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
    return mlflow.MlflowClient()


def test_tiny_run_lowers_the_loss_and_tracks_metrics_and_checkpoints(tmp_path):
    result, _ = train_in_process([*TINY_TRAIN, "train.epochs=4"], tmp_path, "a")
    client = store(tmp_path)
    (run,) = client.search_runs([client.get_experiment_by_name("mrcert").experiment_id])
    assert run.info.status == "FINISHED"
    loss = [m.value for m in client.get_metric_history(run.info.run_id, "train_loss")]
    assert len(loss) == 4 and loss[-1] < loss[0]
    for key in ("train_acc", "val_acc", "lr", "epoch_seconds"):
        assert len(client.get_metric_history(run.info.run_id, key)) == 4
    tags = run.data.tags
    assert (
        tags["mrcert.task"],
        tags["mrcert.model"],
        tags["mrcert.dataset"],
        tags["mrcert.axis"],
        tags["mrcert.variant"],
    ) == ("train", "small_cnn", "metaroom_synth", "tz", "vanilla")
    arts = {a.path for a in client.list_artifacts(run.info.run_id, "checkpoints")}
    assert arts == {"checkpoints/best.pt", "checkpoints/last.pt"}
    assert result["best_val_acc"] == max(m.value for m in client.get_metric_history(run.info.run_id, "val_acc"))


def weights(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)["model"]


def test_killed_run_resumes_to_the_same_weights_in_the_same_mlflow_run(tmp_path):
    args = [*TINY_TRAIN, "train.epochs=6"]
    full, _ = train_in_process(args, tmp_path / "full", "full")
    reference = weights(Path(full["checkpoint"]).with_name("last.pt"))

    outputs = tmp_path / "killed"
    kill_when(args, outputs, lambda: bool(list(outputs.glob("runs/train/*/last.pt"))))
    (ckpt,) = outputs.glob("runs/train/*/last.pt")
    interrupted_at = torch.load(ckpt, weights_only=True)["epoch"]
    assert interrupted_at < 5, "the run finished before it could be killed"

    done = run_cli(args, outputs)  # the same command: resuming is the default
    assert done.returncode == 0, done.stderr[-2000:]
    client = store(outputs)
    (run,) = client.search_runs([client.get_experiment_by_name("mrcert").experiment_id])
    assert run.info.status == "FINISHED"
    assert len(client.get_metric_history(run.info.run_id, "train_loss")) == 6
    resumed = weights(ckpt)
    assert resumed.keys() == reference.keys()
    assert all(torch.equal(resumed[k], reference[k]) for k in reference)


def find_checkpoint(cfg) -> Path:
    """The checkpoint an evaluation config binds to, as a local file."""
    bound, _ = bind(cfg)
    return local_checkpoint(bound.model.checkpoint)


def test_checkpoint_lookup_finds_the_matching_run_and_names_the_command_when_none(tmp_path):
    train_in_process([*TINY_TRAIN, "train.epochs=1"], tmp_path, "vanilla")
    train_in_process([*TINY_TRAIN, "train.epochs=1", "model.variant=augmented"], tmp_path, "augmented")
    evaluation = [*RECIPE, "train.epochs=1", "task=certify"]
    for variant in ("vanilla", "augmented"):
        cfg = compose_cfg([*evaluation, f"model.variant={variant}"], tmp_path)
        path = find_checkpoint(cfg)
        assert torch.load(path, weights_only=True)["variant"] == variant
        model = load_classifier(bind(cfg)[0], TINY_CLASSES, torch.device("cpu"))
        assert model(torch.rand(2, 3, 90, 160)).shape == (2, 3)
    # A vanilla model never saw a motion, so the tz run serves rx too; an augmented one does not.
    rx_vanilla = find_checkpoint(compose_cfg([*evaluation, "motion=rx"], tmp_path))
    assert torch.load(rx_vanilla, weights_only=True)["variant"] == "vanilla"
    missing = compose_cfg([*evaluation, "motion=rx", "model.variant=augmented"], tmp_path)
    with pytest.raises(
        MrcertError,
        match="no finished train run of model=small_cnn variant=augmented axis=rx.*mrcert task=train "
        "data=metaroom_synth profile=quick model=small_cnn motion=rx model.variant=augmented",
    ):
        find_checkpoint(missing)
    # Another recipe is another model: the one-epoch runs do not stand in for it.
    with pytest.raises(MrcertError, match="no finished train run"):
        find_checkpoint(compose_cfg([*evaluation, "train.epochs=2"], tmp_path))
    with pytest.raises(MrcertError, match="cannot be fetched from MLflow"):
        find_checkpoint(
            compose_cfg([*evaluation, "model.checkpoint=runs:/0123456789abcdef/checkpoints/best.pt"], tmp_path)
        )
    with pytest.raises(MrcertError, match="does not exist"):
        find_checkpoint(compose_cfg([*evaluation, f"model.checkpoint={tmp_path / 'nope.pt'}"], tmp_path))
    resnet = [o for o in evaluation if not o.startswith("model")] + ["model=resnet18", f"model.checkpoint={path}"]
    wrong = compose_cfg(resnet, tmp_path)
    with pytest.raises(MrcertError, match="holds a small_cnn for 3 classes, but model=resnet18"):
        load_classifier(wrong, TINY_CLASSES, torch.device("cpu"))


def test_model_selection_uses_the_validation_poses_and_never_reads_the_test_images(tmp_path, monkeypatch):
    args = [*TINY_TRAIN, "train.epochs=4"]
    result, cfg = train_in_process(args, tmp_path / "a", "select")
    best = torch.load(Path(result["checkpoint"]), weights_only=True)
    bundle = load(cfg.data)
    val_x, val_y = as_tensors(bundle.validation())
    assert len(val_y) == 3 * 12 and best["validation"]["source"] == "poses"
    model = build_model(cfg.model, 3)
    model.load_state_dict(best["model"])
    assert evaluate(model, val_x, val_y, "cpu", 64)[0] == best["val_acc"] == result["best_val_acc"]
    client = store(tmp_path / "a")
    (run,) = client.search_runs([client.get_experiment_by_name("mrcert").experiment_id])
    assert run.data.metrics["train_images"] == 48 and run.data.metrics["val_images"] == 36  # every training pose trains
    hist = {
        m: [h.value for h in sorted(client.get_metric_history(run.info.run_id, m), key=lambda h: h.step)]
        for m in ("val_acc", "val_loss", "epoch_test_acc")
    }
    # The chosen epoch: highest validation accuracy, ties to the lower validation loss, then the earlier epoch.
    chosen = min(range(4), key=lambda e: (-hist["val_acc"][e], hist["val_loss"][e], e))
    assert best["epoch"] == chosen and result["best_epoch"] == chosen + 1 and len(hist["epoch_test_acc"]) == 4

    # Other test images -- inverted colours, shifted labels -- leave best.pt bit for bit unchanged.
    from mrcert.data.datasets import ImageSet, PosedCloudData

    original, reads = PosedCloudData.test, []

    def other_test_images(self):
        images = original(self)
        reads.append(1)
        return ImageSet(255 - np.array(images.images), (images.labels + 1) % 3, images.classes)

    monkeypatch.setattr(PosedCloudData, "test", other_test_images)
    other, _ = train_in_process(args, tmp_path / "b", "select")
    other_best = torch.load(Path(other["checkpoint"]), weights_only=True)
    assert reads, "the task did not read the (changed) test images"
    assert other_best["epoch"] == best["epoch"]
    assert all(torch.equal(other_best["model"][k], best["model"][k]) for k in best["model"])
    # ... and each run's test accuracy is best.pt's on the test images it was given.
    test = original(bundle)
    for images, labels, run in (
        (test.images, test.labels, result),
        (255 - np.array(test.images), (test.labels + 1) % 3, other),
    ):
        x, y = as_tensors(ImageSet(np.array(images), labels, test.classes))
        assert evaluate(model, x, y, "cpu", 64)[0] == run["test_acc"]


def test_selection_ties_go_to_the_lower_validation_loss_and_sources_without_poses_hold_out_training_poses(tmp_path):
    assert better((0.9, 0.5), None) and better((1.0, 0.9), (0.9, 0.1)) and not better((0.9, 0.1), (1.0, 0.9))
    assert better((1.0, 0.2), (1.0, 0.3)) and not better((1.0, 0.3), (1.0, 0.2)) and not better((1.0, 0.3), (1.0, 0.3))
    # A source without validation poses: a seeded share of each class's training poses is held out.
    result, cfg = train_in_process([*TINY_TRAIN, "train.epochs=2", "~data.protocol.validation"], tmp_path, "holdout")
    best = torch.load(Path(result["checkpoint"]), weights_only=True)
    _, val = validation_split(load(cfg.data).train().labels, 0.1, 0)
    assert best["validation"]["indices"] == val.tolist() and len(val) == 3 * 2  # round(0.1 * 16) per class
    split = validation_split(np.repeat(np.arange(4), 10), 0.25, seed=5)
    again = validation_split(np.repeat(np.arange(4), 10), 0.25, seed=5)
    assert all((a == b).all() for a, b in zip(split, again, strict=True))  # seeded
    assert [int((np.repeat(np.arange(4), 10)[split[1]] == c).sum()) for c in range(4)] == [2, 2, 2, 2]  # per class
    assert not set(split[0]) & set(split[1]) and len(split[0]) + len(split[1]) == 40


def test_augmentation_changes_images_and_equals_the_projection_at_the_drawn_motions(tmp_path):
    cfg = compose_cfg([*TINY_TRAIN, "data.protocol.train.per_class=4"], tmp_path)
    bundle = load(cfg.data)
    augment = CameraMotionSmoothing(("rz",), (0.122173,))
    vanilla, augmented = np.array(bundle.train().images), np.array(bundle.train(augment, 0).images)
    assert (vanilla != augmented).any(axis=-1).mean(axis=(1, 2)).min() > 0.05
    split, drawn = bundle.split("train"), augment.training_motions(len(vanilla), 0)
    assert (drawn[:, [0, 1, 2, 3, 4]] == 0).all()
    for i in range(len(vanilla)):
        points, colors = bundle.cloud(int(split.labels[i]))
        cam = camera_points(torch.from_numpy(points), matrix_to_motion(torch.from_numpy(split.poses[i])))
        img, _ = project(cam, torch.from_numpy(colors), bundle.K, drawn[i : i + 1], 90, 160)
        expected = (img[0] * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        assert (expected == augmented[i]).all(axis=-1).mean() > 0.995  # equal up to float rounding at pixel edges
    many = CameraMotionSmoothing(("tx",), (0.05,)).training_motions(20000, 3)[:, 0]
    assert abs(float(many.mean())) < 0.002 and abs(float(many.std()) - 0.05) < 0.002
    # The stream augmented models have always been trained on, under the cache key it always had.
    old = np.random.default_rng([3, 1000]).normal(0.0, 0.05, 20000)
    assert np.array_equal(many.numpy(), old)
    assert CameraMotionSmoothing(("tx",), (0.05,)).training_key(3) == {"axis": "tx", "sigma": 0.05, "seed": 3}


def test_a_multi_axis_method_augments_every_axis_it_smooths():
    """Theorem 1's combinations train too: each smoothed axis drawn with its own sigma."""
    dist = CameraMotionSmoothing(("tx", "ty", "tz", "rz"), (0.05, 0.05, 0.1, 0.122173))
    drawn = dist.training_motions(20000, 0)
    assert np.allclose(drawn.std(0).numpy(), [0.05, 0.05, 0.1, 0, 0, 0.122173], atol=0.003)
    assert (drawn[:, 3:5] == 0).all() and dist.training_key(0)["axes"] == ["tx", "ty", "tz", "rz"]


def test_models_normalise_first_and_build_from_config(tmp_path):
    for arch in ("resnet18", "resnet50", "small_cnn"):
        cfg = compose_cfg([f"model={arch}"], tmp_path)
        model = build_model(cfg.model, 20)
        assert model(torch.rand(2, 3, 90, 160)).shape == (2, 20)
        assert torch.equal(model[0](torch.full((1, 3, 2, 2), 0.5)), torch.zeros(1, 3, 2, 2))
    bad = compose_cfg(["model=small_cnn", "model.net._target_=torch.nn.NoSuchLayer"], tmp_path)
    with pytest.raises(MrcertError, match="model.net._target_='torch.nn.NoSuchLayer' is not allowed: an importable"):
        build_model(bad.model, 3)
    # A module that does not take num_classes: named by the one line instantiation gives.
    linear = compose_cfg(["model=small_cnn", "model.net._target_=torch.nn.ReLU", "~model.net.width"], tmp_path)
    with pytest.raises(MrcertError, match="cannot build model.net"):
        build_model(linear.model, 3)
