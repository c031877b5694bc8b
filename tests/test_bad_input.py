"""Bad input everywhere a user can type or point: only our own clear errors, never a crash."""

import errno
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf, open_dict

from mrcert.__main__ import _user_error, check_writable
from mrcert.certify_log import read_log
from mrcert.config import CONF_DIR, validate
from mrcert.data.custom import read_poses
from mrcert.errors import ConfigError, MrcertError
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
VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.integers(-5, 5), max_size=3),
    st.sampled_from(["tx", "rz", "tw", "tx+rz", "cuda:1", "gpu", "vanilla", "???"]),
)


@pytest.fixture(scope="module")
def base_cfg():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=["task=certify"])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(changes=st.dictionaries(st.sampled_from(KEYS), VALUES, min_size=1, max_size=4))
def test_validation_only_ever_raises_config_errors(base_cfg, changes):
    cfg = OmegaConf.create(OmegaConf.to_container(base_cfg))
    with open_dict(cfg):
        for key, value in changes.items():
            OmegaConf.update(cfg, key, value, force_add=True)
    try:
        validate(cfg)
    except ConfigError as exc:
        assert exc.key and "is not allowed" in str(exc)


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
