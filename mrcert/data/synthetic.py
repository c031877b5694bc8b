"""Synthetic datasets: scene clouds per class and the paper's pose protocols (docs/method.md §3).

``metaroom_synth``: the room, the table and one of 20 objects; test poses on a ring (6 yaws
at 2.8 m, pitch 10 deg, roll 0), training poses drawn uniformly in the protocol's ranges and
kept apart from every test pose (see :mod:`mrcert.data.protocols`), with the camera inside
the room. ``tabletop_synth``: one flat shape on a 1 m table; test and training poses drawn
in the robot protocol's ranges, kept apart by its gaps. Every draw comes from a generator
seeded by ``(data.seed, label, split)``, so adding classes or changing counts of one split
never changes the others.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from mrcert.data.datasets import PosedCloudData, Split
from mrcert.data.protocols import PITCH_LAWS, PoseSet, ring_poses, sample_poses
from mrcert.errors import MrcertError
from mrcert.scenes import metaroom, tabletop

Cloud = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class Family:
    """A synthetic scene family: its classes, the parts of the scene around the object (each
    built from the ``data`` config and the room's style), the object (from its class name and
    density), how high a camera may go (None: no ceiling), its room styles (none: no room)."""

    classes: tuple[str, ...]
    parts: dict[str, Callable[..., Cloud]]
    object: Callable[..., Cloud]
    max_camera_z: float | None
    rooms: tuple[str, ...] = ()
    lit: tuple[str, ...] = ()
    """What ``data.ambient`` may set (parts, ``object``): each builder takes ``ambient=``."""


FAMILIES = {
    "metaroom_synth": Family(
        tuple(metaroom.CLASSES),
        {
            "room": lambda d, room, **light: metaroom.room(d.room_density, d.seed, room, **light),
            "table": lambda d, room, **light: metaroom.table(d.density, **light),
        },
        metaroom.object_cloud,
        metaroom.CEILING_Z - 0.05,  # cameras stay 5 cm below the ceiling
        metaroom.ROOMS,
        ("room", "table", "object"),
    ),
    "tabletop_synth": Family(
        tuple(tabletop.CLASSES),
        {"table": lambda d, room: tabletop.table(d.room_density)},
        tabletop.shape_cloud,
        None,
    ),
}

AS_BUILT = {"parts": None, "room": None}
"""``data.surroundings`` as built: every part, the family's first room style."""


def _share(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and 0.0 <= value <= 1.0


SPLITS = ("test", "train", "validation")  # their index seeds each split's generator


def _ranges(train: DictConfig) -> dict[str, tuple[float, float]]:
    return {q: tuple(train[f"{q}_range"]) for q in ("yaw", "pitch", "roll", "radius")}


class SyntheticSource:
    """Scenes and poses of a synthetic dataset described by a ``data`` config."""

    def __init__(self, data: DictConfig):
        self.data = data
        self.family = FAMILIES[data.source]
        known = self.family.classes
        chosen = list(data.classes) if data.get("classes") else list(known)
        unknown = [c for c in chosen if c not in known]
        if unknown:
            raise MrcertError(f"data.classes has unknown classes {unknown}; allowed: {', '.join(known)}")
        self.classes: list[str] = sorted(chosen)
        self.settings = self._check_surroundings(data.get("surroundings") or {})
        self.ambient = self._check_ambient(data.get("ambient") or {})
        self.pitch_law = str(data.protocol.train.get("pitch_law", "angle"))
        if self.pitch_law not in PITCH_LAWS:
            raise MrcertError(
                f"data.protocol.train.pitch_law={self.pitch_law!r} is not allowed; allowed: {', '.join(PITCH_LAWS)} "
                "(uniform in angle, or over the sphere's area)"
            )
        self._parts: dict[str, Cloud] = {}
        self._last: tuple[int, Cloud] | None = None

    def _check_surroundings(self, given: Any) -> dict[str, Any]:
        """``data.surroundings`` checked against the family: one line naming the value and what is allowed."""
        settings = AS_BUILT | (OmegaConf.to_container(given) if OmegaConf.is_config(given) else dict(given))
        parts, room = settings["parts"], settings["room"]
        if parts is not None and any(p not in self.family.parts for p in parts):
            raise MrcertError(
                f"data.surroundings.parts={parts} names a part {self.data.name} does not have; "
                f"allowed: a list of {', '.join(self.family.parts)} ([] for the object alone), or null for all"
            )
        if room is not None and room not in self.family.rooms:
            allowed = ", ".join(self.family.rooms) if self.family.rooms else f"none ({self.data.name} has no room)"
            raise MrcertError(
                f"data.surroundings.room={room!r} is not a room style of {self.data.name}; allowed: {allowed}"
            )
        return settings

    def _check_ambient(self, given: Any) -> dict[str, float]:
        """``data.ambient``: the shares set (null: as built), each a part's or the object's that the
        family lights, in [0, 1]."""
        shares = OmegaConf.to_container(given) if OmegaConf.is_config(given) else dict(given)
        shares = {k: v for k, v in shares.items() if v is not None}
        for what, share in shares.items():
            if what not in self.family.lit:
                lit = ", ".join(self.family.lit) or "nothing"
                raise MrcertError(
                    f"data.ambient.{what}={share} is not allowed: {self.data.name} sets the light of {lit}"
                )
            if not _share(share):
                raise MrcertError(
                    f"data.ambient.{what}={share} is not allowed: a share of ambient light in [0, 1] "
                    "(1: unshaded), or null as built"
                )
        return {k: float(v) for k, v in shares.items()}

    def _light(self, what: str) -> dict[str, float]:
        return {"ambient": self.ambient[what]} if what in self.ambient else {}

    # --- scenes -----------------------------------------------------------------------------
    def part(self, name: str) -> Cloud:
        """One part of the scene around the object (``room``, ``table``): (points, colours), world
        frame, in ``data.surroundings``' room style and ``data.ambient``'s light."""
        if name not in self.family.parts:
            raise MrcertError(f"{self.data.name} has no scene part {name!r}; its parts: {', '.join(self.family.parts)}")
        if name not in self._parts:
            room = self.settings["room"] or (self.family.rooms[0] if self.family.rooms else None)
            self._parts[name] = self.family.parts[name](self.data, room, **self._light(name))
        return self._parts[name]

    @property
    def surroundings(self) -> tuple[str, ...]:
        """The parts around the object in every view (``data.surroundings.parts``; null: all)."""
        chosen = self.settings["parts"]
        return tuple(self.family.parts) if chosen is None else tuple(str(p) for p in chosen)

    @cached_property
    def background(self) -> Cloud:
        """Everything but the object: (points, colours) in the world frame."""
        return self.only(self.surroundings)

    def only(self, parts: tuple[str, ...]) -> Cloud:
        """The named ``parts`` of the scene around the object, concatenated (possibly none)."""
        chosen = [self.part(p) for p in parts]
        if not chosen:
            return np.empty((0, 3)), np.empty((0, 3), np.float32)
        return np.concatenate([p for p, _ in chosen]), np.concatenate([c for _, c in chosen])

    def scene(self, label: int, parts: tuple[str, ...]) -> Cloud:
        """Class ``label``'s object with only the named ``parts`` around it (world frame)."""
        bp, bc = self.only(parts)
        op, oc = self.object(label)
        return np.concatenate([bp, op]), np.concatenate([bc, oc])

    def object(self, label: int) -> tuple[np.ndarray, np.ndarray]:
        return self.family.object(self.classes[label], self.data.density, **self._light("object"))

    def cloud(self, label: int) -> tuple[np.ndarray, np.ndarray]:
        """The scene of class ``label``: background + object, world frame (the last one is kept)."""
        if self._last is None or self._last[0] != label:
            bp, bc = self.background
            op, oc = self.object(label)
            self._last = (label, (np.concatenate([bp, op]), np.concatenate([bc, oc])))
        return self._last[1]

    # --- poses ------------------------------------------------------------------------------
    def _target(self) -> tuple[float, float, float]:
        return tuple(float(v) for v in self.data.protocol.target)

    def _held_out_set(self, name: str, label: int) -> PoseSet | None:
        """The ``test`` or ``validation`` poses of class ``label``: a ring (``ring: true``: ``per_class``
        yaws evenly spread from ``yaw_start``) or drawn uniformly in the split's ranges, each of the
        quantities in ``apart_from_test`` at least that far from every test pose's (never a test
        pose); None when the protocol has no such split."""
        spec = self.data.protocol.get(name)
        if spec is None:
            return None
        if spec.get("ring", False):
            start = float(spec.get("yaw_start", 0.0))
            return ring_poses(
                spec.per_class, (start, start + 360.0), spec.pitch, spec.roll, spec.radius, self._target()
            )
        rng = np.random.default_rng([self.data.seed, label, SPLITS.index(name)])
        gaps = spec.get("apart_from_test")
        apart = [(self._held_out_set("test", label).params, OmegaConf.to_container(gaps))] if gaps else []
        return sample_poses(spec.per_class, _ranges(spec), rng, apart=apart, target=self._target())

    def _train_set(self, label: int) -> PoseSet:
        """Training poses, kept apart (``separation_rule``) from the test poses by ``separation`` and
        from the validation poses by ``validation.separation``."""
        p = self.data.protocol
        rng = np.random.default_rng([self.data.seed, label, SPLITS.index("train")])
        apart = [(self._held_out_set("test", label).params, OmegaConf.to_container(p.separation))]
        validation = self._held_out_set("validation", label)
        if validation is not None:
            apart.append((validation.params, OmegaConf.to_container(p.validation.separation)))
        return sample_poses(
            p.train.per_class,
            _ranges(p.train),
            rng,
            apart=apart,
            rule=str(p.separation_rule),
            max_camera_z=self.family.max_camera_z,
            target=self._target(),
            pitch_law=self.pitch_law,
        )

    def has_split(self, name: str) -> bool:
        return name in ("train", "test") or (name == "validation" and self.data.protocol.get(name) is not None)

    def split(self, name: str) -> Split:
        """The ``train``, ``test`` or ``validation`` split: every class's poses, class by class."""
        if not self.has_split(name):
            raise ValueError(f"{self.data.name} has no {name!r} split")
        make = self._train_set if name == "train" else lambda label: self._held_out_set(name, label)
        sets = [(label, make(label)) for label in range(len(self.classes))]
        params = np.concatenate([s.params for _, s in sets])
        labels = np.concatenate([np.full(len(s), label) for label, s in sets]).astype(np.int64)
        return Split(self.poses(params), params, labels)

    def poses(self, params: np.ndarray) -> np.ndarray:
        """Camera-to-world poses (N, 4, 4) of protocol parameters (N, 4: yaw, pitch, roll in
        degrees, radius in metres), the protocol's ``yaw_offset`` added to each yaw."""
        shifted = np.array(params, np.float64)
        shifted[:, 0] += float(self.data.protocol.get("yaw_offset", 0.0))
        return PoseSet(shifted, self._target()).poses


class SyntheticData(PosedCloudData):
    def __init__(self, data: DictConfig):
        super().__init__(data)
        self.source = SyntheticSource(data)
        self.classes = self.source.classes

    def cloud(self, label: int):
        return self.source.cloud(label)

    def split(self, name: str) -> Split:
        return self.source.split(name)

    def has_split(self, name: str) -> bool:
        return self.source.has_split(name)

    def identity(self) -> dict[str, Any]:
        """What the cached images depend on; surroundings, light and pitch law as built add nothing,
        so that caches made before they were settings stay valid."""
        keep = ("source", "seed", "density", "room_density", "protocol")
        out = {k: OmegaConf.to_container(v) if OmegaConf.is_config(v := self.data[k]) else v for k in keep}
        if out["protocol"].get("train", {}).get("pitch_law") == "angle":
            del out["protocol"]["train"]["pitch_law"]
        source = self.source
        changed = {"surroundings": source.settings} if source.settings != AS_BUILT else {}
        return out | {"classes": self.classes} | changed | ({"ambient": source.ambient} if source.ambient else {})
