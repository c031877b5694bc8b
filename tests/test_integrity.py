"""Nothing wrong is ever certified: damaged logs, cut inputs, non-finite models, configs that
would call functions, and refusals that leave no run behind, each through the command line."""

import os
import re
import signal

import pandas as pd
import pytest
import torch

from mrcert.reporting.certify_log import read_log
from tests.conftest import (
    PER_RUN,
    TINY,
    certify_args,
    certify_logs,
    kill_when,
    run_cli,
    start_cli,
    store_runs,
    wait_until,
    write_cloud,
)


def test_a_damaged_row_left_in_a_killed_run_s_log_is_never_adopted(checkpoints, reference, tmp_path):
    """Killed after its first row, a certify log gains a short row claiming image 1 (label 1
    where its label is 0, radius 5.0), as a torn write or a bad copy could leave: the same
    command sets it aside and certifies image 1 again, giving the uninterrupted run's rows."""
    args = certify_args(checkpoints["a"])
    kill_when(args, tmp_path, lambda: any(len(p.read_text().splitlines()) == 2 for p in certify_logs(tmp_path)))
    (log,) = certify_logs(tmp_path)
    with open(log, "a") as f:
        f.write("1\t1\t1\t5.0\n")
    done = run_cli(args, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    (run,) = store_runs(tmp_path)
    assert run.info.status == "FINISHED"
    pd.testing.assert_frame_equal(read_log(log).drop(columns=PER_RUN, errors="ignore"), reference["a"])
    (aside,) = log.parent.glob("set_aside/rejected_*/certify.rejected.tsv")
    assert "1\t1\t1\t5.0" in aside.read_text()


@pytest.mark.slow
def test_sigterm_is_one_line_and_the_run_is_killed_with_its_time(checkpoints, tmp_path):
    """SIGTERM (``kill``, a scheduler's stop) is handled as Ctrl-C: one line, exit 143, the run
    KILLED with its working time logged, and the same command finishes it."""
    args = certify_args(checkpoints["a"], n=2000)
    proc = start_cli(args, tmp_path)
    wait_until(proc, lambda: any(len(p.read_text().splitlines()) >= 2 for p in certify_logs(tmp_path)))
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 143 and "Traceback" not in err, err[-2000:]
    assert err.strip().splitlines()[-1] == (
        "mrcert: stopped (SIGTERM); the run is marked KILLED and the same command resumes it"
    )
    (run,) = store_runs(tmp_path)
    assert run.info.status == "KILLED" and run.data.metrics["timed_segments"] == 1
    assert run.data.metrics["active_seconds"] > 0
    assert run_cli(args, tmp_path).returncode == 0
    (run,) = store_runs(tmp_path)
    assert run.info.status == "FINISHED"


def test_training_that_diverges_stops_with_one_line_and_a_failed_run(tmp_path):
    """``train.lr=1e12`` makes the loss NaN: training stops in that epoch with one line, nothing
    of it is saved, and the run is FAILED with the reason recorded."""
    proc = run_cli([*TINY, "task=train", "train.lr=1e12", "train.epochs=2", "train.batch_size=8"], tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    diverged = r"mrcert: error: training diverged in epoch 1: .* stopped being finite \(train.lr=1000000000000.0\)"
    assert re.match(diverged, last), last
    (run,) = store_runs(tmp_path)
    assert run.info.status == "FAILED" and "training diverged" in run.data.tags["mrcert.failure"]
    assert not list(tmp_path.glob("runs/train/*/*.pt"))


def test_a_checkpoint_with_non_finite_weights_is_refused(checkpoints, tmp_path):
    """A model whose weights hold a NaN would vote class 0 for every image: it is refused before
    any run exists."""
    state = torch.load(checkpoints["a"], weights_only=True)
    name = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][name].view(-1)[0] = float("nan")
    broken = tmp_path / "nan.pt"
    torch.save(state, broken)
    proc = run_cli(certify_args(broken), tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert f"nan.pt' holds NaN or infinite weights ({name}" in proc.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "mlflow.db").exists() or store_runs(tmp_path) == []  # refused before any run


def test_a_damaged_store_is_one_line_naming_it_and_no_run_starts(checkpoints, tmp_path):
    """A store whose pages are damaged: one line naming the file and what to do, no traceback,
    and nothing left RUNNING (the damage is found before any run is opened)."""
    args = certify_args(checkpoints["a"], n=20)
    assert run_cli(args, tmp_path).returncode == 0
    db = tmp_path / "mlflow.db"
    data = bytearray(db.read_bytes())
    for page in range(1, len(data) // 4096):
        data[page * 4096 + 8 : page * 4096 + 200] = os.urandom(192)
    db.write_bytes(bytes(data))
    proc = run_cli([*args, "seed=1"], tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert f"the MLflow store {db} is damaged" in last and f"mv {db} {db}.broken" in last
    assert len(list(tmp_path.glob("runs/certify/*"))) == 1  # the first run's folder only


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("cut binary cloud", r"bad.ply' declares 100 points but holds data for [45]\d: it is cut short"),
        ("cut ascii cloud", r"bad.ply' declares 100 points but holds data for [45]\d: it is cut short"),
        ("a class twice", r"data.classes=\['mug', 'mug', 'can'\] is not allowed: .* each once"),
        ("a GPU this machine lacks", r"device='cuda:7' is not allowed: auto, cpu, or a GPU of this machine"),
        ("a seed out of range", r"seed=18446744073709551616 is not allowed: an integer in \[0, 2\*\*32\)"),
        ("a target that calls a function", r"model.net._target_='builtins.print' is not allowed: an nn.Module"),
        ("a nested target that writes a file", r"model.net.width._target_='builtins.open' is not allowed: none"),
    ],
)
def test_a_bad_input_or_value_stops_before_any_run_and_calls_nothing(case, message, tmp_path):
    """Each stops with one line before any run or run folder exists: a point cloud cut short (Open3D
    only warns and would leave the missing points in place), a class list with a duplicate (a
    model with an empty class), a GPU the machine does not have, a seed no generator takes, and a
    model target that is not a module, called nowhere (the nested ``builtins.open`` creates no file)."""
    bad, written = tmp_path / "bad.ply", tmp_path / "written.txt"
    if case.startswith("cut"):
        write_cloud(bad, ascii=case == "cut ascii cloud")
        data = bad.read_bytes()
        bad.write_bytes(data[: len(data) - (len(data) - data.index(b"end_header")) // 2])
    args = {
        "cut binary cloud": ["task=render", "data=pointcloud", f"data.path={bad}"],
        "cut ascii cloud": ["task=render", "data=pointcloud", f"data.path={bad}"],
        "a class twice": [*TINY, "task=train", "data.classes=[mug,mug,can]"],
        "a GPU this machine lacks": [*TINY, "task=train", "device=cuda:7"],
        "a seed out of range": [*TINY, "task=train", f"seed={2**64}"],
        "a target that calls a function": [*TINY, "task=train", "model.net._target_=builtins.print"],
        "a nested target that writes a file": [
            *TINY,
            "task=train",
            f"+model.net.width={{_target_:builtins.open,file:{written},mode:w}}",
        ],
    }[case]
    if case == "a GPU this machine lacks" and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a GPU cuda:7")
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("mrcert: error: ") and re.search(message, last), last
    assert not (tmp_path / "mlflow.db").exists() or store_runs(tmp_path) == []  # no run, not even a FAILED one
    assert not [p for p in (tmp_path / "runs").glob("*/*") if p.is_dir()], "a refused launch left its folder"
    assert not written.exists()
