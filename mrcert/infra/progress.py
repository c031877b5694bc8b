"""Progress as its reader sees it: a live bar when a person watches (stderr is a terminal), and
otherwise -- CI, SLURM logs, Hydra job logs -- a log line every ``interval`` seconds instead of a
redraw every 0.1 s."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")
log = logging.getLogger("mrcert.progress")

INTERVAL_S = 10.0


def progress(items: Iterable[T], desc: str, total: int | None = None, interval: float = INTERVAL_S) -> Iterator[T]:
    """``items``, reporting how far along they are."""
    total = total if total is not None else (len(items) if hasattr(items, "__len__") else None)
    if sys.stderr.isatty():
        from tqdm import tqdm

        yield from tqdm(items, desc=desc, total=total, leave=False)
        return
    start = last = time.perf_counter()
    done = 0
    for item in items:
        yield item
        done += 1
        now = time.perf_counter()
        if now - last >= interval:
            last = now
            rate = done / (now - start)
            eta = f", about {(total - done) / rate:.0f} s left" if total and rate > 0 else ""
            log.info("%s: %d%s done (%.2f/s%s)", desc, done, f"/{total}" if total else "", rate, eta)
