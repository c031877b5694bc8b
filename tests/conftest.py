import os
import resource
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from mrcert.infra.config import CONF_DIR

os.environ.setdefault("MLFLOW_ENABLE_ASYNC_LOGGING", "false")
if not torch.cuda.is_available():  # the triton back end's kernels then run under Triton's interpreter
    os.environ.setdefault("TRITON_INTERPRET", "1")

# The paper's 160 x 90 camera (docs/method.md §2).
PAPER_K = torch.tensor([[386.274, 0.0, 80.0], [0.0, 386.274, 45.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def random_cloud(rng: np.random.Generator, n: int = 20000, behind: int = 500) -> tuple[torch.Tensor, torch.Tensor]:
    """Points mostly inside the paper camera's view (some behind it), random colours."""
    front = np.column_stack([rng.uniform(-1.6, 1.6, n), rng.uniform(-0.9, 0.9, n), rng.uniform(0.8, 4.0, n)])
    back = np.column_stack([rng.uniform(-1, 1, behind), rng.uniform(-1, 1, behind), rng.uniform(-2.0, 0.0, behind)])
    pts = np.concatenate([front, back])
    return torch.from_numpy(pts), torch.from_numpy(rng.uniform(0, 1, (len(pts), 3)).astype(np.float32))


def random_motions(rng: np.random.Generator, per_axis: int = 3) -> torch.Tensor:
    """A few motions on each single axis (paper-sized ranges) plus combined ones."""
    scale = np.array([0.05, 0.05, 0.1, 0.0436, 0.0436, 0.122])
    rows = []
    for axis in range(6):
        for _ in range(per_axis):
            m = np.zeros(6)
            m[axis] = rng.uniform(-2, 2) * scale[axis]
            rows.append(m)
    rows += list(rng.uniform(-1, 1, (per_axis, 6)) * scale)
    return torch.tensor(np.array(rows))


# A tiny quick MetaRoom (3 classes, coarse surfaces) and a tiny CNN: real runs in seconds.
TINY_CLASSES = ["apple", "can", "mug"]
"""The classes of the tiny data set, in its order (a model trained on it predicts these)."""

TINY = [
    "data=metaroom_synth",
    "model=small_cnn",
    "model.net.width=8",
    "data.classes=[can,mug,apple]",
    "data.room_density=0.03",
    "data.density=0.01",
    "data.protocol.train.per_class=16",
]


def compose_cfg(overrides: list[str], outputs=None):
    """The composed config for ``overrides``, writing under ``outputs`` when given."""
    extra = [f"paths.outputs={outputs}"] if outputs is not None else []
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=[*overrides, *extra])


ROOT = Path(__file__).resolve().parent.parent


def run_cli(
    args: list[str], outputs, timeout: int = 600, preexec_fn: Callable[[], None] | None = None
) -> subprocess.CompletedProcess:
    """``python -m mrcert ARGS`` writing under ``outputs``; output captured."""
    env = os.environ | {"MRCERT_OUTPUTS": str(outputs)}
    cmd = [sys.executable, "-m", "mrcert", *args]
    return subprocess.run(
        cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout, preexec_fn=preexec_fn
    )


def file_size_limit(kib: int) -> Callable[[], None]:
    """A ``preexec_fn`` that caps every file the child writes at ``kib`` KiB: a write past it
    fails (SIGXFSZ ignored) as it would on a full disk."""

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (kib * 1024, kib * 1024))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    return limit


def start_cli(args: list[str], outputs, interruptible: bool = False) -> subprocess.Popen:
    """``python -m mrcert ARGS`` writing under ``outputs``, started in the background; its
    stderr is captured (read it with ``communicate()``). ``interruptible``: SIGINT acts as
    Ctrl-C in a terminal would, even when the tests themselves run as a background job (whose
    children start with SIGINT ignored)."""
    env = os.environ | {"MRCERT_OUTPUTS": str(outputs)}
    return subprocess.Popen(
        [sys.executable, "-m", "mrcert", *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) if interruptible else None,
    )


def kill_when(args: list[str], outputs, ready: Callable[[], bool], timeout: float = 240) -> None:
    """Start ``mrcert ARGS`` and SIGKILL it as soon as ``ready()`` holds (a crash at that moment)."""
    env = os.environ | {"MRCERT_OUTPUTS": str(outputs)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "mrcert", *args], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    wait_until(proc, ready, timeout)
    proc.send_signal(signal.SIGKILL)
    proc.wait()


def wait_until(proc: subprocess.Popen, ready: Callable[[], bool], timeout: float = 240) -> None:
    """Poll until ``ready()`` holds, ``proc`` has exited or ``timeout`` seconds have passed."""
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None and not ready():
        time.sleep(0.02)


# --- what the fault and integrity tests share ---------------------------------------------

PER_RUN = ["time", "seconds", "check"]  # cells that differ between two runs of one result


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    """Two different tiny models as files: ``a`` (best.pt) and ``b`` (last.pt of a longer run)."""
    from mrcert.__main__ import run_task

    out = tmp_path_factory.mktemp("models")
    run_task(compose_cfg([*TINY, "task=train", "train.epochs=1", "train.batch_size=8"], out), out / "a")
    run_task(compose_cfg([*TINY, "task=train", "train.epochs=3", "train.batch_size=8"], out), out / "b")
    return {"a": out / "a" / "best.pt", "b": out / "b" / "last.pt"}


def certify_args(checkpoint: Path, n: int = 200) -> list[str]:
    return [
        *TINY,
        "task=certify",
        "task.n0=8",
        f"task.n={n}",
        "task.max=4",
        "task.skip=1",
        f"model.checkpoint={checkpoint}",
    ]


@pytest.fixture(scope="module")
def reference(checkpoints, tmp_path_factory) -> dict:
    """The rows an uninterrupted certification gives with each model (data frames)."""
    from mrcert.__main__ import run_task
    from mrcert.reporting.certify_log import read_log

    rows = {}
    for name, path in checkpoints.items():
        out = tmp_path_factory.mktemp(f"reference-{name}")
        run_task(compose_cfg(certify_args(path), out), out / "run")
        rows[name] = read_log(out / "run" / "certify.tsv").drop(columns=PER_RUN, errors="ignore")
    return rows


def store_runs(out: Path, where: str = "") -> list:
    import mlflow

    mlflow.set_tracking_uri(f"sqlite:///{out / 'mlflow.db'}")
    return mlflow.search_runs(search_all_experiments=True, filter_string=where, output_format="list")


def certify_logs(out: Path) -> list[Path]:
    return sorted(out.glob("runs/certify/*/certify.tsv"))


def write_cloud(path: Path, ascii: bool = False) -> None:
    import numpy as np
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.random.default_rng(0).uniform(-1, 1, (100, 3)))
    o3d.io.write_point_cloud(str(path), pcd, write_ascii=ascii)
