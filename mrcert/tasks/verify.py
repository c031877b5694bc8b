"""``task=verify``: VNN-LIB properties of ONNX classifiers answered as the competition's tools
answer them (``unsat``, ``sat`` with a counterexample, ``unknown``, ``timeout``), by bound
propagation with input splitting (:func:`mrcert.core.verification.boxes.verify_box`), over
each input box of the property (:func:`mrcert.formats.vnnlib.read_cases`).

Before an instance is answered, the network mrcert read is run beside the file itself, by an
independent executor (onnxruntime), at the lowest and highest corner, the centre and seeded
random points of each box; a difference beyond float tolerance, a file mrcert refuses (an attribute it does not read,
sizes that do not match the property, a malformed property, one beyond ``task.max_model_mb`` or
``task.max_property_mb``) is ``error`` with its reason in the instance's row, and the other
instances are answered. A counterexample is reported with the executor's outputs, and only when
they lie in the unsafe region.

One instance (``task.onnx`` + ``task.vnnlib``) or a benchmark's ``instances.csv`` (rows
``onnx,vnnlib,timeout`` relative to its folder, gzipped files read as they are). Each answer is
a result file ``results/<idx>.txt`` in the competition's format and a row of ``verify.tsv``;
a restarted run resumes after the instances it has answered."""

from __future__ import annotations

import csv
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig

from mrcert.core.verification.boxes import BoxVerdict, verify_box
from mrcert.core.verification.network import BoundNetwork
from mrcert.errors import MrcertError
from mrcert.formats import shipped
from mrcert.formats.answer import GRACE, RESERVE, process_start, result_file
from mrcert.formats.onnx_model import MAX_MODEL_BYTES, ReferenceCheck, read_onnx
from mrcert.formats.vnnlib import MAX_PROPERTY_BYTES, Property, counterexample_text, read_cases
from mrcert.infra.identity import Identity
from mrcert.infra.progress import progress
from mrcert.infra.runtime import launch_command, machine, resolve_device
from mrcert.infra.tasks import HELPER_IGNORES, Task
from mrcert.infra.tracking import RunContext

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


def _existing(path: Path) -> Path:
    """``path``, or ``path.gz`` where only that exists (:func:`mrcert.formats.shipped`), which must exist."""
    found = shipped(path)
    if not found.is_file():
        raise MrcertError(f"instance file {str(path)!r} does not exist")
    return found


FORWARD_INPUTS = 4096
"""Boxes that perturb at most this many inputs are bounded by linear bounds carried forwards in
those inputs (:class:`~mrcert.core.verification.network.BoundNetwork`): a benchmark's boxes
perturb a few pixels of an image, and every fixed one is a constant."""

CHECK_POINTS = 3
"""Seeded random points of each box (beside its corners and centre) at which the network read is
run by the reference executor before the instance is answered."""


@dataclass
class Network:
    """A network of a benchmark, read once: the module, its bounds, its reference check, its sizes."""

    model: torch.nn.Module
    bounds: BoundNetwork
    reference: ReferenceCheck
    inputs: int
    outputs: int

    @classmethod
    def read(cls, path: Path, device: torch.device, max_bytes: int) -> Network:
        model = read_onnx(path, max_bytes)
        shape = (1, *model.input_shape[1:])
        with torch.no_grad():
            outputs = int(model(torch.zeros(shape)).shape[1])
        reference = ReferenceCheck(model, str(path))
        model = model.to(device)
        return cls(model, BoundNetwork(model, forward_inputs=FORWARD_INPUTS), reference, int(np.prod(shape)), outputs)

    def check(self, cases: list[Property], seed: int) -> None:
        """Refuse (one line) a reading of the file whose outputs are not the reference executor's
        at the lowest and highest corner, the centre and seeded random points of each box."""
        g = np.random.default_rng(seed)
        shape = (-1, *self.model.input_shape[1:])
        for case in cases:
            width = case.high - case.low
            points = [case.low, case.high, (case.low + case.high) / 2]
            points += [case.low + width * g.uniform(size=width.shape) for _ in range(CHECK_POINTS)]
            x = torch.from_numpy(np.stack(points)).reshape(shape)
            self.reference.check(x.float(), self._on_device(self.model), self._on_device(self.bounds.forward))

    def _on_device(self, network):
        device = next(iter(self.bounds.traced.buffers()), torch.zeros(0)).device
        return lambda v: network(v.to(device))


@dataclass(frozen=True)
class Settings:
    """How an instance is answered (``task=verify``'s settings)."""

    relaxation: str = "crown"
    max_boxes: int = 4096
    relu_domains: int = 1024
    bound_steps: int = 20
    seed: int = 0
    max_model_bytes: int = MAX_MODEL_BYTES
    max_property_bytes: int = MAX_PROPERTY_BYTES

    @classmethod
    def from_config(cls, cfg: DictConfig) -> Settings:
        t = cfg.task
        return cls(str(t.relaxation), int(t.max_boxes), int(t.relu_domains), int(t.bound_steps), int(cfg.seed),
                   int(float(t.max_model_mb) * 2**20), int(float(t.max_property_mb) * 2**20))  # fmt: skip


def verify_instance(
    onnx: Path,
    vnnlib: Path,
    timeout: float,
    settings: Settings = Settings(),
    device: torch.device | None = None,
    networks: dict | None = None,
    start: float | None = None,
) -> tuple[BoxVerdict, str]:
    """One instance's verdict and, for ``error``, why it is not answered (module docstring).
    ``networks`` caches the networks read (and those refused) across the instances of a benchmark;
    ``timeout`` counts from ``start`` (``time.perf_counter()``; now when not given)."""
    start = time.perf_counter() if start is None else start
    networks = {} if networks is None else networks
    device = device or torch.device("cpu")
    try:
        source = _existing(Path(onnx))
        if source not in networks:  # a benchmark names one network in many instances: read it once
            try:
                networks[source] = Network.read(source, device, settings.max_model_bytes)
            except MrcertError as exc:
                networks[source] = exc  # refused once, for each of its instances
        network = networks[source]
        if isinstance(network, MrcertError):
            raise network
        cases = read_cases(_existing(Path(vnnlib)), network.inputs, network.outputs, settings.max_property_bytes)
        network.check(cases, settings.seed)
        return answer(network, cases, timeout, settings, start), ""
    except MrcertError as exc:  # this instance cannot be answered
        return BoxVerdict("error", float("nan"), 0, 0), str(exc)


def answer(network: Network, cases: list[Property], timeout: float, settings: Settings, start: float) -> BoxVerdict:
    """An instance's verdict over its input boxes: ``sat`` as soon as one box is (its counterexample
    checked by the reference executor), ``unsat`` when every box is, else what the first box
    left open got (``timeout`` or ``unknown``)."""
    shape = (1, *network.model.input_shape[1:])
    boxes = forwards = 0
    margin = np.inf
    for case in cases:
        remaining = max(timeout - (time.perf_counter() - start), 0.0)
        verdict = verify_box(
            network.model, network.bounds, torch.from_numpy(case.low).reshape(shape),
            torch.from_numpy(case.high).reshape(shape), case.unsafe, remaining, settings.relaxation,
            settings.max_boxes, seed=settings.seed, relu_domains=settings.relu_domains,
            bound_steps=settings.bound_steps,
        )  # fmt: skip
        boxes, forwards = boxes + verdict.boxes, forwards + verdict.forward_passes
        if verdict.result == "sat":  # the counterexample as the reference executor computes it
            y = network.reference.reference(verdict.x.reshape(shape))[0].astype(np.float64)
            if not (case.contains(verdict.x) and case.violated(y)):
                verdict = BoxVerdict("unknown", verdict.margin, 0, 0)
            verdict.y = y
        if verdict.result != "unsat":
            verdict.boxes, verdict.forward_passes = boxes, forwards
            return verdict
        margin = min(margin, verdict.margin)
    return BoxVerdict("unsat", margin, boxes, forwards)


def run(cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
    from mrcert.tasks.run_log import log_headline, result_log

    t = cfg.task
    todo = instances(t)
    single = t.result and len(todo) == 1
    # One instance's limit counts from the process's start (imports, reading, checking included).
    started = process_start()
    answer_file = result_file(Path(str(t.result)), todo[0][2]) if single else None
    device = resolve_device(cfg.device)
    log = result_log(ctx, "verify")
    done = log.done({i: 0 for i in range(len(todo))})
    results = ctx.output_dir / "results"
    results.mkdir(exist_ok=True)
    networks: dict[Path, Network | MrcertError] = {}
    settings = Settings.from_config(cfg)
    for i in progress([i for i in range(len(todo)) if i not in done], "verify"):
        onnx_path, vnnlib_path, timeout = todo[i]
        start = time.perf_counter()
        begun = start - (time.time() - started) if single else start  # on the perf_counter clock
        verdict, reason = verify_instance(onnx_path, vnnlib_path, timeout - RESERVE, settings, device, networks, begun)
        if reason:  # this instance is not answered; the others are
            print(f"error: instance {i} ({onnx_path.name}, {vnnlib_path.name}): {reason}", file=sys.stderr)
        text = verdict.result + "\n"
        if verdict.result == "sat":
            text += counterexample_text(verdict.x, verdict.y)
        if answer_file is not None and answer_file.write(text) != verdict.result:  # the watchdog's timeout
            verdict, text = BoxVerdict("timeout", -np.inf, verdict.boxes, verdict.forward_passes), "timeout\n"
        (results / f"{i}.txt").write_text(text)
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
                "reason": reason,
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


def reading_section() -> str:
    """What ``task=verify`` reads and refuses, from the reader's own tables (the page's section)."""
    from mrcert.formats.onnx_model import ATTRIBUTES, REFUSED
    from mrcert.formats.vnnlib import MAX_DISJUNCTS

    lines = [
        "## What is read, and what is refused",
        "",
        "Every operator below is computed as the ONNX specification defines it, each attribute with the",
        "specification's default where the file gives none; anything else (another operator, a node of",
        "another domain, an attribute not listed, a value listed as refused) makes the instance `error`,",
        "with one line naming the node, the attribute and its value, and the benchmark's other instances",
        "are answered.",
        "",
        "| operator | attributes read | refused |",
        "|---|---|---|",
    ]
    for op, attrs in ATTRIBUTES.items():
        lines.append(f"| {op} | {', '.join(attrs) or '-'} | {REFUSED[op] or '-'} |")
    lines += [
        "",
        "VNN-LIB: the top-level assertions hold together; a formula is a comparison (`<=`, `>=`) of linear",
        "terms over inputs alone (a bound) or outputs alone, or an `and` / `or` of formulas; a disjunction of",
        f"input boxes is answered box by box (at most {MAX_DISJUNCTS:,} disjuncts). Names are checked against",
        "the declarations (numbered from 0, no gap) and the network's input and output sizes; NaN and",
        "infinities are refused; a malformed file is one line naming the file and the line.",
        "",
        "Limits (settings of `task=verify`): a model whose tensors claim more than "
        f"`task.max_model_mb` = {MAX_MODEL_BYTES // 2**20} MB",
        "(initializers and external data, counted before any is loaded; external data only from the",
        f"model's folder), a property file larger than `task.max_property_mb` = {MAX_PROPERTY_BYTES // 2**20} MB",
        "once unzipped (refused before it is parsed).",
        "",
        "The cross-check: before an instance is answered, mrcert's reading of the network (the float32",
        "module that falsification runs and the float64 layers that bounds pass through) is run beside",
        "the file itself, by onnxruntime, at the lowest and the highest corner, the centre and",
        f"{CHECK_POINTS} seeded random points of each box; a difference beyond {ReferenceCheck.ATOL:g} +",
        f"{ReferenceCheck.RTOL:g} x the largest output refuses the instance (`error`). A counterexample is",
        "reported with onnxruntime's outputs, and only when they lie in the unsafe region.",
        "",
        "Soundness is checked on random networks over every operator and attribute above against the",
        "exact truth of a mixed-integer program (`tests/test_verify_fuzz.py`; `make test-full` runs 420).",
    ]
    return "\n".join(lines) + "\n"


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
        "",
    ]
    return "\n".join(lines) + "\n" + reading_section() + "\n" + harness_section()


def harness_section() -> str:
    """How the competition's own runner calls mrcert, and what its time limit promises (the page's section)."""
    return f"""## The competition's harness

`vnncomp/install_tool.sh v1` installs mrcert from its checkout (`make install`);
`vnncomp/prepare_instance.sh v1 CATEGORY ONNX VNNLIB` checks that the files exist (nothing is
converted: plain and gzipped files are read as they are); `vnncomp/run_instance.sh v1 CATEGORY ONNX
VNNLIB RESULT TIMEOUT` runs `mrcert task=verify task.onnx=ONNX task.vnnlib=VNNLIB task.result=RESULT
task.timeout=TIMEOUT tracking=off` (`MRCERT_VNNCOMP_ARGS` replaces `tracking=off`, say with
`tracking=sqlite` to record each instance in the store).

The limit is counted from the start of the process: the search stops {RESERVE:g} s before it, and
a watchdog, started from the command line before anything slow is imported, writes `timeout`
into RESULT {RESERVE:g} s after it when no answer is there yet, whatever the process is doing
then; an answer found later is not written, and a process still busy {GRACE:g} s later is ended.

Beside alpha-beta-CROWN on the same machine, interleaved: docs/peer.md (`benchmarks/peer.py`).
"""


class Verify(Task):
    summary = "verify VNN-LIB properties of ONNX classifiers (unsat, sat, unknown, timeout)"
    # Its files name further files (an instances list): never reused by key.
    identity = Identity(
        defines=("task",),
        ignores=(*HELPER_IGNORES, "task.page", "task.result"),  # where it also writes its answers
        files=("task.onnx", "task.vnnlib", "task.instances"),
    )
    reusable = False
    scene_task = False
    log = "verify.tsv"
    columns = ("idx", "onnx", "vnnlib", "result", "margin", "boxes", "forward_passes", "seconds", "timeout", "reason")
    headline = ("verified", "falsified", "seconds_total")

    def title(self, cfg: DictConfig) -> str:
        return f"verify {cfg.task.instances or cfg.task.vnnlib}"

    def summarize(self, log, cfg: DictConfig) -> dict[str, float]:
        """How many instances each answer got, and the seconds they took."""
        counts = {r: float((log["result"] == r).sum()) for r in ("unsat", "sat", "unknown", "timeout", "error")}
        return {
            "verified": counts["unsat"],
            "falsified": counts["sat"],
            "unknown": counts["unknown"],
            "timeout": counts["timeout"],
            "error": counts["error"],
            "instances": float(len(log)),
            "seconds_total": float(log["seconds"].sum()),
        }

    def run(self, cfg: DictConfig, ctx: RunContext) -> dict[str, Any]:
        return run(cfg, ctx)
