"""The side-by-side section: camera motion smoothing beside pixel-wise smoothing, bound
propagation and image enumeration (:mod:`mrcert.reporting.side_by_side` holds the analysis)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from mrcert.reporting import side_by_side
from mrcert.reporting.experiment_cells import ExperimentCells
from mrcert.reporting.page.commands import make_stage
from mrcert.reporting.page.jobs import share_of
from mrcert.reporting.paper_results import PIXELWISE_REPORTED
from mrcert.reporting.plots import save
from mrcert.reporting.writers import as_text, markdown


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
        "share": share_of(int(pixelwise.iloc[0]["skip"])),
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
