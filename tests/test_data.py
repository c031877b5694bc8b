"""Scenes and datasets: protocols, determinism, cache, crop exactness, loaders, bad files."""

import json
import os
import pickle
import re
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from PIL import Image

from mrcert.core.crop import CropBound
from mrcert.core.generator import GENERATOR_VERSION
from mrcert.core.geometry import matrix_to_motion
from mrcert.core.methods.camera_motion import CameraMotionSmoothing
from mrcert.core.projection import camera_points
from mrcert.data.datasets import DataBundle, render_poses
from mrcert.data.protocols import look_at_poses
from mrcert.data.sources import load
from mrcert.errors import ConfigError, MrcertError
from mrcert.infra.config import CONF_DIR, validate
from mrcert.scenes import metaroom

TINY = ["data.classes=[can,mug]", "data.room_density=0.03", "data.density=0.01"]


def data_cfg(name: str, overrides: list[str], tmp_path):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[f"data={name}", f"paths.outputs={tmp_path}", *overrides])
    return cfg.data


def pose_angles(poses: np.ndarray, target=(0, 0, 0), yaw_offset: float = 0.0) -> np.ndarray:
    """(yaw, pitch, roll, radius) recovered from camera-to-world matrices (degrees, metres)."""
    c = poses[:, :3, 3] - np.asarray(target)
    r = np.linalg.norm(c, axis=1)
    yaw = (np.rad2deg(np.arctan2(c[:, 1], c[:, 0])) - yaw_offset + 180) % 360 - 180
    pitch = np.rad2deg(np.arcsin(c[:, 2] / r))
    right = np.column_stack([-np.sin(np.deg2rad(yaw + yaw_offset)), np.cos(np.deg2rad(yaw + yaw_offset)), 0 * r])
    down = np.cross(poses[:, :3, 2], right)
    x = poses[:, :3, 0]
    roll = np.rad2deg(np.arctan2(np.einsum("ij,ij->i", x, down), np.einsum("ij,ij->i", x, right)))
    # Every camera looks at the target.
    np.testing.assert_allclose(poses[:, :3, 2], -c / r[:, None], atol=1e-12)
    return np.column_stack([yaw, pitch, roll, r])


def test_look_at_poses_are_rigid_and_recover_their_angles(rng):
    params = np.column_stack(
        [rng.uniform(-180, 180, 50), rng.uniform(0, 89, 50), rng.uniform(-60, 60, 50), rng.uniform(1, 3, 50)]
    )
    poses = look_at_poses(*params.T)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(pose_angles(poses), params, atol=1e-9)


def test_metaroom_protocol(tmp_path):
    data = data_cfg("metaroom_synth", [*TINY, "data.protocol.train.per_class=300"], tmp_path)
    bundle = load(data)
    test, train = bundle.split("test"), bundle.split("train")
    assert np.bincount(test.labels).tolist() == [6, 6] and np.bincount(train.labels).tolist() == [300, 300]
    angles = pose_angles(test.poses)
    np.testing.assert_allclose(angles[:, 1:], np.tile([10.0, 0.0, 2.8], (12, 1)), atol=1e-9)
    yaws = np.sort(angles[:6, 0] % 360)
    np.testing.assert_allclose(np.diff(yaws), 60.0, atol=1e-9)
    tr = pose_angles(train.poses)
    assert (tr[:, 3] >= 2.3).all() and (tr[:, 3] <= 2.9).all()
    assert (tr[:, 1] >= 0).all() and (tr[:, 1] <= 90).all() and (np.abs(tr[:, 2]) <= 60 + 1e-9).all()
    assert (train.poses[:, 2, 3] < metaroom.CEILING_Z).all()  # cameras inside the room
    assert_strictly_separated(tr, angles)
    # ... while the ranges are otherwise covered (the rule is not vacuous).
    assert (tr[:, 0] % 360).min() < 20 and (tr[:, 0] % 360).max() > 340 and tr[:, 2].min() < -50 and tr[:, 2].max() > 50
    assert tr[:, 1].min() < 30 and tr[:, 1].max() > 80


def assert_strictly_separated(train: np.ndarray, test: np.ndarray) -> None:
    """Every training pose's yaw, pitch and roll each differ by at least 15 deg from those of
    every test pose (the paper: "at least 15 deg away from any yaw, pitch, or roll angle of
    every pose in the test set")."""
    dyaw = np.abs((train[:, None, 0] - test[None, :, 0] + 180) % 360 - 180)
    dpitch = np.abs(train[:, None, 1] - test[None, :, 1])
    droll = np.abs(train[:, None, 2] - test[None, :, 2])
    assert (dyaw >= 15 - 1e-9).all() and (dpitch >= 15 - 1e-9).all() and (droll >= 15 - 1e-9).all()


@pytest.mark.parametrize("profile", ["quick", "paper"])
def test_every_metaroom_training_pose_is_apart_from_every_test_pose_in_every_angle(profile, tmp_path):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["data=metaroom_synth", f"profile={profile}", f"paths.outputs={tmp_path}"])
    bundle = load(cfg.data)
    test, train = bundle.split("test"), bundle.split("train")
    assert len(train) == 20 * 500
    assert_strictly_separated(pose_angles(train.poses), pose_angles(test.poses))


def test_metaroom_validation_poses_stand_to_the_training_poses_as_the_test_poses_do(tmp_path):
    """Selection poses: as far from every training pose in pitch and roll as the test poses (the
    same pitch extrapolation and roll gap), at yaws spread over the room but at least 15 deg from
    every test yaw (never a test pose), and costing no training pose."""
    bundle = load(data_cfg("metaroom_synth", [*TINY, "data.protocol.train.per_class=300"], tmp_path))
    val, test, train = (pose_angles(bundle.split(s).poses) for s in ("validation", "test", "train"))
    assert np.bincount(bundle.split("validation").labels).tolist() == [12, 12]
    gap = lambda a, b, q: np.abs(a[:, None, q] - b[None, :, q]).min(axis=1)  # nearest, per pose of a
    for q in (1, 2):  # pitch, roll: every validation pose's gaps to the training poses are a test pose's
        assert np.isin(gap(val, train, q).round(9), gap(test, train, q).round(9)).all()
        assert gap(val, train, q).min() >= 15 - 1e-9
    np.testing.assert_allclose(val[:, 3], 2.8)
    d_yaw = np.abs((val[:, None, 0] - test[None, :, 0] + 180) % 360 - 180).min(axis=1)
    assert d_yaw.min() >= 15 - 1e-9 and d_yaw.max() - d_yaw.min() > 5  # not one angle per gap: varied backgrounds
    windows = np.floor(((val[:, 0] + 360) % 360) / 60).astype(int)
    assert len(set(windows)) == 6  # between every pair of neighbouring test yaws
    no_validation = [*TINY, "data.protocol.train.per_class=300", "~data.protocol.validation"]
    without = load(data_cfg("metaroom_synth", no_validation, tmp_path))
    assert not without.has_split("validation") and without.validation() is None
    assert np.array_equal(without.split("train").poses, bundle.split("train").poses)


def test_tabletop_protocol(tmp_path):
    data = data_cfg(
        "tabletop_synth", ["data.protocol.train.per_class=200", "data.density=0.01", "data.room_density=0.02"], tmp_path
    )
    bundle = load(data)
    test, train, val = bundle.split("test"), bundle.split("train"), bundle.split("validation")
    assert np.bincount(test.labels).tolist() == [19] * 6 and np.bincount(train.labels).tolist() == [200] * 6
    assert np.bincount(val.labels).tolist() == [19] * 6
    for split in (test, train, val):
        a = pose_angles(split.poses, yaw_offset=180.0)
        assert (np.abs(a[:, 0]) <= 30 + 1e-9).all() and (a[:, 1] >= 35).all() and (a[:, 1] <= 65).all()
        assert (np.abs(a[:, 2]) <= 60 + 1e-9).all() and (a[:, 3] >= 0.35).all() and (a[:, 3] <= 0.45).all()
        assert (split.poses[:, 0, 3] < 0).all()  # the camera is on the robot's side
    for label in range(6):
        te = pose_angles(test.poses[test.labels == label], yaw_offset=180.0)
        tr = pose_angles(train.poses[train.labels == label], yaw_offset=180.0)
        d = np.abs(tr[:, None, :] - te[None, :, :])
        close = (d[..., 0] < 10) & (d[..., 1] < 5) & (d[..., 2] < 20) & (d[..., 3] < 0.016)
        assert not close.any()
        # The validation poses are drawn like the test poses and kept apart from training the same way.
        va = pose_angles(val.poses[val.labels == label], yaw_offset=180.0)
        d = np.abs(tr[:, None, :] - va[None, :, :])
        assert not ((d[..., 0] < 10) & (d[..., 1] < 5) & (d[..., 2] < 20) & (d[..., 3] < 0.016)).any()
        assert not np.isin(va, te).all(axis=1).any()


def test_generation_is_deterministic_and_seeded(tmp_path):
    a, b = load(data_cfg("metaroom_synth", TINY, tmp_path)), load(data_cfg("metaroom_synth", TINY, tmp_path))
    for label in (0, 1):
        pa, ca = a.cloud(label)
        pb, cb = b.cloud(label)
        assert np.array_equal(pa, pb) and np.array_equal(ca, cb)
    assert np.array_equal(a.split("train").poses, b.split("train").poses)
    c = load(data_cfg("metaroom_synth", [*TINY, "data.seed=1"], tmp_path))
    assert not np.array_equal(a.split("train").poses, c.split("train").poses)


def test_cache_hits_on_same_config_and_misses_on_change(tmp_path):
    data = data_cfg("metaroom_synth", [*TINY, "data.protocol.train.per_class=3"], tmp_path)
    first = load(data)
    images = np.array(first.train().images)
    assert first.cache_info["train"]["hit"] is False
    second = load(data)
    again = second.train()
    assert second.cache_info["train"]["hit"] is True and np.array_equal(np.array(again.images), images)
    # Images are stored losslessly: the cache equals a fresh float render.
    split = second.split("train")
    fresh = render_poses(second.cloud(0), split.poses[:2], second.K, 90, 160, 1.0)
    assert np.array_equal(fresh, images[:2])
    changed = load(
        data_cfg("metaroom_synth", [*TINY, "data.protocol.train.per_class=3", "data.density=0.012"], tmp_path)
    )
    changed.train()
    assert changed.cache_info["train"]["hit"] is False
    assert changed.cache_info["train"]["folder"] != first.cache_info["train"]["folder"]
    aug = load(data)
    augmented = aug.train(CameraMotionSmoothing(("rz",), (0.122173,)))
    assert aug.cache_info["train-rz-aug"]["hit"] is False and not np.array_equal(np.array(augmented.images), images)


def test_a_test_sample_moves_only_its_crop_into_the_camera_frame(tmp_path):
    """Building a data set's test sample, and rendering it within its crop's bound, leaves the
    whole cloud in the world frame (only the crop is moved: per image, most of the sample's
    cost); the first motion beyond the bound moves it, once, into exactly the crop's frame."""
    bundle = load(data_cfg("metaroom_synth", TINY, tmp_path))
    sample = bundle.samples(crop=CropBound((0.0, 0.0, 0.6)))[0]
    sample.render(torch.tensor([[0.0, 0.0, 0.3, 0.0, 0.0, 0.0]], dtype=torch.float64))
    assert "points" not in vars(sample)
    sample.render(torch.tensor([[0.0, 0.0, 0.9, 0.0, 0.0, 0.0]], dtype=torch.float64))  # beyond the bound
    moved = vars(sample)["points"]
    pose = matrix_to_motion(torch.from_numpy(bundle.split("test").poses[0]))
    assert torch.equal(moved, camera_points(torch.from_numpy(bundle.cloud(0)[0]), pose))
    assert torch.equal(moved[sample.crop_rank], sample.crop_points)
    assert sample.points is moved


@pytest.mark.parametrize(
    "bound,scale",
    [
        (None, [0.28] * 6),  # data.crop: the cone test, any rotation
        (CropBound((0.0, 0.0, 0.6)), [0, 0, 0.6, 0, 0, 0]),  # tz: the widened frustum
        (CropBound((0.3, 0.0, 0.0)), [0.3, 0, 0, 0, 0, 0]),  # tx
        (CropBound((0.0, 0.0, 0.0), 0.7), [0, 0, 0, 0, 0, 0.7]),  # rz: roll keeps the distance to the axis
        (CropBound((0.3, 0.3, 0.6), 0.7), [0.3, 0.3, 0.6, 0, 0, 0.7]),  # Theorem 1: translations + roll
    ],
)
def test_crop_is_exact_within_its_bound_and_falls_back_beyond(bound, scale, tmp_path, rng):
    bundle = load(data_cfg("metaroom_synth", TINY, tmp_path))
    sample = bundle.samples(crop=bound)[0]
    assert sample.label == 0 and sample.K[0, 0] == 386.274 and (sample.height, sample.width) == (90, 160)
    assert len(sample.crop_points) < 0.7 * len(sample.points)
    full = type(sample)(sample.points, sample.colors, sample.K, 90, 160, 0)  # no crop
    within = torch.tensor(rng.uniform(-1, 1, (40, 6)) * scale)
    within = within[sample.within_bound(within)]
    assert len(within) > 20
    beyond = torch.tensor(rng.uniform(-1, 1, (10, 6)) * np.maximum(scale, 0.05) * 3)
    assert not sample.within_bound(beyond).all()
    for motions in (within, beyond, torch.cat([within[:5], beyond[:5]])):
        img_c, dep_c = sample.render(motions)
        img_f, dep_f = full.render(motions)
        assert torch.equal(img_c, img_f) and torch.equal(dep_c, dep_f)
    # The sample equals the dataset's clean test image at zero motion.
    img, _ = sample.render(torch.zeros(1, 6, dtype=torch.float64))
    assert torch.equal(
        (img[0] * 255).round().to(torch.uint8).permute(1, 2, 0), torch.from_numpy(np.array(bundle.test().images[0]))
    )


def test_quick_metaroom_has_no_holes(tmp_path):
    """At the quick profile's density every pixel of a test image is covered by some surface."""
    bundle = load(data_cfg("metaroom_synth", ["data.classes=[mug,teddy_bear]"], tmp_path))
    test = bundle.test()
    assert np.array(test.images).max(axis=-1).min() < 255  # sanity: uint8 white would be the background
    assert not (np.array(test.images) == 255).all(axis=-1).any()


def write_release(root, classes=("apple", "bowl")):
    """A tiny copy of the released layout, with a known cloud and pose per certify sample."""
    rng = np.random.default_rng(0)
    base = root / "metaroom_tz_vanilla"
    records = []
    for c in classes:
        for split in ("train", "test"):
            (base / split / c).mkdir(parents=True)
            for k in range(2):
                Image.fromarray(rng.integers(0, 255, (90, 160, 3), dtype=np.uint8)).save(base / split / c / f"{k}.png")
        (base / "certify" / c).mkdir(parents=True)
        for k in range(2):
            pose = look_at_poses(60.0 * k, 10.0, 0.0, 2.8)[0]
            cloud = np.column_stack([rng.uniform(-1, 1, (3000, 3)) * [1.0, 1.0, 0.5], rng.uniform(0, 1, (3000, 3))])
            rec = {
                "intrinsic_matrix": np.array([[3090.192, 0, 640], [0, 3090.192, 360], [0, 0, 1]]),
                "pose": pose,
                "point_cloud": cloud,
            }
            with open(base / "certify" / c / f"{k:03d}.pkl", "wb") as f:
                pickle.dump(rec, f)
            records.append(rec)
    return records


def test_metaroom_room_and_table_share_one_material():
    """The paper's room gives walls, floor, ceiling and table one matte material (Roughcast).
    Each surface's median colour, unshaded (divided by its Lambert factor), is the same within
    the quantisation; the floor is measured around the rug, which is many colours."""
    from mrcert.scenes.textures import LIGHT

    points, colors = metaroom.room(0.05)
    table, table_colors = metaroom.table(0.05)
    half, top = metaroom.HALF, metaroom.CEILING_Z
    beside_rug = np.abs(points[:, :2]).max(axis=1) > metaroom.RUG
    surfaces = {  # (points on the surface, its outward normal)
        "floor": (np.isclose(points[:, 2], metaroom.FLOOR_Z) & beside_rug, (0, 0, 1)),
        "ceiling": (np.isclose(points[:, 2], top), (0, 0, -1)),
        "north wall": (np.isclose(points[:, 1], half), (0, -1, 0)),
        "south wall": (np.isclose(points[:, 1], -half), (0, 1, 0)),
        "east wall": (np.isclose(points[:, 0], half), (-1, 0, 0)),
        "west wall": (np.isclose(points[:, 0], -half), (1, 0, 0)),
    }
    albedo = {}
    for name, (on, normal) in surfaces.items():
        shade = metaroom.AMBIENT + (1 - metaroom.AMBIENT) * max(float(np.dot(normal, LIGHT)), 0.0)
        albedo[name] = np.median(colors[on], axis=0) / shade
    on_top = np.isclose(table[:, 2], 0.0)
    albedo["table top"] = np.median(table_colors[on_top], axis=0) / (
        metaroom.AMBIENT + (1 - metaroom.AMBIENT) * LIGHT[2]
    )
    reference = albedo["floor"]
    for name, value in albedo.items():
        assert np.allclose(value, reference, atol=0.02), f"{name}: {value} vs floor {reference}"
    rug = np.isclose(points[:, 2], metaroom.FLOOR_Z) & ~beside_rug
    assert len(np.unique(np.round(colors[rug] * 10), axis=0)) >= 6  # a floor of many colours behind the object


@pytest.mark.parametrize("name", ["metaroom_synth", "tabletop_synth"])
def test_the_declared_scene_extent_is_the_scenes_diagonal(name, tmp_path):
    """data.extent bounds every translation (validation); it must be the scene's own size."""
    data = data_cfg(name, ["data.density=0.05", "data.room_density=0.05"], tmp_path)
    points = load(data).source.background[0]
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    assert diagonal <= data.extent <= diagonal + 0.01


def test_released_layout_loader(tmp_path):
    records = write_release(tmp_path)
    bundle = load(data_cfg("metaroom", [f"data.path={tmp_path}", "motion=tz"], tmp_path))
    assert bundle.classes == ["apple", "bowl"]
    assert bundle.train().labels.tolist() == [0, 0, 1, 1] and len(bundle.test()) == 4
    samples = bundle.samples()
    assert samples.labels.tolist() == [0, 0, 1, 1]
    for i, rec in enumerate(records):
        s = samples[i]
        assert s.label == i // 2
        np.testing.assert_allclose(s.K.numpy(), [[386.274, 0, 80], [0, 386.274, 45], [0, 0, 1]])
        expected = camera_points(
            torch.from_numpy(rec["point_cloud"][:, :3]), matrix_to_motion(torch.from_numpy(rec["pose"]))
        )
        assert torch.equal(s.points, expected)


def test_released_layout_refuses_code_in_pickles_and_names_missing_folders(tmp_path):
    write_release(tmp_path)
    evil = tmp_path / "metaroom_tz_vanilla" / "certify" / "apple" / "000.pkl"
    evil.write_bytes(b"cos\nsystem\n(S'echo pwned'\ntR.")
    with pytest.raises(MrcertError, match="refusing to load os.system"):
        load(data_cfg("metaroom", [f"data.path={tmp_path}"], tmp_path)).samples()[0]
    with pytest.raises(MrcertError, match="metaroom_rx_vanilla.*does not exist"):
        load(data_cfg("metaroom", [f"data.path={tmp_path}", "motion=rx"], tmp_path))
    with pytest.raises(MrcertError, match="METAROOM_DIR"):
        load(data_cfg("metaroom", [], tmp_path))


def write_custom(tmp_path, points=None, colors=None, poses=None, dtype=np.float64):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (4000, 3)) if points is None else points
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(dtype)))
    if colors is not None:
        pcd.point.colors = o3d.core.Tensor(colors)
    cloud = tmp_path / "scan.ply"
    o3d.t.io.write_point_cloud(str(cloud), pcd)
    if poses is None:
        entries = [(s, c) for s in ("train", "test") for c in ("a", "b")]  # one view each: a yaw of its own
        poses = {
            "classes": ["a", "b"],
            "poses": [
                {"split": s, "label": c, "pose": look_at_poses(30.0 + 5 * k, 20.0, 0.0, 3.0)[0].tolist()}
                for k, (s, c) in enumerate(entries)
            ],
        }
    path = tmp_path / "poses.json"
    path.write_text(json.dumps(poses))
    return [f"data.path={cloud}", f"data.poses={path}"]


def test_custom_scene_renders_its_poses(tmp_path):
    rng = np.random.default_rng(1)
    colors = rng.integers(0, 256, (4000, 3)).astype(np.uint8)
    bundle = load(data_cfg("custom", write_custom(tmp_path, colors=colors), tmp_path))
    assert bundle.classes == ["a", "b"] and bundle.train().labels.tolist() == [0, 1]
    np.testing.assert_array_equal(bundle.points, np.random.default_rng(0).uniform(-1, 1, (4000, 3)))  # as written
    assert bundle.colors.max() <= 1.0 and np.allclose(bundle.colors * 255, colors, atol=1e-4)
    assert len(bundle.samples()) == 2


@pytest.mark.parametrize(
    "case,pattern",
    [
        ("missing", "does not exist"),
        ("empty", "has no points"),
        ("nan", "NaN or infinite coordinates"),
        ("colors", "colours outside"),
        ("rigid", "not a rigid transform"),
        ("label", "label 'c' is not one of the classes"),
    ],
)
def test_custom_scene_bad_files_get_clear_errors(case, pattern, tmp_path):
    pts = np.random.default_rng(0).uniform(-1, 1, (100, 3))
    pose = np.eye(4).tolist()
    kwargs = {}
    if case == "nan":
        pts[5, 1] = np.nan
        kwargs["points"] = pts
    if case == "colors":
        kwargs["colors"] = np.full((4000, 3), 300.0, np.float32)
    if case == "rigid":
        bad = (np.eye(4) * [2, 1, 1, 1]).tolist()
        kwargs["poses"] = {
            "classes": ["a"],
            "poses": [{"split": "train", "label": "a", "pose": bad}, {"split": "test", "label": "a", "pose": pose}],
        }
    if case == "label":
        kwargs["poses"] = {"classes": ["a"], "poses": [{"split": "train", "label": "c", "pose": pose}]}
    overrides = write_custom(tmp_path, **kwargs)
    if case == "missing":
        overrides[0] = f"data.path={tmp_path / 'nope.ply'}"
    if case == "empty":
        (tmp_path / "empty.ply").write_text(
            "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
            "property float y\nproperty float z\nend_header\n"
        )
        overrides[0] = f"data.path={tmp_path / 'empty.ply'}"
    with pytest.raises(MrcertError, match=pattern):
        load(data_cfg("custom", overrides, tmp_path))


def test_focal_length_must_be_positive(tmp_path):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["data=custom", "data.path=a.ply", "data.poses=p.json", "data.image.fx=0"])
    with pytest.raises(ConfigError, match=r"data.image.fx=0(\.0)? is not allowed: a finite number > 0"):
        validate(cfg)


FINGERPRINTS = Path(__file__).with_name("scene_fingerprints.json")


def scene_fingerprint(tmp_path) -> dict[str, list[list[float]]]:
    """Per rendered image (one test and one training image of every class of each synthetic
    dataset, coarse surfaces): the mean of each channel over each tile of a 3x4 grid, and the
    share of background pixels. Local enough that recolouring a part of one object shows."""
    out = {}
    for name, extra in (("metaroom_synth", TINY[1:]), ("tabletop_synth", [])):
        overrides = [*extra, "data.protocol.test.per_class=1", "data.protocol.train.per_class=1"]
        bundle = load(data_cfg(name, overrides, tmp_path))
        images = np.concatenate([np.asarray(bundle.test().images), np.asarray(bundle.train().images)])
        n, h, w, _ = images.shape
        tiles = images.reshape(n, 3, h // 3, 4, w // 4, 3).mean(axis=(2, 4)).reshape(n, -1) / 255
        background = (images == 255).all(axis=-1).reshape(n, -1).mean(axis=1)
        out[name] = np.round(np.column_stack([tiles, background]), 5).tolist()
    return out


def test_a_change_of_the_rendered_scenes_forces_a_generator_version_bump(tmp_path):
    """The data cache trusts GENERATOR_VERSION: a change of scene generation, pose sampling or
    rendering that is not given a new version would silently reuse old cached images. The
    fingerprints of each version are recorded here; a change needs a bump and a new record
    (MRCERT_RECORD_FINGERPRINT=1 pytest -k generator_version writes it)."""
    current = scene_fingerprint(tmp_path)
    recorded = json.loads(FINGERPRINTS.read_text()) if FINGERPRINTS.exists() else {}
    version = str(GENERATOR_VERSION)
    if os.environ.get("MRCERT_RECORD_FINGERPRINT") and version not in recorded:
        FINGERPRINTS.write_text(json.dumps(recorded | {version: current}) + "\n")
        recorded[version] = current
    assert version in recorded, f"GENERATOR_VERSION {version} has no recorded fingerprint: record it"
    for name, rows in recorded[version].items():
        assert np.allclose(current[name], rows, atol=2e-4), (
            f"the rendered {name} scenes changed but GENERATOR_VERSION is still {version}: bump it in "
            "mrcert/data/cache.py (so no old cache entry is reused) and record the new fingerprint"
        )


def test_surroundings_settings_build_the_scene_they_name(tmp_path, monkeypatch):
    """``data.surroundings`` (the parts around the object, the room's style) and ``data.ambient``
    (each one's light), each building what it says; at their as-built values they change neither
    a run key nor the cached images' identity (keys made before they existed stay valid)."""
    from mrcert.infra.identity import defining_values, digest
    from mrcert.infra.tasks import TASKS
    from mrcert.scenes import textures

    def source(*overrides):
        return load(data_cfg("metaroom_synth", [*TINY, *overrides], tmp_path)).source

    built = source()
    room, table = built.part("room"), built.part("table")
    assert built.surroundings == ("room", "table")
    alone, on_table = source("data.surroundings.parts=[]"), source("data.surroundings.parts=[table]")
    assert len(alone.background[0]) == 0
    assert np.array_equal(on_table.background[0], table[0]) and np.array_equal(on_table.background[1], table[1])
    # The plain room: the room's first six surfaces (floor, ceiling, walls), nothing on the walls,
    # the floor roughcast where the furnished room has its rug.
    plain = source("data.surroundings.room=plain").part("room")
    k = len(plain[0])
    assert 0 < k < len(room[0]) and np.array_equal(plain[0], room[0][:k])
    floor = np.isclose(room[0][:k, 2], metaroom.FLOOR_Z)
    rug = floor & (np.abs(room[0][:k, :2]) < metaroom.RUG).all(axis=1)
    assert rug.any() and np.array_equal(plain[1][~rug], room[1][:k][~rug])
    assert (plain[1][rug] != room[1][:k][rug]).any(axis=1).mean() > 0.5
    # Without the rug: the floor's rug area alone differs; the paper's room: the rug and the window.
    no_rug = source("data.surroundings.room=no_rug").part("room")
    assert np.array_equal(no_rug[0], room[0]) and np.array_equal(no_rug[1][:k], plain[1])
    assert np.array_equal(no_rug[1][k:], room[1][k:])
    paper = source("data.surroundings.room=paper").part("room")
    assert np.array_equal(paper[0], room[0])
    differ = (paper[1] != room[1]).any(axis=1)
    east = np.isclose(room[0][:, 0], metaroom.HALF, atol=0.02) & (room[0][:, 2] > -0.01) & (room[0][:, 2] < 1.21)
    assert (
        differ[rug.nonzero()[0]].mean() > 0.5
        and differ[east].any()
        and not differ[~np.pad(rug, (0, len(room[0]) - k)) & ~east].any()
    )
    # Ambient light 1.0: no shading, so the colours do not depend on where the light comes from.
    flat = source("data.ambient.room=1.0", "data.ambient.object=1.0")
    flat_room, flat_object, shaded_object = flat.part("room")[1], flat.object(0)[1], built.object(0)[1]
    monkeypatch.setattr(textures, "LIGHT", -textures.LIGHT)
    relit = source("data.ambient.room=1.0", "data.ambient.object=1.0")
    assert np.array_equal(relit.part("room")[1], flat_room) and np.array_equal(relit.object(0)[1], flat_object)
    assert not np.array_equal(source().part("room")[1], room[1])  # as built, the light shows
    assert not np.array_equal(source().object(0)[1], shaded_object)
    monkeypatch.undo()
    # Keys: as built, the same as without the settings; another value, another key and cache.
    cfg = data_cfg("metaroom_synth", TINY, tmp_path)
    identity = TASKS["train"].identity

    def key(data):
        return digest(defining_values({"task": {"name": "train"}, "data": data}, identity))

    bare = OmegaConf.to_container(cfg, resolve=True)
    del bare["surroundings"], bare["ambient"], bare["protocol"]["train"]["pitch_law"]
    assert key(OmegaConf.to_container(cfg, resolve=True)) == key(bare)
    assert key(
        OmegaConf.to_container(
            data_cfg("metaroom_synth", [*TINY, "data.surroundings.room=plain"], tmp_path), resolve=True
        )
    ) != key(bare)
    assert not {"surroundings", "ambient"} & set(load(cfg).identity())
    assert "pitch_law" not in load(cfg).identity()["protocol"]["train"]
    assert (
        load(data_cfg("metaroom_synth", [*TINY, "data.ambient.object=1.0"], tmp_path)).identity()
        != load(cfg).identity()
    )
    assert (
        load(data_cfg("metaroom_synth", [*TINY, "data.surroundings.parts=[]"], tmp_path)).identity()
        != load(cfg).identity()
    )


@pytest.mark.parametrize(
    "name, override, message",
    [
        ("metaroom_synth", "data.surroundings.parts=[rug]", "data.surroundings.parts=['rug'] names a part"),
        ("metaroom_synth", "data.surroundings.room=castle", "data.surroundings.room='castle' is not a room style"),
        (
            "metaroom_synth",
            "data.ambient.room=2.0",
            "data.ambient.room=2.0 is not allowed: a share of ambient light in [0, 1]",
        ),
        ("tabletop_synth", "data.surroundings.room=plain", "allowed: none (tabletop_synth has no room)"),
        ("tabletop_synth", "data.ambient.table=1.0", "tabletop_synth sets the light of nothing"),
        ("metaroom_synth", "data.protocol.train.pitch_law=sphere", "allowed: angle, area"),
    ],
)
def test_a_surroundings_setting_a_scene_cannot_build_is_one_line(name, override, message, tmp_path):
    from mrcert.tasks.inputs import check_classes

    with pytest.raises(MrcertError, match=re.escape(message)):
        check_classes(data_cfg(name, [*TINY[1:], override], tmp_path))


def test_the_pitch_law_draws_pitches_uniform_in_angle_or_over_the_sphere():
    """``angle``: the pitch uniform in degrees; ``area``: its sine uniform (the hemisphere's
    area), checked by Kolmogorov-Smirnov against each law and against the other."""
    from scipy import stats

    from mrcert.data.protocols import sample_poses

    ranges = {"yaw": (0.0, 360.0), "pitch": (0.0, 90.0), "roll": (0.0, 0.0), "radius": (2.8, 2.8)}
    for law in ("angle", "area"):
        pitch = sample_poses(4000, ranges, np.random.default_rng(1), pitch_law=law).params[:, 1]
        uniform_angle = stats.kstest(pitch / 90.0, "uniform").pvalue
        uniform_sine = stats.kstest(np.sin(np.deg2rad(pitch)), "uniform").pvalue
        assert (uniform_angle, uniform_sine)[law == "area"] > 0.01 and (uniform_angle, uniform_sine)[
            law == "angle"
        ] < 1e-6
    # As built, the draws are those of every other quantity: the same generator, the same numbers.
    a = sample_poses(50, ranges, np.random.default_rng(2)).params
    rng = np.random.default_rng(2)
    rng.uniform(0.0, 360.0, size=100)  # the yaws of the first batch (twice the poses asked for)
    assert np.array_equal(a[:, 1], rng.uniform(0.0, 90.0, size=100)[:50])


@pytest.mark.parametrize(
    "name, scene", [("metaroom_synth", False), ("tabletop_synth", False), ("custom", False), ("metaroom", False),
                    ("testscene", True), ("pointcloud", True)],
)  # fmt: skip
def test_each_data_option_names_the_class_that_builds_it(name, scene, tmp_path):
    """``conf/data/<name>.yaml``'s ``_target_`` is a dataset (DataBundle) or a scene source, and
    a class that is neither, or none, is refused in one line."""
    from mrcert.data.sources import SceneSource, is_scene, source_class

    data = data_cfg(name, [], tmp_path)
    assert issubclass(source_class(data), SceneSource if scene else DataBundle) and is_scene(data) == scene
    for target, says in [("mrcert.nothing.Here", "names no class"), ("mrcert.errors.MrcertError", "neither a dataset")]:
        data._target_ = target
        with pytest.raises(MrcertError, match=says):
            source_class(data)
