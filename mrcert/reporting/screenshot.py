"""A page of the MLflow UI as a headless Chromium with a fresh profile shows it (what a user's
first visit shows): ``mrcert task=ui task.screenshot=PNG``, which ``make figures`` runs for the
README's picture of the runs page.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

from mrcert.errors import MrcertError

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
# Chromium in a closed network: no background connections, no first-run dialogs.
QUIET = (
    "--headless",
    "--disable-gpu",
    "--hide-scrollbars",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


def browser() -> str:
    for name in BROWSERS:
        if found := shutil.which(name):
            return found
    raise MrcertError(f"no headless browser ({', '.join(BROWSERS)}): on Debian, 'sudo apt-get install chromium'")


def wait_until_up(base: str, seconds: float = 90) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"{base}/health", timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    raise MrcertError(f"the MLflow UI at {base} did not answer within {seconds:.0f} s")


def screenshot(link: str, png: Path, size: str = "1920,1000", budget_ms: int = 20000) -> Path:
    """``link`` rendered by a fresh headless Chromium profile into ``png`` (the time budget lets
    the page's scripts load the runs; without it the page is MLflow's loading skeleton)."""
    with tempfile.TemporaryDirectory() as profile:
        args = [browser(), *QUIET, f"--user-data-dir={profile}", f"--window-size={size}"]
        args += [f"--virtual-time-budget={budget_ms}", f"--screenshot={png.resolve()}", link]
        if os.geteuid() == 0:  # Chromium refuses to run as root inside its sandbox
            args.insert(1, "--no-sandbox")
        subprocess.run(args, check=True, capture_output=True, timeout=180)
    return png
