"""``task=viewpoints``: a base classifier's accuracy by viewpoint. At the test poses with the
whole scene it must see exactly the test images, so its accuracy is the train run's test
accuracy; with no surroundings only the object is drawn."""

import numpy as np
import pandas as pd
import pytest
import torch

from mrcert.__main__ import bind, run_task
from mrcert.data.datasets import render_poses
from mrcert.data.sources import load
from mrcert.infra.checkpoints import load_classifier
from mrcert.tasks.viewpoints import classify, midway, object_mask, object_share, occlusion
from tests.conftest import TINY, TINY_CLASSES, compose_cfg, run_cli

SETTINGS = [*TINY, "train.epochs=4", "train.batch_size=8", "model.variant=vanilla"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    out = tmp_path_factory.mktemp("viewpoints")
    trained = run_task(compose_cfg([*SETTINGS, "task=train"], out), out / "runs" / "train")
    return out, trained


def viewpoints(out, name: str, *overrides: str) -> tuple[dict, pd.DataFrame]:
    metrics = run_task(compose_cfg([*SETTINGS, "task=viewpoints", *overrides], out), out / "runs" / name)
    return metrics, pd.read_csv(out / "runs" / name / "viewpoints.tsv", sep="\t")


def test_at_the_test_poses_it_sees_the_test_images_and_reads_the_test_accuracy(store):
    out, trained = store
    cfg = compose_cfg([*SETTINGS, "task=viewpoints"], out)
    bundle = load(cfg.data)
    test = bundle.split("test")
    rendered = np.concatenate(
        [
            render_poses(
                bundle.source.scene(label, ("room", "table")),
                bundle.source.poses(test.params[test.labels == label]),
                bundle.K,
                bundle.height,
                bundle.width,
                bundle.background,
            )
            for label in range(len(bundle.classes))
        ]
    )
    assert np.array_equal(rendered, bundle.test().images)
    yaws, (pitch,), (roll,), (distance,) = (np.unique(test.params[:, i]) for i in range(4))
    metrics, log = viewpoints(
        out, "at-test", f"task.yaws=[{','.join(f'{y:g}' for y in yaws)}]", f"task.pitches=[{pitch:g}]",
        f"task.rolls=[{roll:g}]",
    )  # fmt: skip
    assert len(log) == len(test.labels) and metrics["accuracy"] == pytest.approx(trained["test_acc"], abs=1e-12)
    assert metrics[f"accuracy_pitch{pitch:g}_roll{roll:g}"] == metrics["accuracy"]


def test_every_cell_holds_every_class_at_every_yaw_and_the_metrics_count_its_rows(store):
    out, _ = store
    metrics, log = viewpoints(out, "grid", "task.pitches=[10,40]", "task.rolls=[0,30]")
    cfg = compose_cfg([*SETTINGS, "task=viewpoints"], out)
    test_yaws = load(cfg.data).split("test").params[:, 0]
    assert sorted(log.yaw.unique()) == midway(test_yaws)
    counts = log.groupby(["pitch", "roll", "label"]).size()
    assert len(counts) == 2 * 2 * 3 and (counts == len(midway(test_yaws))).all()
    for (p, r), cell in log.groupby(["pitch", "roll"]):
        assert metrics[f"accuracy_pitch{p:g}_roll{r:g}"] == pytest.approx(cell.correct.mean())
        assert (cell.correct == (cell.predict == cell.label)).all()
    # Each row's prediction is the model's on a view rendered at that row's own angles.
    bundle, model = load(cfg.data), load_classifier(bind(cfg)[0], TINY_CLASSES, torch.device("cpu"))
    for label, rows in log.groupby("label"):
        params = np.column_stack([rows[["yaw", "pitch", "roll"]].to_numpy(float), np.full(len(rows), 2.8)])
        images = render_poses(bundle.cloud(label), bundle.source.poses(params), bundle.K, 90, 160, 1.0)
        assert (classify(model, images, torch.device("cpu"), 16) == rows.predict.to_numpy()).all()


def test_without_surroundings_only_the_object_is_drawn(store):
    out, _ = store
    cfg = compose_cfg([*SETTINGS, "task=viewpoints"], out)
    bundle = load(cfg.data)
    params = np.array([[30.0, 10.0, 0.0, 2.8]])
    alone = render_poses(bundle.source.scene(0, ()), bundle.source.poses(params), bundle.K, 90, 160, 1.0)
    whole = render_poses(bundle.cloud(0), bundle.source.poses(params), bundle.K, 90, 160, 1.0)
    obj = render_poses(bundle.source.object(0), bundle.source.poses(params), bundle.K, 90, 160, 1.0)
    assert np.array_equal(alone, obj)
    empty = (alone == 255).all(axis=-1)
    assert 0 < (~empty).sum() < empty.sum() and not np.array_equal(alone, whole)


def test_midway_yaws_lie_halfway_on_the_circle():
    assert midway(np.array([0.0, 60, 120, 180, 240, 300, 0])) == [30.0, 90.0, 150.0, 210.0, 270.0, 330.0]
    assert midway(np.array([350.0, 10.0])) == [0.0, 180.0]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("task.pitches=[95]", "task.pitches=\\[95.0\\] is not allowed: a non-empty list of angles"),
        ("task.surroundings=[sky]", "task.surroundings=\\['sky'\\] is not allowed: a list of scene parts"),
        ("task.distance=-1", "task.distance=-1.0 is not allowed: a finite number > 0"),
    ],
)
def test_a_bad_viewpoint_setting_stops_before_any_run(override, message, tmp_path):
    import re

    proc = run_cli(["task=viewpoints", *SETTINGS, override], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert re.search(message, proc.stderr.strip().splitlines()[-1]), proc.stderr[-500:]
    assert not (tmp_path / "runs").exists() or not list((tmp_path / "runs").rglob("viewpoints.tsv"))


def test_the_object_mask_is_the_pixels_the_object_covers(store):
    from mrcert.core.geometry import matrix_to_motion
    from mrcert.core.projection import camera_points, project

    out, _ = store
    bundle = load(compose_cfg([*SETTINGS, "task=viewpoints"], out).data)
    poses = bundle.source.poses(np.array([[30.0, 10.0, 0.0, 2.8], [90.0, 40.0, 30.0, 2.8]]))
    masks = object_mask(bundle, 1, poses)
    points, colors = (torch.from_numpy(a) for a in bundle.source.object(1))
    for pose, mask in zip(poses, masks, strict=True):
        local = camera_points(points, matrix_to_motion(torch.from_numpy(pose)))
        _, depth = project(local, colors, bundle.K, torch.zeros(1, 6, dtype=torch.float64), 90, 160)
        assert np.array_equal(mask, torch.isfinite(depth[0]).numpy()) and 0 < mask.sum() < mask.size / 2


def test_occlusion_is_the_fall_of_the_class_probability_under_each_grey_square(store):
    out, _ = store
    cfg = bind(compose_cfg([*SETTINGS, "task=viewpoints"], out))[0]
    model, cpu = load_classifier(cfg, TINY_CLASSES, torch.device("cpu")), torch.device("cpu")
    grey = np.full((90, 160, 3), 128, np.uint8)
    # Covering grey with grey changes nothing (up to float rounding between batch sizes).
    assert np.abs(occlusion(model, grey, 0, 16, cpu, 16)).max() < 1e-6
    image = load(cfg.data).test().images[0]
    falls = occlusion(model, image, 2, 90, cpu, 7)  # squares of the image's height: one row of places
    probability = lambda x: torch.softmax(model(torch.tensor(x).permute(2, 0, 1)[None].float() / 255), 1)[0, 2]
    covered = image.copy()
    covered[:, 0:90] = 128
    with torch.inference_mode():
        expected = float(probability(image) - probability(covered))
    # Column 0 is covered only by the first square (columns 0-44), so its fall is that square's alone.
    assert falls[:, 0] == pytest.approx(expected, abs=1e-6) and (falls[:, 0] == falls[0, 0]).all()
    # The share of the positive falls on the mask; a negative fall (covering helps) is no evidence.
    assert object_share(np.array([[3.0, -0.5], [0.0, 1.0]]), np.array([[True, False], [False, False]])) == 0.75
    assert np.isnan(object_share(np.array([[-1.0, 0.0]]), np.array([[True, False]])))


def test_occlusion_runs_give_each_cells_first_yaw_an_object_share(store):
    out, _ = store
    settings = ("task.pitches=[10,40]", "task.occlusion=true", "task.occlusion_patch=30")
    metrics, log = viewpoints(out, "occlusion", *settings)
    first = log[log.yaw == log.yaw.min()]  # each class's first yaw in each cell; nan: no square lowers it
    assert first.object_share.between(0, 1).any() and log[log.yaw != log.yaw.min()].object_share.isna().all()
    for (p, r), cell in first.groupby(["pitch", "roll"]):
        assert metrics[f"object_share_pitch{p:g}_roll{r:g}"] == pytest.approx(cell.object_share.mean(), nan_ok=True)
    assert (out / "runs" / "occlusion" / "occlusion.png").is_file()
