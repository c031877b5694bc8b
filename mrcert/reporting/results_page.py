"""The evidence page (``docs/results.md``): an experiment's Table 3 beside the paper's, the
certified-accuracy figure, the paper's qualitative findings checked with our numbers, and the
time each stage took -- all computed from the runs that fill the cells, never by hand.

Written by ``make reproduce-tables`` (its last stage: ``mrcert task=tables task.page=docs/results.md``).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mrcert.core.sequential import TOLERANCE
from mrcert.reporting import certify_log, learning_curve, paper_results, paper_tables, side_by_side
from mrcert.reporting.cells import Cell, compose_config
from mrcert.reporting.experiment_cells import SOURCE_COLUMNS, ExperimentCells, Measure, sweep_combos
from mrcert.reporting.paper_results import PIXELWISE_REPORTED
from mrcert.reporting.paper_tables import (
    AXIS_NAMES,
    CERTIFIED,
    REPRODUCTION,
    SMOOTHED_BENIGN,
    arch_name,
    model_label,
    robust,
)
from mrcert.reporting.plots import save
from mrcert.reporting.writers import as_text, markdown


@dataclass
class Job:
    """One job of the experiment (axis, variant) and its cells."""

    axis: str
    variant: str
    arch: str
    certify: Cell
    smooth: Cell
    attack: Cell


def jobs_of(src: ExperimentCells, experiment: str) -> list[Job]:
    """The experiment's jobs with their certify, smooth and attack cells (the attack at the
    experiment's own ``attack.k``)."""
    jobs = []
    for combo, first in src.rows(experiment, SMOOTHED_BENIGN):
        cfg = first.cfg
        jobs.append(
            Job(
                str(cfg.motion.axis),
                str(cfg.model.variant),
                str(cfg.model.arch),
                src.cell(experiment, combo, CERTIFIED),
                first,
                src.cell(experiment, combo, robust("smoothed", int(cfg.attack.k))),
            )
        )
    return jobs


def findings(src: ExperimentCells, jobs: list[Job]) -> dict:
    """The paper's three qualitative findings, each counted over our rows: for each, how many
    rows hold, of how many, and each row's two numbers; the attack's K and n and CERTIFY's alpha
    come from the runs' configs."""
    by = {(j.axis, j.variant): j for j in jobs}
    axes = [a for a in AXIS_NAMES if (a, "vanilla") in by and (a, "augmented") in by]
    # 1. Augmented models certify more than vanilla ones, per axis.
    pairs = [
        (a, src.index.metric(by[(a, "augmented")].certify, "certified_accuracy"),
         src.index.metric(by[(a, "vanilla")].certify, "certified_accuracy"))
        for a in axes
    ]  # fmt: skip
    done = [(a, aug, van) for a, aug, van in pairs if not (np.isnan(aug) or np.isnan(van))]
    augmented = _counted(
        [aug > van for _, aug, van in done], [f"{AXIS_NAMES[a]} {aug:.3f} vs {van:.3f}" for a, aug, van in done]
    )
    # 2. The smoothed model's K-perturbed accuracy is at least the base model's.
    rows = []
    for j in jobs:
        base = src.index.metric(j.attack, "base_robust_accuracy")
        smoothed = src.index.metric(j.attack, "smoothed_robust_accuracy")
        if not (np.isnan(base) or np.isnan(smoothed)):
            rows.append((j, base, smoothed))
    smoothed = _counted(
        [s >= b for _, b, s in rows], [f"{AXIS_NAMES[j.axis]} {j.variant} {s:.3f} vs {b:.3f}" for j, b, s in rows]
    )
    # 3. Certified accuracy is at most the smoothed model's empirical robust accuracy.
    rows, abstained, wrong, certified_broken = [], 0, 0, 0
    for j in jobs:
        clog, alog = src.index.log(j.certify), src.index.log(j.attack)
        if clog is None or alog is None:
            continue
        images = set(alog["idx"].tolist())
        radius = float(j.certify.cfg.motion.radius)
        cert = certify_log.certified_accuracy(clog[clog["idx"].isin(images)], radius)
        emp = float((alog["smoothed_robust"] == 1).mean())
        rows.append((j, cert, emp))
        ok = clog[certify_log.certified(clog, radius)]["idx"]
        broken = alog[alog["idx"].isin(set(ok.tolist())) & (alog["smoothed_robust"] != 1)]
        certified_broken += len(broken)
        if "smoothed_failure" in broken:
            abstained += int((broken["smoothed_failure"] == "abstain").sum())
            wrong += int((broken["smoothed_failure"] == "wrong").sum())
    certified = _counted(
        [c <= e for _, c, e in rows], [f"{AXIS_NAMES[j.axis]} {j.variant} {c:.3f} vs {e:.3f}" for j, c, e in rows]
    )
    attack = jobs[0].attack.cfg if jobs else None
    return {
        "augmented": augmented,
        "smoothed": smoothed,
        "certified": certified,
        "broken": certified_broken,
        "abstained": abstained,
        "wrong": wrong,
        "k": int(attack.attack.k) if attack is not None else None,
        "attack_n": int(attack.task.n) if attack is not None else None,
        "alpha": float(jobs[0].certify.cfg.task.alpha) if jobs else None,
    }


def _counted(holds: list[bool], rows: list[str]) -> dict:
    return {"holds": sum(holds), "total": len(holds), "rows": rows}


def base_models(src: ExperimentCells, jobs: list[Job]) -> pd.DataFrame:
    """Each evaluated model's training record: accuracy on its validation poses (what selected
    ``best.pt``) and on the test images (measured once, after training), and its train run."""
    rows = {}
    for j in jobs:
        run = j.certify.train_run if j.certify.filled else None  # None: an import
        key = j.variant + (j.axis if j.variant == "augmented" else "")
        metrics = src.index.metrics(run) if isinstance(run, str) else None
        if metrics is None or key in rows:
            continue
        label = "vanilla (every axis)" if j.variant == "vanilla" else f"augmented on {j.axis}"
        rows[key] = {
            "model": f"{j.arch} {label}",
            "validation accuracy": metrics.get("best_val_acc", np.nan),
            "test accuracy": metrics.get("test_acc", np.nan),
            TRAIN_RUN: run,
        }
    return pd.DataFrame(list(rows.values()))


TRAIN_RUN = "train run"
"""The column of :func:`base_models` that names each model's train run (recorded, not shown)."""


def record_models(src: ExperimentCells, models: pd.DataFrame) -> pd.DataFrame:
    """Record each base model's accuracies with its train run; the table as the page shows it."""
    for _, m in models.iterrows():
        for column in ("validation accuracy", "test accuracy"):
            src.record("base_models", m["model"], column, m[column], [m[TRAIN_RUN]])
    return models.drop(columns=TRAIN_RUN, errors="ignore")


# The paper's model whose Table 3 values stand beside ours on the page, whatever our architecture.
PAPER_ARCH = "resnet18"


def record_curve(src: ExperimentCells, curve: pd.DataFrame) -> pd.DataFrame:
    """The learning curve's table, each row's test accuracy recorded with the train runs behind it."""
    shown = learning_curve.table(curve)
    for _, row in shown.iterrows():
        keys = [row[k] for k in learning_curve.KEYS]
        runs = curve[(curve[learning_curve.KEYS] == keys).all(axis=1)]["run_id"]
        src.record("learning_curve", tuple(keys), "test accuracy (median)", row["test accuracy (median)"], list(runs))
    return shown


def curve_summary(models: pd.DataFrame, curve: pd.DataFrame) -> dict:
    """What the learning curve says, per architecture: the median test accuracy under `every`
    with the fewest and the most training poses (and under `any` with the most), and the range
    of the evaluated base models' validation and test accuracy."""
    archs = []
    for model, runs in curve.groupby("model", sort=False):
        med = runs.groupby(["separation rule", "training poses per class"])["test accuracy"].median()
        rules = set(med.index.get_level_values(0))
        if "every" not in rules or len(med["every"]) < 2:
            continue
        every = med["every"]
        fewest, most = every.index.min(), every.index.max()
        top = med["any"].index.max() if "any" in rules else None
        archs.append(
            {
                "name": arch_name(model),
                "fewest": int(fewest),
                "most": int(most),
                "fewest_acc": float(every[fewest]),
                "most_acc": float(every[most]),
                "any": None if top is None else {"poses": int(top), "acc": float(med["any"][top])},
            }
        )
    ranges = None
    if len(models):
        val, test = models["validation accuracy"].astype(float), models["test accuracy"].astype(float)
        ranges = {"val": (val.min(), val.max()), "test": (test.min(), test.max())}
    return {"archs": archs, "models": ranges}


def _validation(cfg) -> str:
    spec = cfg.data.protocol.get("validation")
    if spec is None:
        return f"{int(cfg.train.val_fraction * 100)}% of the training poses held out"
    return f"{spec.per_class} validation poses per class (docs/method.md §3)"


def _images(src: ExperimentCells, cell: Cell) -> int | str:
    log = src.index.log(cell)
    return "its" if log is None else len(log)


def _share(skip: int) -> str:
    return "every test image" if skip == 1 else f"one test image in {skip}"


def _verdict(counted: dict) -> str:
    holds, total = counted["holds"], counted["total"]
    if total == 0:
        return "not checked (no filled cells)"
    return f"holds in {holds} of {total}" if holds < total else f"holds in all {total}"


ATTACK_WORDS = {"uniform": "uniform", "grid": "evenly spaced"}
"""How the page names an attack's motions (``attack.name``)."""


def setup(src: ExperimentCells, jobs: list[Job]) -> dict | None:
    """The experiment's settings as its runs' composed configs have them."""
    if not jobs:
        return None
    c, s, a = jobs[0].certify.cfg, jobs[0].smooth.cfg, jobs[0].attack.cfg
    classes = len(c.data.classes) if c.data.get("classes") else int(c.data.num_classes)
    return {
        "data": c.data.name,
        "profile": c.profile.name,
        "classes": classes,
        "train_poses": c.data.protocol.train.per_class,
        "validation": _validation(c),
        "test_images": c.data.protocol.test.per_class * classes,
        "arch": c.model.arch,
        "epochs": c.train.epochs,
        "lr": c.train.lr,
        "n0": c.task.n0,
        "n": c.task.n,
        "alpha": c.task.alpha,
        "look": c.task.look,
        "tolerance": TOLERANCE,
        "predict_n": s.task.n,
        "k": a.attack.k,
        "attack": ATTACK_WORDS.get(str(a.attack.name), str(a.attack.name)),
        "attack_n": a.task.n,
        "share": _shares({"certify": c, "smooth": s, "attack": a}),
    }


def _shares(configs: dict) -> str:
    """Which test images each task's columns cover: one phrase when all cover the same."""
    shares = {task: _share(int(cfg.task.skip)) for task, cfg in configs.items()}
    if len(set(shares.values())) == 1:
        return f"Every column covers {next(iter(shares.values()))}, the same images in each."
    return "Columns cover " + "; ".join(f"{task}: {share}" for task, share in shares.items()) + "."


def separation(cfg) -> str:
    """The protocol's separation of training from test poses, in words."""
    gaps = cfg.data.protocol.get("separation") or {}
    return ", ".join(f"{quantity} {value:g} degrees" for quantity, value in gaps.items())


def run_seconds(run: pd.Series) -> float:
    """A run's working wall-clock: the time its processes worked on it (``active_seconds``),
    leaving out the time it was down between an interruption and its resumption; from its
    start to its end when a process of it was killed outright and logged no time."""
    timed, segments = run.get("metrics.timed_segments"), run.get("metrics.segments")
    if pd.notna(timed) and timed == segments:
        return float(run["metrics.active_seconds"])
    return (run["end_time"] - run["start_time"]).total_seconds()


def stage_times(src: ExperimentCells) -> pd.DataFrame:
    """Time per stage of the runs behind the tables built from ``src`` so far (``src.read``):
    per experiment, the train runs of its evaluated models, then each evaluation stage in the
    order first read; each with its runs' working wall-clock (``run_seconds``) summed, the
    machines they ran on and the seconds per test image measured in the per-image logs (work
    only); a last row sums every stage."""
    df = src.index.df.set_index("run_id")
    stages: dict[tuple[str, str], tuple[list[str], list[Cell]]] = {}
    trained: set[str] = set()
    for experiment in dict.fromkeys(e for e, _ in src.read):
        cells = [c for (e, _), read in src.read.items() if e == experiment for c in read.values()]
        train = [r for r in dict.fromkeys(c.train_run for c in cells) if r and r in df.index and r not in trained]
        trained.update(train)
        stages[(experiment, "train")] = (train, [])
        for (e, stage), read in src.read.items():
            if e == experiment:
                ids = [r for c in read.values() for r in c.run_ids if r in df.index]
                stages[(e, stage)] = (ids, list(read.values()))
    rows, total = [], 0.0
    for (experiment, stage), (ids, cells) in stages.items():
        if not ids:
            continue
        seconds = float(sum(run_seconds(df.loc[i]) for i in ids))
        total += seconds
        logs = [log for log in (src.index.log(c) for c in cells) if log is not None]
        images = sum(len(log) for log in logs)
        work = sum(float(log["seconds"].sum()) if "seconds" in log else float("nan") for log in logs)
        machines = df.loc[ids, "tags.mrcert.machine"].dropna() if "tags.mrcert.machine" in df else pd.Series()
        rows.append(
            {
                "experiment": experiment,
                "stage": stage,
                "runs": len(ids),
                "test images": images or "",
                "run time, summed (h)": seconds / 3600,
                "machines": "; ".join(
                    f"{m} ({n} run{'s' if n > 1 else ''})" for m, n in machines.value_counts().sort_index().items()
                ),
                "seconds per image": work / images if images else "",
            }
        )
    if rows:
        runs = sum(r["runs"] for r in rows)
        rows.append({"experiment": "every stage", "stage": "", "runs": runs, "run time, summed (h)": total / 3600})
    return pd.DataFrame(rows, columns=STAGE_COLUMNS).fillna("")


STAGE_COLUMNS = ["experiment", "stage", "runs", "test images", "run time, summed (h)", "machines", "seconds per image"]


def shown_times(times: pd.DataFrame) -> str:
    """The time table as the page prints it: hours and seconds to two decimals."""
    shown = times.astype(str)
    for column in ("run time, summed (h)", "seconds per image"):
        shown[column] = times[column].map(lambda v: v if v == "" else f"{v:.2f}")
    return markdown(shown)


MAKEFILE = Path(__file__).resolve().parents[2] / "Makefile"


def make_stage(target: str, profile: str) -> list[str]:
    """The mrcert commands that ``make TARGET`` runs, as the Makefile writes them (continued
    lines joined, comments dropped, ``$(MRCERT)`` as ``mrcert``, ``$(PROFILE)`` as
    ``profile``, ``$(REPRODUCTION)`` as its experiment, the default ``ATTACKS``); the page's
    last stage, the tables, not among them. Empty without the
    Makefile (an installed copy)."""
    if not MAKEFILE.is_file():
        return []
    lines = MAKEFILE.read_text().split("\n")
    start = next((i for i, line in enumerate(lines) if line.startswith(f"{target}:")), None)
    if start is None:
        return []
    commands, current = [], ""
    for line in lines[start + 1 :]:
        if not line.startswith("\t"):
            break
        text = line.strip().split("  #", 1)[0].rstrip()
        current += " " + text.rstrip("\\").strip()
        if not text.endswith("\\"):
            commands.append(current.strip())
            current = ""
    named = {
        "$(MRCERT)": "mrcert",
        "$(PROFILE)": profile,
        "$(REPRODUCTION)": REPRODUCTION.format(profile=profile),
        "$(ATTACK_SETTING)": "",  # ATTACKS=fixed, the default
    }
    shown = []
    for command in commands:
        for variable, value in named.items():
            command = command.replace(variable, value)
        shown.append(command.strip())
    return [c for c in shown if c.startswith("mrcert ")]


def sequential_attack_section(src: ExperimentCells, experiment: str) -> dict | None:
    """Per attack cell (axis, model, K) that has both: the smoothed K-perturbed accuracy under
    fixed-n PREDICT and under sequential PREDICT on the same images and motions, the images
    whose verdict differs, and each one's seconds per image; None when no sequential attack has
    run. The sequential runs' time also enters the time table (their own stage)."""
    rows = []
    for combo, first in src.rows(experiment, SMOOTHED_BENIGN):
        cfg = first.cfg
        for k in dict.fromkeys((int(cfg.attack.k), 100)):
            cells = {
                name: src.cell(
                    experiment,
                    combo,
                    Measure("attack", "smoothed_robust_accuracy", (f"attack.k={k}", f"task.sequential={flag}")),
                )
                for name, flag in (("fixed", "false"), ("sequential", "true"))
            }
            fixed, sequential = (src.index.log(cells[name]) for name in ("fixed", "sequential"))
            if fixed is None or sequential is None:
                continue
            n = int(cells["fixed"].cfg.task.n)  # the paper's attack: PREDICT with n samples per pose
            both = fixed.merge(sequential, on="idx", suffixes=("_fixed", "_sequential"))
            robust = {n: (both[f"smoothed_robust_{n}"] == 1) for n in ("fixed", "sequential")}
            seconds = {n: float(both[f"seconds_{n}"].mean()) for n in ("fixed", "sequential")}
            rows.append(
                {
                    "Axis": AXIS_NAMES.get(str(cfg.motion.axis), str(cfg.motion.axis)),
                    "Model": model_label(str(cfg.model.arch), str(cfg.model.variant)),
                    "K": k,
                    "images": len(both),
                    "fixed n": f"{robust['fixed'].mean():.3f}",
                    "sequential": f"{robust['sequential'].mean():.3f}",
                    "difference (images)": int(robust["sequential"].sum() - robust["fixed"].sum()),
                    "images whose verdict differs": int((robust["fixed"] != robust["sequential"]).sum()),
                    "s per image, fixed n": f"{seconds['fixed']:.2f}",
                    "s per image, sequential": f"{seconds['sequential']:.2f}",
                    "time, sequential / fixed": f"{seconds['sequential'] / seconds['fixed']:.2f}",
                }
            )
    if not rows:
        return None
    table = pd.DataFrame(rows)
    return {
        "table": markdown(table),
        "cells": len(table),
        "largest": int(table["difference (images)"].abs().max()),
        "n": n,
    }


def profile_hours(times: pd.DataFrame, experiment: str) -> dict | None:
    """The experiment's stages summed (hours), with its fixed-n attacks and, when sequential
    attacks ran too, with those in their place; None without sequential attacks."""
    own = times[times["experiment"] == experiment]
    attack = own["stage"].str.startswith("attack")
    sequential = attack & own["stage"].str.contains("task.sequential=true", regex=False)
    if not sequential.any():
        return None
    hours = own["run time, summed (h)"].astype(float)
    return {"fixed": float(hours[~sequential].sum()), "sequential": float(hours[~(attack & ~sequential)].sum())}


def side_by_side_section(src: ExperimentCells, page: Path) -> dict | None:
    """Camera motion smoothing beside pixel-wise smoothing, when ``make side-by-side`` has run."""
    pair = side_by_side.runs(src)
    if not len(pair):
        return None
    plot = page.with_name(f"{page.stem}_side_by_side.png")
    save(side_by_side.figure(pair), [plot])
    reported = pd.DataFrame(
        [[("-" if v is None else str(v)) for v in row] for row in PIXELWISE_REPORTED],
        columns=["axis", "half-width (m)", "method", "model", "pixel sigma", "frames", "certified accuracy"],
    )
    pixelwise = pair[pair["frames"].notna()]
    for _, r in side_by_side.shown_once(pair).iterrows():
        row = (r["axis"], r["interval"], r["method"], r["base model"])
        models = [r["train_run"]] if isinstance(r["train_run"], str) else []
        for column in ("certified accuracy", "seconds / image"):
            src.record("side_by_side", row, column, r[column], [r["run_id"]], models)
    costs = side_by_side.costs(pair)
    return {
        "caps": _pixel_noise_caps(pair),
        "experiment": side_by_side.EXPERIMENT,
        "commands": make_stage("side-by-side", src.profile),
        "share": _share(int(pixelwise.iloc[0]["skip"])),
        "table": markdown(as_text(side_by_side.table(pair))),
        "costs": markdown(as_text(costs)),
        "machine": None if "machine" in costs else str(pair["machine"].iloc[0]),
        "picture": plot.name,
        "reported": markdown(as_text(reported)),
    }


def _pixel_noise_caps(pair: pd.DataFrame) -> dict | None:
    """The pixel-noise base models' test accuracy on clean and on noisy images, each as one value
    or a range over the models (None without such a model)."""
    noisy = pair[pair["base noisy accuracy"].notna()]
    if not len(noisy):
        return None

    def span(column: str) -> str:
        low, high = noisy[column].min(), noisy[column].max()
        return f"{low:.3f}" if f"{low:.3f}" == f"{high:.3f}" else f"{low:.3f}-{high:.3f}"

    return {"clean": span("base clean accuracy"), "noisy": span("base noisy accuracy")}


PAPER_PROFILE = "paper"
PROFILE_STAGES = (
    CERTIFIED,
    paper_tables.SEQUENTIAL,
    SMOOTHED_BENIGN,
    robust("smoothed", 5),
    robust("smoothed", 100),
    *(Measure("attack", "smoothed_robust_accuracy", (f"attack.k={k}", "task.sequential=true")) for k in (5, 100)),
)
"""A measure of each evaluation stage ``make reproduce-tables`` runs for the experiment (fixed-n
and sequential CERTIFY, PREDICT, the 5- and 100-perturbed attacks with fixed-n and sequential
PREDICT): reading them puts every such run of the paper's profile in its stage times."""


def paper_profile_section(src: ExperimentCells) -> dict | None:
    """The paper's own profile (``profile=paper``: the paper's data settings, ResNets and
    100-epoch recipe, a GPU's work), when the store holds any of its Table 3 runs (e.g. gathered
    from a GPU with ``task=gather``): the filled rows beside the paper, their base models, and the
    time each stage took on which machine; when it holds none, how many jobs it lacks."""
    if src.profile == PAPER_PROFILE:  # the page's own
        return None
    experiment = REPRODUCTION.format(profile=PAPER_PROFILE)
    missing = {"profile": PAPER_PROFILE, "experiment": experiment, "missing": len(sweep_combos(experiment))}
    profiles = src.index.df.get("tags.mrcert.profile", pd.Series(dtype=str))
    if not (profiles == PAPER_PROFILE).any():
        return missing
    # Its cells are recorded with the page's, so that the page's sources name their runs too.
    paper = ExperimentCells(
        src.index, profile=PAPER_PROFILE, overrides=src.overrides, link=src.link, provenance=src.provenance
    )
    every = jobs_of(paper, experiment)
    filled = {
        (AXIS_NAMES.get(j.axis, j.axis), model_label(j.arch, j.variant)): j
        for j in every
        if any(c.filled for c in (j.certify, j.smooth, j.attack))
    }  # one job per row (cell overrides can make two of the sweep's jobs one)
    if not filled:
        return missing
    jobs = list(filled.values())
    table = paper_tables.TABLE3.build(paper, show_paper=True, name="paper_profile")
    for measure in PROFILE_STAGES:  # the stages Table 3 does not read, for their times
        list(paper.rows(experiment, measure))
    cfg = jobs[0].certify.cfg
    return {
        "profile": PAPER_PROFILE,
        "experiment": experiment,
        "missing": 0,
        "train_poses": cfg.data.protocol.train.per_class,
        "epochs": cfg.train.epochs,
        "lr": cfg.train.lr,
        "n0": cfg.task.n0,
        "n": cfg.task.n,
        "alpha": cfg.task.alpha,
        "images": _images(paper, jobs[0].certify),
        "table": markdown(as_text(table.loc[list(filled)])),
        "models": markdown(as_text(record_models(paper, base_models(paper, jobs)))),
        "times": shown_times(stage_times(paper)),
        "estimate": profile_estimate(paper, experiment, every),
    }


def profile_estimate(src: ExperimentCells, experiment: str, jobs: list[Job]) -> dict:
    """The whole experiment's run time at the paces measured here: per stage and architecture
    with runs in the store, the mean working time of a job (its runs summed), times the jobs the
    experiment has for that stage and architecture (for training, the distinct models its jobs
    bind). An architecture without a run here is named, not estimated."""
    from mrcert.infra.resolver import train_key

    df = src.index.df.set_index("run_id")
    cells = {(j.axis, j.variant, j.arch): j for j in jobs}  # overrides can make two of the sweep's jobs one
    need = pd.Series([arch for _, _, arch in cells]).value_counts()
    models = pd.Series([a for a, _ in {(j.arch, train_key(j.certify.cfg)) for j in cells.values()}]).value_counts()
    per_job: dict[tuple[str, str], list[float]] = {}
    trained: dict[str, str] = {}
    for (e, stage), read in src.read.items():
        if e != experiment:
            continue
        for cell in read.values():
            arch = str(cell.cfg.model.arch)
            ids = [r for r in cell.run_ids if r in df.index]
            per_job.setdefault((stage, arch), []).append(sum(run_seconds(df.loc[r]) for r in ids))
            if cell.train_run in df.index:
                trained[cell.train_run] = arch
    for run, arch in trained.items():
        per_job.setdefault(("train", arch), []).append(run_seconds(df.loc[run]))
    rows, total = [], 0.0
    for (stage, arch), seconds in sorted(per_job.items(), key=lambda kv: (kv[0][0] != "train", kv[0])):
        jobs_there = int((models if stage == "train" else need)[arch])
        mean = float(np.mean(seconds))
        total += mean * jobs_there / 3600
        rows.append(
            {
                "stage": stage,
                "architecture": arch,
                "jobs measured": len(seconds),
                "hours per job": f"{mean / 3600:.3f}",
                "jobs in the profile": jobs_there,
                "estimated hours": f"{mean * jobs_there / 3600:.2f}",
            }
        )
    archs, stages = {arch for _, arch in per_job}, {stage for stage, _ in per_job}
    unmeasured = [f"{a} ({int(need[a])} jobs)" for a in need.index if a not in archs]
    unmeasured += [s for s in dict.fromkeys(["train", *map(src.stage, PROFILE_STAGES)]) if s not in stages]
    return {"table": markdown(pd.DataFrame(rows)), "hours": f"{total:.2f}", "unmeasured": "; ".join(unmeasured)}


TEMPLATE = "results.md"
"""The page's text (``mrcert/reporting/templates/``): every number in it comes from the context."""


def render(context: dict) -> str:
    """The page: :data:`TEMPLATE` rendered with ``context``."""
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("mrcert.reporting", "templates"),
        undefined=jinja2.StrictUndefined,
        keep_trailing_newline=True,
        autoescape=False,
    )
    env.globals["verdict"] = _verdict
    return env.get_template(TEMPLATE).render(**context)


def page_context(
    src: ExperimentCells,
    experiment: str,
    table: pd.DataFrame,
    picture: str,
    page: Path,
    command: str,
    views: tuple[Path, str] | None = None,
) -> dict:
    """Everything the page states, from the runs and their composed configs (figures that
    belong to the page are written beside it)."""
    jobs = jobs_of(src, experiment)
    filled = any(c.filled for j in jobs for c in (j.certify, j.smooth, j.attack))
    models = record_models(src, base_models(src, jobs))
    curve = learning_curve.runs(src)
    curve_section = None
    if len(curve):
        plot = page.with_name(f"{page.stem}_learning_curve.png")
        save(learning_curve.figure(curve, learning_curve.histories(curve)), [plot])
        protocol = jobs[0].certify.cfg if jobs else compose_config((f"experiment={learning_curve.EXPERIMENTS[0]}",))
        curve_section = {
            "experiments": learning_curve.EXPERIMENTS,
            "shown": len(curve),
            "defined": sum(len(sweep_combos(e)) for e in learning_curve.EXPERIMENTS),
            "separation": separation(protocol),
            "table": markdown(as_text(record_curve(src, curve))),
            "picture": plot.name,
        } | curve_summary(models, curve)
    low, high = paper_results.base_benign_range(PAPER_ARCH)
    attack_section = sequential_attack_section(src, experiment) if filled else None
    side = side_by_side_section(src, page)
    paper_profile = paper_profile_section(src)
    times = stage_times(src) if filled else pd.DataFrame(columns=STAGE_COLUMNS)
    machines = sorted({str(m) for m in src.index.df.get("tags.mrcert.machine", pd.Series(dtype=str)).dropna()})
    versions = (src.index.run_tags(r) or {} for r in src.cited_runs())
    codes = sorted({v["mrcert.code_version"] for v in versions if "mrcert.code_version" in v})
    return {
        "experiment": experiment,
        "reproduction": experiment == REPRODUCTION.format(profile=src.profile),
        "profile": src.profile,
        "command": command,
        "stages": make_stage("reproduce-tables", src.profile),
        "setup": setup(src, jobs),
        "paper": {
            "dataset": paper_results.DATASET,
            "arch": arch_name(PAPER_ARCH),
            "train_poses": paper_results.TRAIN_POSES,
            "test_images": paper_results.TEST_IMAGES,
            "lowest_base": low,
            "highest_base": high,
        },
        "filled": filled,
        "table": markdown(as_text(table)) if filled else "",
        "figure": picture,
        "findings": findings(src, jobs) if filled else None,
        "models": markdown(as_text(models)) if len(models) else "",
        "views": None if views is None else {"picture": views[0].name, "sentence": views[1]},
        "curve": curve_section,
        "side": side,
        "sequential_attack": attack_section,
        "paper_profile": paper_profile,
        "times": shown_times(times) if filled else "",
        "profile_hours": profile_hours(times, experiment) if filled else None,
        "machines": "; ".join(machines) or "unknown",
        "code": ", ".join(f"`{c}`" for c in codes) or "an unrecorded version",
        "sources": f"{page.stem}_sources.csv",
    }


def write_page(
    src: ExperimentCells,
    experiment: str,
    table: pd.DataFrame,
    figure: Path,
    page: Path,
    command: str,
    views: tuple[Path, str] | None = None,
) -> Path:
    """Write the evidence page for ``experiment`` to ``page`` (the figure is copied beside it).
    ``views``: a picture of test views beside their nearest training views (written beside the
    page) and a sentence on their angles."""
    page.parent.mkdir(parents=True, exist_ok=True)
    picture = page.with_name(f"{page.stem}_certified_accuracy_vs_radius.png")
    shutil.copyfile(figure, picture)
    page.write_text(render(page_context(src, experiment, table, picture.name, page, command, views)))
    sources = pd.DataFrame(src.provenance, columns=SOURCE_COLUMNS)
    sources.drop(columns="links").to_csv(page.with_name(f"{page.stem}_sources.csv"), index=False, na_rep="")
    return page
