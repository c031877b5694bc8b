"""Bad input everywhere a user can type or point: only our own clear errors, never a crash."""

import errno
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf, ValidationError

from mrcert.__main__ import _user_error, check_writable
from mrcert.core.axes import AXES
from mrcert.data.custom import read_poses
from mrcert.errors import ConfigError, MrcertError
from mrcert.infra.config import CONF_DIR, validate
from mrcert.reporting.certify_log import read_log
from mrcert.scenes.scene import read_point_cloud

ROOT = Path(__file__).resolve().parent.parent
KEYS = [
    "motion.sigma",
    "motion.radius",
    "motion.axis",
    "motion.radius_step",
    "task.n0",
    "task.n",
    "task.alpha",
    "task.decision",
    "task.skip",
    "task.max",
    "task.shard",
    "task.num_shards",
    "task.batch_size",
    "task.crop_sigmas",
    "data.image.height",
    "data.image.width",
    "data.image.fx",
    "data.image.cy",
    "data.density",
    "seed",
    "device",
    "model.variant",
    "attack.k",
    "attack.radius",
    "data.protocol.train.yaw_range",
    "data.crop.max_rotation",
]
GPUS = torch.cuda.device_count() if torch.cuda.is_available() else 0
VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.sampled_from([2**32 - 1, 2**32, 2**64]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(alphabet=st.characters(blacklist_characters="${}\\"), max_size=8),
    st.lists(st.integers(-5, 5), max_size=3),
    st.sampled_from(
        ["tx", "rz", "tw", "tx+rz", "cuda", "cuda:0", "cuda:1", "gpu", "vanilla", "vote", "predict", "???"]
    ),
)


@pytest.fixture(scope="module")
def base_cfg():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=["task=certify"])


def number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def integer(v, low: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= low


# What each key allows, written here independently of mrcert's rules (the oracle).
ALLOWED = {
    "motion.sigma": lambda v: number(v) and v > 0,
    "motion.radius": lambda v: number(v) and v >= 0,
    "motion.axis": lambda v: v in AXES,  # a one-axis motion (several: motion.axes)
    "motion.radius_step": lambda v: number(v) and v > 0,
    "task.n0": lambda v: integer(v, 1),
    "task.n": lambda v: integer(v, 1),
    "task.alpha": lambda v: number(v) and 0 < v < 1,
    "task.decision": lambda v: v in ("predict", "vote"),
    "task.skip": lambda v: integer(v, 1),
    "task.max": lambda v: v is None or integer(v, 1),
    "task.shard": lambda v: integer(v, 0),
    "task.num_shards": lambda v: integer(v, 1),
    "task.batch_size": lambda v: v == "auto" or integer(v, 1),
    "task.crop_sigmas": lambda v: number(v) and v > 0,
    "data.image.height": lambda v: integer(v, 1),
    "data.image.width": lambda v: integer(v, 1),
    "data.image.fx": lambda v: number(v) and v > 0,
    "data.image.cy": number,
    "data.density": lambda v: number(v) and v > 0,
    "seed": lambda v: integer(v, 0) and v < 2**32,
    "device": lambda v: (
        isinstance(v, str) and (v in ("auto", "cpu") or GPUS > 0 and v in ("cuda", *(f"cuda:{i}" for i in range(GPUS))))
    ),
    "model.variant": lambda v: v in ("vanilla", "augmented"),
    "attack.k": lambda v: integer(v, 1),
    "attack.radius": lambda v: number(v) and v >= 0,
    "data.protocol.train.yaw_range": lambda v: (
        isinstance(v, list) and len(v) == 2 and all(map(number, v)) and v[0] <= v[1]
    ),
    "data.crop.max_rotation": lambda v: number(v) and v >= 0,
}


ROOM_DIAGONAL = math.sqrt(6**2 + 6**2 + 3.7**2)  # the synthetic MetaRoom: 6 m x 6 m, 3.7 m high


def motion_in_scale(motion) -> bool:
    """What a motion can represent (each key already allowed on its own): a rotation angle at
    most pi, a translation within the room, and a certified-accuracy curve (up to 5 sigma or the
    radius) of at most 100,000 radii."""
    bound = math.pi if motion.axis.startswith("r") else ROOM_DIAGONAL
    curve_points = max(5 * motion.sigma, motion.radius) / motion.radius_step
    return max(motion.sigma, motion.radius) <= bound and curve_points <= 1e5


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(changes=st.dictionaries(st.sampled_from(KEYS), VALUES, min_size=1, max_size=4))
@example(changes={"task.shard": 1, "device": None})  # a bad shard is reported before a bad device
@example(changes={"task.shard": "0"})  # the schema holds it as the integer 0: a valid shard
def test_validation_rejects_exactly_the_values_that_are_not_allowed(base_cfg, changes):
    """Each value is refused by its type as the config is composed (a value its schema's type
    cannot hold), or else by validation exactly when it is not allowed."""
    cfg = base_cfg.copy()
    for key, value in changes.items():
        try:
            OmegaConf.update(cfg, key, value, merge=False)
        except ValidationError as exc:  # what composing the config with key=value refuses
            assert exc.full_key == key and not ALLOWED[key](value)
            return
    stored = {k: v if v == "???" else OmegaConf.select(cfg, k) for k, v in changes.items()}  # as the schema holds it
    stored = {k: OmegaConf.to_container(v) if OmegaConf.is_config(v) else v for k, v in stored.items()}
    bad = {k for k, v in stored.items() if v == "???" or not ALLOWED[k](v)}
    shards = stored.get("task.num_shards", 1)
    both_valid = "task.shard" in stored and not {"task.shard", "task.num_shards"} & bad
    if both_valid and stored["task.shard"] >= shards:
        bad.add("task.shard")  # a shard outside [0, num_shards), whatever else is bad
    scale = {"motion.sigma", "motion.radius", "motion.radius_step"}
    if not any(k.startswith("motion.") for k in bad) and not motion_in_scale(cfg.motion):
        bad |= scale  # a motion out of scale may be reported before another key's bad value
    if bad:
        with pytest.raises(ConfigError) as info:
            validate(cfg)
        # The error names one of the bad keys (a "???" anywhere is reported as a missing value).
        assert info.value.key.split("[")[0] in bad and "is not allowed" in str(info.value)
    else:
        validate(cfg)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(blob=st.binary(max_size=400), suffix=st.sampled_from([".ply", ".pcd", ".json", ".tsv", ".txt"]))
def test_random_files_only_ever_raise_clear_errors(tmp_path, blob, suffix):
    path = tmp_path / f"f{suffix}"
    path.write_bytes(blob)
    for reader in (read_point_cloud, read_poses, read_log):
        try:
            reader(path)
        except MrcertError as exc:
            assert str(path) in str(exc) or "poses[" in str(exc)


def test_unwritable_outputs_get_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert "not writable" in check_writable(blocker / "outputs")
    proc = subprocess.run(
        [sys.executable, "-m", "mrcert", "task=render", "data=testscene", f"paths.outputs={blocker / 'outputs'}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "is not writable" in proc.stderr and "Traceback" not in proc.stderr
    assert check_writable(tmp_path / "new" / "folder") is None


def test_full_or_read_only_disks_are_user_errors():
    full = _user_error(OSError(errno.ENOSPC, "No space left on device", "/data/x.npy"))
    assert "/data/x.npy" in full and "No space left on device" in full and "MRCERT_OUTPUTS" in full
    assert "Read-only file system" in _user_error(OSError(errno.EROFS, "Read-only file system", "/ro"))
    assert _user_error(ValueError("a bug")) is None
