"""The one table of tasks: name -> what a task is, apart from its computation -- what defines
its result (its :class:`~mrcert.infra.identity.Identity`), the per-image log it writes and that
log's columns, the headline metrics the MLflow runs page shows, and the run's name.

The computations live above this layer and are found by the task's name: its ``run(cfg, ctx)``
in :mod:`mrcert.tasks` (:func:`mrcert.tasks.run_function`), and the headline metrics of its
per-image log in :mod:`mrcert.reporting.metrics` (:func:`mrcert.reporting.metrics.summarize`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

from omegaconf import DictConfig, OmegaConf

from mrcert.infra.identity import PARTITION, Identity


@dataclass(frozen=True)
class Task:
    summary: str
    identity: Identity
    """Which config keys define the task's result (see :mod:`mrcert.infra.identity`)."""
    reusable: bool = True
    """Whether a FINISHED run of the same run key may stand in for a new one (``skip_finished``)."""
    log: str | None = None
    """The per-image log the task writes (in its run folder and artifacts), for tables and shards."""
    columns: tuple[str, ...] = ()
    """The log's columns, in order."""
    headline: tuple[str, ...] = ()
    """Of the headline metrics of its log, the ones the MLflow runs page shows as columns."""
    title: Callable[[DictConfig], str] = lambda cfg: f"{cfg.task.name} {cfg.data.name}"
    """The run's name: what it is, in words, what tells runs apart first (the runs page cuts long names)."""


def _model_title(cfg: DictConfig) -> str:
    """``certify tz augmented small_cnn`` (plus a method other than motion smoothing, the attack's
    k, the shard): a train, certify, smooth or attack run."""
    task = str(cfg.task.name)
    ignored = TASKS[task].identity.ignored(cfg)
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


CERTIFY_COLUMNS = ("idx", "label", "predict", "radius", "correct", "time")
"""The columns of Cohen et al.'s certify logs, which an imported log needs and ours begins with."""


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

FIXED_PREDICT = (("task.sequential", False, "task.sequential"), ("task.sequential", False, "task.look"))
"""Fixed-n PREDICT (smooth, attack) keeps the keys it had before sequential PREDICT existed."""

HELPER_IGNORES = ("data", "model", "motion", "method", "seed", "profile", "train", "attack")
"""What a helper task (import, gather) never depends on: the composed data, model and recipe."""

TASKS: dict[str, Task] = {
    "render": Task(
        "render a scene under motions, or a dataset's images into the cache",
        Identity(
            defines=("task", "data", "motion", "method", "seed", "profile"),
            ignores=("model", "train", "attack", "task.backend"),
            files=DATA_FILES,
            method="result",
        ),
    ),
    "train": Task(
        "train a vanilla or motion-augmented base classifier",
        Identity(
            defines=("task.name", "data", "model", "train", "motion", "method", "seed", "profile"),
            # A method's certify.* never trains; model.trained_for is refused here (an evaluation's).
            ignores=("task", "model.checkpoint", "model.trained_for", "attack", "method.certify"),
            ignore_when=(  # a vanilla model never sees a motion or a method
                ("model.variant", "vanilla", "motion"),
                ("model.variant", "vanilla", "method"),
            ),
            files=DATA_FILES,
            method="model",
        ),
        headline=("test_acc",),
        title=_model_title,
    ),
    "certify": Task(
        "CERTIFY each test image of the smoothed classifier (certify.tsv)",
        replace(EVALUATION, ignore_when=(("task.sequential", False, "task.look"),)),  # fixed n: no looks
        log="certify.tsv",
        columns=(
            *CERTIFY_COLUMNS,
            "count_a",
            "n0",
            "n",
            "p_a_lower",
            "sigma",
            "axis",
            "seconds",
            "projected",
            "margin",
            "radius_unit",
            "sigma_unit",
        ),
        headline=("certified_accuracy", "clean_accuracy", "mean_samples"),
        title=_model_title,
    ),
    "smooth": Task(
        "smoothed benign accuracy: PREDICT at each test pose",
        replace(EVALUATION, ignore_when=FIXED_PREDICT),
        log="smooth.tsv",
        columns=("idx", "label", "predict", "correct", "n", "axis", "seconds"),
        headline=("smoothed_benign_accuracy",),
        title=_model_title,
    ),
    "attack": Task(
        "K-perturbed empirical robust accuracy, base and smoothed",
        replace(
            EVALUATION,
            defines=(*EVALUATION.defines, "attack"),
            ignores=tuple(i for i in EVALUATION.ignores if i != "attack"),
            ignore_when=FIXED_PREDICT,
        ),
        log="attack.tsv",
        columns=(
            "idx",
            "label",
            "axis",
            "k",
            "base_benign",
            "base_robust",
            "base_worst",
            "smoothed_robust",
            "smoothed_worst",
            "smoothed_failure",
            "motion_unit",
            "seconds",
        ),
        headline=("smoothed_robust_accuracy", "base_benign_accuracy"),
        title=_model_title,
    ),
    "verify": Task(
        "verify VNN-LIB properties of ONNX classifiers (unsat, sat, unknown, timeout)",
        # Its files name further files (an instances list): never reused by key.
        Identity(
            defines=("task",),
            ignores=(*HELPER_IGNORES, "task.page", "task.result"),  # where it also writes its answers
            files=("task.onnx", "task.vnnlib", "task.instances"),
        ),
        reusable=False,
        log="verify.tsv",
        columns=(
            "idx",
            "onnx",
            "vnnlib",
            "result",
            "margin",
            "boxes",
            "forward_passes",
            "seconds",
            "timeout",
        ),  # fmt: skip
        headline=("verified", "falsified", "seconds_total"),
        title=lambda cfg: f"verify {cfg.task.instances or cfg.task.vnnlib}",
    ),
    "export": Task(
        "write test images' pose intervals as ONNX + VNN-LIB verification instances",
        replace(EVALUATION, ignores=(*EVALUATION.ignores, "task.sequential", "task.look")),  # it samples nothing
        title=_model_title,
    ),
    "viewpoints": Task(
        "a base classifier's accuracy by camera pitch and roll (synthetic scenes)",
        # The base classifier alone, identified by its checkpoint's content: no smoothing, no motion.
        Identity(
            defines=("task", "data", "model", "seed", "profile"),
            ignores=("train", "model.trained_for", "attack", "motion", "method", "task.batch_size"),
            files=("model.checkpoint", *DATA_FILES),
            needs_model=True,
        ),
        headline=("accuracy",),
        title=lambda cfg: f"viewpoints {cfg.model.variant} {cfg.model.arch}",
    ),
    "tables": Task(
        "the paper's tables and figure from finished MLflow runs",
        Identity(defines=("task", "profile"), ignores=("data", "model", "motion", "method", "seed", "attack", "train")),
        reusable=False,  # its result depends on the store's runs, not only on its config
        title=lambda cfg: f"tables {cfg.task.experiment or 'paper'}",
    ),
    "import": Task(
        "record a certify log computed elsewhere as an MLflow run",
        # The log's metadata (task.dataset, task.arch, ...) is all it is; one cell may hold one log.
        Identity(
            defines=("task",),
            ignores=HELPER_IGNORES,
            files=("task.path",),
            partition=("task.path",),
        ),
        log="certify.tsv",
        columns=CERTIFY_COLUMNS,  # what an imported log needs
        headline=("certified_accuracy", "clean_accuracy"),
        title=lambda cfg: f"import {cfg.task.axis} {cfg.task.arch} {cfg.task.variant}",
    ),
    "gather": Task(
        "copy the finished runs of another store into this one",
        # What it copies depends on the other store's runs, not only on its config.
        Identity(
            defines=("task",),
            ignores=HELPER_IGNORES,
            files=("task.store",),  # checked before any run starts (mrcert.tasks.inputs)
        ),
        reusable=False,
        title=lambda cfg: f"gather {cfg.task.store}",
    ),
}
