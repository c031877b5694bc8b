"""The evidence page (``docs/results.md``): an experiment's Table 3 beside the paper's, the
certified-accuracy figure, the paper's qualitative findings checked with our numbers, and the
time each stage took -- all computed from the runs that fill the cells, never by hand.

Written by ``mrcert task=tables task.experiment=results task.page=docs/results.md``.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mrcert.reporting import certify_log, learning_curve, side_by_side, tables
from mrcert.reporting.cells import Cell
from mrcert.reporting.paper_results import PIXELWISE_REPORTED
from mrcert.reporting.plots import save
from mrcert.reporting.source import Source
from mrcert.reporting.tables import AXIS_NAMES, CERTIFIED, SMOOTHED_BENIGN, arch_name, model_label, robust
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


def jobs_of(src: Source, experiment: str, k: int) -> list[Job]:
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
                src.cell(experiment, combo, robust("smoothed", k)),
            )
        )
    return jobs


def findings(src: Source, jobs: list[Job]) -> list[str]:
    """The paper's three qualitative findings, each checked in one sentence with our numbers."""
    by = {(j.axis, j.variant): j for j in jobs}
    axes = [a for a in AXIS_NAMES if (a, "vanilla") in by and (a, "augmented") in by]
    out = []
    # 1. Augmented models certify more than vanilla ones, per axis.
    pairs = [
        (a, src.index.metric(by[(a, "augmented")].certify, "certified_accuracy"),
         src.index.metric(by[(a, "vanilla")].certify, "certified_accuracy"))
        for a in axes
    ]  # fmt: skip
    done = [(a, aug, van) for a, aug, van in pairs if not (np.isnan(aug) or np.isnan(van))]
    holds = [a for a, aug, van in done if aug > van]
    detail = ", ".join(f"{AXIS_NAMES[a]} {aug:.3f} vs {van:.3f}" for a, aug, van in done)
    out.append(
        f"**Motion-augmented models have higher certified accuracy than vanilla ones** (at r = sigma): "
        f"{_verdict(len(holds), len(done))} -- augmented vs vanilla: {detail}."
    )
    # 2. The smoothed model's K-perturbed accuracy is at least the base model's.
    rows = []
    for j in jobs:
        base = src.index.metric(j.attack, "base_robust_accuracy")
        smoothed = src.index.metric(j.attack, "smoothed_robust_accuracy")
        if not (np.isnan(base) or np.isnan(smoothed)):
            rows.append((j, base, smoothed))
    holds = [r for r in rows if r[2] >= r[1]]
    detail = ", ".join(f"{AXIS_NAMES[j.axis]} {j.variant} {s:.3f} vs {b:.3f}" for j, b, s in rows)
    out.append(
        f"**The smoothed model's 5-perturbed accuracy is at least the base model's**: "
        f"{_verdict(len(holds), len(rows))} (same images, same motions) -- smoothed vs base: {detail}."
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
    holds = [r for r in rows if r[1] <= r[2]]
    detail = ", ".join(f"{AXIS_NAMES[j.axis]} {j.variant} {c:.3f} vs {e:.3f}" for j, c, e in rows)
    out.append(
        f"**Certified accuracy is at most the smoothed model's empirical robust accuracy**: "
        f"{_verdict(len(holds), len(rows))} on the attacked images -- certified vs 5-perturbed: {detail}. "
        f"Of the certified images, {certified_broken} failed the attack: {abstained} by a PREDICT abstention at a "
        f"perturbed pose (n = 100 samples cannot separate the top two classes there; an abstention counts as "
        f"an error) and {wrong} by another class -- a certificate fails with probability at most alpha = 0.01."
    )
    return out


def base_models(src: Source, jobs: list[Job]) -> pd.DataFrame:
    """Each evaluated model's training record: accuracy on its validation poses (what selected
    ``best.pt``) and on the test images (measured once, after training)."""
    df = src.index.df.set_index("run_id")
    rows = {}
    for j in jobs:
        run = j.certify.runs[0].get("tags.mrcert.train_run") if j.certify.filled else None  # None: an import
        key = j.variant + (j.axis if j.variant == "augmented" else "")
        if not isinstance(run, str) or run not in df.index or key in rows:
            continue
        label = "vanilla (every axis)" if j.variant == "vanilla" else f"augmented on {j.axis}"
        rows[key] = {
            "model": f"{j.arch} {label}",
            "validation accuracy": df.loc[run].get("metrics.best_val_acc", np.nan),
            "test accuracy": df.loc[run].get("metrics.test_acc", np.nan),
        }
    return pd.DataFrame(list(rows.values()))


NORMAL = 0.858  # the lowest benign accuracy of the paper's base models on the test views (its Table 1)
# The paper's model whose Table 3 values stand beside ours on the page, whatever our architecture.
PAPER_ARCH = "resnet18"


def why(models: pd.DataFrame, curve: pd.DataFrame) -> str:
    """Sentences from the numbers: how well the evaluated base models generalise, and what the
    learning curve says about the number of training poses under each separation rule, per
    architecture."""
    text = []
    if len(models):
        val, test = models["validation accuracy"].astype(float), models["test accuracy"].astype(float)
        text.append(
            f"The evaluated base models reach {val.min():.2f} to {val.max():.2f} on the validation poses and "
            f"{test.min():.2f} to {test.max():.2f} on the test images."
        )
    for model, runs in curve.groupby("model", sort=False):
        med = runs.groupby(["separation rule", "training poses per class"])["test accuracy"].median()
        rules = set(med.index.get_level_values(0))
        if "every" not in rules or len(med["every"]) < 2:
            continue
        every = med["every"]
        fewest, most = every.index.min(), every.index.max()
        sentence = (
            f"Under `every` the median test accuracy of {arch_name(model)} is {every[fewest]:.2f} with "
            f"{fewest} training poses per class and {every[most]:.2f} with {most}"
        )
        if "any" in rules:
            top = med["any"].index.max()
            sentence += f" (under `any`: {med['any'][top]:.2f} with {top})"
        if every[most] >= NORMAL:
            verdict = (
                f"with {most} per class the base classifier performs normally on the test views (the paper's base "
                f"models: {NORMAL:.2f} and more)"
            )
        elif every[most] - every[fewest] >= 0.1:
            verdict = (
                f"more training poses help, but with {most} per class the base classifier is still far from performing "
                f"normally on the test views (the paper's base models: {NORMAL:.2f} and more)"
            )
        else:
            verdict = "the number of training poses alone does not move it"
        text.append(f"{sentence}: {verdict}.")
    return " ".join(text)


def _validation(cfg) -> str:
    spec = cfg.data.protocol.get("validation")
    if spec is None:
        return f"{int(cfg.train.val_fraction * 100)}% of the training poses held out"
    return f"{spec.per_class} validation poses per class (docs/method.md §3)"


def _images(src: Source, cell: Cell) -> int | str:
    log = src.index.log(cell)
    return "its" if log is None else len(log)


def _share(skip: int) -> str:
    return "every test image" if skip == 1 else f"one test image in {skip}"


def _verdict(holds: int, total: int) -> str:
    if total == 0:
        return "not checked (no filled cells)"
    return f"holds in {holds} of {total}" if holds < total else f"holds in all {total}"


def run_seconds(run: pd.Series) -> float:
    """A run's working wall-clock: the time its processes worked on it (``active_seconds``),
    leaving out the time it was down between an interruption and its resumption; from its
    start to its end when a process of it was killed outright and logged no time."""
    timed, segments = run.get("metrics.timed_segments"), run.get("metrics.segments")
    if pd.notna(timed) and timed == segments:
        return float(run["metrics.active_seconds"])
    return (run["end_time"] - run["start_time"]).total_seconds()


def stage_times(src: Source, jobs: list[Job]) -> pd.DataFrame:
    """Time per stage: the runs' working wall-clock (``run_seconds``) summed over the stage's
    runs, the machines they ran on, and the seconds per test image measured in the per-image
    logs (work only)."""
    runs = {"train": set(), "certify": set(), "smooth": set(), "attack": set()}
    images = {"certify": 0, "smooth": 0, "attack": 0}
    work = {"certify": 0.0, "smooth": 0.0, "attack": 0.0}
    for j in jobs:
        for stage in ("certify", "smooth", "attack"):
            cell = getattr(j, stage)
            runs[stage].update(cell.run_ids)
            log = src.index.log(cell)
            if log is not None:
                images[stage] += len(log)
                work[stage] += float(log["seconds"].sum()) if "seconds" in log else float("nan")
            if cell.filled and "tags.mrcert.train_run" in cell.runs[0]:
                runs["train"].add(str(cell.runs[0]["tags.mrcert.train_run"]))
    df = src.index.df.set_index("run_id")
    rows = []
    for stage, ids in runs.items():
        ids = [i for i in ids if i in df.index]
        seconds = float(sum(run_seconds(df.loc[i]) for i in ids))
        machines = df.loc[ids, "tags.mrcert.machine"].dropna() if "tags.mrcert.machine" in df else pd.Series()
        rows.append(
            {
                "stage": stage,
                "runs": len(ids),
                "test images": images.get(stage, ""),
                "run time, summed (h)": round(seconds / 3600, 2),
                "machines": "; ".join(
                    f"{m} ({n} run{'s' if n > 1 else ''})" for m, n in machines.value_counts().sort_index().items()
                ),
                "seconds per image": round(work[stage] / images[stage], 2) if images.get(stage) else "",
            }
        )
    return pd.DataFrame(rows)


def side_by_side_section(src: Source, page: Path) -> list[str]:
    """Camera motion smoothing beside pixel-wise smoothing, when ``make side-by-side`` has run."""
    pair = side_by_side.runs(src)
    if not len(pair):
        return []
    plot = page.with_name(f"{page.stem}_side_by_side.png")
    save(side_by_side.figure(pair), [plot])
    reported = pd.DataFrame(
        [[("-" if v is None else str(v)) for v in row] for row in PIXELWISE_REPORTED],
        columns=["axis", "half-width (m)", "method", "model", "pixel sigma", "frames", "certified accuracy"],
    )
    pixelwise = pair[pair["frames"].notna()]
    return [
        "## Camera motion smoothing beside pixel-wise smoothing",
        "",
        f"`make side-by-side` (`mrcert -m experiment={side_by_side.EXPERIMENT} task=train,certify`): a pixel-noise "
        "model of the same architecture, certified by pixel-wise smoothing (docs/method.md §8) for whole intervals "
        "[-a, a], beside the motion-augmented model above on the same test images "
        f"({_share(int(pixelwise.iloc[0]['skip']))}). "
        "Pixel-wise smoothing certifies an interval or nothing: its certified accuracy at radius a is the share of "
        "images certified for the whole interval; motion smoothing's is the share with a certified radius of at "
        "least a. Fixed-n CERTIFY (n0 + n per frame for pixel-wise smoothing, at alpha / frames each).",
        "",
        markdown(as_text(side_by_side.table(pair))),
        "",
        f"![camera motion smoothing and pixel-wise smoothing]({plot.name})",
        "",
        "For reference, as the pixel-wise smoothing authors' released logs report it (their MetaRoom, "
        "their models; not these test views):",
        "",
        markdown(as_text(reported)),
        "",
    ]


PAPER_PROFILE = "paper"


def paper_profile_section(src: Source) -> list[str]:
    """The paper's own profile (``profile=paper``: the paper's data settings, ResNets and
    100-epoch recipe, a GPU's work), when the store holds any of its Table 3 runs (e.g. gathered
    from a GPU with ``task=gather``): the filled rows beside the paper, their base models, and the
    time each stage took on which machine."""
    profiles = src.index.df.get("tags.mrcert.profile", pd.Series(dtype=str))
    if not (profiles == PAPER_PROFILE).any():  # nothing to show: compose none of its cells
        return []
    paper = Source(src.index, profile=PAPER_PROFILE, overrides=src.overrides, link=src.link)
    filled = {
        (AXIS_NAMES.get(j.axis, j.axis), model_label(j.arch, j.variant)): j
        for j in jobs_of(paper, "table3", 5)
        if any(c.filled for c in (j.certify, j.smooth, j.attack))
    }  # one job per row (cell overrides can make two of the sweep's jobs one)
    if not filled:
        return []
    jobs = list(filled.values())
    table = tables.certified_table(paper, show_paper=True, name="paper_profile")
    keep = list(filled)
    times = stage_times(paper, jobs)
    cfg = jobs[0].certify.cfg
    return [
        "## The paper's profile",
        "",
        f"`profile=paper` (`mrcert -m experiment=table3 profile=paper task=train,certify ...`, a GPU's work; "
        "runs made on another machine join this store with `mrcert task=gather`): the paper's data "
        f"settings ({cfg.data.protocol.train.per_class} training poses per class), its architectures and recipe "
        f"({cfg.train.epochs} epochs at lr {cfg.train.lr}), fixed-n CERTIFY at r = sigma (n0 = {cfg.task.n0}, "
        f"n = {cfg.task.n}, alpha = {cfg.task.alpha}) over {_images(paper, jobs[0].certify)} test images. Only "
        "the cells this store holds "
        "runs for; an empty cell was not run. The paper's values in parentheses.",
        "",
        markdown(as_text(table.loc[keep])),
        "",
        markdown(as_text(base_models(paper, jobs))),
        "",
        markdown(times[times["runs"] > 0].astype(str)),
        "",
    ]


def write_page(
    src: Source,
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
    jobs = jobs_of(src, experiment, 5)
    page.parent.mkdir(parents=True, exist_ok=True)
    picture = page.with_name(f"{page.stem}_certified_accuracy_vs_radius.png")
    shutil.copyfile(figure, picture)
    first = next((j.certify.cfg for j in jobs), None)
    machines = sorted({str(m) for m in src.index.df.get("tags.mrcert.machine", pd.Series(dtype=str)).dropna()})
    times = stage_times(src, jobs)
    lines = [
        f"# Results: mrcert's own pipeline, experiment `{experiment}`",
        "",
        f"Written by `{command}` from the runs of `make results` -- not by hand; rerun it to refresh.",
        "",
    ]
    if first is not None:
        lines += [
            f"Setup: {first.data.name} ({first.profile.name} profile: {first.data.num_classes} classes, "
            f"{first.data.protocol.train.per_class} training poses per class, model selection on "
            f"{_validation(first)}; "
            f"{first.data.protocol.test.per_class * first.data.num_classes} test images), {first.model.arch} from "
            f"scratch, {first.train.epochs} epochs at lr {first.train.lr}. Certified accuracy: fixed-n CERTIFY at "
            f"r = sigma (the paper's procedure), n0 = {first.task.n0}, n = {first.task.n}, alpha = {first.task.alpha}; "
            f"the sequential columns: sequential CERTIFY (looks from {first.task.look} samples, doubling, planned "
            f"to certify at least as often as fixed n = {first.task.n} at every pA; docs/method.md §7), an extra "
            "procedure the paper does not have; its samples per image are estimation samples, after the n0. "
            f"Smoothed benign accuracy: PREDICT with n = {jobs[0].smooth.cfg.task.n}; "
            "attack: 5 uniform perturbations within +-r (PREDICT with "
            f"n = {jobs[0].attack.cfg.task.n} at each). Every column covers "
            f"{_share(int(jobs[0].attack.cfg.task.skip))}, the same images in each. The paper's values are in "
            f"parentheses (MetaRoom, {arch_name(PAPER_ARCH)}, 500 training poses per class, 120 test images).",
            "",
        ]
    filled = any(c.filled for j in jobs for c in (j.certify, j.smooth, j.attack))
    lines += ["## Table 3, ours (paper)", ""]
    if filled:
        lines += [markdown(as_text(table)), ""]
    else:
        lines += [
            f"Not run yet: no finished certify, smooth or attack run of experiment `{experiment}` in this store "
            "(`make results` runs its stages; each finished stage is kept).",
            "",
        ]
    lines += ["## Certified accuracy against radius", ""]
    lines += [
        "Each curve is the exact step function of a fixed-n CERTIFY log (n = 1000 for every image, so the radius "
        "of an image does not depend on the radius asked for); sequential CERTIFY stops once r = sigma is decided "
        "and draws no curve here.",
        "",
    ]
    lines += [f"![certified accuracy against radius]({picture.name})", ""]
    if filled:
        lines += ["## The paper's findings, checked", ""]
        lines += [f"{i}. {text}" for i, text in enumerate(findings(src, jobs), 1)] + [""]
    models = base_models(src, jobs)
    if len(models):
        lines += [
            "## The base models",
            "",
            "Certified accuracy can be no higher than what the base model gets right under the smoothing noise, "
            "and the base models' own test accuracy bounds that: each model's accuracy on its validation poses "
            "(which selected `best.pt`) and on the test images (measured once).",
            "",
            markdown(as_text(models)),
            "",
        ]
    if views is not None:
        lines += [
            "## Test views beside the nearest training views",
            "",
            views[1],
            "",
            f"![test views and the nearest training views]({views[0].name})",
            "",
        ]
    curve = learning_curve.runs(src)
    if len(curve):
        plot = page.with_name(f"{page.stem}_learning_curve.png")
        save(learning_curve.figure(curve, learning_curve.histories(curve)), [plot])
        lines += [
            "## Learning curve: what it takes to generalise to the test views",
            "",
            "`make learning-curve` ("
            + ", then ".join(f"`mrcert -m experiment={e} task=train`" for e in learning_curve.EXPERIMENTS)
            + "): vanilla base classifiers of each architecture trained with each number of training poses per "
            "class, pose-separation rule and seed of the experiments' sweeps (the table counts the seeds), "
            "everything else as above. `every` keeps each angle of a training pose at least 15 degrees from that "
            "angle of every test pose (the paper's rule: no training pose has a roll within 15 degrees of the test "
            "poses' 0, a pitch within 15 of their 10, or a yaw within 15 of theirs); `any` only keeps training poses "
            "out of the box around each test pose. Validation and test accuracy of the selected `best.pt`; the "
            "test accuracy after every epoch is recorded for this figure only and selects nothing.",
            "",
            markdown(as_text(learning_curve.table(curve))),
            "",
            f"![learning curve]({plot.name})",
            "",
            why(models, curve),
            "",
        ]
    lines += side_by_side_section(src, page)
    lines += paper_profile_section(src)
    if filled:
        lines += [
            "## Time per stage",
            "",
            "Each run's wall-clock while a process worked on it (a run that was interrupted and resumed does not "
            "count the time it was down, unless a process of it was killed outright and could not log its time: "
            "then it counts from its start to its end), summed over the stage's runs: runs that ran side by side "
            "on one machine each "
            "count in full, so the sum is not the stage's elapsed time. Seconds per image from the per-image logs, "
            "each run's own pace (slower when runs shared a machine); the machines are the ones each run started on.",
            "",
            markdown(times.astype(str)),
            "",
        ]
    lines += [f"Machine: {'; '.join(machines) or 'unknown'}.", ""]
    lines += [
        "## Where the numbers come from",
        "",
        "Each cell is the run of exactly its composed config; `table3_certified_sources.csv` beside the tables "
        "names the run behind every number, with a link into MLflow.",
        "",
    ]
    page.write_text("\n".join(lines))
    return page
