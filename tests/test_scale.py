"""Scale-out on existing engines: an MLflow server, Hydra's joblib and submitit launchers, shards."""

import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import mlflow
import pytest

from tests.conftest import run_cli
from tests.test_tables import COHEN

ROOT = Path(__file__).resolve().parent.parent
SIGMAS = "0.01,0.02,0.03,0.04,0.05,0.06,0.07,0.08"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server(tmp_path):
    """A real `mlflow server` on a loopback port, stopped after the test."""
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--backend-store-uri",
            f"sqlite:///{tmp_path / 'server.db'}",
            "--artifacts-destination",
            str(tmp_path / "server-artifacts"),
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.time() + 120
    while time.time() < deadline:
        try:
            if urllib.request.urlopen(f"{url}/health", timeout=2).status == 200:
                break
        except OSError:
            time.sleep(0.5)
    else:
        proc.kill()
        pytest.fail("mlflow server did not start")
    yield url
    proc.terminate()
    proc.wait(timeout=30)


def import_args(tmp_path) -> list[str]:
    log = tmp_path / "cohen.tsv"
    log.write_text(COHEN)
    return ["task=import", f"task.path={log}", "task.dataset=metaroom_synth", "motion=tz"]


def children_of_one_parent(client):
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    (parent,) = [r for r in runs if r.data.tags.get("mrcert.multirun") == "parent"]
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    return parent, children, runs


@pytest.mark.slow
def test_eight_job_multirun_against_a_tracking_server(server, tmp_path):
    proc = run_cli(
        [
            "-m",
            *import_args(tmp_path),
            f"motion.sigma={SIGMAS}",
            "tracking=server",
            f"tracking.uri={server}",
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
        ],
        tmp_path / "out",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    mlflow.set_tracking_uri(server)
    client = mlflow.MlflowClient()
    parent, children, runs = children_of_one_parent(client)
    assert parent.info.status == "FINISHED" and len(children) == 8 and len(runs) == 9
    assert sorted(float(c.data.params["motion.sigma"]) for c in children) == [0.01 * k for k in range(1, 9)]
    for c in children:
        assert c.info.status == "FINISHED" and c.info.experiment_id == parent.info.experiment_id
        assert c.data.metrics["certified_accuracy"] == pytest.approx(
            0.4 if float(c.data.params["motion.sigma"]) <= 0.1 else 0.0
        )
        assert {"num_images", "clean_accuracy", "abstain_rate", "mean_radius"} <= set(c.data.metrics)
    assert client.get_experiment(parent.info.experiment_id).name == "mrcert"


@pytest.mark.slow
def test_submitit_local_launcher(tmp_path):
    proc = run_cli(
        [
            "-m",
            *import_args(tmp_path),
            "motion.sigma=0.05,0.1",
            "hydra/launcher=submitit_local",
            "hydra.launcher.timeout_min=10",
        ],
        tmp_path / "out",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'out' / 'mlflow.db'}")
    parent, children, _ = children_of_one_parent(mlflow.MlflowClient())
    assert parent.info.status == "FINISHED" and len(children) == 2
    assert all(c.info.status == "FINISHED" and c.data.metrics["num_images"] == 5 for c in children)
