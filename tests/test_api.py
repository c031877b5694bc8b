"""The Python API (docs/api.md): its example runs and prints what the page says, and a
certificate from Python is the one the command line logs for the same image and seed."""

from __future__ import annotations

import contextlib
import io
import re
import subprocess
import sys

import pytest
import torch

import mrcert
from tests.conftest import ROOT, certify_args, compose_cfg

PAGE = ROOT / "docs" / "api.md"


def blocks(text: str) -> tuple[str, str]:
    """The page's Python example and the output it shows."""
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    shown = re.search(r"```text\n(.*?)```", text, re.S).group(1)
    return code, shown


def test_the_pages_example_prints_what_the_page_shows():
    code, shown = blocks(PAGE.read_text())
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(PAGE), "exec"), {"__name__": "example"})
    assert out.getvalue() == shown


def test_a_certificate_from_python_is_the_command_lines(checkpoints, tmp_path):
    """Two test images of the tiny data set: CERTIFY through the API (the trained checkpoint
    read by load_model, each image's cloud as a Scene) gives the class, count and radius that
    ``task=certify`` logs for it with the same seed; and at a nonzero seed the draws differ."""
    from mrcert.__main__ import run_task
    from mrcert.reporting.certify_log import read_log
    from mrcert.tasks.evaluation import prepare

    args = [*certify_args(checkpoints["a"], n=100), "task.max=2", "seed=3"]
    cfg = compose_cfg(args, tmp_path)
    run_task(cfg, tmp_path / "run")
    logged = read_log(tmp_path / "run" / "certify.tsv").set_index("idx")
    ev = prepare(cfg)
    model = mrcert.load_model(checkpoints["a"])
    for i in ev.indices:
        s = ev.samples[i]
        scene = mrcert.Scene(s.points, s.colors, s.K, s.height, s.width, s.background)
        smooth = mrcert.CameraMotionSmoothing(model, scene, axis=str(cfg.motion.axis), sigma=float(cfg.motion.sigma))
        cert = smooth.certify(n0=int(cfg.task.n0), n=int(cfg.task.n), alpha=float(cfg.task.alpha), seed=3, index=i)
        row = logged.loc[i]
        assert (cert.prediction, cert.count_a, cert.radius) == (row["predict"], row["count_a"], row["radius"])
        other = smooth.certify(n0=int(cfg.task.n0), n=int(cfg.task.n), alpha=float(cfg.task.alpha), seed=4, index=i)
        assert other.count_a != cert.count_a or other.prediction != cert.prediction or cert.count_a == int(cfg.task.n)


def test_bad_values_are_refused_in_one_line():
    scene = mrcert.Scene(torch.zeros(1, 3) + 2, torch.ones(1, 3), torch.eye(3, dtype=torch.float64), 4, 4)
    model = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(48, 2))
    with pytest.raises(mrcert.api.MrcertError, match=r"pose=\[1, 2\] is not allowed: six finite numbers"):
        mrcert.CameraMotionSmoothing(model, scene).certify(pose=[1, 2], n0=1, n=1)
    with pytest.raises(mrcert.api.MrcertError, match="half_width=0 is not allowed"):
        mrcert.BoundPropagation(model, scene).verify(half_width=0)
    with pytest.raises(mrcert.api.MrcertError, match="kind='line' is not allowed: one of uniform, grid"):
        mrcert.attack(model, scene, "tz", 0.1, kind="line")


def test_importing_mrcert_imports_no_torch():
    code = "import sys, mrcert; mrcert.__version__; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "False"
