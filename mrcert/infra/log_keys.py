"""A run's per-image log is bound to its run key: each row ends in a check value (a hash of the
key and the row), and ``<log>.owner`` beside the log names the run key and run id that wrote it.
The log itself (writing, resuming, validating rows) is :class:`mrcert.reporting.certify_log.ResultLog`;
here is what ties it to a key, and how a log follows its run when the run's key is migrated."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

CHECK = "check"
"""The last column of every per-image log a run writes: the row's check value."""


def check_value(key: str, line: str) -> str:
    """The check value of a log line (its cells before the check) written for run key ``key``:
    a hash of both, so that a row changed, cut short or copied from another run's log fails."""
    return hashlib.sha256(f"{key}\n{line}".encode()).hexdigest()[:16]


def owner_path(log: Path) -> Path:
    return log.with_name(log.name + ".owner")


def read_owner(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def replace_text(path: Path, text: str) -> None:
    """Write ``path`` whole or not at all: a crash never leaves it half written."""
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_owner(path: Path, owner: dict) -> None:
    replace_text(path, json.dumps(owner, sort_keys=True) + "\n")


def rekey(log: Path, run_id: str, old: str, new: str) -> bool:
    """Bind the log of run ``run_id`` written under run key ``old`` to key ``new``: every row
    whose check value holds for ``old`` gets its value for ``new`` (any other row is left to
    fail validation as it would have), and the owner file names ``new``. False when the log is
    not that run's under that key (nothing is changed)."""
    owner = read_owner(owner_path(log))
    if owner != {"run_key": old, "run_id": run_id} or not log.is_file():
        return False
    lines = log.read_text().split("\n")
    for i, line in enumerate(lines[1:], start=1):
        body, _, check = line.rpartition("\t")
        if body and check == check_value(old, body):
            lines[i] = f"{body}\t{check_value(new, body)}"
    replace_text(log, "\n".join(lines))
    write_owner(owner_path(log), {"run_key": new, "run_id": run_id})
    return True
