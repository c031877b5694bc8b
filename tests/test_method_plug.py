"""The plug point of a certification method: the four places a further method touches, as
docs/method.md §8 lists them, and nothing in ``mrcert/infra/`` or ``mrcert/tasks/`` naming one."""

from __future__ import annotations

import ast
import dataclasses
import importlib

import pytest
import yaml

from mrcert.core import methods
from mrcert.core.methods import schemas as method_schemas
from mrcert.core.methods.base import Method
from mrcert.infra.config import CONF_DIR, plain
from mrcert.infra.identity import identify
from mrcert.infra.schema import SCHEMAS
from mrcert.infra.tasks import TASKS
from tests.conftest import ROOT, compose_cfg


def _naming(source: str) -> list[str]:
    """Where ``source`` names a registered method: a comparison with a method's name, a method's
    name, or a method's class (no method shares its name with a config group)."""
    names = set(methods.METHODS)
    classes = {m.target.split(":")[1] for m in methods.METHODS.values()}
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare) and any(isinstance(op, ast.Eq | ast.NotEq) for op in node.ops):
            found += [
                f"line {node.lineno}: compares with {o.value!r}"
                for o in (node.left, *node.comparators)
                if isinstance(o, ast.Constant) and o.value in names
            ]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if node.value in names or any(c in node.value for c in classes):
                found.append(f"line {node.lineno}: the string {node.value!r}")
        elif isinstance(node, ast.Name) and node.id in classes:
            found.append(f"line {node.lineno}: {node.id}")
        elif isinstance(node, ast.alias) and node.name in classes:
            found.append(f"imports {node.name}")
    return found


def test_no_method_is_named_like_a_config_group():
    """``method=motion`` read as a motion; a method's name says which method it is."""
    groups = {p.name for p in CONF_DIR.iterdir() if p.is_dir()}
    assert not set(methods.METHODS) & groups


def test_the_check_finds_a_method_named_in_each_way():
    assert _naming('if cfg.method.name == "camera_motion":\n    pass')
    assert _naming('RULE = ("method.name", "camera_motion")')
    assert _naming("from mrcert.core.methods.camera_motion import CameraMotionSmoothing")
    assert not _naming('if "motion" in ignored:\n    words.remove(str(cfg.method.name))')


@pytest.mark.parametrize("layer", ["infra", "tasks", "reporting"])
def test_no_module_of_infra_or_tasks_names_a_method(layer):
    found = {
        str(path.relative_to(ROOT)): hits
        for path in sorted((ROOT / "mrcert" / layer).glob("*.py"))
        if (hits := _naming(path.read_text()))
    }
    assert not found, f"methods named outside their plug point: {found}"


@pytest.mark.parametrize("name", sorted(methods.METHODS))
def test_each_method_lives_in_the_four_places_the_docs_list(name):
    entry = methods.METHODS[name]
    module, cls_name = entry.target.split(":")
    cls = getattr(importlib.import_module(module), cls_name)
    # 1. its own module of mrcert/core/, a subclass of Method
    assert issubclass(cls, Method) and module.startswith("mrcert.core.") and cls.__module__ == module
    # 2. one line of METHODS (this entry); 3. its schema in mrcert/core/methods/schemas.py,
    # registered under its name
    assert dataclasses.is_dataclass(entry.schema) and entry.schema.__module__ == method_schemas.__name__
    assert SCHEMAS["method"][name] is entry.schema
    # 4. its YAML, checked against that schema
    spec = yaml.safe_load((CONF_DIR / "method" / f"{name}.yaml").read_text())
    assert spec["name"] == name and {"/schema/method@_here_": name} in spec["defaults"]
    assert set(spec) - {"defaults"} == {f.name for f in dataclasses.fields(entry.schema)}
    section = (ROOT / "docs" / "method.md").read_text().split("## §8")[1].split("\n## ")[0]
    places = (
        "mrcert/core/",
        "`METHODS` in `mrcert/core/methods/__init__.py`",
        "mrcert/core/methods/schemas.py",
        "conf/method/",
    )
    assert all(place in section for place in places)


def _identity(task: str, *overrides: str):
    cfg = plain(compose_cfg([f"task={task}", "model.variant=augmented", *overrides]))
    cfg["model"]["checkpoint"] = "runs:/0123456789abcdef/checkpoints/best.pt"
    return identify(cfg, TASKS[task].identity)


def _key(task: str, *overrides: str) -> str:
    return _identity(task, *overrides).key


def test_what_a_method_leaves_out_of_run_keys_is_its_registry_line_alone(monkeypatch):
    pixel = ("method=pixelwise",)
    # As registered: a pixel-noise model serves every axis; its certifications differ by axis.
    assert _key("train", *pixel, "motion=tz") == _key("train", *pixel, "motion=rx")
    assert _key("certify", *pixel, "motion=tz") != _key("certify", *pixel, "motion=rx")
    # Motion smoothing's group adds nothing to any key (runs made before methods keep theirs).
    for task in ("train", "certify", "smooth", "attack", "render"):
        assert not [k for k in _identity(task, "method=camera_motion").values if k.startswith("method")]
        assert [k for k in _identity(task, *pixel).values if k.startswith("method")]
    line = methods.METHODS["pixelwise"]
    monkeypatch.setitem(methods.METHODS, "pixelwise", dataclasses.replace(line, unkeyed_model=()))
    assert _key("train", *pixel, "motion=tz") != _key("train", *pixel, "motion=rx")
    monkeypatch.setitem(methods.METHODS, "pixelwise", dataclasses.replace(line, unkeyed=("method.sigma",)))
    assert _key("certify", *pixel, "method.sigma=0.5") == _key("certify", *pixel)
