"""A screenshot of the MLflow UI exactly as ``make ui`` serves and links it, taken by a headless
Chromium with a fresh profile (what a user's first visit shows):

    python -m mrcert.reporting.screenshot OUTPUTS PNG [--port 5077]

``make figures`` uses it for the README's picture of the runs page.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

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
    raise SystemExit(f"no headless browser ({', '.join(BROWSERS)}): on Debian, 'sudo apt-get install chromium'")


def serve(outputs: Path, port: int) -> tuple[subprocess.Popen, str]:
    """``make ui`` on ``outputs``: the server's process and the link it prints."""
    proc = subprocess.Popen(
        ["make", "--no-print-directory", "ui", f"OUTPUTS={outputs}", f"PORT={port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    for line in proc.stdout:
        if line.startswith("MLflow UI: "):
            return proc, line.split(": ", 1)[1].strip()
    raise SystemExit(f"make ui exited ({proc.wait()}) without printing its link")


def wait_until_up(base: str, seconds: float = 90) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"{base}/health", timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    raise SystemExit(f"the MLflow UI at {base} did not answer within {seconds:.0f} s")


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outputs", type=Path, help="the store's outputs folder (holding mlflow.db)")
    parser.add_argument("png", type=Path)
    parser.add_argument("--port", type=int, default=5077)
    args = parser.parse_args(argv)
    proc, link = serve(args.outputs.resolve(), args.port)
    try:
        wait_until_up(link.split("/#/")[0])
        screenshot(link, args.png)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    print(f"{args.png}: {link}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
