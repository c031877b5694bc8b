"""Every option of every config group composes and validates; bad values are named."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from mrcert.config import CONF_DIR, validate
from mrcert.errors import ConfigError

GROUPS = sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and p.name not in ("hydra", "experiment"))


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def compose_cfg(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=overrides, return_hydra_config=True)


@pytest.mark.parametrize("group,option", [(g, o) for g in GROUPS for o in options(g)])
def test_every_option_composes_and_validates(group, option):
    required = {
        ("data", "pointcloud"): ["data.path=scan.ply"],
        ("data", "custom"): ["data.path=scan.ply", "data.poses=poses.json"],
        ("task", "import"): ["task.path=certify.tsv"],
    }
    overrides = [f"{group}={option}", *required.get((group, option), [])]
    cfg = compose_cfg(overrides)
    validate(cfg)
    assert OmegaConf.select(cfg, "hydra.run.dir").startswith(str(cfg.paths.outputs))


def test_groups_the_issue_asks_for_exist():
    assert {"task", "data", "motion", "model", "attack", "tracking"} <= set(GROUPS)
    assert {"tx", "ty", "tz", "rx", "ry", "rz"} <= set(options("motion"))
    assert options("tracking") == ["off", "server", "sqlite"]


@pytest.mark.parametrize(
    "axis,sigma", [("tz", 0.1), ("tx", 0.05), ("ty", 0.05), ("rz", 0.122173), ("rx", 0.0436332), ("ry", 0.0436332)]
)
def test_motion_configs_carry_the_paper_numbers(axis, sigma):
    m = compose_cfg([f"motion={axis}"]).motion
    assert (m.axis, m.sigma, m.radius) == (axis, sigma, sigma)
    assert m.radius_step == pytest.approx(sigma / 10)


def test_default_store_is_an_absolute_sqlite_uri_under_outputs():
    cfg = compose_cfg([])
    uri = cfg.tracking.uri
    assert uri.startswith("sqlite:////") and uri.endswith("/outputs/mlflow.db")
    assert Path(cfg.tracking.artifact_location).is_absolute()


@pytest.mark.parametrize(
    "override,key,value,allowed",
    [
        ("motion.axis=tw", "motion.axis", "'tw'", "tx, ty, tz, rx, ry, rz"),
        ("motion.sigma=0", "motion.sigma", "0", "> 0"),
        ("motion.sigma=-0.1", "motion.sigma", "-0.1", "> 0"),
        ("motion.radius=-1", "motion.radius", "-1", ">= 0"),
        ("+certify.alpha=1.5", "certify.alpha", "1.5", "strictly between 0 and 1"),
        ("+certify.alpha=0", "certify.alpha", "0", "strictly between 0 and 1"),
        ("data.image.height=0", "data.image.height", "0", "integer >= 1"),
        ("data.image.width=0", "data.image.width", "0", "integer >= 1"),
        ("data.image.fx=-3", "data.image.fx", "-3", "> 0"),
        ("task.axes=[tx,up]", "task.axes", "['tx', 'up']", "list of axes"),
        ("device=gpu", "device", "'gpu'", "auto, cpu, cuda or cuda:N"),
    ],
)
def test_bad_values_are_rejected_with_key_value_and_allowed(override, key, value, allowed):
    cfg = compose_cfg([override])
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    message = str(info.value)
    assert f"{key}={value}" in message and allowed in message
