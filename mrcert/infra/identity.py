"""Run identity: which run a config describes, from the trained model to the table cell.

Every task declares, with an :class:`Identity`, which config keys define its result and which
do not (batch size, back end, device, output paths, resume flags...). :func:`identify` turns a
config into two keys:

* the **run key**: a hash of every result-defining value. Skipping finished work, resuming
  interrupted work, finding a trained model and filling a table cell all compare run keys,
  and nothing else;
* the **cell key**: the run key without the keys that only split one result into pieces
  (``task.shard``/``task.num_shards``: a sharded certification is one result in several runs).

A file given by path (a checkpoint, a point cloud, an imported log) is identified by the
sha256 of its content, so editing the file changes the key; the model an evaluation reads is
identified by its train run's key and its checkpoint's content, never by a store's run id
(:mod:`mrcert.infra.resolver`, which binds it).

Classification is by the longest matching prefix of a dotted key among ``defines`` and
``ignores``; a key that neither mentions defines the result (a new key is never silently
ignored). ``tests/test_identity.py`` checks that every key of every shipped config is
classified and that changing any defining key changes the run key.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mrcert.core.generator import GENERATOR_VERSION
from mrcert.core.methods import unkeyed
from mrcert.infra.config import plain

COMMON_IGNORES = (
    "paths",
    "tracking",
    "device",
    "skip_finished",
    "data.cache_dir",
    "data.extent",
    "per_task",
    "task._target_",
    "attack._target_",
    "data._target_",
)
"""Where outputs go and how runs are tracked or scheduled, bounds that only validation reads
(``data.extent``), an experiment's settings of single tasks (``per_task``: the task's own keys,
which are part of its result, hold them) and the classes that run a task, draw an attack's
motions and build the data (``*._target_``: their names say which): never part of a result."""

AS_BUILT = tuple(
    (key, value, key)
    for key, value in (
        ("data.surroundings.parts", None),
        ("data.surroundings.room", None),
        ("data.ambient.room", None),
        ("data.ambient.table", None),
        ("data.ambient.object", None),
        ("data.protocol.train.pitch_law", "angle"),
    )
)
"""Data settings at their as-built values, which keys made before the settings existed lack:
ignored (``Identity.ignore_when``), so those keys stay valid."""

KEY_SCHEME = ("mrcert.key_scheme", "content")
"""Tag of a run whose keys name its model by content (:mod:`mrcert.infra.resolver`); a run without
it was keyed by its train run's id, and is migrated (:mod:`mrcert.infra.key_migration`)."""

PARTITION = ("task.shard", "task.num_shards")
"""Keys that split one result over several runs (shards): in the run key, not in the cell key."""


@dataclass(frozen=True)
class Identity:
    """Which config keys define a task's result.

    ``defines`` / ``ignores``: dotted prefixes; the longest match wins, and a key matching
    neither defines the result. ``ignore_when``: ``(key, value, prefix)`` -- ignore ``prefix``
    when ``key`` has ``value`` (a vanilla model never sees the motion axis). ``files``: keys
    whose value is a file path, identified by the file's content. ``partition``: keys left
    out of the cell key. ``needs_model``: the task evaluates a trained classifier, whose
    checkpoint (``model.checkpoint``) must be bound before the key exists. ``method``: the
    task's result depends on the certification method as its run (``"result"``) or as the
    model it trains (``"model"``), less what the method declares it never depends on
    (:func:`mrcert.core.methods.unkeyed`).
    """

    defines: tuple[str, ...]
    ignores: tuple[str, ...] = ()
    ignore_when: tuple[tuple[str, Any, str], ...] = ()
    files: tuple[str, ...] = ()
    partition: tuple[str, ...] = ()
    needs_model: bool = False
    method: str | None = None

    def ignored(self, cfg: Mapping[str, Any]) -> tuple[str, ...]:
        extra = tuple(prefix for key, value, prefix in (*AS_BUILT, *self.ignore_when) if _get(cfg, key) == value)
        if self.method is not None:
            extra += unkeyed(_get(cfg, "method.name"), model=self.method == "model")
        return (*COMMON_IGNORES, *self.ignores, *extra)

    def classify(self, key: str, ignored: tuple[str, ...]) -> bool | None:
        """True when ``key`` defines the result, False when it is ignored, None when neither
        prefix list mentions it (it then defines the result too)."""
        longest = lambda prefixes: max((len(p) for p in prefixes if _matches(key, p)), default=-1)  # noqa: E731
        defines, ignores = longest(self.defines), longest(ignored)
        if defines < 0 and ignores < 0:
            return None
        return defines > ignores  # on a tie (ignore_when naming a defined group) the key is ignored


@dataclass(frozen=True)
class RunIdentity:
    """The keys of one run and the values they hash."""

    key: str
    cell: str
    values: dict[str, str] = field(repr=False)
    checkpoint: str | None = None
    train_run: str | None = None

    def tags(self) -> dict[str, str]:
        tags = {"mrcert.key": self.key, "mrcert.cell": self.cell, KEY_SCHEME[0]: KEY_SCHEME[1]}
        if self.checkpoint:
            tags["mrcert.checkpoint"] = self.checkpoint
        if self.train_run:
            tags["mrcert.train_run"] = self.train_run
        return tags

    def params(self) -> dict[str, str]:
        """What a run records about the model it used (the train run, or the file's digest)."""
        out = {}
        if self.checkpoint:
            out["checkpoint.identity"] = self.checkpoint
        if self.train_run:
            out["checkpoint.train_run_id"] = self.train_run
        return out


def _matches(key: str, prefix: str) -> bool:
    return key == prefix or key.startswith(prefix + ".")


def _get(cfg: Mapping[str, Any], dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts and lists as ``{"a.b.0": value}`` (empty containers kept as leaves)."""
    if isinstance(data, Mapping):
        items = data.items()
    elif isinstance(data, list):
        items = enumerate(data)
    else:
        return {prefix: data}
    out: dict[str, Any] = {}
    for key, value in items:
        out.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    if not out and prefix:
        out[prefix] = data
    return out


_DIGESTS: dict[tuple[str, int, int], str] = {}


def sha256_file(path: Path | str) -> tuple[int, str]:
    """A file's length and sha256 (hex), read in blocks."""
    h, size = hashlib.sha256(), 0
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
            size += len(block)
    return size, h.hexdigest()


def file_identity(value: Any) -> Any:
    """``sha256:<hex>`` of a file's content; ``runs:/`` URIs, folders and unset values as given."""
    if not isinstance(value, str) or not value or value == "???" or ":/" in value:
        return value
    path = Path(value)
    if not path.is_file():
        return os.path.abspath(value)
    stat = path.stat()
    cache = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if cache not in _DIGESTS:
        _DIGESTS[cache] = "sha256:" + sha256_file(path)[1]
    return _DIGESTS[cache]


def defining_values(cfg: DictConfig | Mapping[str, Any], identity: Identity) -> dict[str, Any]:
    """Every result-defining leaf of ``cfg`` (files replaced by their content's identity)."""
    data = plain(cfg)
    ignored = identity.ignored(data)
    out = {}
    for key, value in flatten(data).items():
        if identity.classify(key, ignored) is False:
            continue
        out[key] = file_identity(value) if any(_matches(key, f) for f in identity.files) else value
    return out


def digest(values: Mapping[str, Any]) -> str:
    blob = json.dumps(values, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


def identify(cfg: DictConfig | Mapping[str, Any], identity: Identity, model: Any = None) -> RunIdentity:
    """The run and cell keys of ``cfg``. For a task that evaluates a model, ``model`` is the
    bound :class:`mrcert.infra.resolver.Model`, whose identity stands for ``model.checkpoint``
    (without one, the value of ``model.checkpoint`` itself, as keys were made before models
    were named by content: :mod:`mrcert.infra.key_migration` recomputes those)."""
    values = defining_values(cfg, identity) | {"generator_version": GENERATOR_VERSION}
    checkpoint = train_run = None
    if identity.needs_model:
        if model is not None:
            values["model.checkpoint"] = model.identity
            train_run = model.train_run
        checkpoint = values.get("model.checkpoint")
        if not checkpoint:
            raise ValueError("identify() needs the model bound for a task that evaluates one (mrcert.infra.resolver)")
    cell = {k: v for k, v in values.items() if not any(_matches(k, p) for p in identity.partition)}
    return RunIdentity(digest(values), digest(cell), values, checkpoint, train_run)
