"""A run's outputs sealed: what is read of a run later is the bytes the run recorded.

The files a task seals are its per-image log and, for ``task=train``, its checkpoints
(:func:`sealed_files`). A seal is the file's length and sha256 (``<bytes> <hex>``), recorded in
the run's MLflow tags as ``mrcert.sealed.<file name>``:

* while a run works, after every row it appends to its per-image log (the log's prefix so far:
  a resumed run adopts only rows that the run itself recorded, and drops an unrecorded tail);
* when it finishes, for every sealed file (:func:`seals`).

Whoever reads a finished run's file again checks it with :func:`verify` (the tables, ``task=gather``,
an evaluation's checkpoint); a mismatch is one line naming the run and the file. Runs that
finished before seals existed are sealed once, as their files then are
(:func:`mrcert.infra.key_migration.migrate_once`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from mrcert.errors import MrcertError
from mrcert.infra.identity import sha256_file

PREFIX = "mrcert.sealed."
"""Tag name of a file's seal, before the file's name (``mrcert.sealed.certify.tsv``)."""

CHECKPOINTS = ("best.pt", "last.pt")
"""The files ``task=train`` seals (its checkpoints)."""


def tag(name: str) -> str:
    return PREFIX + Path(name).name


def seal_file(path: Path | str) -> str:
    """The seal of a file's content."""
    size, digest = sha256_file(path)
    return f"{size} {digest}"


def sealed_files(task: str, log: str | None) -> tuple[str, ...]:
    """The files of a run of ``task`` (whose per-image log is ``log``) that it seals."""
    return (*((log,) if log else ()), *(CHECKPOINTS if task == "train" else ()))


def seals(folder: Path, names: tuple[str, ...]) -> dict[str, str]:
    """The seal tags of the files ``names`` that exist in ``folder``."""
    return {tag(n): seal_file(folder / n) for n in names if (folder / n).is_file()}


def verify(run_id: str, tags: dict[str, str], path: Path | str, name: str | None = None) -> None:
    """Raise a one-line error unless the file ``path`` (the run's file ``name``, by default the
    path's own name) is, byte for byte, the one the run ``run_id`` sealed."""
    name = Path(name or path).name
    recorded = tags.get(tag(name))
    if recorded is None:
        raise MrcertError(f"run {run_id} recorded no seal of its {name}: its content cannot be verified")
    actual = seal_file(path)
    if actual != recorded:
        raise MrcertError(
            f"run {run_id}'s {name} ({path}) is not the file the run recorded: {_words(actual)} where it "
            f"sealed {_words(recorded)}; it was changed after the run wrote it (rerun the run's command "
            "into a new store, or restore the file)"
        )


def sealed_prefix(recorded: str | None, data: bytes) -> bytes | None:
    """The part of ``data`` that the seal ``recorded`` covers (its first bytes, whose sha256 it
    names), or None when they differ from what was recorded (or nothing was)."""
    if not recorded:
        return None
    size, digest = recorded.split(" ", 1)
    head = data[: int(size)]
    return head if len(head) == int(size) and hashlib.sha256(head).hexdigest() == digest else None


def _words(seal: str) -> str:
    size, digest = seal.split(" ", 1)
    return f"{size} bytes, sha256 {digest[:12]}"
