"""The evidence page (``docs/results.md``): an experiment's Table 3 beside the paper's, the
certified-accuracy figure, the paper's qualitative findings checked with our numbers, and the
time each stage took -- all computed from the runs that fill the cells, never by hand.

A short composer: each section is built by its own module under :mod:`mrcert.reporting.page`
(the jobs, findings and base models; the learning curve; the side-by-side; the sequential
attack; the paper's profile; the stage times; the commands read from the Makefile), and the page
is their context rendered with the template ``mrcert/reporting/templates/results.md``.

Written by ``make reproduce-tables`` (its last stage: ``mrcert task=tables task.page=docs/results.md``).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd

from mrcert.reporting import paper_results
from mrcert.reporting.experiment_cells import SOURCE_COLUMNS, ExperimentCells
from mrcert.reporting.page.commands import make_stage
from mrcert.reporting.page.curve import learning_curve_section
from mrcert.reporting.page.jobs import PAPER_ARCH, base_models, findings, jobs_of, record_models, setup, verdict
from mrcert.reporting.page.paper_profile import paper_profile_section
from mrcert.reporting.page.sequential_attack import sequential_attack_section
from mrcert.reporting.page.side_by_side import side_by_side_section
from mrcert.reporting.page.times import STAGE_COLUMNS, profile_hours, shown_times, stage_times
from mrcert.reporting.paper_tables import REPRODUCTION, arch_name
from mrcert.reporting.writers import as_text, markdown

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
    env.globals["verdict"] = verdict
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
    curve_section = learning_curve_section(src, jobs, models, page)
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
