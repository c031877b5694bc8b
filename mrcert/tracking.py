"""MLflow tracking: one MLflow run per task run, children of one parent per multirun.

The parent run, the experiment and (for SQLite) the schema are created once, by
:class:`MultirunParentCallback` before any job starts, and the ids reach the jobs through a
file in the sweep directory -- never by jobs racing to create them (SPEC section 6).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from mrcert.errors import MrcertError

log = logging.getLogger(__name__)

PARENT_FILE = "mlflow_parent.json"
MAX_PARAM_CHARS = 6000


def flatten(data: Any, prefix: str = "") -> dict[str, str]:
    """Nested dicts and lists as ``{"a.b.0": "value"}`` strings, for MLflow params."""
    if isinstance(data, dict):
        items = data.items()
    elif isinstance(data, list):
        items = enumerate(data)
    else:
        return {prefix: str(data)[:MAX_PARAM_CHARS]}
    out: dict[str, str] = {}
    for key, value in items:
        out.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    if not out and prefix:  # an empty dict or list still records that it was empty
        out[prefix] = str(data)
    return out


def configure(tracking: DictConfig):
    """The mlflow module pointed at the configured store; makes the SQLite folder."""
    import mlflow

    uri = str(tracking.uri)
    if uri.startswith("sqlite:///"):
        db = Path(uri[len("sqlite:///") :])
        try:
            db.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise MrcertError(f"cannot create the MLflow store folder {db.parent}: {exc}") from None
        if not os.access(db.parent, os.W_OK):
            raise MrcertError(f"the MLflow store folder {db.parent} is not writable; set tracking.uri elsewhere")
    mlflow.set_tracking_uri(uri)
    return mlflow


def ensure_experiment(tracking: DictConfig) -> str:
    """Id of the configured experiment, created (with its artifact location) if missing."""
    mlflow = configure(tracking)
    client = mlflow.MlflowClient()
    try:
        exp = client.get_experiment_by_name(tracking.experiment)
    except Exception as exc:  # unreachable server, corrupt store
        raise MrcertError(f"cannot reach the MLflow store at {tracking.uri}: {exc}") from None
    if exp is not None:
        return exp.experiment_id
    location = tracking.artifact_location
    if location:
        Path(location).mkdir(parents=True, exist_ok=True)
        location = Path(location).as_uri()
    return client.create_experiment(tracking.experiment, artifact_location=location)


def run_tags(cfg: DictConfig) -> dict[str, str]:
    """Tags that tables and look-ups filter on."""
    select = lambda key: OmegaConf.select(cfg, key, default=None)  # noqa: E731
    tags = {
        "mrcert.task": select("task.name"),
        "mrcert.axis": select("motion.axis"),
        "mrcert.model": select("model.arch"),
        "mrcert.dataset": select("data.name"),
        "mrcert.variant": select("model.variant"),
        "mrcert.profile": select("profile.name"),
    }
    overrides = OmegaConf.select(cfg, "task.tags", default=None)  # e.g. an imported log's metadata
    if overrides:
        tags.update(OmegaConf.to_container(overrides, resolve=True))
    return {k: str(v) for k, v in tags.items() if v is not None}


VOLATILE = ("task.resume",)
"""Keys that change how a run starts but not what it computes: not params, not in the config key."""


def config_key(cfg: DictConfig) -> str:
    """Hash of what a run computes: the config keys its task uses (all but tracking, paths and
    device when it does not say), without volatile keys. A vanilla model's key ignores the
    motion axis, which it never sees."""
    from mrcert.config import plain
    from mrcert.tasks import TASKS

    uses = TASKS[cfg.task.name].uses
    if cfg.task.name == "train" and OmegaConf.select(cfg, "model.variant") == "vanilla":
        uses = tuple(u for u in uses if u != "motion")
    data = {
        k: v
        for k, v in flatten(plain(cfg)).items()
        if k not in VOLATILE
        and not k.startswith(("tracking.", "paths.", "model.checkpoint"))
        and k != "device"
        and (uses is None or k.split(".", 1)[0] in uses)
    }
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


@dataclass
class Tracker:
    """What a task logs through (does nothing when tracking is off), and where its files live."""

    output_dir: Path
    run_id: str | None = None
    resumed: bool = False

    @property
    def enabled(self) -> bool:
        return self.run_id is not None

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        if self.enabled:
            import mlflow

            mlflow.log_metrics({k: float(v) for k, v in metrics.items()}, step=step)

    def log_artifact(self, path: Path | str, artifact_path: str | None = None) -> None:
        if self.enabled:
            import mlflow

            path = Path(path)
            if path.is_dir():
                mlflow.log_artifacts(str(path), artifact_path=artifact_path or path.name)
            else:
                mlflow.log_artifact(str(path), artifact_path=artifact_path)


def _parent_info() -> dict[str, str] | None:
    """``{"run_id", "experiment_id"}`` of the sweep's parent run when this job is in a multirun."""
    try:
        hc = HydraConfig.get()
    except ValueError:
        return None
    path = Path(hc.sweep.dir) / PARENT_FILE
    if hc.mode != RunMode.MULTIRUN or not path.exists():
        return None
    return json.loads(path.read_text())


def fail_parent(cfg: DictConfig) -> None:
    """Mark the multirun's parent run FAILED (called when one of its jobs fails)."""
    info = _parent_info()
    if cfg.tracking.enabled and info is not None:
        configure(cfg.tracking).MlflowClient().set_terminated(info["run_id"], "FAILED")


def shard_group(cfg: DictConfig) -> str:
    """The config key shared by every shard of one sharded job (``task.shard`` set to 0)."""
    whole = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    whole.task.shard = 0
    return config_key(whole)


def same_config_run(cfg: DictConfig, experiment_id: str, finished: bool):
    """The latest FINISHED (or, with ``finished=False``, not finished) run of this config."""
    import mlflow

    status = "=" if finished else "!="
    runs = mlflow.search_runs(
        experiment_ids=[experiment_id],
        filter_string=f"tags.`mrcert.config_key` = '{config_key(cfg)}' and attributes.status {status} 'FINISHED'",
        order_by=["attributes.start_time DESC"],
        max_results=1,
        output_format="list",
    )
    return runs[0] if runs else None


def finished_run(cfg: DictConfig):
    """A FINISHED run with this config, when ``skip_finished`` is on (reproductions), else None."""
    if not (cfg.get("skip_finished") and cfg.tracking.enabled):
        return None
    return same_config_run(cfg, ensure_experiment(cfg.tracking), finished=True)


@contextmanager
def task_run(cfg: DictConfig, output_dir: Path) -> Iterator[Tracker]:
    """An MLflow run around one task: params, tags and the resolved config on entry,
    status FINISHED or FAILED on exit; a child of the sweep's parent run in a multirun.

    With ``task.resume=true`` the latest unfinished run of the same config is reopened and
    the task continues in that run's output directory.
    """
    from mrcert.config import plain, to_yaml

    output_dir.mkdir(parents=True, exist_ok=True)
    resolved = output_dir / "resolved_config.yaml"
    resolved.write_text(to_yaml(cfg))
    if not cfg.tracking.enabled:
        yield Tracker(output_dir)
        return
    info = _parent_info() or {}
    parent_id = info.get("run_id")
    mlflow = configure(cfg.tracking)
    experiment_id = info.get("experiment_id") or ensure_experiment(cfg.tracking)
    previous = same_config_run(cfg, experiment_id, finished=False) if cfg.task.get("resume") else None
    if previous is not None:
        output_dir = Path(previous.data.tags["mrcert.output_dir"])
        log.info("resuming MLflow run %s from %s", previous.info.run_id, output_dir)
        run_ctx = mlflow.start_run(run_id=previous.info.run_id)
    else:
        tags = run_tags(cfg) | {"mrcert.output_dir": str(output_dir.resolve()), "mrcert.config_key": config_key(cfg)}
        if int(OmegaConf.select(cfg, "task.num_shards", default=1) or 1) > 1:
            tags["mrcert.shard_group"] = shard_group(cfg)
        run_ctx = mlflow.start_run(experiment_id=experiment_id, parent_run_id=parent_id, tags=tags)
    with run_ctx as run:
        if previous is None:
            params = {k: v for k, v in flatten(plain(cfg)).items() if k not in VOLATILE}
            mlflow.log_params(params)
            mlflow.log_artifact(str(resolved))
        log.info("MLflow run %s in experiment %s at %s", run.info.run_id, experiment_id, cfg.tracking.uri)
        try:
            yield Tracker(output_dir, run.info.run_id, resumed=previous is not None)
        except BaseException:
            mlflow.end_run("FAILED")
            raise


class MultirunParentCallback(Callback):
    """Creates the experiment and a parent run before a multirun's jobs start, and closes
    it FINISHED (or FAILED when any child failed) when they are done."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        if not config.tracking.enabled:
            return
        experiment_id = ensure_experiment(config.tracking)
        client = configure(config.tracking).MlflowClient()
        sweep_dir = Path(config.hydra.sweep.dir)
        tags = run_tags(config) | {
            "mrcert.multirun": "parent",
            "mrcert.sweep_dir": str(sweep_dir.resolve()),
            "mrcert.overrides": " ".join(config.hydra.overrides.task),
        }
        run = client.create_run(experiment_id, tags=tags, run_name=f"sweep-{sweep_dir.name}")
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / PARENT_FILE).write_text(json.dumps({"run_id": run.info.run_id, "experiment_id": experiment_id}))
        log.info("MLflow parent run %s for sweep %s", run.info.run_id, sweep_dir)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if not config.tracking.enabled:
            return
        info = json.loads((Path(config.hydra.sweep.dir) / PARENT_FILE).read_text())
        mlflow = configure(config.tracking)
        children = mlflow.search_runs(
            experiment_ids=[info["experiment_id"]],
            filter_string=f"tags.mlflow.parentRunId = '{info['run_id']}'",
            output_format="list",
        )
        failed = any(r.info.status != "FINISHED" for r in children)
        mlflow.MlflowClient().set_terminated(info["run_id"], "FAILED" if failed else "FINISHED")
