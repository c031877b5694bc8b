"""Scale-out on existing engines: an MLflow server, Hydra's joblib and submitit launchers, shards."""

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import mlflow
import pandas as pd
import pytest

from tests.conftest import run_cli
from tests.test_tables import COHEN

ROOT = Path(__file__).resolve().parent.parent
SIGMAS = "0.01,0.02,0.03,0.04,0.05,0.06,0.07,0.08"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def mlflow_server(backend_uri: str, artifacts: Path):
    """A real `mlflow server` on a loopback port for ``backend_uri``, stopped afterwards."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", backend_uri,
         "--artifacts-destination", str(artifacts), "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
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
    try:
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@pytest.fixture
def server(tmp_path):
    with mlflow_server(f"sqlite:///{tmp_path / 'server.db'}", tmp_path / "server-artifacts") as url:
        yield url


def postgres_bin() -> Path | None:
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"))
    return found[-1].parent if found else None


@pytest.fixture
def postgres(tmp_path):
    """A throwaway PostgreSQL server (Debian's package) with a database ``mlflow``; its URI."""
    bin_dir = postgres_bin()
    if bin_dir is None:
        pytest.skip("PostgreSQL is not installed (Debian: apt-get install postgresql)")
    pytest.importorskip("psycopg", reason="the postgres extra is not installed (pip install -e '.[postgres]')")
    # Its own folder: the postgres user must reach it (pytest's tmp folders are private to root).
    home = Path(tempfile.mkdtemp(prefix="mrcert-pg-"))
    data, port = home / "pgdata", free_port()
    data.mkdir()
    as_user = []
    if os.geteuid() == 0:  # PostgreSQL refuses to run as root: use the package's own user
        home.chmod(0o755)
        shutil.chown(home, "postgres")
        shutil.chown(data, "postgres")
        as_user = ["runuser", "-u", "postgres", "--"]
    run = lambda *cmd: subprocess.run([*as_user, *cmd], check=True, capture_output=True, text=True)  # noqa: E731
    run(str(bin_dir / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres")
    run(str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(home / "pg.log"), "-w", "start",
        "-o", f"-p {port} -k {home} -c listen_addresses=127.0.0.1")  # fmt: skip
    try:
        run(str(bin_dir / "createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "postgres", "mlflow")
        yield f"postgresql://postgres@127.0.0.1:{port}/mlflow"
    finally:
        run(str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop")
        shutil.rmtree(home, ignore_errors=True)


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


@pytest.mark.slow
def test_the_postgresql_recipe_a_4_job_multirun_through_mlflow_server_and_its_table(postgres, tmp_path):
    """The cluster recipe of docs/tracking.md for real: PostgreSQL, `mlflow server` on it, a 4-job multirun
    of evaluations through the server, and the table built from those runs."""
    from tests.test_tables import DEMO, SETTINGS

    with mlflow_server(postgres, tmp_path / "artifacts") as url:
        server = ["tracking=server", f"tracking.uri={url}"]
        # ++: a key of the swept tasks, not of the default task Hydra composes the sweep's own config with.
        for sweep in (["task=train", "model.variant=vanilla,augmented"], ["task=smooth,certify", "++task.max=2"]):
            proc = run_cli(["-m", *DEMO, *server, *sweep], tmp_path)
            assert proc.returncode == 0, proc.stderr[-3000:]
        client = mlflow.MlflowClient(url)
        runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
        jobs = [r for r in runs if r.data.tags.get("mrcert.multirun") != "parent"]
        assert len(jobs) == 6 and all(r.info.status == "FINISHED" for r in jobs)  # 2 train + 4 evaluation jobs
        assert sorted(r.data.tags["mrcert.task"] for r in jobs if r.data.tags["mrcert.task"] != "train") == [
            "certify", "certify", "smooth", "smooth"
        ]  # fmt: skip
        quoted = ",".join(f"'{o}'" for o in [*SETTINGS, "task.max=2"])
        proc = run_cli(["task=tables", "task.experiment=demo", f"task.overrides=[{quoted}]", *server], tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
    table = pd.read_csv(tmp_path / "tables" / "table3_certified.csv", keep_default_na=False)
    filled = table[["Benign Acc", "Certified Acc"]].map(lambda v: v != "")
    assert filled.all().all() and len(table) == 2  # every cell of the two models, through PostgreSQL
