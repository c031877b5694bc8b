"""The store and the job runner survive kills, races and outages; bad inputs fail early."""

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pandas as pd
import pytest
import torch

from mrcert.__main__ import run_task
from mrcert.errors import MrcertError
from mrcert.infra.store import FileLock, ensure_sqlite_store, uninterrupted
from mrcert.reporting.certify_log import read_log
from tests.conftest import (
    PER_RUN,
    ROOT,
    TINY_CLASSES,
    certify_args,
    certify_logs,
    compose_cfg,
    file_size_limit,
    kill_when,
    run_cli,
    start_cli,
    store_runs,
    wait_until,
    write_cloud,
)


def test_a_certificate_counts_the_camera_poses_it_projected(reference):
    """Motion smoothing renders each of its n0 + n samples once: the cost a table reports."""
    from mrcert.core.axes import unit

    for rows in reference.values():
        assert (rows.projected == 8 + 200).all()
        # Its radii and sigma are in the axis's unit, and the log says so.
        assert (rows.radius_unit == rows.axis.map(unit)).all() and (rows.sigma_unit == rows.radius_unit).all()


def started_for(seconds: float):
    t0 = time.time()
    return lambda: time.time() - t0 > seconds


@pytest.mark.parametrize(
    "phase", [pytest.param("before", marks=pytest.mark.slow), "during", pytest.param("after", marks=pytest.mark.slow)]
)
def test_a_kill_at_any_phase_of_a_first_run_is_finished_by_the_same_command(phase, checkpoints, reference, tmp_path):
    args = certify_args(checkpoints["a"])
    db = tmp_path / "mlflow.db"
    building = lambda: any(tmp_path.glob(".mlflow.db.tmp-*"))  # noqa: E731
    ready = {
        "before": started_for(1.0),  # the interpreter is still importing: no store yet
        "during": building,
        "after": lambda: any(len(p.read_text().splitlines()) >= 2 for p in certify_logs(tmp_path)),
    }[phase]
    kill_when(args, tmp_path, ready)
    if phase == "before":
        assert not db.exists()
    if phase == "during":
        assert building() and not db.exists()  # killed while the store was being built
    if phase == "after":
        assert db.exists()
    done = run_cli(args, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    (run,) = store_runs(tmp_path)
    assert run.info.status == "FINISHED"
    (log,) = certify_logs(tmp_path)  # one run folder: a resume adopts the new launch's folder
    pd.testing.assert_frame_equal(read_log(log).drop(columns=PER_RUN), reference["a"])


def test_a_half_made_store_is_explained_in_one_line(tmp_path):
    import sqlalchemy
    from mlflow.store.tracking.dbmodels.initial_models import Base

    db = tmp_path / "mlflow.db"
    engine = sqlalchemy.create_engine(f"sqlite:///{db}")
    Base.metadata.create_all(engine)  # the tables, but no schema stamp: what a kill mid-creation leaves
    engine.dispose()
    proc = run_cli(["task=render", "data=testscene", "data.density=0.05", "task.num=2", "task.axes=[tx]"], tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert f"the MLflow store {db} is incomplete" in line and f"mv {db} {db}.broken" in line


@pytest.mark.slow
def test_a_full_disk_while_creating_the_store_is_one_line(tmp_path):
    """No room for the store (here a 200 KB file size limit, which SQLite
    meets as a full disk would be met): one line naming the store and the fix, nothing half
    made left behind, and the same command works once there is room."""
    args = ["task=render", "data=testscene", "data.density=0.05", "task.num=2", "task.axes=[tx]"]
    full = run_cli(args, tmp_path, timeout=300, preexec_fn=file_size_limit(200))
    assert full.returncode == 2 and "Traceback" not in full.stderr, full.stderr[-2000:]
    db = tmp_path / "mlflow.db"
    line = full.stderr.strip().splitlines()[-1]
    assert line.startswith(f"mrcert: error: cannot create the MLflow store {db}") and "free some space" in line
    assert not db.exists() and not list(tmp_path.glob(".mlflow.db.tmp-*"))
    assert not list((tmp_path / "runs").glob("*/*"))  # the refused launch left no folder
    assert run_cli(args, tmp_path).returncode == 0


@pytest.mark.slow  # over 20 s: make test-full
def test_independent_jobs_started_together_on_a_new_store_all_finish(tmp_path):
    jobs = [
        start_cli(["task=render", "data=testscene", "data.density=0.05", "task.num=2", f"task.axes=[{axis}]"], tmp_path)
        for axis in ("tx", "ty", "rz", "rx")
    ]
    errors = [job.communicate(timeout=300)[1] for job in jobs]
    assert [job.returncode for job in jobs] == [0, 0, 0, 0], "\n".join(e[-1500:] for e in errors)
    runs = store_runs(tmp_path)
    assert len(runs) == 4 and all(r.info.status == "FINISHED" for r in runs)
    assert len({r.info.experiment_id for r in runs}) == 1


def test_resume_never_mixes_two_models_in_one_run(checkpoints, reference, tmp_path):
    first = certify_args(checkpoints["a"])
    kill_when(first, tmp_path, lambda: any(len(p.read_text().splitlines()) >= 2 for p in certify_logs(tmp_path)))
    (killed_log,) = certify_logs(tmp_path)
    rows_before = killed_log.read_text()
    run_task(compose_cfg(certify_args(checkpoints["b"]), tmp_path), tmp_path / "runs" / "certify" / "other")
    assert killed_log.read_text() == rows_before  # another model: a new run, not the killed one
    (finished,) = store_runs(tmp_path, "attributes.status = 'FINISHED'")
    pd.testing.assert_frame_equal(
        read_log(Path(finished.data.tags["mrcert.output_dir"]) / "certify.tsv").drop(columns=PER_RUN), reference["b"]
    )
    again = run_cli(first, tmp_path)  # the first model's command resumes its own run
    assert again.returncode == 0, again.stderr[-2000:]
    assert len(store_runs(tmp_path)) == 2
    pd.testing.assert_frame_equal(read_log(killed_log).drop(columns=PER_RUN), reference["a"])
    assert list(killed_log.parent.glob("resumed/*/*.log"))  # the resuming process's log is kept with the run


@pytest.mark.slow
def test_a_run_folder_reused_by_another_model_never_mixes_rows(checkpoints, reference, tmp_path):
    """Certify model a into a folder, kill it after a row, certify model b
    into the same folder, then rerun a's command: each run's log holds only its own rows."""
    folder = tmp_path / "same"
    log = folder / "certify.tsv"
    a = [*certify_args(checkpoints["a"]), f"hydra.run.dir={folder}"]
    b = [*certify_args(checkpoints["b"]), f"hydra.run.dir={folder}"]
    kill_when(a, tmp_path, lambda: log.exists() and len(log.read_text().splitlines()) >= 2)
    assert len(log.read_text().splitlines()) >= 2
    done_b = run_cli(b, tmp_path)
    assert done_b.returncode == 0, done_b.stderr[-2000:]
    pd.testing.assert_frame_equal(read_log(log).drop(columns=PER_RUN), reference["b"])  # none of a's rows
    (run_b,) = store_runs(tmp_path, "attributes.status = 'FINISHED'")
    again = run_cli(a, tmp_path)  # a's command resumes a's own run, with a's own rows
    assert again.returncode == 0, again.stderr[-2000:]
    pd.testing.assert_frame_equal(read_log(log).drop(columns=PER_RUN), reference["a"])
    runs = {r.info.run_id: r for r in store_runs(tmp_path)}
    assert len(runs) == 2 and all(r.info.status == "FINISHED" for r in runs.values())
    kept_b = mlflow.artifacts.download_artifacts(run_id=run_b.info.run_id, artifact_path="certify.tsv")
    pd.testing.assert_frame_equal(read_log(kept_b).drop(columns=PER_RUN), reference["b"])  # b's result intact
    (aside,) = folder.glob("set_aside/*/certify.tsv")  # and b's rows are still on disk
    pd.testing.assert_frame_equal(read_log(aside).drop(columns=PER_RUN), reference["b"])


@pytest.mark.slow
def test_identical_jobs_started_together_make_one_run(checkpoints, reference, tmp_path):
    """Four identical certify jobs, each in its own folder, started together:
    one run computes, the others stop at once naming it; no second run of the key exists."""
    ensure_sqlite_store(tmp_path / "mlflow.db")  # an existing store: the jobs race only for the run
    args = certify_args(checkpoints["a"], n=2000)
    jobs = [start_cli([*args, f"hydra.run.dir={tmp_path / f'job{k}'}"], tmp_path) for k in range(4)]
    errors = [job.communicate(timeout=600)[1] for job in jobs]
    codes = sorted(job.returncode for job in jobs)
    assert codes == [0, 2, 2, 2], "\n".join(e[-1500:] for e in errors)
    refused = [e.strip().splitlines()[-1] for e, job in zip(errors, jobs, strict=True) if job.returncode == 2]
    named = "mrcert: error: an identical job is computing this config now"
    assert all(line.startswith(named) for line in refused), refused
    (run,) = store_runs(tmp_path)
    assert run.info.status == "FINISHED"


def test_ctrl_c_is_one_line_and_the_run_is_killed(checkpoints, tmp_path):
    """Ctrl-C during certification prints one line (no traceback), exits 130,
    and leaves the run KILLED for the same command to resume."""
    proc = start_cli(certify_args(checkpoints["a"], n=2000), tmp_path, interruptible=True)
    wait_until(proc, lambda: any(len(p.read_text().splitlines()) >= 2 for p in certify_logs(tmp_path)))
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 130 and "Traceback" not in err, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert last == "mrcert: interrupted; the run is marked KILLED and the same command resumes it"
    (run,) = store_runs(tmp_path)
    assert run.info.status == "KILLED"


@pytest.fixture
def ctrl_c():
    """Ctrl-C raising KeyboardInterrupt in this process, as in a user's shell (a test worker may
    ignore SIGINT), for the test's length."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def test_a_signal_during_a_store_write_waits_for_the_write(ctrl_c):
    """Ctrl-C or SIGTERM arriving while a store write runs is delivered when the write ends,
    through the handler that was in place."""
    from mrcert.__main__ import Terminated, _terminate

    done = []
    with pytest.raises(KeyboardInterrupt):
        with uninterrupted():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            done.append("write")
    assert done == ["write"] and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    before = signal.signal(signal.SIGTERM, _terminate)
    try:
        with pytest.raises(Terminated), uninterrupted():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            done.append("write")
        assert done == ["write", "write"] and signal.getsignal(signal.SIGTERM) is _terminate
    finally:
        signal.signal(signal.SIGTERM, before)


def test_ctrl_c_in_the_middle_of_recording_a_row_keeps_the_row_and_the_time(checkpoints, tmp_path, monkeypatch, ctrl_c):
    """Ctrl-C landing inside the write of a row's seal: the seal is recorded whole, the run is
    closed KILLED with its working time, and the same command resumes it without computing
    that row again."""
    real = mlflow.set_tag

    def ctrl_c_mid_write(key, value):
        if key == "mrcert.sealed.certify.tsv":
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        real(key, value)

    cfg = compose_cfg(certify_args(checkpoints["a"], n=40), tmp_path)
    monkeypatch.setattr(mlflow, "set_tag", ctrl_c_mid_write)
    with pytest.raises(KeyboardInterrupt):
        run_task(cfg, tmp_path / "runs" / "certify")
    monkeypatch.undo()
    (run,) = store_runs(tmp_path)
    log = tmp_path / "runs" / "certify" / "certify.tsv"
    assert run.info.status == "KILLED" and len(read_log(log)) == 1
    assert int(run.data.tags["mrcert.sealed.certify.tsv"].split()[0]) == log.stat().st_size
    assert run.data.metrics["segments"] == run.data.metrics["timed_segments"] == 1
    run_task(compose_cfg(certify_args(checkpoints["a"], n=40), tmp_path), tmp_path / "runs" / "again")
    (run,) = store_runs(tmp_path)
    assert run.info.status == "FINISHED" and read_log(log)["idx"].tolist() == [0, 1, 2, 3]


def test_ctrl_c_landing_inside_a_compiled_kernel_is_still_an_interruption(checkpoints, tmp_path, monkeypatch):
    """An interrupt that arrives while a numba kernel runs reaches Python as a SystemError whose
    cause is the KeyboardInterrupt: the run is closed KILLED (not FAILED), the interrupt goes on
    as Ctrl-C, and the same command resumes the run."""
    import mrcert.data.samples as samples

    real, calls = samples.project, []

    def interrupted_in_a_kernel(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as stop:
                raise SystemError(
                    "CPUDispatcher(<function _block_bounds>) returned a result with an exception set"
                ) from stop
        return real(*args, **kwargs)

    monkeypatch.setattr(samples, "project", interrupted_in_a_kernel)
    with pytest.raises(KeyboardInterrupt):
        run_task(compose_cfg(certify_args(checkpoints["a"], n=40), tmp_path), tmp_path / "runs" / "certify")
    monkeypatch.undo()
    (run,) = store_runs(tmp_path)
    assert run.info.status == "KILLED" and "mrcert.failure" not in run.data.tags
    run_task(compose_cfg(certify_args(checkpoints["a"], n=40), tmp_path), tmp_path / "runs" / "again")
    (run,) = store_runs(tmp_path)
    log = read_log(tmp_path / "runs" / "certify" / "certify.tsv")
    assert run.info.status == "FINISHED" and log["idx"].tolist() == [0, 1, 2, 3]


def test_a_store_locked_by_a_stopped_process_is_one_line(tmp_path):
    """Another process holding the SQLite store's write lock (suspended mid-write): one line
    naming the store and what to do, no traceback, no run."""
    import sqlite3

    ensure_sqlite_store(tmp_path / "mlflow.db")
    holder = sqlite3.connect(tmp_path / "mlflow.db")
    holder.execute("BEGIN EXCLUSIVE")
    try:
        proc = run_cli(["task=render", "data=testscene"], tmp_path)
    finally:
        holder.rollback()
        holder.close()
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith(f"mrcert: error: the MLflow store sqlite:///{tmp_path}/mlflow.db stayed locked"), line
    assert not store_runs(tmp_path)


@pytest.mark.slow
def test_a_resumed_run_counts_its_working_time_not_the_time_it_was_down(checkpoints, tmp_path):
    """The time table's run time is what the run's processes worked: a run interrupted by
    Ctrl-C and resumed after a pause of ``down`` seconds reports at most its start-to-end
    time less the pause; one of whose processes was killed outright (no time logged) falls
    back to start-to-end."""
    from mrcert.reporting.page.times import run_seconds

    args, down = certify_args(checkpoints["a"], n=2000), 5.0
    proc = start_cli(args, tmp_path, interruptible=True)
    wait_until(proc, lambda: any(len(p.read_text().splitlines()) >= 2 for p in certify_logs(tmp_path)))
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=120)
    time.sleep(down)
    done = run_cli(args, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    (run,) = [r for _, r in mlflow.search_runs(search_all_experiments=True).iterrows()]
    assert run["status"] == "FINISHED" and run["metrics.segments"] == run["metrics.timed_segments"] == 2
    span = (run["end_time"] - run["start_time"]).total_seconds()
    assert 0 < run_seconds(run) == run["metrics.active_seconds"] <= span - down
    killed = run.copy()
    killed["metrics.segments"] = 3  # a third process started and was killed before it could log
    assert run_seconds(killed) == span


def test_a_run_resumed_from_before_the_time_count_is_not_reported_as_fully_timed():
    """A run whose earlier processes logged no time (begun by code without the count) is resumed:
    its resuming process must not pass its own time off as the whole run's."""
    from types import SimpleNamespace

    from mrcert.infra.resumption import timed_segment

    logged: dict[str, float] = {}
    fake = SimpleNamespace(log_metric=lambda k, v: logged.update({k: v}), log_metrics=logged.update)
    for previous, segments in [(None, 1), (SimpleNamespace(data=SimpleNamespace(metrics={"loss": 0.1})), 2)]:
        with timed_segment(fake, previous):
            pass
        assert (logged["segments"], logged["timed_segments"]) == (segments, 1)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("sweep", [[], ["-m", "motion=tx,rz"]], ids=["run", "multirun"])
def test_an_unreachable_tracking_server_fails_in_seconds(sweep, tmp_path):
    uri = f"http://127.0.0.1:{free_port()}"
    t0 = time.time()
    proc = run_cli([*sweep, "task=render", "data=testscene", "tracking=server", f"tracking.uri={uri}"], tmp_path)
    assert time.time() - t0 < 30
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert f"mrcert: error: cannot reach the MLflow tracking server at {uri}" in proc.stderr


def test_bad_input_files_fail_before_any_run_exists(checkpoints, tmp_path):
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(os.urandom(2000))
    cloud, poses, log, scan = tmp_path / "bad.ply", tmp_path / "bad.json", tmp_path / "bad.tsv", tmp_path / "scan.ply"
    cloud.write_text("ply\nformat nonsense\n")
    poses.write_text("{not json")
    log.write_text("a\tb\n1\t2\n")
    write_cloud(scan)
    cases = [
        (certify_args(tmp_path / "missing.pt"), "model.checkpoint=.*missing.pt' does not exist"),
        (certify_args(garbage), "is not a mrcert checkpoint"),
        (["task=render", "data=pointcloud", f"data.path={cloud}"], "has no points"),
        (["task=train", "data=custom", f"data.path={tmp_path / 'none.ply'}", f"data.poses={poses}"], "does not exist"),
        (["task=train", "data=custom", f"data.path={scan}", f"data.poses={poses}"], "is not valid UTF-8 JSON"),
        (["task=import", f"task.path={log}"], "lacks the columns"),
        (["task=train", "data.classes=[apple,nonexistent]"], r"data.classes has unknown classes \['nonexistent'\]"),
        (["task=certify", "data.classes=[nonexistent]"], r"data.classes has unknown classes \['nonexistent'\]"),
    ]
    for args, message in cases:
        with pytest.raises(MrcertError, match=message) as info:
            run_task(compose_cfg(args, tmp_path), tmp_path / "runs" / "x")
        assert "weights_only" not in str(info.value)
    assert not (tmp_path / "mlflow.db").exists() or store_runs(tmp_path) == []  # no run, not even a FAILED one
    t0 = time.time()
    proc = run_cli(certify_args(garbage), tmp_path)  # and on the command line: one line, in seconds
    assert time.time() - t0 < 30 and proc.returncode == 2 and "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("mrcert: error: ") and "is not a mrcert checkpoint" in last
    assert not list((tmp_path / "runs" / "certify").glob("*")), "a refused launch left its folder behind"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["motion=tz", "motion.sigma=1e9"], "sigma=1000000000.0 .* at most 9.26 m, the extent of the metaroom_synth"),
        (["motion=rz", "motion.radius=4"], "motion.radius=4.0 .* a rotation angle in radians, at most pi"),
        (["motion=tz", "motion.radius_step=1e-9"], "motion.radius_step=1e-09 .* would have more than 100000 radii"),
    ],
    ids=["translation beyond the scene", "rotation beyond pi", "curve too fine"],
)
def test_a_motion_the_scene_cannot_represent_is_refused_at_once(args, message, tmp_path):
    """A motion the scene cannot represent (motion.sigma=1e9 would ask for a radius grid of
    1.2 TiB) stops at once with one line, before any run exists."""
    t0 = time.time()
    proc = run_cli(["task=certify", *args], tmp_path)
    assert time.time() - t0 < 30 and proc.returncode == 2 and "Traceback" not in proc.stderr
    assert re.search(message, proc.stderr.strip().splitlines()[-1]), proc.stderr[-1000:]
    assert not (tmp_path / "mlflow.db").exists() or store_runs(tmp_path) == []


def test_a_checkpoint_of_another_model_config_is_named(checkpoints, tmp_path):
    cfg = compose_cfg([*certify_args(checkpoints["a"]), "model.net.width=16"], tmp_path)
    from mrcert.infra.checkpoints import load_classifier

    with pytest.raises(MrcertError, match=r"trained with another model: model.net.width=8 \(checkpoint\) vs 16"):
        load_classifier(cfg, TINY_CLASSES, torch.device("cpu"))


def test_a_file_lock_is_exclusive_and_dies_with_its_process(tmp_path):
    path = tmp_path / "x.lock"
    code = f"from mrcert.infra.store import FileLock; import time; lock = FileLock('{path}'); lock.acquire(); "
    code += "print('held', flush=True); time.sleep(60)"
    holder = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    lock = FileLock(path)
    assert not lock.acquire(blocking=False) and f"pid {holder.pid}" in lock.holder()
    holder.kill()
    holder.wait()
    assert lock.acquire(blocking=False)
    lock.release()
