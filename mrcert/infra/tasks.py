"""What a task is, apart from its computation, and where each task is found.

A task is a subclass of :class:`Task` in its own module under :mod:`mrcert.tasks`, named by
``_target_`` in its YAML (``conf/task/<name>.yaml``): what defines its result (its
:class:`~mrcert.infra.identity.Identity`), the per-image log it writes and that log's columns,
its headline metrics (:meth:`Task.summarize`), the run's name (:meth:`Task.title`) and its
computation (:meth:`Task.run`). Adding a task is that module and that YAML.

:data:`TASKS` finds a task by name: from a composed config (:meth:`Registry.of`, which is how
the entry point meets it), else from its YAML. A task's module is imported only when the task
is asked for, never by this module.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar

from omegaconf import DictConfig, OmegaConf

from mrcert.errors import ConfigError, MrcertError
from mrcert.infra.config import CONF_DIR
from mrcert.infra.identity import PARTITION, Identity


class Task:
    """One task: subclass it, set the class attributes, implement :meth:`run`."""

    summary: ClassVar[str] = ""
    """One line for ``mrcert --help``."""
    identity: ClassVar[Identity] = Identity(defines=("task",))
    """Which config keys define the task's result (see :mod:`mrcert.infra.identity`)."""
    reusable: ClassVar[bool] = True
    """Whether a FINISHED run of the same run key may stand in for a new one (``skip_finished``)."""
    needs: ClassVar[str | None] = None
    """The artifact without which a FINISHED run no longer stands in for a new one (a train
    run's checkpoint: a store copied without it trains the model again)."""
    tracked: ClassVar[bool] = True
    """Whether it runs inside an MLflow run of its own (``task=ui`` serves the store and adds no run to it)."""
    scene_task: ClassVar[bool] = True
    """Whether it reads the composed data set, model and method, which are then checked (and
    their modules imported) before it runs; ``task=verify`` reads files of its own."""
    log: ClassVar[str | None] = None
    """The per-image log the task writes (in its run folder and artifacts), for tables and shards."""
    columns: ClassVar[tuple[str, ...]] = ()
    """The log's columns, in order."""
    headline: ClassVar[tuple[str, ...]] = ()
    """Of the headline metrics of its log, the ones the MLflow runs page shows as columns."""

    def title(self, cfg: DictConfig) -> str:
        """The run's name: what it is, in words, what tells runs apart first (the runs page cuts long names)."""
        return f"{cfg.task.name} {cfg.data.name}"

    def summarize(self, log: Any, cfg: DictConfig) -> dict[str, float]:
        """The headline metrics of the task's per-image ``log`` (a DataFrame, whole or merged from
        shards): what the run logs when it ends and what a table cell shows."""
        raise NotImplementedError(f"task {cfg.task.name} writes no per-image log")

    def run(self, cfg: DictConfig, ctx: Any) -> dict[str, Any]:
        """Compute the task's result into ``ctx`` (a :class:`mrcert.infra.tracking.RunContext`);
        its headline metrics."""
        raise NotImplementedError


class Registry(Mapping[str, Task]):
    """The tasks by name: each resolved once from its ``_target_``."""

    def __init__(self) -> None:
        self._tasks: dict[str, Task] = {}

    def of(self, cfg: DictConfig) -> Task:
        """The task ``cfg.task`` names, resolved from its own ``_target_`` (a task defined outside
        this package's ``conf/`` included)."""
        name = str(cfg.task.name)
        if name not in self._tasks:
            target = OmegaConf.select(cfg, "task._target_", default=None) or _target(name)
            if target is None:
                raise ConfigError(
                    "task.name", name, f"one of {', '.join(self)} (or a task whose config names its _target_)"
                )
            self._tasks[name] = _load(name, target)
        return self._tasks[name]

    def __getitem__(self, name: str) -> Task:
        if name not in self._tasks:
            target = _target(name)
            if target is None:
                raise KeyError(name)
            self._tasks[name] = _load(name, target)
        return self._tasks[name]

    def summary(self, name: str) -> str:
        """The task's one line for ``mrcert --help`` (its class's ``summary``), read from its
        module's source when it is a literal there, so that listing the tasks imports none of
        them (nor torch); otherwise from the class."""
        import importlib.util

        module, _, attr = (_target(name) or "").rpartition(".")
        spec = importlib.util.find_spec(module) if module else None
        if spec is not None and spec.origin and spec.origin.endswith(".py"):
            found = _literal_summary(Path(spec.origin).read_text(), attr)
            if found is not None:
                return found
        return self[name].summary

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and (name in self._tasks or _target(name) is not None)

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(set(self._tasks) | set(_names())))

    def __len__(self) -> int:
        return len(set(self._tasks) | set(_names()))


def _literal_summary(source: str, cls: str) -> str | None:
    """``summary = "..."`` in class ``cls`` of a module's ``source``, if written as a literal."""
    import ast

    for node in ast.parse(source).body:
        if isinstance(node, ast.ClassDef) and node.name == cls:
            for item in node.body:
                named = isinstance(item, ast.Assign) and [getattr(t, "id", None) for t in item.targets] == ["summary"]
                if named and isinstance(item.value, ast.Constant) and isinstance(item.value.value, str):
                    return item.value.value
    return None


def _names() -> list[str]:
    return [p.stem for p in sorted((CONF_DIR / "task").glob("*.yaml")) if _target(p.stem)]


def _target(name: str) -> str | None:
    path = CONF_DIR / "task" / f"{name}.yaml"
    if not path.is_file():
        return None
    target = OmegaConf.load(path).get("_target_")
    return None if target is None else str(target)


def _load(name: str, target: str) -> Task:
    import importlib

    module, _, attr = target.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise MrcertError(f"task {name!r} names _target_={target!r}, which cannot be imported: {exc}") from None
    if not (isinstance(cls, type) and issubclass(cls, Task)):
        raise MrcertError(f"task {name!r} names _target_={target!r}, which is not a mrcert Task")
    return cls()


TASKS = Registry()
"""Every task, by name (``conf/task/<name>.yaml``'s ``_target_``)."""


def model_title(cfg: DictConfig) -> str:
    """``certify tz augmented small_cnn`` (plus a method other than motion smoothing, the attack's
    k, the shard): a train, certify, smooth or attack run."""
    task = str(cfg.task.name)
    ignored = TASKS.of(cfg).identity.ignored(cfg)
    words = [task, str(cfg.motion.axis), str(cfg.method.name), str(cfg.model.variant), str(cfg.model.arch)]
    if "method" in ignored:  # a method that adds nothing to the key (camera motion smoothing) goes unnamed
        words.remove(str(cfg.method.name))
    if "motion" in ignored:  # a model that never sees the motion (vanilla, pixel noise) has no axis
        words.remove(str(cfg.motion.axis))
    if task == "attack":
        words.append(f"k={cfg.attack.k}")
    if int(OmegaConf.select(cfg, "task.num_shards", default=1) or 1) > 1:
        words.append(f"shard {cfg.task.shard}/{cfg.task.num_shards}")
    return " ".join(words)


# --- identities that several tasks share ----------------------------------------------------
DATA_FILES = ("data.path", "data.poses")
EVALUATION = Identity(
    defines=("task", "data", "model", "motion", "method", "seed", "profile"),
    # The recipe in train.* and the method the model was trained for are named by the
    # checkpoint's identity; the crop is exact.
    ignores=(
        "train",
        "model.trained_for",
        "attack",
        "task.batch_size",
        "task.backend",
        "task.resume",
        "task.crop_sigmas",
    ),
    files=("model.checkpoint", *DATA_FILES),
    partition=PARTITION,
    needs_model=True,
    method="result",
)
"""An evaluation of a trained model (certify, smooth, attack, export)."""

FIXED_PREDICT = (("task.sequential", False, "task.sequential"), ("task.sequential", False, "task.look"))
"""Fixed-n PREDICT (smooth, attack) keeps the keys it had before sequential PREDICT existed."""

HELPER_IGNORES = ("data", "model", "motion", "method", "seed", "profile", "train", "attack")
"""What a helper task (import, gather, ui) never depends on: the composed data, model and recipe."""
