"""A verification instance's result file, as the competition's harness reads it, and the promise
that it is written in time: ``timeout`` at the latest at the instance's limit (plus
:data:`RESERVE`), counted from the start of the process, whatever the process is doing then
(starting, importing, reading, checking, bounding).

The file is written once: the first of the answer and the watchdog to hold its lock (a
``.lock`` file beside it) and find it absent writes it; the other leaves it. A stale file is
removed when the instance starts, as the competition's harness removes it.

Light on purpose (no torch, no Hydra): ``mrcert task=verify task.result=R task.timeout=T``
starts its watchdog from the command line itself (:func:`watch_command_line`), before any
import, in a small process of its own -- a thread could not run while an import holds the
interpreter -- which also ends the launch :data:`GRACE` seconds after it wrote ``timeout``."""

from __future__ import annotations

import fcntl
import os
import signal
import threading
import time
from pathlib import Path

RESERVE = 0.5
"""Seconds of an instance's limit kept for writing its answer: the search stops this much before
the limit, and the watchdog writes ``timeout`` this much after it."""

GRACE = 2.0
"""Seconds a launch that the watchdog answered for is given to stop by itself before it is ended."""


def process_start() -> float:
    """When this process started, in ``time.time()`` seconds: read from the kernel's record of it
    (``/proc/self/stat``), so that a time limit counts the interpreter's own start and every
    import; where there is no such record, the time this module was first imported."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        ticks = int(fields[19])  # starttime: clock ticks after boot (field 22 of proc(5))
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return time.time() - uptime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return _IMPORTED


_IMPORTED = time.time()


def write_once(path: Path, text: str) -> bool:
    """Write ``text`` to ``path`` unless it is already there; whether it was written."""
    with open(path.with_name(path.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if path.exists():
            return False
        path.write_text(text)
        return True


class ResultFile:
    """An instance's result file (module docstring); ``deadline``: ``time.time()`` seconds at
    which ``timeout`` is written when no answer is, by a thread of this process (an instance
    answered in-process) unless a watchdog process already keeps it (``watched``)."""

    def __init__(self, path: Path, deadline: float, watched: bool = False):
        self.path = Path(path)
        self._timer = None
        if not watched:
            self.path.unlink(missing_ok=True)
            self._timer = threading.Timer(max(deadline - time.time(), 0.0), write_once, (self.path, "timeout\n"))
            self._timer.daemon = True
            self._timer.start()

    def write(self, text: str) -> str:
        """Write ``text`` unless an answer is already written; the result the file holds."""
        if self._timer is not None:
            self._timer.cancel()
        write_once(self.path, text)
        return self.path.read_text().split("\n", 1)[0]


_WATCHED: dict[Path, float] = {}


def result_file(path: Path, timeout: float) -> ResultFile:
    """The result file ``path`` of an instance limited to ``timeout`` seconds from the process's
    start, kept by the watchdog the command line started (once), else by a thread."""
    key = Path(path).absolute()
    deadline = _WATCHED.pop(key, None)
    if deadline is not None:
        return ResultFile(key, deadline, watched=True)
    return ResultFile(key, process_start() + timeout + RESERVE)


def watch_command_line(argv: list[str]) -> None:
    """Start the watchdog process of ``task=verify task.result=R task.timeout=T`` as typed,
    before the launch imports anything slow or composes its config (a command without all
    three, or with values that are not a path and a positive number, is left to the config's
    own checks)."""
    given = dict(a.split("=", 1) for a in argv if "=" in a and not a.startswith(("+", "~")))
    if given.get("task") != "verify" or not given.get("task.result") or "task.instances" in given:
        return
    try:
        timeout = float(given.get("task.timeout", ""))
    except ValueError:
        return
    if not (timeout > 0 and timeout < float("inf")) or given["task.result"] in ("null", "None"):
        return
    path = Path(given["task.result"]).absolute()
    try:
        path.unlink(missing_ok=True)  # a stale answer
    except OSError:
        return
    deadline = process_start() + timeout + RESERVE
    parent = os.getpid()
    if os.fork() == 0:  # the watchdog: waits for the deadline or the launch's end
        _watch(path, deadline, parent)
    _WATCHED[path] = deadline


def _watch(path: Path, deadline: float, parent: int) -> None:  # pragma: no cover - a child process
    try:
        os.setsid()  # not stopped by the launch's Ctrl-C
        while time.time() < deadline:
            if os.getppid() != parent:  # the launch ended before its limit
                os._exit(0)
            time.sleep(min(0.05, max(deadline - time.time(), 0.0)))
        if os.getppid() == parent and write_once(path, "timeout\n"):  # no answer by the deadline
            time.sleep(GRACE)
            if os.getppid() == parent:
                os.write(2, f"mrcert: the time limit passed; {path} says timeout\n".encode())
                os.kill(parent, signal.SIGTERM)
                time.sleep(1.0)
                if os.getppid() == parent:
                    os.kill(parent, signal.SIGKILL)
    finally:
        os._exit(0)
