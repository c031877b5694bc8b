"""``task=verify``: VNN-LIB properties of ONNX classifiers answered as the competition's tools
answer them (``unsat``, ``sat`` with a counterexample, ``unknown``, ``timeout``), by bound
propagation with input splitting (:func:`mrcert.core.methods.bound_propagation.verify_box`).

One instance (``task.onnx`` + ``task.vnnlib``) or a benchmark's ``instances.csv`` (rows
``onnx,vnnlib,timeout`` relative to its folder, gzipped files read as they are). Each answer is
a result file ``results/<idx>.txt`` in the competition's format and a row of ``verify.tsv``;
a restarted run resumes after the instances it has answered."""

from __future__ import annotations

import csv
import gzip
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from omegaconf import DictConfig

from mrcert.core.methods.bound_propagation import verify_box
from mrcert.core.propagation import BoundNetwork
from mrcert.errors import MrcertError
from mrcert.formats.onnx_model import read_onnx
from mrcert.formats.vnnlib import counterexample_text, read_vnnlib
from mrcert.infra.identity import Identity
from mrcert.infra.progress import progress
from mrcert.infra.runtime import launch_command, machine, resolve_device
from mrcert.infra.tasks import HELPER_IGNORES, Task
from mrcert.infra.tracking import RunContext
from mrcert.tasks.evaluation import log_headline, result_log

DEFAULT_TIMEOUT = 300.0


def instances(t: DictConfig) -> list[tuple[Path, Path, float]]:
    """The (onnx, vnnlib, timeout) instances ``task`` names, each file checked to exist."""
    if t.instances:
        if t.onnx or t.vnnlib:
            raise MrcertError(
                "task.instances and task.onnx/task.vnnlib exclude each other: give one instance or a list"
            )
        listing = Path(str(t.instances))
        rows = []
        with open(listing, newline="") as f:
            for k, row in enumerate(csv.reader(f)):
                if not row or not "".join(row).strip():
                    continue
                if len(row) < 2:
                    raise MrcertError(f"{listing}: line {k + 1} is not onnx,vnnlib[,timeout]")
                seconds = float(row[2]) if len(row) > 2 and row[2].strip() else DEFAULT_TIMEOUT
                rows.append((listing.parent / row[0].strip(), listing.parent / row[1].strip(), seconds))
        chosen = [r for r in rows if not t.filter or str(t.filter) in r[0].name]
        if not chosen:
            raise MrcertError(f"task.filter={t.filter!r} matches none of the {len(rows)} instances of {listing}")
        for o, v, _ in chosen:
            _existing(o), _existing(v)
        return [(o, v, float(t.timeout) if t.timeout else s) for o, v, s in chosen]
    if not (t.onnx and t.vnnlib):
        raise MrcertError("task=verify needs task.onnx and task.vnnlib, or task.instances")
    return [(Path(str(t.onnx)), Path(str(t.vnnlib)), float(t.timeout or DEFAULT_TIMEOUT))]


def _plain(path: Path, folder: Path) -> Path:
    """``path``, or its gunzipped copy in ``folder`` (a benchmark ships .onnx.gz, .vnnlib.gz)."""
    if path.suffix != ".gz":
        return path
    out = folder / path.with_suffix("").name
    with gzip.open(path, "rb") as src, open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return out


def _existing(path: Path) -> Path:
    """``path``, or ``path.gz`` where only that exists (a listing may name a file shipped gzipped)."""
    if path.is_file():
        return path
    zipped = path.with_name(path.name + ".gz")
    if zipped.is_file():
        return zipped
    raise MrcertError(f"instance file {str(path)!r} does not exist")


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    t = cfg.task
    todo = instances(t)
    device = resolve_device(cfg.device)
    log = result_log(ctx, "verify")
    done = log.done({i: 0 for i in range(len(todo))})
    results = ctx.output_dir / "results"
    results.mkdir(exist_ok=True)
    networks: dict[Path, tuple[torch.nn.Module, BoundNetwork]] = {}
    with tempfile.TemporaryDirectory() as scratch:
        for i in progress([i for i in range(len(todo)) if i not in done], "verify"):
            onnx_path, vnnlib_path, timeout = todo[i]
            start = time.perf_counter()
            source = _existing(onnx_path)
            if source not in networks:  # a benchmark names one network in many instances: read it once
                model = read_onnx(_plain(source, Path(scratch))).to(device)
                networks[source] = (model, BoundNetwork(model))
            model, network = networks[source]
            prop = read_vnnlib(_plain(_existing(vnnlib_path), Path(scratch)))
            shape = (1, *model.input_shape[1:])
            if prop.low.size != int(torch.tensor(shape).prod()):
                raise MrcertError(f"{vnnlib_path}: {prop.low.size} inputs where {onnx_path} takes {shape}")
            low = torch.from_numpy(prop.low).reshape(shape)
            high = torch.from_numpy(prop.high).reshape(shape)
            remaining = max(timeout - (time.perf_counter() - start), 0.0)
            verdict = verify_box(
                model,
                network,
                low,
                high,
                prop.unsafe,
                remaining,
                str(t.relaxation),
                int(t.max_boxes),
                seed=int(cfg.seed),
            )
            text = verdict.result + "\n"
            if verdict.result == "sat":
                text += counterexample_text(verdict.x, verdict.y)
            (results / f"{i}.txt").write_text(text)
            if t.result and len(todo) == 1:
                Path(str(t.result)).write_text(text)
            log.append(
                {
                    "idx": i,
                    "onnx": onnx_path.name,
                    "vnnlib": vnnlib_path.name,
                    "result": verdict.result,
                    "margin": float(verdict.margin),
                    "boxes": verdict.boxes,
                    "forward_passes": verdict.forward_passes,
                    "seconds": time.perf_counter() - start,
                    "timeout": float(timeout),
                }
            )
    ctx.tracker.log_artifact(results)
    metrics = log_headline(ctx, "verify", log.path, cfg)
    command = launch_command() or "mrcert task=verify " + " ".join(
        f"task.{k}={v}" for k, v in t.items() if k not in ("name", "_target_") and v is not None
    )
    text = comparison(pd.read_csv(log.path, sep="\t"), machine(), command)
    if text is not None:
        (ctx.output_dir / "comparison.md").write_text(text)
        ctx.tracker.log_artifact(ctx.output_dir / "comparison.md")
        if t.page:
            Path(str(t.page)).write_text(text)
    return metrics


PUBLISHED = Path(__file__).resolve().parents[1] / "formats" / "vnncomp2023_metaroom_4cnn.csv"
"""The VNN-COMP 2023 tools' answers and seconds on the MetaRoom benchmark's 46 4cnn instances
(the competition's published results, ``ChristopherBrix/vnncomp2023_results``)."""

TOOLS = {"alpha_beta_crown": "alpha-beta-CROWN", "neuralsat": "NeuralSAT", "pyrat": "PyRAT", "nnenum": "nnenum"}


def comparison(log: pd.DataFrame, machine: str, command: str) -> str | None:
    """This run's answers beside the published ones on the same instances (matched by property
    file), as Markdown; None unless every instance of the run is one of theirs."""
    published = pd.read_csv(PUBLISHED)
    names = log["vnnlib"].str.replace(r"\.gz$", "", regex=True)
    if not names.isin(set(published["vnnlib"])).all():
        return None
    ours = dict(zip(names, log["result"], strict=True))
    theirs = published[published["vnnlib"].isin(set(names))]
    rows = [("mrcert (this run)", log["result"].tolist(), float(log["seconds"].sum()), machine)]
    for tool, name in TOOLS.items():
        part = theirs[theirs["tool"] == tool]
        rows.append((name, part["result"].tolist(), float(part["seconds"].sum()), "the competition's machines"))
    lines = [
        "# Deterministic verification: the VNN-COMP 2023 MetaRoom instances",
        "",
        "Written by `task=verify` (`task.page`). The benchmark's ONNX networks and VNN-LIB properties",
        "(the competition's repository, `git clone https://github.com/ChristopherBrix/vnncomp2023_benchmarks`)",
        f"answered by mrcert's bound propagation (docs/method.md §9), {len(log)} instances:",
        "",
        "```bash",
        command,
        "```",
        "",
        "beside the answers and seconds the competition's tools published for the same instances",
        "(`ChristopherBrix/vnncomp2023_results`; each tool on the machine it chose there).",
        "",
        "| verifier | verified (unsat) | falsified (sat) | unknown, timeout or error | seconds, all instances "
        "| machine |",
        "|---|---|---|---|---|---|",
    ]
    for name, results, seconds, where in rows:
        unsat, sat = results.count("unsat"), results.count("sat")
        lines.append(f"| {name} | {unsat} | {sat} | {len(results) - unsat - sat} | {seconds:.1f} | {where} |")
    falsified = set(theirs.loc[theirs["result"] == "sat", "vnnlib"])
    verified_by_them = set(theirs.loc[theirs["result"] == "unsat", "vnnlib"])
    wrong = sorted(n for n in falsified if ours.get(n) == "unsat")
    contradicted = sorted(n for n in verified_by_them if ours.get(n) == "sat")
    lines += [
        "",
        f"Instances a competition tool falsified that this run verified: {', '.join(wrong) or 'none'}.",
        f"Instances a competition tool verified that this run falsified: {', '.join(contradicted) or 'none'}.",
        "Instances this run left unanswered: "
        + (", ".join(f"{n} ({ours[n]})" for n in sorted(ours) if ours[n] not in ("unsat", "sat")) or "none")
        + ".",
    ]
    return "\n".join(lines) + "\n"


class Verify(Task):
    summary = "verify VNN-LIB properties of ONNX classifiers (unsat, sat, unknown, timeout)"
    # Its files name further files (an instances list): never reused by key.
    identity = Identity(
        defines=("task",),
        ignores=(*HELPER_IGNORES, "task.page", "task.result"),  # where it also writes its answers
        files=("task.onnx", "task.vnnlib", "task.instances"),
    )
    reusable = False
    log = "verify.tsv"
    columns = ("idx", "onnx", "vnnlib", "result", "margin", "boxes", "forward_passes", "seconds", "timeout")
    headline = ("verified", "falsified", "seconds_total")

    def title(self, cfg: DictConfig) -> str:
        return f"verify {cfg.task.instances or cfg.task.vnnlib}"

    def summarize(self, log, cfg: DictConfig) -> dict[str, float]:
        """How many instances each answer got, and the seconds they took."""
        counts = {r: float((log["result"] == r).sum()) for r in ("unsat", "sat", "unknown", "timeout")}
        return {
            "verified": counts["unsat"],
            "falsified": counts["sat"],
            "unknown": counts["unknown"],
            "timeout": counts["timeout"],
            "instances": float(len(log)),
            "seconds_total": float(log["seconds"].sum()),
        }

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
