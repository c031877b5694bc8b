"""The paper's own profile (``profile=paper``), when the store holds its runs: its rows beside the
paper, its base models, its stage times and the whole experiment's time estimated from them."""

from __future__ import annotations

import numpy as np
import pandas as pd

from mrcert.reporting import paper_tables
from mrcert.reporting.experiment_cells import ExperimentCells, Measure, sweep_combos
from mrcert.reporting.page.jobs import Job, base_models, images_of, jobs_of, record_models
from mrcert.reporting.page.times import run_seconds, shown_times, stage_times
from mrcert.reporting.paper_tables import AXIS_NAMES, CERTIFIED, REPRODUCTION, SMOOTHED_BENIGN, model_label, robust
from mrcert.reporting.writers import as_text, markdown

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
        "images": images_of(paper, jobs[0].certify),
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
