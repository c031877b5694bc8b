"""The certify log: Cohen et al.'s / the paper authors' TSV, plus our extra columns.

Columns ``idx label predict radius correct time`` first (radius at full precision, predict
-1 for abstain, time as ``H:MM:SS.ffffff``), then ``count_a n0 n p_a_lower sigma axis
seconds``. Rows are appended and flushed one by one; a restarted run keeps every complete
row and drops a torn last line. Metrics and the certified-accuracy curve are computed from
the exact step function of the radii.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pandas as pd

from mrcert.errors import MrcertError
from mrcert.infra.tasks import CERTIFY_COLUMNS, TASKS

log = logging.getLogger(__name__)

COHEN_COLUMNS = list(CERTIFY_COLUMNS)
COLUMNS = list(TASKS["certify"].columns)


def format_row(row: dict, columns: list[str]) -> str:
    """One TSV line; floats in shortest round-trip form (full precision)."""
    values = dict(row)
    if "time" in columns:
        values["time"] = str(datetime.timedelta(seconds=float(row["seconds"])))
    return "\t".join(repr(v) if isinstance(v, float) else str(v) for v in (values[c] for c in columns))


class ResultLog:
    """An append-only per-image TSV (first column ``idx``) that a restarted run resumes.

    A log belongs to one run: ``owner`` (the run key and, when tracked, the MLflow run id) is
    written beside it as ``<log>.owner``. Rows are adopted only by the run that wrote them; a
    log of any other run found in the folder (a reused ``hydra.run.dir``, an overwritten
    checkpoint) is moved aside to ``set_aside/`` before the first row, never mixed, and is
    taken back when its own run resumes there."""

    def __init__(self, path: Path, columns: list[str] = COLUMNS, owner: dict[str, str | None] | None = None):
        self.path, self.columns = Path(path), list(columns)
        self.owner = owner
        self._claimed = owner is None

    @property
    def owner_path(self) -> Path:
        return self.path.with_name(self.path.name + ".owner")

    def _claim(self) -> None:
        """Make the file this run's: set aside another run's log, take back this run's own."""
        if self._claimed:
            return
        theirs = _read_owner(self.owner_path)
        if theirs != self.owner and (self.path.exists() or self.owner_path.exists()):
            run = (theirs or {}).get("run_id") or "unknown-run"
            aside = self.path.parent / SET_ASIDE / f"{run}_{time.strftime('%Y%m%d-%H%M%S')}_{os.getpid()}"
            aside.mkdir(parents=True, exist_ok=True)
            for f in (self.path, self.owner_path):
                if f.exists():
                    os.replace(f, aside / f.name)
            log.warning(
                "%s held rows of another run (%s); moved them to %s: a run only adopts its own rows",
                self.path,
                _describe(theirs),
                aside,
            )
        if not self.path.exists():  # this run's rows may have been set aside by another run
            kept = (self.path.parent / SET_ASIDE).glob(f"*/{self.owner_path.name}")
            mine = sorted((k for k in kept if _read_owner(k) == self.owner), reverse=True)
            newest = next((k.parent for k in mine if (k.parent / self.path.name).exists()), None)
            if newest is not None:
                os.replace(newest / self.path.name, self.path)
                log.info("took back this run's own rows from %s", newest)
            for k in mine:  # taken back (or never held rows): no second copy left behind
                k.unlink()
        tmp = self.owner_path.with_name(self.owner_path.name + f".tmp-{os.getpid()}")
        tmp.write_text(json.dumps(self.owner, sort_keys=True) + "\n")
        os.replace(tmp, self.owner_path)
        self._claimed = True

    def done(self) -> set[int]:
        """Indices already done by this run; truncates a torn last line left by a crash."""
        self._claim()
        if not self.path.exists():
            return set()
        text = self.path.read_text()
        if text and not text.endswith("\n"):
            text = text[: text.rfind("\n") + 1]
            self.path.write_text(text)
        lines = text.splitlines()
        if not lines:
            return set()
        header = lines[0].split("\t")
        if header != self.columns[: len(header)]:
            raise MrcertError(f"{self.path} has header {lines[0]!r}, expected {' '.join(self.columns)}")
        if len(header) < len(self.columns):  # older code wrote fewer columns: its rows stay, those cells empty
            self.path.write_text("\n".join(["\t".join(self.columns), *lines[1:]]) + "\n")
        return {int(line.split("\t", 1)[0]) for line in lines[1:]}

    def append(self, row: dict) -> None:
        self._claim()
        new = not self.path.exists() or self.path.stat().st_size == 0
        with open(self.path, "a") as f:
            if new:
                f.write("\t".join(self.columns) + "\n")
            f.write(format_row(row, self.columns) + "\n")
            f.flush()


SET_ASIDE = "set_aside"
"""Where a run folder keeps per-image logs of other runs that were found in it."""


def _read_owner(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _describe(owner: dict | None) -> str:
    if not owner:
        return "no owner recorded"
    return f"run {owner.get('run_id') or '(untracked)'}, key {owner.get('run_key')}"


def read_log(path: Path, required: list[str] = COHEN_COLUMNS[:5]) -> pd.DataFrame:
    """A per-image log sorted by idx; by default a certify log in Cohen's format, with or
    without the extra columns."""
    path = Path(path)
    if not path.is_file():
        raise MrcertError(f"log {str(path)!r} does not exist")
    try:
        df = pd.read_csv(path, sep="\t", dtype={"time": str})
    except Exception as exc:
        raise MrcertError(f"cannot parse log {str(path)!r}: {exc}") from None
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise MrcertError(f"log {str(path)!r} lacks the columns {missing} (expected: {' '.join(required)} ...)")
    return df.sort_values("idx").reset_index(drop=True)


def merge_logs(paths: Iterable[Path]) -> pd.DataFrame:
    """Shards (or pieces) of one certification merged into one table; an index twice is an error."""
    return concat_logs([read_log(p) for p in paths])


def concat_logs(logs: list[pd.DataFrame]) -> pd.DataFrame:
    """Logs of disjoint image sets as one, sorted by idx; an index twice is an error."""
    df = pd.concat(logs, ignore_index=True)
    dup = df["idx"][df["idx"].duplicated()]
    if len(dup):
        raise MrcertError(f"test images {sorted(set(dup.tolist()))[:10]} appear in more than one log")
    return df.sort_values("idx").reset_index(drop=True)


def certified(df: pd.DataFrame, radius: float) -> pd.Series:
    """Per image: a correct prediction certified with radius >= ``radius`` (an abstention never is)."""
    return (df["correct"] == 1) & (df["radius"] >= radius) & (df["predict"] >= 0)


def certified_accuracy(df: pd.DataFrame, radius: float) -> float:
    """Fraction of images with a correct prediction and radius >= ``radius`` (abstain = wrong)."""
    if len(df) == 0:
        return float("nan")
    return float(certified(df, radius).mean())


def radius_grid(step: float, max_radius: float) -> np.ndarray:
    """``k * step`` for k = 0..K (multiplied, never accumulated)."""
    k = np.arange(int(np.floor(max_radius / step + 1e-9)) + 1)
    return k * step


def curve(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """The exact step function: certified accuracy is ``acc[i]`` on ``(r[i-1], r[i]]``.

    Returns the distinct radii of correct predictions (with 0 first) and the accuracy at each.
    """
    ok = df[(df["correct"] == 1) & (df["predict"] >= 0)]["radius"].to_numpy(float)
    radii = np.unique(np.concatenate([[0.0], ok]))
    acc = np.array([(ok >= r).sum() for r in radii]) / max(len(df), 1)
    return radii, acc


def grid(df: pd.DataFrame, step: float, max_radius: float) -> pd.DataFrame:
    """The certified accuracy at each radius of :func:`radius_grid`."""
    radii = radius_grid(step, max_radius)
    return pd.DataFrame({"radius": radii, "certified_accuracy": [certified_accuracy(df, r) for r in radii]})


def metrics(df: pd.DataFrame, radius: float, step: float, max_radius: float) -> tuple[dict[str, float], pd.DataFrame]:
    """Headline metrics and the certified accuracy over the radius grid."""
    abstain = df["predict"] < 0
    correct = (df["correct"] == 1) & ~abstain
    table = grid(df, step, max_radius)
    out = {
        "num_images": float(len(df)),
        "clean_accuracy": float(correct.mean()) if len(df) else float("nan"),
        "certified_accuracy": certified_accuracy(df, radius),
        "abstain_rate": float(abstain.mean()) if len(df) else float("nan"),
        "mean_radius": float(df.loc[~abstain, "radius"].mean()) if (~abstain).any() else 0.0,
        "average_certified_radius": float((df["radius"] * correct).mean()) if len(df) else float("nan"),
    }
    if "seconds" in df.columns:
        out["seconds_per_image"] = float(df["seconds"].mean())
    return out, table
