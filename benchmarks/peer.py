"""mrcert beside alpha-beta-CROWN on the same VNN-COMP instances, on the same machine, interleaved.

For each instance of an ``instances.csv`` (rows ``onnx,vnnlib,timeout`` relative to its folder,
files plain or gzipped), one process of each tool, one after the other, each given the instance's
time limit: mrcert through its competition harness (``vnncomp/run_instance.sh``, which runs
``mrcert task=verify ... tracking=off``), alpha-beta-CROWN as its own harness runs it
(``abcrown.py --config CONFIG --onnx_path ... --vnnlib_path ... --timeout T``, from the
``complete_verifier`` folder of a checkout the user gives). Printed per instance and in total:
each tool's answer, its whole-process seconds, its own reported seconds (mrcert: ``verify.tsv``'s
``seconds``, reading and checking included; alpha-beta-CROWN: its ``Time:`` line) and its peak
memory (the process's maximum resident set, from ``wait4``), and the ratios of their medians
and totals. Answers that disagree (one ``sat``, the other ``unsat``) are printed as such.

Usage:
  python benchmarks/peer.py --instances vnncomp2023_benchmarks/benchmarks/metaroom/instances.csv \
      --filter 4cnn --abcrown PATH/alpha-beta-CROWN/complete_verifier --python PATH/venv/bin/python \
      [--config exp_configs/vnncomp23/metaroom.yaml] [--threads 2] [--limit N] [--tsv OUT.tsv]
Without ``--abcrown`` (or when its folder has no ``abcrown.py``) the peer is skipped with one line
and only mrcert is measured.
"""

from __future__ import annotations

import argparse
import csv
import gzip
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def plain(path: Path, folder: Path) -> Path:
    """``path`` as a plain file (``path.gz`` unzipped into ``folder`` where only that exists):
    alpha-beta-CROWN reads plain files, and both tools are given the same ones."""
    if path.is_file() and path.suffix != ".gz":
        return path
    zipped = path if path.suffix == ".gz" else path.with_name(path.name + ".gz")
    out = folder / zipped.with_suffix("").name
    if not out.exists():
        out.write_bytes(gzip.decompress(zipped.read_bytes()))
    return out


def timed(cmd: list[str], cwd: Path, env: dict, limit: float) -> tuple[float, float, str]:
    """Whole-process seconds, peak resident memory (GB) and output of ``cmd``; killed at ``limit``."""
    start = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out:
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = start + limit
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() > deadline:
                os.killpg(proc.pid, 9)
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.02)
        seconds = time.perf_counter() - start
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        return seconds, usage.ru_maxrss / 2**20, out.read()


def first_line(path: Path) -> str:
    try:
        return (path.read_text().split("\n", 1)[0].strip()) or "none"
    except OSError:
        return "none"


def run_mrcert(onnx: Path, vnnlib: Path, timeout: float, work: Path, env: dict) -> dict:
    store = work / "mrcert_store"
    shutil.rmtree(store, ignore_errors=True)
    result = work / "mrcert.txt"
    cmd = ["bash", str(ROOT / "vnncomp" / "run_instance.sh"), "v1", "bench", str(onnx), str(vnnlib), str(result),
           f"{timeout:g}"]  # fmt: skip
    seconds, memory, _ = timed(cmd, ROOT, env | {"MRCERT_OUTPUTS": str(store)}, timeout + 60)
    own = float("nan")
    for log in store.glob("runs/verify/*/verify.tsv"):
        rows = list(csv.DictReader(log.open(), delimiter="\t"))
        own = float(rows[-1]["seconds"]) if rows else own
    return {"answer": first_line(result), "seconds": seconds, "own": own, "memory": memory}


def run_abcrown(onnx: Path, vnnlib: Path, timeout: float, work: Path, args, env: dict) -> dict:
    result = work / "abcrown.txt"
    result.unlink(missing_ok=True)
    cmd = [args.python, "abcrown.py", "--config", args.config, "--onnx_path", str(onnx), "--vnnlib_path", str(vnnlib),
           "--results_file", str(result), "--timeout", f"{timeout:g}", "--device", "cpu", "--root_path", "",
           "--csv_name", ""]  # fmt: skip
    seconds, memory, out = timed(cmd, Path(args.abcrown), env, timeout + 60)
    own = re.findall(r"^Time: ([0-9.]+)", out, re.M)
    return {"answer": first_line(result), "seconds": seconds, "own": float(own[-1]) if own else float("nan"),
            "memory": memory}  # fmt: skip


def summary(name: str, rows: list[dict]) -> dict:
    answers = {a: sum(r["answer"] == a for r in rows) for a in sorted({r["answer"] for r in rows})}
    own = [r["own"] for r in rows if r["own"] == r["own"]]
    return {
        "name": name,
        "answers": ", ".join(f"{n} {a}" for a, n in answers.items()),
        "median": statistics.median(r["seconds"] for r in rows),
        "total": sum(r["seconds"] for r in rows),
        "own median": statistics.median(own) if own else float("nan"),
        "own total": sum(own),
        "memory": max(r["memory"] for r in rows),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--instances", required=True, type=Path)
    ap.add_argument("--filter", default="", help="only instances whose network's name contains this")
    ap.add_argument("--abcrown", default="", help="alpha-beta-CROWN's complete_verifier folder")
    ap.add_argument("--python", default=sys.executable, help="the Python alpha-beta-CROWN is installed for")
    ap.add_argument("--config", default="exp_configs/vnncomp23/metaroom.yaml", help="relative to --abcrown")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--limit", type=int, default=0, help="the first N instances only")
    ap.add_argument("--tsv", type=Path, help="write the per-instance rows here")
    ap.add_argument("--page", type=Path, help="write the figures as a Markdown page here (docs/peer.md)")
    ap.add_argument("--peer", default="", help="what the peer checkout is (release, versions), for the page")
    args = ap.parse_args()
    peer = bool(args.abcrown) and (Path(args.abcrown) / "abcrown.py").is_file()
    if "/" in args.python:  # alpha-beta-CROWN runs in its own folder
        args.python = str(Path(args.python).absolute())
    if not peer:
        print(f"alpha-beta-CROWN skipped: no abcrown.py in --abcrown={args.abcrown!r}; measuring mrcert alone")
    env = os.environ | {"OMP_NUM_THREADS": str(args.threads), "MKL_NUM_THREADS": str(args.threads)}
    with open(args.instances, newline="") as f:
        listed = [r for r in csv.reader(f) if r and "".join(r).strip()]
    chosen = [r for r in listed if args.filter in Path(r[0]).name][: args.limit or None]
    folder = args.instances.absolute().parent  # each tool runs in its own folder
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for k, row in enumerate(chosen):
            onnx, vnnlib = plain(folder / row[0].strip(), work), plain(folder / row[1].strip(), work)
            timeout = float(row[2]) if len(row) > 2 and row[2].strip() else 300.0
            tools = {"mrcert": lambda o=onnx, v=vnnlib, t=timeout: run_mrcert(o, v, t, work, env)}
            if peer:
                tools["alpha-beta-CROWN"] = lambda o=onnx, v=vnnlib, t=timeout: run_abcrown(o, v, t, work, args, env)
            order = list(tools) if k % 2 == 0 else list(tools)[::-1]  # interleaved: each goes first in turn
            got = {name: tools[name]() for name in order}
            line = {"idx": k, "onnx": onnx.name, "vnnlib": vnnlib.name, "timeout": timeout}
            for name, r in got.items():
                line |= {f"{name} {key}": value for key, value in r.items()}
            rows.append(line)
            print(f"{k:3d} {vnnlib.name:38s} " + "  ".join(
                f"{name}: {r['answer']:7s} {r['seconds']:6.1f} s (own {r['own']:6.2f}) {r['memory']:.2f} GB"
                for name, r in got.items()), flush=True)  # fmt: skip
            answers = {r["answer"] for r in got.values()}
            if {"sat", "unsat"} <= answers:
                print(f"    DISAGREE on {vnnlib.name}: {got}", flush=True)
    if args.tsv:
        with open(args.tsv, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]), delimiter="\t")
            w.writeheader()
            w.writerows(rows)
    names = ["mrcert", "alpha-beta-CROWN"] if peer else ["mrcert"]
    stats = [summary(n, [{k.split(" ", 1)[1]: v for k, v in r.items() if k.startswith(n + " ")} for r in rows])
             for n in names]  # fmt: skip
    table = ["| | " + " | ".join(s["name"] for s in stats) + (" | ratio |" if peer else " |"),
             "|---" * (len(stats) + 1 + peer) + "|",
             "| answered | " + " | ".join(s["answers"] for s in stats) + (" | |" if peer else " |")]  # fmt: skip
    for key, label, unit in (("median", "whole process, median", "s"), ("total", "whole process, total", "s"),
                             ("own median", "own reported, median", "s"), ("own total", "own reported, total", "s"),
                             ("memory", "peak memory", "GB")):  # fmt: skip
        cells = [f"{s[key]:.2f} {unit}" for s in stats]
        ratio = [f"{stats[0][key] / stats[1][key]:.2f}"] if peer and stats[1][key] else ([""] if peer else [])
        table.append(f"| {label} | " + " | ".join(cells + ratio) + " |")
    print(f"\n{len(rows)} instances, {args.threads} threads each, one process at a time")
    print("\n".join(table))
    if args.page:
        args.page.write_text(page(args, rows, table, names))


def page(args, rows: list[dict], table: list[str], names: list[str]) -> str:
    """The figures as a Markdown page: the command, the machine, the totals, every instance."""
    from mrcert.infra.runtime import machine

    kept, skip = [], False
    for a in sys.argv[1:]:  # the command as typed (paths from where it ran), less where it wrote
        if skip or a in ("--tsv", "--page"):
            skip = not skip and a in ("--tsv", "--page")
            continue
        kept.append(shlex.quote(os.path.relpath(a) if os.path.isabs(a) and os.path.exists(a) else a))
    where = args.page.absolute()
    command = " ".join(["python benchmarks/peer.py", *kept, "--page",
                        str(where.relative_to(ROOT) if where.is_relative_to(ROOT) else args.page)])  # fmt: skip
    lines = [
        "# mrcert beside alpha-beta-CROWN on the VNN-COMP MetaRoom instances",
        "",
        "Written by `benchmarks/peer.py` (`--page`): both tools on the same machine, one process at a time,",
        "interleaved (each goes first on every other instance), each given the instance's own limit.",
        f"Machine: {machine()}, {args.threads} threads for each tool.",
        *([f"alpha-beta-CROWN: {args.peer}."] if args.peer else []),
        "",
        "```bash",
        command,
        "```",
        "",
        "Whole process: from launch to exit (mrcert through `vnncomp/run_instance.sh`, alpha-beta-CROWN",
        "through `abcrown.py` as its harness runs it). Own reported time: mrcert's `verify.tsv` seconds",
        "(reading the files, checking them against onnxruntime and answering); alpha-beta-CROWN's `Time:`",
        "line. Peak memory: the process's largest resident set.",
        "",
        *table,
        "",
        "| instance | " + " | ".join(f"{n} answer | {n} s (own)" for n in names) + " |",
        "|---" * (1 + 2 * len(names)) + "|",
    ]
    for r in rows:
        cells = [f"{r[n + ' answer']} | {r[n + ' seconds']:.1f} ({r[n + ' own']:.2f})" for n in names]
        name = f"{r['onnx'].split('_no_custom')[0]}, {r['vnnlib'].split('_eps')[0]}"
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
