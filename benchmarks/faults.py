"""Fault injection: random SIGKILLs across training and certification, then the same command.

Each trial starts from an empty outputs folder (so kills also land before and during the
store's creation), runs one tiny job (train with ``task.resume=true``, or certify; both with
``skip_finished=true``, as in a reproduction), SIGKILLs it 1-3 times at random moments (a
kill counts only when the process was still running), then runs the same command to the end. It then checks the
result against an uninterrupted reference computed first: the certify rows (all but the two
timing columns) or the final weights must be identical, no test image may appear twice, and
the store must hold exactly one run. Prints the totals, e.g.
``20 kills, 0 results lost, 0 duplicate rows, 0 extra runs``.

Two more scenarios follow, each against its own reference:

* **a reused run folder**: certify model a into one ``hydra.run.dir``, SIGKILL it at a random
  moment, certify model b (another checkpoint) into the same folder to the end, then run a's
  command again to the end. a's log must equal a's reference and b's logged result b's: rows
  of the other model in either are counted as *mixed*.
* **identical jobs at once**: ``--jobs`` identical certify jobs, each with its own folder,
  started together on an existing store: exactly one run may exist afterwards (others are
  counted as *duplicate runs*), and its rows must equal the reference.
* **a full disk while the store is created**: the certify job on a new outputs folder under a
  file size limit of 64 KiB, 256 KiB and 1 MiB (as a full disk is met): it must end with one
  line, no traceback; the same command with room must then give the reference's rows and one
  run.

Then damage and bad input, each counted when it gets through: a killed certification whose
log gains a short row and a row with its radius edited (forged certificates: rows that differ
from the reference), point clouds cut short (binary and ASCII PLY), a checkpoint with a NaN
weight and a training that diverges (non-finite models certified), model targets that are not
modules or that write a file (arbitrary calls), and refused values (a GPU the machine lacks, a
seed out of range, a class twice) that leave a run RUNNING or FAILED.

Usage: python benchmarks/faults.py [--kills 20] [--jobs 8] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from tests.conftest import TINY, file_size_limit  # noqa: E402 - the tests' tiny data and model, the full-disk limit: shared

TRAIN = [*TINY, "task=train", "train.epochs=6", "train.batch_size=8", "task.resume=true", "skip_finished=true"]


def certify(checkpoint: Path) -> list[str]:
    return [
        *TINY,
        "task=certify",
        "task.n0=8",
        "task.n=300",
        "task.max=6",
        "task.skip=1",
        "skip_finished=true",
        f"model.checkpoint={checkpoint}",
    ]


def mrcert(args: list[str], outputs: Path, env: dict, preexec_fn=None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mrcert", *args],
        cwd=ROOT,
        env=env | {"MRCERT_OUTPUTS": str(outputs)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=preexec_fn,
    )


def finish(args: list[str], outputs: Path, env: dict) -> float:
    t0 = time.time()
    proc = mrcert(args, outputs, env)
    _, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"mrcert {' '.join(args)} failed:\n{err[-3000:]}")
    return time.time() - t0


def outcome(kind: str, outputs: Path):
    """(result, duplicate rows, runs in the store) of a finished trial."""
    import mlflow
    import torch

    mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
    runs = mlflow.search_runs(search_all_experiments=True, output_format="list")
    finished = [r for r in runs if r.info.status == "FINISHED"]
    if len(finished) != 1:
        return None, 0, runs
    folder = Path(finished[0].data.tags["mrcert.output_dir"])
    if kind == "train":
        return torch.load(folder / "last.pt", weights_only=True)["model"], 0, runs
    rows = certify_rows(folder)
    return rows, int(rows["idx"].duplicated().sum()), runs


def same(kind: str, a, b) -> bool:
    import torch

    if a is None:
        return False
    if kind == "train":
        return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    return a.equals(b)


def certify_rows(folder: Path):
    """A certify log without its timing and check columns (which differ between identical runs)."""
    from mrcert.reporting.certify_log import read_log

    return read_log(folder / "certify.tsv").drop(columns=["time", "seconds", "check"], errors="ignore")


def reused(work: Path, a: Path, b: Path, reference_a, rng: random.Random, duration: float, env: dict) -> int:
    """Rows of the wrong model in a's and b's results after b reuses a's run folder."""
    import mlflow

    outputs, folder = work / "reused", work / "reused" / "same-folder"
    job_a, job_b = (certify(c) + [f"hydra.run.dir={folder}"] for c in (a, b))
    finish(certify(b), work / "reference-b", env)
    reference_b = outcome("certify", work / "reference-b")[0]
    proc = mrcert(job_a, outputs, env)
    time.sleep(kill_time(rng, duration))
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finish(job_b, outputs, env)
    mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
    (run_b,) = mlflow.search_runs(
        search_all_experiments=True, filter_string="attributes.status = 'FINISHED'", output_format="list"
    )
    finish(job_a, outputs, env)
    logged_b = Path(mlflow.artifacts.download_artifacts(run_id=run_b.info.run_id, artifact_path="certify.tsv"))
    got_a, got_b = certify_rows(folder), certify_rows(logged_b.parent)
    return _foreign(got_a, reference_a) + _foreign(got_b, reference_b)


def _foreign(rows, reference) -> int:
    """Rows that are not the reference's row of the same image (or images the reference lacks)."""
    merged = rows.merge(reference, on="idx", how="left", suffixes=("", "_ref"), indicator=True)
    cols = [c for c in rows.columns if c != "idx"]
    differs = merged["_merge"] != "both"
    for c in cols:
        differs |= merged[c].astype(str) != merged[f"{c}_ref"].astype(str)
    return int(differs.sum()) + max(0, len(reference) - len(rows))


def simultaneous(work: Path, job: list[str], n: int, reference, env: dict) -> tuple[int, int]:
    """(duplicate runs, 1 if the one run's rows differ from the reference) of ``n`` identical
    jobs started together on an existing store."""
    from mrcert.infra.store import ensure_sqlite_store

    outputs = work / "simultaneous"
    outputs.mkdir()
    ensure_sqlite_store(outputs / "mlflow.db")
    procs = [mrcert([*job, f"hydra.run.dir={outputs / f'job{k}'}"], outputs, env) for k in range(n)]
    for p in procs:
        p.communicate()
    codes = [p.returncode for p in procs]
    result, _, runs = outcome("certify", outputs)
    print(f"{n} identical jobs: exit codes {sorted(codes)}, runs: {[r.info.status for r in runs]}", flush=True)
    return len(runs) - 1, int(not same("certify", result, reference))


def disk_full(work: Path, job: list[str], reference, env: dict, limits_kib=(64, 256, 1024)) -> tuple[int, int, int]:
    """(results lost, extra runs, tracebacks) when the disk fills while a new store is created:
    each job runs under a file size limit (as a full disk is met), then again with room."""
    lost = extra = tracebacks = 0
    for kib in limits_kib:
        outputs = work / f"disk-full-{kib}k"
        proc = mrcert(job, outputs, env, preexec_fn=file_size_limit(kib))
        stderr = proc.communicate()[1]
        tracebacks += "Traceback" in stderr
        finish(job, outputs, env)
        result, _, runs = outcome("certify", outputs)
        lost += not same("certify", result, reference)
        extra += len(runs) - 1
        print(f"disk full at {kib} KiB: exit {proc.returncode}, {stderr.strip().splitlines()[-1:]}", flush=True)
    return lost, extra, tracebacks


def hostile(work: Path, checkpoint: Path, reference, env: dict) -> dict[str, int]:
    """Damage and bad input as a hostile but realistic user would bring them; counts of what
    got through: rows forged into a certificate, partial clouds accepted, non-finite models
    certified, functions a config called, and runs left RUNNING or FAILED by a refusal."""
    import numpy as np
    import open3d as o3d
    import torch

    counts = dict.fromkeys(("forged", "partial", "non_finite", "calls", "left"), 0)
    # A killed certification whose log gains a short row and a row with its radius edited.
    outputs, job = work / "forged", certify(checkpoint)
    proc = mrcert(job, outputs, env)
    logs = lambda: list(outputs.glob("runs/certify/*/certify.tsv"))  # noqa: E731
    while proc.poll() is None and not any(len(p.read_text().splitlines()) >= 2 for p in logs()):
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    (log,) = logs()
    first = log.read_text().splitlines()[1].split("\t")
    edited = "\t".join([first[0], first[1], first[2], "5.0", *first[4:]])
    with open(log, "a") as f:
        f.write(f"1\t1\t1\t5.0\n{edited}\n")
    finish(job, outputs, env)
    counts["forged"] = _foreign(certify_rows(log.parent), reference)
    # Inputs and values that must be refused before any run: (outputs, args, what got through).
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).uniform(-1, 1, (100, 3))))
    state = torch.load(checkpoint, weights_only=True)
    state["model"][next(k for k, v in state["model"].items() if v.is_floating_point())].view(-1)[0] = float("nan")
    torch.save(state, work / "nan.pt")
    written = work / "written.txt"
    cases = []
    for ascii_ in (False, True):
        path = work / f"cut-{ascii_}.ply"
        o3d.io.write_point_cloud(str(path), pcd, write_ascii=ascii_)
        path.write_bytes(path.read_bytes()[: -(path.stat().st_size // 3)])
        cases.append(("partial", ["task=render", "data=pointcloud", f"data.path={path}"]))
    cases += [
        ("non_finite", certify(work / "nan.pt")),
        ("calls", [*TINY, "task=train", "model.net._target_=builtins.print"]),
        ("calls", [*TINY, "task=train", f"+model.net.width={{_target_:builtins.open,file:{written},mode:w}}"]),
        ("left", [*TINY, "task=train", "device=cuda:7"]),
        ("left", [*TINY, "task=train", f"seed={2**64}"]),
        ("left", [*TINY, "task=train", "data.classes=[mug,mug,can]"]),
    ]
    for k, (what, args) in enumerate(cases):
        outputs = work / f"refused-{k}"
        proc = mrcert(args, outputs, env)
        proc.communicate()
        counts[what] += proc.returncode == 0 or written.exists()
        counts["left"] += sum(r.info.status in ("RUNNING", "FAILED") for r in outcome("certify", outputs)[2])
        written.unlink(missing_ok=True)
    # A model that diverges in training: its run FAILED with the reason, nothing certified with it.
    outputs = work / "diverged"
    proc = mrcert([*TRAIN, "train.lr=1e12", "train.epochs=2"], outputs, env)
    proc.communicate()
    for best in outputs.glob("runs/train/*/best.pt"):
        certified = mrcert(certify(best), outputs, env)
        certified.communicate()
        counts["non_finite"] += certified.returncode == 0
    return counts


SEALED = [*TINY, "train.epochs=1", "train.batch_size=8"]
SEALED_CERTIFY = [*SEALED, "task=certify", "task.n0=8", "task.n=40", "task.max=3", "task.skip=1"]


def sealed(work: Path, env: dict, rng: random.Random) -> dict[str, int]:
    """What a table shows against what its runs recorded; counts of what got through: forged
    cells (a cell showing a log edited after its run, in its store or gathered into another),
    substituted models (an evaluation that ran on a checkpoint swapped under its train run),
    poisoned trainings (a model trained on a damaged image cache, or a damaged cache that stops
    training), misleading poses accepted (a test pose twice, one pose with two labels, a test
    pose that is a training pose), torn tables (a table file left other than a complete run
    writes it, by a kill during ``task=tables``) and runs left RUNNING."""
    import mlflow
    import numpy as np
    import open3d as o3d
    import pandas as pd
    import torch

    from mrcert.reporting.cells import RunIndex
    from mrcert.tasks.evaluation import run_images

    counts = dict.fromkeys(("forged", "substituted", "poisoned", "poses", "torn", "running"), 0)

    def certified(outputs: Path) -> float:
        mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
        index = RunIndex.load("mrcert", run_images)
        return index.metric(index.cell([*SEALED_CERTIFY, f"paths.outputs={outputs}"]), "certified_accuracy")

    def forge(log: Path) -> None:
        df = pd.read_csv(log, sep="\t", dtype=str)
        df["predict"], df["correct"], df["radius"] = df["label"], "1", "0.05"
        df.to_csv(log, sep="\t", index=False)

    def seeded(outputs: Path, seed: str) -> Path:
        mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
        (run,) = mlflow.search_runs(
            search_all_experiments=True, filter_string=f"params.seed = '{seed}'", output_format="list"
        )
        return Path(run.data.tags["mrcert.output_dir"])

    store = work / "sealed"
    finish([*SEALED, "task=train"], store, env)
    finish(SEALED_CERTIFY, store, env)
    honest = certified(store)
    for log in [*store.glob("runs/certify/*/certify.tsv"), *(store / "mlartifacts").rglob("certify.tsv")]:
        forge(log)
    counts["forged"] += not np.isnan(certified(store)) and certified(store) != honest
    other = work / "gathered"
    finish(["task=gather", f"task.store={store}"], other, env)
    counts["forged"] += not np.isnan(certified(other))
    (best,) = (store / "mlartifacts").rglob("checkpoints/best.pt")
    state = torch.load(best, weights_only=True)
    state["model"] = {k: v + 1 if v.is_floating_point() else v for k, v in state["model"].items()}
    torch.save(state, best)
    proc = mrcert([*SEALED_CERTIFY, "task.n=41"], store, env)
    proc.communicate()
    counts["substituted"] += proc.returncode == 0
    # The image cache: labels flipped, then images cut short; each training must match a clean store's.
    clean, cache = work / "clean", work / "cache"
    finish([*SEALED, "task=train", "seed=1"], clean, env)
    finish([*SEALED, "task=train"], cache, env)
    (labels,) = cache.glob("data/*-train-*/labels.npy")
    np.save(labels, np.load(labels)[::-1].copy())
    finish([*SEALED, "task=train", "seed=1"], cache, env)
    a, b = (torch.load(seeded(o, "1") / "last.pt", weights_only=True)["model"] for o in (clean, cache))
    counts["poisoned"] += not all(torch.equal(a[k], b[k]) for k in a)
    (images,) = cache.glob("data/*-train-*/images.npy")
    images.write_bytes(images.read_bytes()[:1000])
    proc = mrcert([*SEALED, "task=train", "seed=2"], cache, env)
    proc.communicate()
    counts["poisoned"] += proc.returncode != 0
    # Custom poses that mislead: a test pose twice, one pose with two labels, a test pose trained on.
    cloud = work / "scene.ply"
    points = np.random.default_rng(0).uniform(-1, 1, (500, 3)) + [0, 0, 3]
    o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    here, there = np.eye(4).tolist(), (np.eye(4) + np.eye(4, k=3) * 0.1).tolist()
    for k, first in enumerate((("test", "mug"), ("train", "can"), ("train", "mug"))):
        poses = [{"split": first[0], "label": first[1], "pose": here}, {"split": "test", "label": "mug", "pose": here}]
        poses.append({"split": "train", "label": "can", "pose": there})
        path = work / f"poses-{k}.json"
        path.write_text(json.dumps({"classes": ["mug", "can"], "poses": poses}))
        proc = mrcert(["task=render", "data=custom", f"data.path={cloud}", f"data.poses={path}"], work / "poses", env)
        proc.communicate()
        counts["poses"] += proc.returncode == 0
    # A kill during task=tables: every table file as a complete run writes it, or as it was.
    tables = ["task=tables", "task.experiment=demo"]
    finish(tables, store, env)
    written = {p.name: p.read_bytes() for p in (store / "tables").iterdir() if p.suffix in (".md", ".csv", ".tex")}
    for _ in range(3):
        proc = mrcert(tables, store, env)
        time.sleep(rng.uniform(1.0, 8.0))
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
        now = {p.name: p.read_bytes() for p in (store / "tables").iterdir() if p.suffix in (".md", ".csv", ".tex")}
        counts["torn"] += sum(now.get(name) != data for name, data in written.items())
    finish(tables, store, env)
    for outputs in (store, other, clean, cache):
        mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
        runs = mlflow.search_runs(search_all_experiments=True, output_format="list")
        counts["running"] += sum(r.info.status == "RUNNING" for r in runs)
    return counts


def report_sealed(counts: dict[str, int]) -> None:
    print(
        f"{counts['forged']} forged cells, {counts['substituted']} substituted models, "
        f"{counts['poisoned']} trainings on a damaged cache, {counts['poses']} misleading custom poses accepted, "
        f"{counts['torn']} table files torn by a kill, {counts['running']} runs left RUNNING"
    )


def kill_time(rng: random.Random, duration: float) -> float:
    """A moment to kill a job whose uninterrupted run takes ``duration`` s: within its first
    70%, so that a resumed job, which has less left to do, is mostly still running."""
    return rng.uniform(0.2, 0.7) * duration


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--jobs", type=int, default=8, help="identical jobs started together")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--keep", action="store_true", help="keep the work folder (printed) for inspection")
    ap.add_argument("--sealed-only", action="store_true", help="only the trials of what tables show (sealed runs)")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    env = os.environ | {"OMP_NUM_THREADS": str(args.threads), "NUMBA_NUM_THREADS": str(args.threads)}
    work = Path(tempfile.mkdtemp(prefix="mrcert-faults-"))
    try:
        if args.sealed_only:
            report_sealed(sealed(work, env, rng))
            return
        finish([*TRAIN, "train.epochs=1"], work / "model", env)
        (checkpoint,) = (work / "model").glob("runs/train/*/best.pt")
        jobs = {"train": TRAIN, "certify": certify(checkpoint)}
        reference, duration = {}, {}
        for kind, job in jobs.items():
            duration[kind] = finish(job, work / f"reference-{kind}", env)
            reference[kind] = outcome(kind, work / f"reference-{kind}")[0]
        kills = lost = duplicates = extra = trials = 0
        while kills < args.kills:
            kind = ("train", "certify")[trials % 2]
            outputs = work / f"trial-{trials}"
            for _ in range(min(rng.randint(1, 3), args.kills - kills)):
                proc = mrcert(jobs[kind], outputs, env)
                time.sleep(kill_time(rng, duration[kind]))
                if proc.poll() is None:  # still running: a real kill
                    proc.send_signal(signal.SIGKILL)
                    kills += 1
                proc.wait()
            finish(jobs[kind], outputs, env)
            result, dup, runs = outcome(kind, outputs)
            ok = same(kind, result, reference[kind])
            lost += not ok
            duplicates += dup
            extra += len(runs) - 1
            trials += 1
            states = ", ".join(f"{r.info.run_id[:8]} {r.info.status}" for r in runs)
            print(f"trial {trials} ({kind}, {outputs}): {kills} kills; runs: {states}; same: {ok}", flush=True)
        print(f"{kills} kills, {lost} results lost, {duplicates} duplicate rows, {extra} extra runs ({trials} trials)")
        finish([*TRAIN, "train.epochs=2"], work / "model-b", env)
        (other,) = (work / "model-b").glob("runs/train/*/last.pt")
        mixed = reused(work, checkpoint, other, reference["certify"], rng, duration["certify"], env)
        dup_runs, wrong = simultaneous(work, certify(checkpoint), args.jobs, reference["certify"], env)
        print(f"reused run folder: {mixed} mixed rows; {args.jobs} identical jobs at once: {dup_runs} duplicate runs")
        full_lost, full_extra, tracebacks = disk_full(work, certify(checkpoint), reference["certify"], env)
        print(f"disk full while creating the store: {tracebacks} tracebacks, {full_lost} results lost afterwards")
        lost, extra = lost + wrong + full_lost, extra + dup_runs + full_extra
        print(f"{lost} results lost, {mixed} mixed rows, {extra} duplicate or extra runs in all")
        bad = hostile(work, checkpoint, reference["certify"], env)
        print(
            f"{bad['forged']} forged certificates, {bad['partial']} partial clouds accepted, "
            f"{bad['non_finite']} non-finite models certified, {bad['calls']} arbitrary calls, "
            f"{bad['left']} runs left RUNNING or FAILED by a refusal"
        )
        report_sealed(sealed(work, env, rng))
    finally:
        if args.keep:
            print(f"work folder kept: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
