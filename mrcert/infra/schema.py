"""Structured configs: one dataclass schema per config group option, registered in Hydra's
ConfigStore under ``schema/<group>`` and named first in each option's defaults list
(``- /schema/task@_here_: certify``). A key the schema does not have, or a value of the wrong
type, then fails at composition, with Hydra's message naming the key.

Each field's range is declared where the field is (:func:`~mrcert.core.checks.checked`), and
relations between values in the schema's ``relations``; :func:`mrcert.infra.config.validate` runs
both before any run exists.

The schemas mirror the YAML files key for key: a field with a default that a file does not set
would add a key to every run's config, and so change its run key.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from mrcert.core.axes import AXES, is_translation
from mrcert.core.checks import (
    AXES_OR_NULL,
    AXIS,
    BACKEND,
    COUNT,
    FINITE,
    FRACTION,
    METRES,
    METRES_OR_NULL,
    NON_NEGATIVE,
    POSITIVE,
    POSITIVE_INT,
    PROBABILITY,
    RANGE,
    SEED,
    VARIANT,
    Check,
    check_values,
    checked,
    integer,
    number,
    one_of,
)
from mrcert.core.methods import METHODS
from mrcert.errors import ConfigError

AUTO_BATCH = {"cpu": 16, "cuda": 200}
"""``batch_size: auto``: samples rendered and classified at once, by device type
(docs/performance.md): on a CPU 16 keep the activations in cache (3x faster than 200 for the
small CNN); on an H100, 1,100 ResNet-18 forward passes took 0.047 s in batches of 200 against
0.171 s in batches of 16."""
AUTO_OR_COUNT = Check(
    lambda v: v == "auto" or integer(v) and v >= 1,
    f"an integer >= 1, or auto ({AUTO_BATCH['cpu']} on a CPU, {AUTO_BATCH['cuda']} on a GPU)",
)
ALL_OR_COUNT = Check(lambda v: v is None or POSITIVE_INT.holds(v), "an integer >= 1, or null for all")
ANGLES = Check(
    lambda v: isinstance(v, list) and len(v) > 0 and all(number(x) for x in v),
    "a non-empty list of finite angles in degrees",
)
PITCHES = Check(
    lambda v: ANGLES.holds(v) and all(-90 < x < 90 for x in v),
    "a non-empty list of angles in degrees strictly between -90 and 90",
)
MAX_SEQUENTIAL_PREDICT = 400
"""The largest ``task.n`` sequential PREDICT plans for (about 20 s on 2 CPU cores at 400)."""


# --- task --------------------------------------------------------------------------------
@dataclass
class EvaluationTask:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    n: int = checked(POSITIVE_INT)
    alpha: float = checked(PROBABILITY)
    decision: str = checked(one_of("predict", "vote"))
    batch_size: Any = checked(AUTO_OR_COUNT)
    skip: int = checked(POSITIVE_INT)
    max: int | None = checked(
        Check(lambda v: v is None or POSITIVE_INT.holds(v), "an integer >= 1, or null for all"), None
    )
    shard: int = checked(COUNT)
    num_shards: int = checked(POSITIVE_INT)
    crop_sigmas: float = checked(POSITIVE)
    resume: bool = MISSING
    backend: str = checked(BACKEND)
    sequential: bool = MISSING
    look: int = checked(POSITIVE_INT)

    @staticmethod
    def relations(task: Mapping[str, Any], where: str, root: Mapping[str, Any]) -> None:
        """The shard is one of the shards; sequential CERTIFY's first look within n; sequential
        PREDICT by Cohen's test, with an n its exact plan can be made for."""
        shard, shards, n, look = (task.get(k) for k in ("shard", "num_shards", "n", "look"))
        if not 0 <= shard < shards:
            raise ConfigError(f"{where}.shard", shard, f"an integer in [0, task.num_shards={shards})")
        if not task.get("sequential"):
            return
        if not 1 <= look <= n:
            why = f"an integer in [1, task.n={n}]: the sequential procedure's first look"
            raise ConfigError(f"{where}.look", look, why)
        if task.get("name") in ("smooth", "attack"):
            if task.get("decision") == "vote":
                why = "false with task.decision=vote: sequential PREDICT uses Cohen's test"
                raise ConfigError(f"{where}.sequential", True, why)
            if n > MAX_SEQUENTIAL_PREDICT:
                why = (
                    f"at most {MAX_SEQUENTIAL_PREDICT} with task.sequential=true (its exact plan grows with n squared)"
                )
                raise ConfigError(f"{where}.n", n, why)


@dataclass
class Certify(EvaluationTask):
    n0: int = checked(POSITIVE_INT)


@dataclass
class Smooth(EvaluationTask):
    pass


@dataclass
class Attack(EvaluationTask):
    smoothed: bool = MISSING


@dataclass
class Train:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    eval_batch_size: int = checked(POSITIVE_INT)
    resume: bool = MISSING


@dataclass
class Render:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    axes: list[str] | None = checked(AXES_OR_NULL, None)
    num: int = checked(POSITIVE_INT)
    extent: dict[str, float] = field(default_factory=dict)
    motions: Any = None
    backend: str = checked(BACKEND)
    variants: list[str] = field(default_factory=list)
    showcase: str = MISSING

    @staticmethod
    def relations(task: Mapping[str, Any], where: str, root: Mapping[str, Any]) -> None:
        """Each axis's extent is a motion of at least 0."""
        for axis, value in (task.get("extent") or {}).items():
            if axis not in AXES or not number(value) or value < 0:
                why = f"axes from {', '.join(AXES)} with finite values >= 0"
                raise ConfigError(f"{where}.extent.{axis}", value, why)


@dataclass
class Tables:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    profile: str = MISSING
    experiment: str | None = None
    overrides: list[str] = field(default_factory=list)
    archs: list[str] | None = None
    axes: list[str] | None = checked(AXES_OR_NULL, None)
    certify_task: str = MISSING
    show_paper: bool = MISSING
    parent: str | None = None
    output_dir: str = MISSING
    print: str = MISSING
    ui_url: str = MISSING
    page: str | None = None


@dataclass
class Import:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    path: str = MISSING
    dataset: str = MISSING
    arch: str = MISSING
    axis: str = checked(AXIS)
    variant: str = checked(VARIANT)
    profile: str = MISSING
    sigma: float = checked(POSITIVE)
    radius: float = checked(NON_NEGATIVE)
    radius_step: float = checked(POSITIVE)
    tags: dict[str, str] = field(default_factory=dict)


@dataclass
class Gather:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    store: str = MISSING
    without: list[str] = field(default_factory=list)


@dataclass
class Export(EvaluationTask):
    pieces: int = MISSING
    timeout: float = MISSING


@dataclass
class Verify:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    onnx: str | None = None
    vnnlib: str | None = None
    instances: str | None = None
    filter: str | None = None
    timeout: float | None = None
    relaxation: str = MISSING
    max_boxes: int = MISSING
    relu_domains: int = checked(COUNT)
    bound_steps: int = checked(COUNT)
    max_model_mb: float = checked(POSITIVE)
    max_property_mb: float = checked(POSITIVE)
    result: str | None = None
    page: str | None = None


@dataclass
class Ui:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    port: int = checked(Check(lambda v: integer(v) and 1 <= v <= 65535, "a port number in [1, 65535]"))
    screenshot: str | None = None


@dataclass
class Viewpoints:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    pitches: list[float] = checked(PITCHES)
    rolls: list[float] = checked(ANGLES)
    yaws: list[float] | None = checked(Check(lambda v: v is None or ANGLES.holds(v), ANGLES.allowed), None)
    distance: float | None = checked(METRES_OR_NULL, None)
    surroundings: list[str] = checked(
        Check(
            lambda v: isinstance(v, list) and all(x in ("room", "table") for x in v),
            "a list of scene parts from room, table (or [] for the object alone)",
        )
    )
    batch_size: Any = checked(AUTO_OR_COUNT)
    occlusion: bool = MISSING
    occlusion_patch: int = checked(Check(POSITIVE_INT.holds, "an integer >= 1 (pixels)"))


# --- data --------------------------------------------------------------------------------
@dataclass
class Gaps:
    """Least differences between poses, per quantity (degrees, metres)."""

    yaw: float = checked(NON_NEGATIVE)
    pitch: float = checked(NON_NEGATIVE)
    roll: float = checked(NON_NEGATIVE)
    radius: float = checked(NON_NEGATIVE)


@dataclass
class Poses:
    """One split's poses in a synthetic data set's protocol: a ring (one pitch, roll and radius)
    or uniform draws within ranges. For checks only: ``data.protocol`` keeps each data set's own
    keys, as its run keys hold them."""

    per_class: int = checked(POSITIVE_INT)
    yaw_range: list[float] = checked(RANGE)
    pitch_range: list[float] = checked(RANGE)
    roll_range: list[float] = checked(RANGE)
    radius_range: list[float] = checked(RANGE)
    pitch: float = checked(FINITE)
    roll: float = checked(FINITE)
    radius: float = checked(NON_NEGATIVE)
    pitch_law: str = checked(one_of("angle", "area"))
    separation: Gaps = field(default_factory=Gaps)
    apart_from_test: Gaps = field(default_factory=Gaps)


@dataclass
class Protocol:
    """A synthetic data set's pose protocol (``data.protocol``; for checks only, as :class:`Poses`)."""

    yaw_offset: float = checked(FINITE)
    test: Poses = field(default_factory=Poses)
    validation: Poses = field(default_factory=Poses)
    train: Poses = field(default_factory=Poses)
    separation: Gaps = field(default_factory=Gaps)
    separation_rule: str = checked(one_of("every", "any"))


@dataclass
class Camera:
    height: int = checked(POSITIVE_INT)
    width: int = checked(POSITIVE_INT)
    fx: float = checked(POSITIVE)
    fy: float = checked(POSITIVE)
    cx: float = checked(FINITE)
    cy: float = checked(FINITE)
    background: float = MISSING


@dataclass
class Crop:
    max_translation: float = checked(Check(NON_NEGATIVE.holds, "a finite number >= 0 (metres)"))
    max_rotation: float = checked(Check(NON_NEGATIVE.holds, "a finite number >= 0 (radians)"))


@dataclass
class Scene:
    _target_: str = MISSING  # the class that builds it (mrcert.data)
    name: str = MISSING
    source: str = MISSING
    path: str | None = None
    num_classes: int = MISSING
    density: float = checked(METRES)
    image: Camera = field(default_factory=Camera)


@dataclass
class Surroundings:
    """What surrounds the object in a synthetic scene (null: as built; checked against the data set)."""

    parts: list[str] | None = None  # the scene's parts in every view ([]: the object alone)
    room: str | None = None  # the room's style


@dataclass
class Ambient:
    """The share of ambient light of the room, the table and the object (null: as built)."""

    room: float | None = None
    table: float | None = None
    object: float | None = None


@dataclass
class Synthetic:
    _target_: str = MISSING  # the class that builds it (mrcert.data)
    name: str = MISSING
    source: str = MISSING
    num_classes: int = MISSING
    classes: list[str] | None = checked(
        Check(
            lambda v: v is None or isinstance(v, list) and len(v) > 0 and len(set(v)) == len(v),
            "null (every class), or a non-empty list of class names, each once",
        ),
        None,
    )
    seed: int = checked(SEED)
    density: float = checked(METRES)
    room_density: float = checked(METRES)
    extent: float | None = checked(METRES_OR_NULL, None)  # the scene's largest dimension: no translation goes further
    image: Camera = field(default_factory=Camera)
    protocol: Any = MISSING  # pose protocol (its shape is the data set's): checked by relations
    crop: Crop = field(default_factory=Crop)
    downsample: bool = MISSING
    surroundings: Surroundings = field(default_factory=Surroundings)
    ambient: Ambient = field(default_factory=Ambient)
    cache_dir: str = MISSING

    @staticmethod
    def relations(data: Mapping[str, Any], where: str, root: Mapping[str, Any]) -> None:
        """The pose protocol's values (:class:`Protocol`)."""
        protocol = data.get("protocol")
        if not isinstance(protocol, Mapping):
            why = "the pose protocol: a mapping of its splits (test, validation, train) and gaps"
            raise ConfigError(f"{where}.protocol", protocol, why)
        check_values(Protocol, protocol, f"{where}.protocol")


@dataclass
class Released:
    _target_: str = MISSING  # the class that builds it (mrcert.data)
    name: str = MISSING
    source: str = MISSING
    path: str | None = None
    axis: str = checked(AXIS)
    variant: str = checked(VARIANT)
    num_classes: int = MISSING
    extent: float | None = checked(METRES_OR_NULL, None)  # the scene's largest dimension: no translation goes further
    image: Camera = field(default_factory=Camera)
    crop: Crop = field(default_factory=Crop)
    downsample: bool = MISSING


@dataclass
class Custom:
    _target_: str = MISSING  # the class that builds it (mrcert.data)
    name: str = MISSING
    source: str = MISSING
    path: str = MISSING
    poses: str = MISSING
    num_classes: int | None = None
    image: Camera = field(default_factory=Camera)
    crop: Crop = field(default_factory=Crop)
    downsample: bool = MISSING
    cache_dir: str = MISSING


# --- the other groups ----------------------------------------------------------------------
@dataclass
class Downsample:
    every_k: int = checked(POSITIVE_INT)
    voxel: float = checked(METRES)


CURVE_POINTS = 100_000
"""The most radii a certified-accuracy curve may have (``5 sigma / radius_step``: CERTIFY's
largest radius is 2.6 sigma at n = 1000 and under 5 sigma up to n = 10^6)."""


@dataclass
class Motion:
    axis: str = checked(AXIS)
    sigma: float = checked(POSITIVE)
    radius: float = checked(NON_NEGATIVE)
    radius_step: float = checked(POSITIVE)
    downsample: Downsample = field(default_factory=Downsample)

    @staticmethod
    def relations(motion: Mapping[str, Any], where: str, root: Mapping[str, Any]) -> None:
        """Sigma and radius a motion can represent: a rotation angle is at most pi (a larger one
        is a smaller rotation the other way), a translation at most the scene's extent where the
        data set declares one (``data.extent``: a camera moved further sees none of it), and the
        certified-accuracy curve has at most :data:`CURVE_POINTS` radii."""
        data = root.get("data", {})
        sigma, radius, step, extent = motion["sigma"], motion["radius"], motion["radius_step"], data.get("extent")
        if motion.get("axes"):  # multi-axis: radii in sigma units, one sigma per axis
            axes = zip(motion["axes"], motion["sigmas"], strict=False)
            scales = [(f"{where}.sigmas[{i}]", a, v) for i, (a, v) in enumerate(axes)]
        else:
            scales = [(f"{where}.{k}", motion["axis"], v) for k, v in (("sigma", sigma), ("radius", radius))]
        for key, axis, value in scales:
            if axis not in AXES:
                continue  # several joined by '+': the method refuses it when built (one axis each)
            if not is_translation(axis) and value > math.pi:
                raise ConfigError(key, value, "a rotation angle in radians, at most pi")
            if is_translation(axis) and number(extent) and value > extent:
                scene = f"the extent of the {data.get('name')} scene (data.extent)"
                raise ConfigError(key, value, f"at most {extent:.3g} m, {scene}")
        largest = max(5 * sigma, radius)
        if largest / step > CURVE_POINTS:
            raise ConfigError(
                f"{where}.radius_step",
                step,
                f"at least {largest / CURVE_POINTS:.3g}: the certified-accuracy curve up to "
                f"{largest:.6g} (5 sigma or the radius) would have more than {CURVE_POINTS} radii",
            )


@dataclass
class MultiAxisMotion(Motion):
    axes: list[str] = checked(AXES_OR_NULL)
    sigmas: list[float] = checked(
        Check(
            lambda v: isinstance(v, list) and len(v) > 0 and all(POSITIVE.holds(x) for x in v),
            "a non-empty list of finite numbers > 0",
        )
    )


@dataclass
class Model:
    arch: str = MISSING
    net: Any = MISSING  # instantiated from its _target_ (any nn.Module taking num_classes): see core.models.check_net
    variant: str = checked(VARIANT)
    checkpoint: str | None = None
    trained_for: Any = None  # a method's training settings ({name: pixelwise, sigma: 0.25}): see mrcert.infra.resolver


@dataclass
class AttackGroup:
    _target_: str = MISSING  # the class that draws its motions (mrcert.core.attacks)
    name: str = MISSING
    k: int = checked(POSITIVE_INT)
    radius: float = checked(NON_NEGATIVE)


@dataclass
class Tracking:
    enabled: bool = MISSING
    uri: str | None = None
    artifact_location: str | None = None
    experiment: str = MISSING


@dataclass
class Recipe:
    epochs: int = checked(POSITIVE_INT)
    batch_size: int = checked(POSITIVE_INT)
    lr: float = checked(POSITIVE)
    momentum: float = checked(FRACTION)
    weight_decay: float = checked(NON_NEGATIVE)
    step_size: int = checked(POSITIVE_INT)
    gamma: float = checked(Check(lambda v: number(v) and 0 < v <= 1, "a number in (0, 1]"))
    val_fraction: float = checked(FRACTION)
    amp: bool = MISSING


@dataclass
class Profile:
    name: str = MISSING


@dataclass
class Root:
    """The root config (conf/config.yaml and its groups), for checks: its keys, in order, and
    the checks of the values set at the top."""

    task: Any = None
    data: Any = None
    profile: Any = None
    train: Any = None
    motion: Any = None
    method: Any = None
    model: Any = None
    attack: Any = None
    tracking: Any = None
    paths: Any = None
    seed: int = checked(SEED)
    device: str = "auto"  # a device of this machine: checked by validate (it asks torch)
    skip_finished: bool = False
    per_task: Any = None  # each task's settings, checked by that task's schema


SCHEMAS: dict[str, dict[str, type]] = {
    "task": {
        "certify": Certify,
        "smooth": Smooth,
        "attack": Attack,
        "train": Train,
        "render": Render,
        "tables": Tables,
        "import": Import,
        "gather": Gather,
        "viewpoints": Viewpoints,
        "verify": Verify,
        "export": Export,
        "ui": Ui,
    },
    "data": {"scene": Scene, "synthetic": Synthetic, "released": Released, "custom": Custom, "camera": Camera},
    "motion": {"single": Motion, "multi": MultiAxisMotion},
    "method": {name: method.schema for name, method in METHODS.items()},
    "model": {"model": Model},
    "attack": {"attack": AttackGroup},
    "tracking": {"tracking": Tracking},
    "train": {"recipe": Recipe},
    "profile": {"profile": Profile},
}


def register() -> None:
    """Store every schema as ``schema/<group>/<name>`` (idempotent)."""
    store = ConfigStore.instance()
    for group, schemas in SCHEMAS.items():
        for name, node in schemas.items():
            store.store(group=f"schema/{group}", name=name, node=node)
