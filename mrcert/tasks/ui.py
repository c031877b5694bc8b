"""``task=ui``: the MLflow UI on this store, opened on the experiment's runs page as the tables'
links point there; with ``task.screenshot=PNG``, that page as a fresh headless Chromium shows it
(a user's first visit), after which the UI stops. It runs outside any MLflow run: the store
gains no run from it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra.experiment import ui_link
from mrcert.infra.identity import Identity
from mrcert.infra.tasks import HELPER_IGNORES, Task
from mrcert.reporting.screenshot import screenshot, wait_until_up


def serve(tracking: DictConfig, port: int) -> subprocess.Popen:
    """``mlflow ui`` on the store ``tracking`` names (a SQLite file and its artifact folder)."""
    uri = str(tracking.uri)
    mlflow = Path(sys.executable).with_name("mlflow")
    artifacts = str(tracking.artifact_location)
    args = [str(mlflow), "ui", "--backend-store-uri", uri, "--default-artifact-root", artifacts]
    args += ["--artifacts-destination", artifacts, "--host", "127.0.0.1", "--port", str(port)]
    return subprocess.Popen(args, start_new_session=True)


class Ui(Task):
    summary = "the MLflow UI on the store, opened on the experiment's runs (task.screenshot: a picture of the page)"
    tracked = False
    identity = Identity(defines=("task",), ignores=(*HELPER_IGNORES, "task.port", "task.screenshot"))

    def run(self, cfg: DictConfig, ctx: Any) -> dict[str, Any]:
        if not str(cfg.tracking.uri).startswith("sqlite:///"):
            why = "task=ui serves a SQLite store; a tracking server has its own UI"
            raise MrcertError(f"tracking.uri={cfg.tracking.uri!r}: {why}")
        base = f"http://127.0.0.1:{cfg.task.port}"
        link = ui_link(cfg.tracking, base)
        proc = serve(cfg.tracking, int(cfg.task.port))
        try:
            if cfg.task.screenshot is None:
                print(f"MLflow UI: {link}", flush=True)
                proc.wait()
                return {}
            wait_until_up(base)
            png = screenshot(link, Path(str(cfg.task.screenshot)))
            print(f"{png}: {link}")
            return {}
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(timeout=30)
