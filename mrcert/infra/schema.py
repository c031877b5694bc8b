"""Structured configs: one dataclass schema per config group option, registered in Hydra's
ConfigStore under ``schema/<group>`` and named first in each option's defaults list
(``- /schema/task@_here_: certify``). A key the schema does not have, or a value of the wrong
type, then fails at composition, with Hydra's message naming the key. What a type cannot say
-- ranges, axis names, licensed combinations -- :func:`mrcert.infra.config.validate` checks.

The schemas mirror the YAML files key for key: a field with a default that a file does not set
would add a key to every run's config, and so change its run key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from mrcert.core.methods import METHODS


# --- task --------------------------------------------------------------------------------
@dataclass
class EvaluationTask:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    n: int = MISSING
    alpha: float = MISSING
    decision: str = MISSING
    batch_size: Any = MISSING  # an integer >= 1 or auto: checked by validate
    skip: int = MISSING
    max: int | None = None
    shard: int = MISSING
    num_shards: int = MISSING
    crop_sigmas: float = MISSING
    resume: bool = MISSING
    backend: str = MISSING
    sequential: bool = MISSING
    look: int = MISSING


@dataclass
class Certify(EvaluationTask):
    n0: int = MISSING


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
    eval_batch_size: int = MISSING
    resume: bool = MISSING


@dataclass
class Render:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    axes: list[str] | None = None
    num: int = MISSING
    extent: dict[str, float] = field(default_factory=dict)
    motions: Any = None
    backend: str = MISSING
    variants: list[str] = field(default_factory=list)
    showcase: str = MISSING


@dataclass
class Tables:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    profile: str = MISSING
    experiment: str | None = None
    overrides: list[str] = field(default_factory=list)
    archs: list[str] | None = None
    axes: list[str] | None = None
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
    axis: str = MISSING
    variant: str = MISSING
    profile: str = MISSING
    sigma: float = MISSING
    radius: float = MISSING
    radius_step: float = MISSING
    tags: dict[str, str] = field(default_factory=dict)


@dataclass
class Gather:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    store: str = MISSING


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
    result: str | None = None
    page: str | None = None


@dataclass
class Viewpoints:
    _target_: str = MISSING  # the Task class that runs it
    name: str = MISSING
    pitches: list[float] = MISSING
    rolls: list[float] = MISSING
    yaws: list[float] | None = None
    distance: float | None = None
    surroundings: list[str] = MISSING
    batch_size: Any = MISSING  # an integer >= 1 or auto: checked by validate
    occlusion: bool = MISSING
    occlusion_patch: int = MISSING


# --- data --------------------------------------------------------------------------------
@dataclass
class Camera:
    height: int = MISSING
    width: int = MISSING
    fx: float = MISSING
    fy: float = MISSING
    cx: float = MISSING
    cy: float = MISSING
    background: float = MISSING


@dataclass
class Crop:
    max_translation: float = MISSING
    max_rotation: float = MISSING


@dataclass
class Scene:
    _target_: str = MISSING  # the class that builds it (mrcert.data)
    name: str = MISSING
    source: str = MISSING
    path: str | None = None
    num_classes: int = MISSING
    density: float = MISSING
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
    classes: list[str] | None = None
    seed: int = MISSING
    density: float = MISSING
    room_density: float = MISSING
    extent: float | None = None  # the scene's largest dimension (m): translations are bounded by it
    image: Camera = field(default_factory=Camera)
    protocol: Any = MISSING  # pose protocol: checked by validate (ranges, counts, gaps)
    crop: Crop = field(default_factory=Crop)
    downsample: bool = MISSING
    surroundings: Surroundings = field(default_factory=Surroundings)
    ambient: Ambient = field(default_factory=Ambient)
    cache_dir: str = MISSING


@dataclass
class Released:
    _target_: str = MISSING  # the class that builds it (mrcert.data)
    name: str = MISSING
    source: str = MISSING
    path: str | None = None
    axis: str = MISSING
    variant: str = MISSING
    num_classes: int = MISSING
    extent: float | None = None  # the scene's largest dimension (m): translations are bounded by it
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
    every_k: int = MISSING
    voxel: float = MISSING


@dataclass
class Motion:
    axis: str = MISSING
    sigma: float = MISSING
    radius: float = MISSING
    radius_step: float = MISSING
    downsample: Downsample = field(default_factory=Downsample)


@dataclass
class MultiAxisMotion(Motion):
    axes: list[str] = MISSING
    sigmas: list[float] = MISSING


@dataclass
class Model:
    arch: str = MISSING
    net: Any = MISSING  # instantiated from its _target_ (any nn.Module taking num_classes)
    variant: str = MISSING
    checkpoint: str | None = None
    trained_for: Any = None  # a method's training settings ({name: pixelwise, sigma: 0.25}): see mrcert.infra.stages


@dataclass
class AttackGroup:
    _target_: str = MISSING  # the class that draws its motions (mrcert.core.attacks)
    name: str = MISSING
    k: int = MISSING
    radius: float = MISSING


@dataclass
class Tracking:
    enabled: bool = MISSING
    uri: str | None = None
    artifact_location: str | None = None
    experiment: str = MISSING


@dataclass
class Recipe:
    epochs: int = MISSING
    batch_size: int = MISSING
    lr: float = MISSING
    momentum: float = MISSING
    weight_decay: float = MISSING
    step_size: int = MISSING
    gamma: float = MISSING
    val_fraction: float = MISSING
    amp: bool = MISSING


@dataclass
class Profile:
    name: str = MISSING


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
