"""Config resolvers and validation.

Importing this module registers the OmegaConf resolvers the configs in ``conf/`` use.
:func:`validate` checks every value a user can type before any work starts and raises
:class:`~mrcert.errors.ConfigError` naming the key, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import secrets
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, MissingMandatoryValue, OmegaConf

from mrcert.core.checks import check_values
from mrcert.errors import ConfigError
from mrcert.infra.schema import SCHEMAS, Root, register

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

PER_TASK_KEYS = ("n", "decision", "skip", "sequential")
"""What an experiment may set for one task only, under ``per_task.<task>`` (``per_task: {attack:
{skip: 2}}``): the evaluation tasks' files read these keys through ``${task_setting:KEY,DEFAULT}``,
so a value given on the command line (``task.skip=1``) still wins."""


def task_setting(key: str, default: Any, *, _root_: DictConfig) -> Any:
    """``${task_setting:skip,1}``: the experiment's ``per_task.<this task>.<key>``, else ``default``."""
    return OmegaConf.select(_root_, f"per_task.{_root_.task.name}.{key}", default=default)


OmegaConf.register_new_resolver("task_setting", task_setting, replace=True)


# --- validation -------------------------------------------------------------------------


def structured_nodes(cfg: DictConfig, where: str) -> Iterator[tuple[type, str]]:
    """(schema, dotted key) of the node at ``where`` and of its children, for those a schema
    types (``- /schema/<group>@_here_: <name>`` in their option's defaults), in order."""
    node = OmegaConf.select(cfg, where)
    if not isinstance(node, DictConfig):
        return
    schema = OmegaConf.get_type(node)
    if dataclasses.is_dataclass(schema):
        yield schema, where
    for key in node:
        yield from structured_nodes(cfg, f"{where}.{key}")


def _at(data: Mapping[str, Any], where: str) -> Any:
    for key in where.split("."):
        data = data[key]
    return data


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


TOP_LEVEL = tuple(f.name for f in dataclasses.fields(Root))
"""The root config's keys; anything else at the top, such as a mistyped ``+seeed=1``, is refused
instead of silently making a separate result."""


def _unknown_top_level(cfg: DictConfig) -> None:
    for key in (k for k in cfg if k != "hydra" and k not in TOP_LEVEL):
        near = difflib.get_close_matches(str(key), TOP_LEVEL, n=3, cutoff=0.5)
        hint = f"did you mean {' or '.join(near)}? " if near else ""
        raise ConfigError(
            str(key),
            OmegaConf.select(cfg, str(key)),
            f"not a key of mrcert's config; {hint}its keys: {', '.join(TOP_LEVEL)}",
        )


def _method(cfg: DictConfig, data: dict) -> None:
    """The method is one mrcert has, it accepts its parameters and the motion, and it does what
    the task asks of it (built here once, so that a refusal comes before any run opens)."""
    from mrcert.core.methods import build_method
    from mrcert.core.methods.base import SERVICES

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
        method = registered(str(value["name"]))
    except ConfigError as exc:
        raise ConfigError("model.trained_for.name", value["name"], exc.allowed) from None
    check_values(method.schema, value, "model.trained_for")
    schema = OmegaConf.structured(method.schema)
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


def validate(cfg: DictConfig, scene_task: bool = True) -> None:
    """Raise :class:`ConfigError` for the first value that breaks a rule (hydra node excluded);
    the method and the model only for a task that reads them (``scene_task``)."""
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
    check_values(Root, data, "")
    _per_task(data.get("per_task"))  # before the task's own values: a bad one is named where it was set
    nodes = [node for group in data for node in structured_nodes(cfg, group)]
    for schema, where in (node for node in nodes if "." not in node[1]):  # a group's schema checks its nested ones
        check_values(schema, data[where], where)
    for schema, where in nodes:
        relations = getattr(schema, "relations", None)
        if relations is not None:
            relations(_at(data, where), where, data)
    if scene_task:  # the method and the model, built and checked once (their imports take seconds)
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
        check_values(SCHEMAS["task"][task], values, f"per_task.{task}")


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
