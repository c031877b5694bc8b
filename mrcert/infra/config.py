"""Config resolvers and validation.

Importing this module registers the OmegaConf resolvers the configs in ``conf/`` use.
:func:`validate` checks every value a user can type before any work starts and raises
:class:`~mrcert.errors.ConfigError` naming the key, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import secrets
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, MissingMandatoryValue, OmegaConf

from mrcert.core.geometry import AXES, is_translation
from mrcert.errors import ConfigError
from mrcert.infra.runtime import AUTO_BATCH
from mrcert.infra.schema import SCHEMAS, register

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
_FALLBACK_UID = secrets.token_hex(3)


def run_uid() -> str:
    """Suffix that makes run directories unique; one per launch, shared by its jobs."""
    return os.environ.get("MRCERT_RUN_UID", _FALLBACK_UID)


def new_launch_uid() -> None:
    """Draw a fresh launch suffix; exported so that launcher workers inherit it."""
    os.environ["MRCERT_RUN_UID"] = secrets.token_hex(3)


register()  # the structured-config schemas the option files name
OmegaConf.register_new_resolver("mrcert_uid", run_uid, replace=True)
OmegaConf.register_new_resolver("mrcert_abspath", lambda p: os.path.abspath(str(p)), replace=True)

PROFILES = tuple(sorted(p.stem for p in (CONF_DIR / "profile").glob("*.yaml")))
"""The profiles (``conf/profile/``): how much of the paper's protocol a run does."""


def per_profile(values: Mapping[str, Any], *, _root_: DictConfig) -> Any:
    """``${per_profile:{paper: 0.0025, quick: 0.004}}``: the value for the selected profile. A
    value that depends on the profile names every profile, so that no data set or recipe falls
    back to another profile's settings (a profile added later is refused until it is given one)."""
    if not isinstance(values, Mapping) or set(values) != set(PROFILES):
        raise ConfigError("per_profile", values, f"a value for each profile: {', '.join(PROFILES)}")
    return values[_root_.profile.name]


OmegaConf.register_new_resolver("per_profile", per_profile, replace=True)

MAX_SEQUENTIAL_PREDICT = 400
"""The largest ``task.n`` sequential PREDICT plans for (about 20 s on 2 CPU cores at 400)."""

PER_TASK_KEYS = ("n", "decision", "skip", "sequential")
"""What an experiment may set for one task only, under ``per_task.<task>`` (``per_task: {attack:
{skip: 2}}``): the evaluation tasks' files read these keys through ``${task_setting:KEY,DEFAULT}``,
so a value given on the command line (``task.skip=1``) still wins."""


def task_setting(key: str, default: Any, *, _root_: DictConfig) -> Any:
    """``${task_setting:skip,1}``: the experiment's ``per_task.<this task>.<key>``, else ``default``."""
    return OmegaConf.select(_root_, f"per_task.{_root_.task.name}.{key}", default=default)


OmegaConf.register_new_resolver("task_setting", task_setting, replace=True)


# --- validation -------------------------------------------------------------------------

Rule = tuple[Callable[[Any], bool], str]


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _positive(v: Any) -> bool:
    return _number(v) and v > 0


def _positive_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


def _axis(v: Any) -> bool:
    """One axis, or several joined by '+' (a multi-axis smoothing's name)."""
    return isinstance(v, str) and all(a in AXES for a in v.split("+"))


_ANGLES = "a non-empty list of finite angles in degrees"
RULES: dict[str, Rule] = {
    # Rules by the last component of a key, so that every group's keys of that name obey them.
    "sigma": (_positive, "a finite number > 0"),
    "radius": (lambda v: _number(v) and v >= 0, "a finite number >= 0"),
    "radius_step": (_positive, "a finite number > 0"),
    "alpha": (lambda v: _number(v) and 0 < v < 1, "a number strictly between 0 and 1"),
    "height": (_positive_int, "an integer >= 1"),
    "width": (_positive_int, "an integer >= 1"),
    "fx": (_positive, "a finite number > 0"),
    "fy": (_positive, "a finite number > 0"),
    "cx": (_number, "a finite number"),
    "cy": (_number, "a finite number"),
    "density": (_positive, "a finite number > 0 (metres)"),
    "extent": (lambda v: v is None or _positive(v), "a finite number > 0 (metres), or null"),
    "num": (_positive_int, "an integer >= 1"),
    "k": (_positive_int, "an integer >= 1"),
    "axis": (_axis, f"one of {', '.join(AXES)} (or several joined by '+')"),
    "axes": (
        lambda v: v is None or isinstance(v, list) and len(v) > 0 and all(_axis(a) for a in v),
        f"a non-empty list of axes from {', '.join(AXES)} (or null for all)",
    ),
    "backend": (lambda v: v in ("auto", "numba", "torch", "triton"), "one of auto, numba, torch, triton"),
    "decision": (lambda v: v in ("predict", "vote"), "predict or vote"),
    "seed": (lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**32, "an integer in [0, 2**32)"),
    "room_density": (_positive, "a finite number > 0 (metres)"),
    "per_class": (_positive_int, "an integer >= 1"),
    "max_translation": (lambda v: _number(v) and v >= 0, "a finite number >= 0 (metres)"),
    "max_rotation": (lambda v: _number(v) and v >= 0, "a finite number >= 0 (radians)"),
    "every_k": (_positive_int, "an integer >= 1"),
    "voxel": (_positive, "a finite number > 0 (metres)"),
    "variant": (lambda v: v in ("vanilla", "augmented"), "vanilla or augmented"),
    "epochs": (_positive_int, "an integer >= 1"),
    "val_fraction": (lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)"),
    "batch_size": (_positive_int, "an integer >= 1"),
    "eval_batch_size": (_positive_int, "an integer >= 1"),
    "lr": (_positive, "a finite number > 0"),
    "momentum": (lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)"),
    "weight_decay": (lambda v: _number(v) and v >= 0, "a finite number >= 0"),
    "step_size": (_positive_int, "an integer >= 1"),
    "gamma": (lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]"),
    "n": (_positive_int, "an integer >= 1"),
    "n0": (_positive_int, "an integer >= 1"),
    "skip": (_positive_int, "an integer >= 1"),
    "max": (lambda v: v is None or _positive_int(v), "an integer >= 1, or null for all"),
    "shard": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "an integer >= 0"),
    "num_shards": (_positive_int, "an integer >= 1"),
    "crop_sigmas": (_positive, "a finite number > 0"),
    "look": (_positive_int, "an integer >= 1"),
    "sigmas": (
        lambda v: isinstance(v, list) and len(v) > 0 and all(_positive(x) for x in v),
        "a non-empty list of finite numbers > 0",
    ),
    "pitches": (
        lambda v: isinstance(v, list) and len(v) > 0 and all(_number(x) and -90 < x < 90 for x in v),
        "a non-empty list of angles in degrees strictly between -90 and 90",
    ),
    "rolls": (lambda v: isinstance(v, list) and len(v) > 0 and all(_number(x) for x in v), _ANGLES),
    "yaws": (lambda v: v is None or isinstance(v, list) and len(v) > 0 and all(_number(x) for x in v), _ANGLES),
    "distance": (lambda v: v is None or _positive(v), "a finite number > 0 (metres), or null"),
    "occlusion_patch": (_positive_int, "an integer >= 1 (pixels)"),
    "classes": (
        lambda v: v is None or isinstance(v, list) and len(v) > 0 and len(set(v)) == len(v),
        "null (every class), or a non-empty list of class names, each once",
    ),
    "surroundings": (
        lambda v: isinstance(v, list) and all(x in ("room", "table") for x in v),
        "a list of scene parts from room, table (or [] for the object alone)",
    ),
}
TASK_BATCH_RULE: Rule = (
    lambda v: v == "auto" or _positive_int(v),
    f"an integer >= 1, or auto ({AUTO_BATCH['cpu']} on a CPU, {AUTO_BATCH['cuda']} on a GPU)",
)
RANGE_RULE: Rule = (
    lambda v: isinstance(v, list) and len(v) == 2 and all(_number(x) for x in v) and v[0] <= v[1],
    "a list [low, high] of two finite numbers with low <= high",
)


def rule_for(path: str) -> Rule | None:
    """The rule for a dotted key, by its last component (``*_range`` keys share one rule)."""
    name = path.rsplit(".", 1)[-1]
    if path.startswith("task.tags."):
        return None
    if path == "task.batch_size":
        return TASK_BATCH_RULE
    return RANGE_RULE if name.endswith("_range") else RULES.get(name)


def _leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted key, value) of every leaf; a list with a rule of its own (``axes``, ``*_range``) is one leaf."""
    if isinstance(node, dict):
        children = [(f"{prefix}.{k}" if prefix else str(k), v) for k, v in node.items()]
    else:
        children = [(f"{prefix}[{i}]", v) for i, v in enumerate(node)]
    for path, value in children:
        if isinstance(value, dict) or (isinstance(value, list) and rule_for(path) is None):
            yield from _leaves(value, path)
        else:
            yield path, value


def _unknown_keys(node: Any, prefix: str) -> Iterator[tuple[str, list[str]]]:
    """Keys of a structured node (and its structured children) that its schema does not have,
    e.g. added with ``+task.x=1``: (dotted key, the schema's keys)."""
    if not isinstance(node, DictConfig):
        return
    schema = OmegaConf.get_type(node)
    if dataclasses.is_dataclass(schema):
        known = [f.name for f in dataclasses.fields(schema)]
        for key in node:
            if key not in known:
                yield f"{prefix}.{key}", known
    for key in node:
        child = node._get_node(key)
        if isinstance(child, DictConfig):
            yield from _unknown_keys(child, f"{prefix}.{key}")


TOP_LEVEL = (
    "task",
    "data",
    "profile",
    "train",
    "motion",
    "method",
    "model",
    "attack",
    "tracking",
    "paths",
    "seed",
    "device",
    "skip_finished",
    "per_task",
)
"""The root config's keys (conf/config.yaml and its groups); anything else at the top, such as
a mistyped ``+seeed=1``, is refused instead of silently making a separate result."""


def _unknown_top_level(cfg: DictConfig) -> None:
    for key in (k for k in cfg if k != "hydra" and k not in TOP_LEVEL):
        near = difflib.get_close_matches(str(key), TOP_LEVEL, n=3, cutoff=0.5)
        hint = f"did you mean {' or '.join(near)}? " if near else ""
        raise ConfigError(
            str(key),
            OmegaConf.select(cfg, str(key)),
            f"not a key of mrcert's config; {hint}its keys: {', '.join(TOP_LEVEL)}",
        )


CURVE_POINTS = 100_000
"""The most radii a certified-accuracy curve may have (``5 sigma / radius_step``: CERTIFY's
largest radius is 2.6 sigma at n = 1000 and under 5 sigma up to n = 10^6)."""


def _motion_scale(motion: Mapping[str, Any], data: Mapping[str, Any]) -> None:
    """Sigma and radius a motion can represent: a rotation angle is at most pi (a larger one is a
    smaller rotation the other way), a translation at most the scene's extent where the data
    set declares one (``data.extent``: a camera moved further sees none of it), and the
    certified-accuracy curve has at most ``CURVE_POINTS`` radii."""
    sigma, radius, step = (motion.get(k) for k in ("sigma", "radius", "radius_step"))
    if not all(_number(v) for v in (sigma, radius, step)) or step <= 0:
        return  # reported by the per-key rules
    extent = data.get("extent")
    if motion.get("axes"):  # multi-axis: radii in sigma units, one sigma per axis
        axes = zip(motion["axes"], motion["sigmas"], strict=False)
        scales = [(f"motion.sigmas[{i}]", a, v) for i, (a, v) in enumerate(axes)]
    else:
        scales = [(f"motion.{k}", str(motion.get("axis")), v) for k, v in (("sigma", sigma), ("radius", radius))]
    for key, axis, value in scales:
        if axis not in AXES:
            continue  # reported by the per-key rules
        if not is_translation(axis) and value > math.pi:
            raise ConfigError(key, value, "a rotation angle in radians, at most pi")
        if is_translation(axis) and _number(extent) and value > extent:
            scene = f"the extent of the {data.get('name')} scene (data.extent)"
            raise ConfigError(key, value, f"at most {extent:.3g} m, {scene}")
    largest = max(5 * sigma, radius)
    if largest / step > CURVE_POINTS:
        raise ConfigError(
            "motion.radius_step",
            step,
            f"at least {largest / CURVE_POINTS:.3g}: the certified-accuracy curve up to "
            f"{largest:.6g} (5 sigma or the radius) would have more than {CURVE_POINTS} radii",
        )


def _method(cfg: DictConfig, data: dict) -> None:
    """The method is one mrcert has, it accepts its parameters and the motion, and it does what
    the task asks of it (built here once, so that a refusal comes before any run opens)."""
    from mrcert.core.method import SERVICES
    from mrcert.core.methods import build_method

    if "method" not in data or "motion" not in data:
        return
    method = build_method(cfg)
    task = data.get("task", {})
    name, asked = data["method"]["name"], None
    if task.get("name") in ("smooth", "attack") and (task.get("name") != "attack" or task.get("smoothed")):
        asked = ("task", task["name"], task["name"])
    elif task.get("name") == "train" and data.get("model", {}).get("variant") != "vanilla":
        asked = ("model.variant", data["model"]["variant"], "train")
    elif task.get("name") == "certify" and task.get("sequential"):
        asked = ("task.sequential", True, "sequential")
    if asked and asked[2] not in method.serves:
        key, value, service = asked
        served = "; ".join(["task=certify", *(SERVICES[s] for s in sorted(method.serves))])
        raise ConfigError(key, value, f"something method={name} serves: {served}")


def trained_for(data: dict) -> dict | None:
    """The method the model that ``data`` (a plain config) evaluates was trained for, when it is
    not the evaluation's own (``model.trained_for``: that method's training settings, as
    ``method.*`` would give them), checked against the method's schema; else None."""
    from mrcert.core.methods import registered

    value = data.get("model", {}).get("trained_for")
    if value is None:
        return None
    allowed = "a method's training settings, e.g. {name: pixelwise, sigma: 0.25} or {name: camera_motion}"
    if not isinstance(value, dict) or "name" not in value:
        raise ConfigError("model.trained_for", value, allowed)
    try:
        schema = OmegaConf.structured(registered(str(value["name"])).schema)
    except ConfigError as exc:
        raise ConfigError("model.trained_for.name", value["name"], exc.allowed) from None
    try:
        merged = OmegaConf.merge(schema, value)
    except Exception:  # noqa: BLE001 - an unknown key or a value of the wrong type
        raise ConfigError("model.trained_for", value, f"{allowed}; keys: {', '.join(schema)}") from None
    unset = [k for k in merged if k != "certify" and OmegaConf.is_missing(merged, k)]
    if unset:
        raise ConfigError("model.trained_for", value, f"{allowed}; it lacks {', '.join(unset)}")
    return value


def _trained_for(data: dict) -> None:
    """``model.trained_for`` names a method's training settings, for an evaluation only."""
    value = data.get("model", {}).get("trained_for")
    if value is not None and data.get("task", {}).get("name") == "train":
        raise ConfigError(
            "model.trained_for",
            value,
            "null for task=train (it picks an evaluation's model); train for a method with method=...",
        )
    trained_for(data)


def validate(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for the first value that breaks a rule (hydra node excluded)."""
    _unknown_top_level(cfg)
    try:
        data = plain(cfg, throw_on_missing=True)
    except MissingMandatoryValue as exc:
        raise ConfigError(exc.full_key, "???", "a value must be given") from None
    for group in (k for k in cfg if k != "hydra"):
        for key, known in _unknown_keys(cfg._get_node(group), str(group)):
            raise ConfigError(
                key, OmegaConf.select(cfg, key), f"not a key of this {group}; its keys: {', '.join(known)}"
            )
    for path, value in _leaves(data):
        rule = rule_for(path)
        if rule is not None and not rule[0](value):
            raise ConfigError(path, value, rule[1])
    task = data.get("task", {})
    shard, shards = task.get("shard", 0), task.get("num_shards")
    if isinstance(shards, int) and isinstance(shard, int) and not 0 <= shard < shards:
        raise ConfigError("task.shard", task.get("shard"), f"an integer in [0, task.num_shards={task['num_shards']})")
    look, n = task.get("look"), task.get("n")
    if task.get("sequential") and isinstance(n, int) and not (isinstance(look, int) and 1 <= look <= n):
        raise ConfigError("task.look", look, f"an integer in [1, task.n={n}]: the sequential procedure's first look")
    if task.get("sequential") and task.get("name") in ("smooth", "attack"):
        if task.get("decision") == "vote":
            raise ConfigError(
                "task.sequential", True, "false with task.decision=vote: sequential PREDICT uses Cohen's test"
            )
        if isinstance(n, int) and n > MAX_SEQUENTIAL_PREDICT:
            limit = f"at most {MAX_SEQUENTIAL_PREDICT} with task.sequential=true (its exact plan grows with n squared)"
            raise ConfigError("task.n", n, limit)
    extent = task.get("extent") or {}
    for axis, value in extent.items():
        if axis not in AXES or not _number(value) or value < 0:
            raise ConfigError(f"task.extent.{axis}", value, f"axes from {', '.join(AXES)} with finite values >= 0")
    motion = data.get("motion", {})
    _motion_scale(motion, data.get("data", {}))
    _per_task(data.get("per_task"))
    _method(cfg, data)
    _trained_for(data)
    if "model" in data:
        from mrcert.core.models import check_net

        check_net(data["model"].get("net"))
    _device(data.get("device", "auto"))


def _per_task(settings: Any) -> None:
    """``per_task``: for tasks that read them (their schema has every key of :data:`PER_TASK_KEYS`),
    a mapping of some of those keys; checked whatever the task run, so that a mistyped name in
    an experiment is refused before it could be silently ignored."""
    if settings is None:
        return
    readers = [
        n for n, schema in SCHEMAS["task"].items() if set(PER_TASK_KEYS) <= {f.name for f in dataclasses.fields(schema)}
    ]
    if not isinstance(settings, dict):
        raise ConfigError("per_task", settings, f"a mapping from task names ({', '.join(readers)}) to their settings")
    for task, values in settings.items():
        if task not in readers:
            raise ConfigError(f"per_task.{task}", values, f"settings of one of the tasks {', '.join(readers)}")
        if not isinstance(values, dict):
            raise ConfigError(f"per_task.{task}", values, f"a mapping of some of {', '.join(PER_TASK_KEYS)}")
        for key, value in values.items():
            if key not in PER_TASK_KEYS:
                raise ConfigError(
                    f"per_task.{task}.{key}", value, f"one of the per-task settings {', '.join(PER_TASK_KEYS)}"
                )


def _device(device: Any) -> None:
    """``auto``, ``cpu``, or a GPU this machine has (``cuda``, ``cuda:N``)."""
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    gpus = f"cuda, cuda:0 to cuda:{count - 1}" if count else "no GPU on this machine"
    if device in ("auto", "cpu") or count and device == "cuda":
        return
    if isinstance(device, str) and device.startswith("cuda:") and device[5:].isdigit() and int(device[5:]) < count:
        return
    raise ConfigError("device", device, f"auto, cpu, or a GPU of this machine ({gpus})")


def plain(cfg: DictConfig | Mapping[str, Any], throw_on_missing: bool = False) -> dict[str, Any]:
    """The config resolved into plain dicts and lists, without Hydra's own ``hydra`` node."""
    if not OmegaConf.is_config(cfg):
        return {k: v for k, v in dict(cfg).items() if k != "hydra"}
    return {
        key: OmegaConf.to_container(value, resolve=True, throw_on_missing=throw_on_missing)
        if OmegaConf.is_config(value)
        else value
        for key, value in ((k, cfg[k]) for k in cfg if k != "hydra")
    }


def to_yaml(cfg: DictConfig) -> str:
    """The config resolved, as YAML (hydra node excluded)."""
    return OmegaConf.to_yaml(OmegaConf.create(plain(cfg)))
