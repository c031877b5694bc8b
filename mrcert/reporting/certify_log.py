"""The certify log: Cohen et al.'s / the paper authors' TSV, plus our extra columns.

Columns ``idx label predict radius correct time`` first (radius at full precision, predict
-1 for abstain, time as ``H:MM:SS.ffffff``), then ``count_a n0 n p_a_lower sigma axis
seconds projected margin radius_unit sigma_unit`` (docs/tasks.md). Rows are appended and
flushed one by one; a restarted run keeps every complete row and drops a torn last line.
Metrics and the certified-accuracy curve are computed from the exact step function of the radii.
"""

from __future__ import annotations

import datetime
import hashlib
import logging
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from mrcert.errors import MrcertError
from mrcert.infra.log_keys import CHECK, check_value, owner_path, read_owner, replace_text, write_owner
from mrcert.infra.seals import sealed_prefix, tag

log = logging.getLogger(__name__)

COHEN_COLUMNS = ["idx", "label", "predict", "radius", "correct", "time"]
"""The columns of Cohen et al.'s certify logs, which an imported log needs and ours begins with."""
COLUMNS = [
    *COHEN_COLUMNS,
    "count_a",
    "n0",
    "n",
    "p_a_lower",
    "sigma",
    "axis",
    "seconds",
    "projected",
    "margin",
    "radius_unit",
    "sigma_unit",
]
"""The columns of a certify run's log (``task=certify``)."""


def format_row(row: dict, columns: list[str]) -> str:
    """One TSV line; floats in shortest round-trip form (full precision)."""
    values = dict(row)
    if "time" in columns:
        values["time"] = str(datetime.timedelta(seconds=float(row["seconds"])))
    return "\t".join(repr(v) if isinstance(v, float) else str(v) for v in (values[c] for c in columns))


class ResultLog:
    """An append-only per-image TSV (first column ``idx``, last column ``check``) that a
    restarted run resumes.

    A log belongs to one run: ``owner`` (the run key and, when tracked, the MLflow run id) is
    written beside it as ``<log>.owner``. Rows are adopted only by the run that wrote them; a
    log of any other run found in the folder (a reused ``hydra.run.dir``, an overwritten
    checkpoint) is moved aside to ``set_aside/`` before the first row, never mixed, and is
    taken back when its own run resumes there. Every row carries a check value bound to the run
    key (:func:`check_value`); on resume a row is adopted only when it has every column, its
    check value, an index of this run's images and that image's label. Any other row (a torn
    write, a bad copy, a hand edit) is set aside with its reason and its image computed again.

    A tracked run also seals its log as it writes it (``record``: after every row, the log's
    length and sha256 into the run, :mod:`mrcert.infra.seals`); resumed, it adopts only the
    rows within the seal the run last recorded (``recorded``): a log edited since, even with
    check values made anew, is set aside whole (a run begun before logs were sealed recorded
    none: its rows are checked as above)."""

    def __init__(
        self,
        path: Path,
        columns: list[str] = COLUMNS,
        owner: dict[str, str | None] | None = None,
        record: Callable[[str, str], None] | None = None,
        recorded: str | None = None,
    ):
        self.path = Path(path)
        self.columns = [c for c in columns if c != CHECK]
        self.owner = owner
        self.key = str((owner or {}).get("run_key") or "")
        self._claimed = owner is None
        self.record, self.recorded = record, recorded
        self._digest = None  # the running sha256 of the log as written (a tracked run)
        self._size = 0

    @property
    def owner_path(self) -> Path:
        return owner_path(self.path)

    def _claim(self) -> None:
        """Make the file this run's: set aside another run's log, take back this run's own."""
        if self._claimed:
            return
        theirs = read_owner(self.owner_path)
        if theirs != self.owner and (self.path.exists() or self.owner_path.exists()):
            aside = self._aside((theirs or {}).get("run_id") or "unknown-run")
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
            mine = sorted((k for k in kept if read_owner(k) == self.owner), reverse=True)
            newest = next((k.parent for k in mine if (k.parent / self.path.name).exists()), None)
            if newest is not None:
                os.replace(newest / self.path.name, self.path)
                log.info("took back this run's own rows from %s", newest)
            for k in mine:  # taken back (or never held rows): no second copy left behind
                k.unlink()
        write_owner(self.owner_path, self.owner)
        self._claimed = True

    def _aside(self, name: str) -> Path:
        aside = self.path.parent / SET_ASIDE / f"{name}_{time.strftime('%Y%m%d-%H%M%S')}_{os.getpid()}"
        aside.mkdir(parents=True, exist_ok=True)
        return aside

    def done(self, expected: Mapping[int, int] | None = None) -> set[int]:
        """Indices already done by this run. ``expected``: each of this run's image indices with
        its label in the data set; a row of any other index, of another label, without every
        column or whose check value fails is set aside (``set_aside/rejected_*``), never adopted.
        A torn last line left by a crash is dropped; rows of older code with fewer columns are
        kept (their new cells empty)."""
        self._claim()
        if not self.path.exists():
            return set()
        data, rejected = self._sealed(self.path.read_bytes())
        text = data.decode(errors="replace")
        lines = text.split("\n")[:-1]  # the text after the last newline: empty, or a line torn by a crash
        if not lines:
            self._set_aside(rejected)
            self.path.write_text("")
            self._seal()
            return set()
        header = lines[0].split("\t")
        own = header[:-1] if header[-1] == CHECK else header
        if own != self.columns[: len(own)]:
            raise MrcertError(f"{self.path} has header {lines[0]!r}, expected {' '.join([*self.columns, CHECK])}")
        kept, seen = [], set()
        for line in lines[1:]:
            cells = line.split("\t")
            reason = self._reason(cells, header, expected, seen)
            if reason:
                rejected.append(f"{reason}\t{line}")
                continue
            seen.add(int(cells[0]))
            row = dict(zip(own, cells[:-1], strict=True))
            kept.append(self._line("\t".join(row.get(c, "") for c in self.columns)))
        rewritten = ["\t".join([*self.columns, CHECK]), *kept]
        if rewritten != lines or not text.endswith("\n") or len(data) < self.path.stat().st_size:
            self._set_aside(rejected)
            replace_text(self.path, "\n".join(rewritten) + "\n")
            self._seal()
        return seen

    def _sealed(self, data: bytes) -> tuple[bytes, list[str]]:
        """The part of the log ``data`` that this run sealed as it wrote it, and every other
        complete line with its reason (all of ``data`` when the run is not tracked)."""
        if self.record is None or self.recorded is None:  # untracked, or begun before runs sealed their logs
            return data, []
        head = sealed_prefix(self.recorded, data)
        if head is None:
            why = "not the log this run recorded as it wrote it"
            head = data[: data.find(b"\n") + 1]  # the header: checked as ever
        else:
            why = "written after this run last recorded its log"
        rest = data[len(head) :].decode(errors="replace").split("\n")[:-1]  # a torn last line: dropped as ever
        return head, [f"{why}\t{line}" for line in rest if line]

    def _set_aside(self, rejected: list[str]) -> None:
        if not rejected:
            return
        aside = self._aside("rejected") / f"{self.path.stem}.rejected.tsv"
        aside.write_text("\n".join(["reason\tline", *rejected]) + "\n")
        log.warning(
            "%s: %d rows failed validation (first: %s); set aside to %s, their images are computed again",
            self.path,
            len(rejected),
            rejected[0].split("\t", 1)[0],
            aside,
        )

    def _seal(self, appended: bytes | None = None) -> None:
        """Record the log as it now is in the run (a tracked run only): hashed whole once, then
        carried on with each ``appended`` row, so a long log costs no more per row than a short one."""
        if self.record is None:
            return
        if appended is None or self._digest is None:
            data = self.path.read_bytes()
            self._digest, self._size = hashlib.sha256(data), len(data)
        else:
            self._digest.update(appended)
            self._size += len(appended)
        self.recorded = f"{self._size} {self._digest.hexdigest()}"
        self.record(tag(self.path.name), self.recorded)

    def _reason(self, cells: list[str], header: list[str], expected: Mapping[int, int] | None, seen: set[int]) -> str:
        """Why a row cannot be adopted ('' when it can)."""
        if header[-1] != CHECK:
            return "written without a check value"
        if len(cells) != len(header):
            return f"{len(cells)} cells where the header has {len(header)}"
        if check_value(self.key, "\t".join(cells[:-1])) != cells[-1]:
            return "its check value does not match the row and this run's key"
        try:
            idx = int(cells[0])
        except ValueError:
            return f"idx {cells[0]!r} is not an integer"
        if idx in seen:
            return f"image {idx} is logged twice"
        if expected is not None and idx not in expected:
            return f"image {idx} is not one of this run's"
        if expected is not None and "label" in header:
            label = cells[header.index("label")]
            if label != str(expected[idx]):
                return f"label {label} where the data set's label of image {idx} is {expected[idx]}"
        return ""

    def _line(self, body: str) -> str:
        return f"{body}\t{check_value(self.key, body)}"

    def append(self, row: dict) -> None:
        self._claim()
        new = not self.path.exists() or self.path.stat().st_size == 0
        text = (
            ("\t".join([*self.columns, CHECK]) + "\n" if new else "") + self._line(format_row(row, self.columns)) + "\n"
        )
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(text)
            f.flush()
        self._seal(None if new else text.encode("utf-8"))


SET_ASIDE = "set_aside"
"""Where a run folder keeps per-image logs of other runs that were found in it."""


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


def certified_interval(df: pd.DataFrame, radius: float, level: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) interval at ``level`` for the certified accuracy at ``radius``, the
    log's images taken as a sample of the test views (NaN, NaN for an empty log)."""
    if len(df) == 0:
        return float("nan"), float("nan")
    from scipy.stats import binomtest

    ci = binomtest(int(certified(df, radius).sum()), len(df)).proportion_ci(confidence_level=level, method="exact")
    return float(ci.low), float(ci.high)


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


def samples(log: pd.DataFrame, n: int) -> pd.Series:
    """Samples classified per image: the log's ``n`` (estimation samples, ``n`` per estimate: one
    estimate per frame that pixel-wise smoothing certified) and ``n0`` class-guess samples per
    estimate (none logged: none drawn)."""
    n0 = log["n0"] if "n0" in log.columns else 0
    return log["n"] + n0 * np.ceil(log["n"] / n).clip(lower=1)
