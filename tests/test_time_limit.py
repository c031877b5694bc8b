"""The time limit of ``task=verify`` is a promise: one instance's answer (``timeout`` if need be)
is in its result file within the limit plus one second of the process's start, whatever the
process is doing then, and an answer found later never replaces it."""

from __future__ import annotations

import gzip
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from mrcert.formats.answer import GRACE, ResultFile
from mrcert.formats.onnx_model import read_onnx
from mrcert.formats.vnnlib import read_vnnlib
from tests.conftest import ROOT
from tests.onnx_graphs import vnnlib_text

BENCH = ROOT / "tests" / "data" / "metaroom_vnncomp"


def test_the_watchdog_answers_timeout_and_a_later_answer_does_not_replace_it(tmp_path):
    late = ResultFile(tmp_path / "late.txt", time.time() + 0.3)
    early = ResultFile(tmp_path / "early.txt", time.time() + 0.3)
    assert early.write("unsat\n") == "unsat"
    time.sleep(0.8)
    assert (tmp_path / "late.txt").read_text() == "timeout\n"
    assert late.write("sat\n((X_0 0.5))\n") == "timeout"  # found after the limit: not written
    assert (tmp_path / "late.txt").read_text() == "timeout\n"
    assert (tmp_path / "early.txt").read_text() == "unsat\n"  # answered in time: the watchdog stays quiet


def hard_instance(folder: Path) -> tuple[Path, Path]:
    """The benchmark's network with every one of its 5,376 inputs free over a wide box: neither
    verified nor falsified in seconds (one bound of it takes a minute on 2 CPU cores)."""
    onnx = folder / "net.onnx"
    onnx.write_bytes(gzip.decompress((BENCH / "onnx" / "4cnn_ry_33_5_no_custom_OP.onnx.gz").read_bytes()))
    plain = folder / "p0.vnnlib"
    plain.write_bytes(gzip.decompress((BENCH / "vnnlib" / "spec_idx_40_eps_0.00000436.vnnlib.gz").read_bytes()))
    prop = read_vnnlib(plain)
    centre = (prop.low + prop.high) / 2
    with torch.no_grad():
        label = int(read_onnx(onnx)(torch.from_numpy(centre).float().reshape(1, 3, 32, 56)).argmax())
    low, high = np.clip(centre - 0.02, 0, 1), np.clip(centre + 0.02, 0, 1)
    vnnlib = folder / "wide.vnnlib"
    vnnlib.write_text(vnnlib_text(low, high, [[(j, label)] for j in range(20) if j != label], 20))
    return onnx, vnnlib


def test_a_tiny_limit_on_a_hard_instance_is_answered_timeout_in_time(tmp_path):
    onnx, vnnlib = hard_instance(tmp_path)
    result = tmp_path / "result.txt"
    limit = 1.0
    env = os.environ | {"MRCERT_OUTPUTS": str(tmp_path / "store")}
    cmd = [sys.executable, "-m", "mrcert", "task=verify", f"task.onnx={onnx}", f"task.vnnlib={vnnlib}",
           f"task.result={result}", f"task.timeout={limit}", "tracking=off"]  # fmt: skip
    launched = time.time()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert result.read_text() == "timeout\n"
    assert result.stat().st_mtime - launched <= limit + 1.0
    assert "the time limit passed" in err  # the search was still on: the process was ended
    assert time.time() - launched < limit + 1.0 + GRACE + 30


def test_the_competition_harness_answers_an_instance_into_its_result_file(tmp_path):
    """``vnncomp/run_instance.sh`` as the competition's runner calls it: spec_idx_40, which the
    competition's tools verified, is ``unsat`` in the result file; ``prepare_instance.sh`` refuses a
    file that is not there, in one line."""
    onnx, vnnlib = (
        BENCH / "onnx" / "4cnn_ry_33_5_no_custom_OP.onnx",
        BENCH / "vnnlib" / "spec_idx_40_eps_0.00000436.vnnlib",
    )
    env = os.environ | {
        "MRCERT_OUTPUTS": str(tmp_path / "store"),
        "MRCERT": str(Path(sys.executable).parent / "mrcert"),
    }
    prepare = ROOT / "vnncomp" / "prepare_instance.sh"
    assert (
        subprocess.run(["bash", prepare, "v1", "metaroom", onnx, vnnlib], env=env).returncode == 0
    )  # gzipped: read as is
    missing = subprocess.run(["bash", prepare, "v1", "metaroom", tmp_path / "none.onnx", vnnlib], env=env,
                             capture_output=True, text=True)  # fmt: skip
    assert missing.returncode != 0 and "none.onnx" in missing.stderr
    result = tmp_path / "out.txt"
    cmd = ["bash", ROOT / "vnncomp" / "run_instance.sh", "v1", "metaroom", onnx, vnnlib, result, "60"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert result.read_text() == "unsat\n"
