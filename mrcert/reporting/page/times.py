"""The time each stage of the page's runs took: working wall-clock per run, summed per stage."""

from __future__ import annotations

import pandas as pd

from mrcert.reporting.cells import Cell
from mrcert.reporting.experiment_cells import ExperimentCells
from mrcert.reporting.writers import markdown


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
