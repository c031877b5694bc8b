"""Stores written before models were named by content: their evaluations re-keyed when a launch
first opens the store (never by a read).

An evaluation made before :mod:`mrcert.infra.resolver` existed holds in its run and cell keys the
``runs:/<train run id>/...`` URI of its model, an id that only its own store knows. Migrating a
run recomputes its keys from its ``resolved_config.yaml`` with the model named by content (its
train run's key and its checkpoint's digest) and tags it :data:`~mrcert.infra.identity.KEY_SCHEME`,
so that the same config finds it again: a finished run keeps filling its table cell and is
skipped by ``skip_finished``, an interrupted one is resumed with the rows it logged (its
per-image log is bound to the new key: :func:`mrcert.infra.log_keys.rekey`). A run is re-keyed only when its
config, read back, gives its recorded key (the config is the one that made it); otherwise it
keeps its keys and is counted. Its train run is the run of that id, or the copy of it that
``task=gather`` made (tagged ``mrcert.gathered_from``).

A store is migrated once (the experiment is then tagged :data:`KEY_SCHEME`); ``task=gather``
migrates what it copies.

Runs that finished before runs sealed their files (:mod:`mrcert.infra.seals`) are sealed once,
as their files are when this version first opens the store (:func:`seal_finished`; the store
is then tagged :data:`SEAL_SCHEME`, each such run ``mrcert.sealed_late``): from then on, a
change to them is refused as to any other run's. A copy tagged :data:`UNSEALED` is never sealed.
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from mrcert.infra import seals
from mrcert.infra.checkpoints import ARTIFACT_DIR
from mrcert.infra.experiment import artifact, read_run_config, run_file
from mrcert.infra.identity import KEY_SCHEME, identify
from mrcert.infra.log_keys import rekey
from mrcert.infra.run_store import FINISHED, all_runs
from mrcert.infra.tasks import TASKS

log = logging.getLogger(__name__)

SEAL_SCHEME = ("mrcert.seal_scheme", "sealed")
"""Tag of an experiment whose finished runs have all been sealed."""

GATHERED = "mrcert.gathered_from"
"""Tag of a run ``task=gather`` copied: the id of the run it was copied from."""

UNSEALED = "mrcert.unsealed"
"""Tag of a copy whose files its source held without seals, in a store whose runs are sealed:
nothing vouches for them, and they are never sealed late."""


class _StoreRuns:
    """:class:`mrcert.infra.resolver.RunRecords` over one experiment's runs, by id or by origin."""

    def __init__(self, client, runs: list):
        self.client = client
        self.by_id = {r.info.run_id: r for r in runs}
        self.copies = {r.data.tags[GATHERED]: r for r in runs if GATHERED in r.data.tags}

    def run(self, run_id: str):
        return self.by_id.get(run_id) or self.copies.get(run_id)

    def run_tags(self, run_id: str) -> dict[str, str] | None:
        run = self.run(run_id)
        return None if run is None else dict(run.data.tags)

    def artifact(self, run_id: str, path: str) -> Path:
        return artifact(self.client, self.run(run_id).info.run_id, path)


def _config(client, run) -> DictConfig | None:
    """A run's ``resolved_config.yaml`` (None when it is gone or unreadable)."""
    path = run_file(client, run.info.run_id, run.data.tags.get("mrcert.output_dir"), "resolved_config.yaml")
    try:
        return None if path is None else read_run_config(path)
    except Exception:  # noqa: BLE001 - a config this version cannot read
        return None


def migrate(client, experiment_id: str) -> dict[str, int]:
    """Re-key every evaluation of the experiment that names its model by run id; counts of
    ``migrated`` runs and of runs that ``kept`` their keys."""
    from mrcert.infra.resolver import Model, model_identity, run_of

    runs = all_runs(client, experiment_id)
    store = _StoreRuns(client, runs)
    counts = {"migrated": 0, "kept": 0}
    for run in runs:
        tags = run.data.tags
        if "mrcert.train_run" not in tags or tags.get(KEY_SCHEME[0]) == KEY_SCHEME[1]:
            continue
        task = TASKS.get(tags.get("mrcert.task", ""))
        cfg = _config(client, run) if task is not None and task.identity.needs_model else None
        ref = run_of(str(cfg.model.checkpoint)) if cfg is not None and cfg.model.get("checkpoint") else None
        try:
            same = ref is not None and identify(cfg, task.identity).key == tags.get("mrcert.key")
            model = Model(str(cfg.model.checkpoint), model_identity(store, *ref), ref[0]) if same else None
        except Exception:  # noqa: BLE001 - a config this version cannot read, a checkpoint that is gone
            model = None
        if model is None or store.run(ref[0]) is None:
            counts["kept"] += 1
            continue
        ident = identify(cfg, task.identity, model)
        folder = tags.get("mrcert.output_dir")
        if task.log and folder:  # its per-image log follows it: an interrupted run resumes its rows
            rekey(Path(folder) / task.log, run.info.run_id, tags["mrcert.key"], ident.key)
        for k, v in {**ident.tags(), "mrcert.train_run": tags["mrcert.train_run"]}.items():
            if tags.get(k) != v:
                client.set_tag(run.info.run_id, k, v)
        counts["migrated"] += 1
    if counts["migrated"] or counts["kept"]:
        log.info("content keys: %d runs re-keyed, %d kept their keys", counts["migrated"], counts["kept"])
    return counts


def seal_finished(client, experiment_id: str) -> int:
    """Seal every FINISHED task run of the experiment that finished without seals, as its
    files now are; the number of runs sealed."""
    sealed = 0
    for run in all_runs(client, experiment_id, FINISHED):
        tags = run.data.tags
        task = TASKS.get(tags.get("mrcert.task", ""))
        if task is None or UNSEALED in tags or any(k.startswith(seals.PREFIX) for k in tags):
            continue
        found = {}
        for name in seals.sealed_files(tags["mrcert.task"], task.log):
            for path in (name, f"{ARTIFACT_DIR}/{name}"):
                local = run_file(client, run.info.run_id, tags.get("mrcert.output_dir"), path)
                if local is not None:
                    found[seals.tag(name)] = seals.seal_file(local)
                    break
        if found:
            for k, v in {**found, "mrcert.sealed_late": "true"}.items():
                client.set_tag(run.info.run_id, k, v)
            sealed += 1
    if sealed:
        log.info("seals: %d runs that finished before runs sealed their files sealed as they are now", sealed)
    return sealed


def migrate_once(client, experiment: str) -> None:
    """Migrate the experiment named ``experiment`` unless it is tagged as migrated (then tag
    it), and seal its unsealed finished runs unless it is tagged as sealed."""
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return
    if exp.tags.get(KEY_SCHEME[0]) != KEY_SCHEME[1]:
        migrate(client, exp.experiment_id)
        client.set_experiment_tag(exp.experiment_id, *KEY_SCHEME)
    if exp.tags.get(SEAL_SCHEME[0]) != SEAL_SCHEME[1]:
        seal_finished(client, exp.experiment_id)
        client.set_experiment_tag(exp.experiment_id, *SEAL_SCHEME)
