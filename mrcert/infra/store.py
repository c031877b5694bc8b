"""The MLflow store, made safe against kills, races and outages.

* A new SQLite store comes into existence atomically: it is built complete in a temporary
  file and renamed into place, under a cross-process lock, so a kill during its creation
  leaves no half-made store and jobs started together on a new store never race to create
  its schema. A half-made store from an older version is detected and explained in one line.
* A tracking server is probed once, with a short timeout, before any work: an unreachable
  one fails in seconds with a line naming its URI (MLflow's own retries stay on for
  transient errors during a run).
* :class:`FileLock` is the cross-process lock: ``flock``, released by the kernel when its
  process dies, so a killed process never leaves a stale lock.
* :func:`uninterrupted` holds Ctrl-C and SIGTERM back while a write to the store completes: a
  SQLite transaction cut half-way keeps the store locked for the rest of the process, so the
  run could not be closed KILLED nor its working time logged.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import os
import signal
import socket
import sqlite3
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

from mrcert.errors import MrcertError

PROBE_TIMEOUT_S = 5.0


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """Run the block whole: SIGINT and SIGTERM arriving meanwhile are delivered when it ends
    (their handlers then run as they would have; the main thread only, where Python runs them)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[tuple[int, object]] = []
    numbers = (signal.SIGINT, signal.SIGTERM)
    before = {n: signal.signal(n, lambda signum, frame: held.append((signum, frame))) for n in numbers}
    try:
        yield
    finally:
        for n, handler in before.items():
            signal.signal(n, handler)
        for signum, frame in held[:1]:
            handler = before[signum]
            if callable(handler):
                handler(signum, frame)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)


class FileLock:
    """An exclusive ``flock`` on ``path`` (created if missing), naming its holder inside."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._file = None

    def acquire(self, blocking: bool = True) -> bool:
        """Take the lock; with ``blocking=False``, False (and nothing held) when another live
        process holds it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = open(self.path, "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except OSError:
            f.close()
            return False
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        f.flush()
        self._file = f
        return True

    def holder(self) -> str:
        try:
            return self.path.read_text().strip() or "unknown"
        except OSError:
            return "unknown"

    def release(self) -> None:
        if self._file is not None:
            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()
            self._file = None

    def __enter__(self) -> FileLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def is_locked(exc: BaseException) -> bool:
    """Whether ``exc`` (SQLite's, or MLflow's around it) says another process held the store's
    lock for longer than SQLite waits."""
    return "database is locked" in str(exc)


def locked(store: str) -> MrcertError:
    """The one-line error for a store that another process keeps locked."""
    return MrcertError(
        f"the MLflow store {store} stayed locked by another process: one suspended or stuck in a write "
        "(Ctrl-Z, SIGSTOP, a hung disk); resume or end it and rerun, or run many jobs at once through a "
        "tracking server (tracking=server)"
    )


@functools.cache
def schema_head() -> str:
    """The schema revision this MLflow writes (alembic head)."""
    from mlflow.store.db.utils import _get_latest_schema_revision

    return _get_latest_schema_revision()


@contextlib.contextmanager
def _opened(db: Path) -> Iterator[sqlite3.Connection]:
    """``db`` opened for writing, as MLflow opens it (a process killed inside a transaction leaves
    a journal that SQLite rolls back on opening); a lock another process keeps is the one-line
    :func:`locked` error, any other SQLite error is raised as it is."""
    try:
        with sqlite3.connect(f"file:{db}?mode=rw", uri=True) as conn:
            yield conn
    except sqlite3.Error as exc:
        if is_locked(exc):
            raise locked(f"sqlite:///{db}") from None
        raise


def schema_version(db: Path) -> str | None:
    """The alembic revision stamped in a SQLite store, or None when it has none."""
    try:
        with _opened(db) as conn:
            row = conn.execute("SELECT version_num FROM alembic_version").fetchone()
    except sqlite3.Error:
        return None
    return row[0] if row else None


def damage(db: Path) -> str | None:
    """What SQLite's ``quick_check`` finds wrong in ``db`` (damaged pages), or None (opened by
    :func:`_opened`: read-only, SQLite could not roll a killed transaction's journal back, and
    would call the store damaged)."""
    try:
        with _opened(db) as conn:
            found = [row[0] for row in conn.execute("PRAGMA quick_check")]
    except sqlite3.Error as exc:
        return str(exc)
    return None if found == ["ok"] else "; ".join(found[:2])


def check_sqlite_store(db: Path) -> None:
    """Raise a one-line error when ``db`` is damaged or not a complete store of this MLflow's schema."""
    broken = damage(db)
    if broken:
        raise MrcertError(
            f"the MLflow store {db} is damaged ({broken}): restore it from a backup, or move it aside "
            f"(mv {db} {db}.broken) to start a new store and rerun; the run folders keep their files"
        )
    version = schema_version(db)
    if version == schema_head():
        return
    uri = f"sqlite:///{db}"
    raise MrcertError(
        f"the MLflow store {db} is incomplete or of another MLflow version (schema {version or 'missing'}, "
        f"expected {schema_head()}): if a first run was killed while creating it, move it aside "
        f"(mv {db} {db}.broken) and rerun; if an older MLflow made it, back it up and run: mlflow db upgrade {uri}"
    )


def store_lock(db: Path) -> FileLock:
    """The cross-process lock of the SQLite store ``db``, held while its file or its experiment's
    settings are made or changed."""
    return FileLock(db.with_name(f".{db.name}.lock"))


def ensure_sqlite_store(db: Path) -> None:
    """Create the SQLite store ``db`` atomically if it does not exist, then check it."""
    db = Path(db)
    if not db.exists():
        with store_lock(db):
            if not db.exists():
                _build(db)
    check_sqlite_store(db)


def _build(db: Path) -> None:
    """Build a complete store in a temporary file and rename it into place (lock held)."""
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    for stale in db.parent.glob(f".{db.name}.tmp-*"):  # left by a killed builder: we hold the lock
        stale.unlink(missing_ok=True)
    from sqlalchemy.exc import OperationalError

    tmp = db.with_name(f".{db.name}.tmp-{os.getpid()}")
    try:
        store = SqlAlchemyStore(f"sqlite:///{tmp}", default_artifact_root=str(db.parent / ARTIFACT_ROOT))
        store.engine.dispose()
        os.replace(tmp, db)
    except (OperationalError, OSError) as exc:  # a full disk, a file size limit, a read-only folder
        tmp.unlink(missing_ok=True)
        reason = getattr(exc, "orig", None) or getattr(exc, "strerror", None) or exc
        raise MrcertError(
            f"cannot create the MLflow store {db} ({reason}): free some space in {db.parent} or point "
            "paths.outputs / MRCERT_OUTPUTS at another folder, then rerun"
        ) from None


@functools.cache
def probe_server(uri: str) -> None:
    """Fail in seconds, naming ``uri``, when no MLflow tracking server answers there."""
    url = uri.rstrip("/") + "/health"
    try:
        with urllib.request.urlopen(url, timeout=PROBE_TIMEOUT_S) as response:
            if response.status == 200:
                return
            reason = f"HTTP {response.status}"
    except urllib.error.HTTPError as exc:
        reason = f"HTTP {exc.code}"
    except (urllib.error.URLError, OSError) as exc:
        reason = str(getattr(exc, "reason", exc))
    raise MrcertError(
        f"cannot reach the MLflow tracking server at {uri} ({reason}); start it (e.g. `make server`) "
        "or point tracking.uri at a running one"
    )


ARTIFACT_ROOT = "mlartifacts"
"""The folder beside ``mlflow.db`` under which a store keeps its runs' artifacts."""


def run_artifacts(folder: Path, run_id: str) -> Path:
    """Where the store in ``folder`` keeps a run's artifacts (its own artifact root)."""
    return folder / ARTIFACT_ROOT / run_id / "artifacts"


def relocate_artifacts(db: Path, experiment_id: str, location: str) -> None:
    """Set the artifact location of experiment ``experiment_id`` in the SQLite store ``db`` (MLflow
    has no call for it): for a store folder that moved, whose experiment still names the folder it
    was made in, new runs' files go into its own folder (the caller holds the store's lock)."""
    with _opened(db) as conn:
        update = "UPDATE experiments SET artifact_location = ? WHERE experiment_id = ?"
        conn.execute(update, (location, int(experiment_id)))


def moved_artifact(run_id: str, path: str) -> Path | None:
    """A run's artifact in a store folder moved after its runs were made (copied off the machine
    that made them, or committed and cloned elsewhere): under :func:`run_artifacts` of the
    folder the tracking URI names, for a run whose recorded location is gone. None when it is
    not there either, or when the store is not a local folder."""
    import mlflow

    uri = mlflow.get_tracking_uri()
    if not uri.startswith("sqlite:///"):
        return None
    local = run_artifacts(Path(uri[len("sqlite:///") :]).parent, run_id) / path
    return local if local.exists() else None
