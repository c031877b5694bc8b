"""Stages and their keys: the one resolver from a config to the key of the run that holds its result.

The pipeline's stages are render (the data cache, keyed by its data config), train, evaluate
(certify, smooth, attack, viewpoints) and the table cell. A stage's key is the digest of its own
result-defining config values (its task's :class:`~mrcert.infra.identity.Identity`) and of what
it reads from the stage above it:

* a **train** run: its data, model, recipe, seed and profile (the motion and method too for an
  augmented model): :func:`train_key`, whatever the task that asks for the model;
* an **evaluation**: its own keys and its model's identity (:class:`Model`): for a model bound
  from a train run ``train:<train key> sha256:<digest of best.pt>``, for a file
  ``sha256:<digest of the file>``;
* a **table cell**: an evaluation's key less the keys that split one result into shards.

No key holds a store's run id, so a run copied into another store (``task=gather``) keeps its
keys there, and a cell composed anywhere finds it. :func:`resolve` binds an evaluation to its
model and computes the key: the launch (``mrcert task=...``) resolves through the live store
(:class:`LiveRuns`), the tables through their index of finished runs
(:class:`mrcert.reporting.cells.RunIndex`), both through the same :class:`TrainRuns` protocol,
and both ask :mod:`mrcert.infra.run_store` which run. A store written before these keys existed
is migrated when a launch opens it (:mod:`mrcert.infra.key_migration`).
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from mrcert.errors import MrcertError
from mrcert.infra.checkpoints import BEST_PATH
from mrcert.infra.config import plain, trained_for
from mrcert.infra.identity import RunIdentity, file_identity, identify
from mrcert.infra.tasks import TASKS

DIGEST_TAG = "mrcert.checkpoint_sha256"
"""Tag of a train run: the content identity (``sha256:<hex>``) of its ``best.pt``."""


@dataclass(frozen=True)
class Model:
    """The one model an evaluation reads: ``ref`` loads it (a file path or ``runs:/`` URI),
    ``identity`` keys it (store-independent), ``train_run`` is its train run in this store."""

    ref: str
    identity: str
    train_run: str | None = None


class RunRecords(Protocol):
    """What naming a run's model reads from a store: a run by id."""

    def run_tags(self, run_id: str) -> dict[str, str] | None:
        """A run's tags (None when the store has no such run)."""

    def artifact(self, run_id: str, path: str) -> Path:
        """A run's artifact as a local file (downloaded when the store is remote)."""


class TrainRuns(RunRecords, Protocol):
    """What the resolver reads from a store: a run by id, and a train run by key."""

    def newest_train_run(self, key: str) -> str | None:
        """The newest FINISHED train run with run key ``key``."""


def train_config(cfg: DictConfig) -> dict:
    """The config of the train run that makes the model ``cfg`` asks for, whatever ``cfg``'s
    task: ``cfg`` as a train task, trained for ``model.trained_for`` when that is set."""
    data = plain(cfg) | {"task": {"name": "train"}}
    method = trained_for(data)
    if method is not None:
        data["method"] = method
    return data


def train_key(cfg: DictConfig) -> str:
    """The run key of the train run that makes the model ``cfg`` asks for."""
    return identify(train_config(cfg), TASKS["train"].identity).key


def model_identity(runs: RunRecords, run_id: str, path: str = BEST_PATH) -> str:
    """The identity of a run's checkpoint ``path``: its train key (for a train run's model) and
    its content's digest (recorded on the train run, else computed from the file)."""
    tags = runs.run_tags(run_id) or {}
    digest = tags.get(DIGEST_TAG) if path == BEST_PATH else None
    if not digest:
        digest = file_identity(str(runs.artifact(run_id, path)))
    if tags.get("mrcert.task") == "train" and tags.get("mrcert.key"):
        return f"train:{tags['mrcert.key']} {digest}"
    return digest


def run_of(ref: str) -> tuple[str, str] | None:
    """``(run id, artifact path)`` of a ``runs:/<run_id>/<path>`` reference, else None."""
    if not ref.startswith("runs:/"):
        return None
    run_id, _, path = ref[len("runs:/") :].partition("/")
    return run_id, path


def train_command(cfg: DictConfig) -> str:
    """The command that trains the model ``cfg`` asks for: this launch's overrides with the
    task swapped for ``train`` (from Hydra when launched from the command line), and the method
    set to ``model.trained_for`` when that is given."""
    method = trained_for(plain(cfg))
    try:
        overrides = list(HydraConfig.get().overrides.task)
    except ValueError:  # composed outside a launch (the API, tests)
        profile = f"profile={cfg.profile.name}" if "profile" in cfg else ""
        overrides = [
            f"data={cfg.data.name}",
            profile,
            f"model={cfg.model.arch}",
            f"motion={cfg.motion.axis}",
            f"model.variant={cfg.model.variant}",
        ]
    dropped = ("task=", "task.", "model.checkpoint", "model.trained_for") + (("method",) if method else ())
    kept = [o for o in overrides if o and not o.lstrip("+~").startswith(dropped)]
    if method:  # the method it was trained for, as a train command sets it
        kept += [f"method={method['name']}"] + [f"method.{k}={v}" for k, v in method.items() if k != "name"]
    return " ".join(["mrcert", "task=train", *kept])


def bind_model(cfg: DictConfig, runs: TrainRuns | None) -> tuple[DictConfig, Model]:
    """``cfg`` with ``model.checkpoint`` set to the one model it evaluates, and that model.

    A given reference is checked now, before any run exists: a file must exist, a ``runs:/``
    URI must name a run of the store. A null one is the newest FINISHED train run of
    :func:`train_key` (``runs`` is None when tracking is off: then a file must be given)."""
    ref = cfg.model.get("checkpoint")
    if ref:
        ref = str(ref)
        if ":/" in ref:
            parts = run_of(ref)
            if parts is None or not parts[1]:
                raise MrcertError(f"model.checkpoint={ref!r} is not allowed: a file path or runs:/<run_id>/<path>")
            if runs is None or runs.run_tags(parts[0]) is None:
                raise MrcertError(f"model.checkpoint={ref!r} cannot be fetched from MLflow: no such run in the store")
            return cfg, Model(ref, model_identity(runs, *parts), parts[0])
        if not Path(ref).is_file():
            raise MrcertError(f"model.checkpoint={ref!r} does not exist; give a file path or runs:/<run_id>/<path>")
        bound = copy.deepcopy(cfg)
        bound.model.checkpoint = os.path.abspath(ref)
        return bound, Model(bound.model.checkpoint, file_identity(bound.model.checkpoint))
    if runs is None:
        raise MrcertError(
            "model.checkpoint is not set and tracking is off, so no train run can be looked up; "
            "set model.checkpoint=/path/to/best.pt"
        )
    run_id = runs.newest_train_run(train_key(cfg))
    if run_id is None:
        axis = f" axis={cfg.motion.axis}" if cfg.model.variant != "vanilla" else ""
        raise MrcertError(
            f"no finished train run of model={cfg.model.arch} variant={cfg.model.variant}{axis} with this data, "
            f"profile, seed and train.* recipe in {cfg.tracking.uri}; train it with: {train_command(cfg)}"
        )
    bound = copy.deepcopy(cfg)
    bound.model.checkpoint = f"runs:/{run_id}/{BEST_PATH}"
    return bound, Model(bound.model.checkpoint, model_identity(runs, run_id), run_id)


def resolve(cfg: DictConfig, runs: TrainRuns | None) -> tuple[DictConfig, RunIdentity]:
    """``cfg`` bound to its model (for a task that evaluates one) and its run identity."""
    task = TASKS.of(cfg)
    model = None
    if task.identity.needs_model:
        cfg, model = bind_model(cfg, runs)
    return cfg, identify(cfg, task.identity, model)


class LiveRuns:
    """:class:`TrainRuns` over the configured MLflow store (a launch's view)."""

    def __init__(self, tracking: DictConfig):
        from mrcert.infra.experiment import configure

        self.tracking = tracking
        self.client = configure(tracking).MlflowClient()

    def newest_train_run(self, key: str) -> str | None:
        from mrcert.infra.run_store import newest_train_run

        return newest_train_run(self.tracking, key)

    def run_tags(self, run_id: str) -> dict[str, str] | None:
        try:
            return dict(self.client.get_run(run_id).data.tags)
        except Exception:  # noqa: BLE001 - an unknown run id, an unreachable store
            return None

    def artifact(self, run_id: str, path: str) -> Path:
        from mrcert.infra.experiment import artifact

        return artifact(self.client, run_id, path)
