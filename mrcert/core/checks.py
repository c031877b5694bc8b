"""What a config value must be: the checks a schema's fields declare.

A schema (a dataclass of :mod:`mrcert.infra.schema` or :mod:`mrcert.core.methods.schemas`)
declares each field's range with :func:`checked` and the relations between its values (and
other nodes') in a static ``relations(values, where, root)`` method. Config validation runs
them on the composed config before any run exists; a value that fails is one
:class:`~mrcert.errors.ConfigError` line naming the key, the value and what is allowed. Plain
Python, no torch: ``mrcert --help`` and validation stay light.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from mrcert.core.axes import AXES
from mrcert.errors import ConfigError

CHECK = "mrcert.check"
"""The key of a field's check in its metadata."""


@dataclass(frozen=True)
class Check:
    """A value's condition and, in words, what it allows."""

    holds: Callable[[Any], bool]
    allowed: str

    def __call__(self, where: str, value: Any) -> None:
        if not self.holds(value):
            raise ConfigError(where, value, self.allowed)


def checked(check: Check, default: Any = MISSING) -> Any:
    """A schema field whose values must pass ``check``."""
    return field(default=default, metadata={CHECK: check})


def field_checks(schema: type) -> Iterator[tuple[str, Check]]:
    """(field name, check) of every checked field of a schema dataclass."""
    for f in dataclasses.fields(schema):
        if CHECK in f.metadata:
            yield f.name, f.metadata[CHECK]


def check_values(schema: type, values: Mapping[str, Any], where: str) -> None:
    """Every checked field of ``schema`` that ``values`` holds (``where``: their node's dotted
    key), and those of a nested schema (a field made by a dataclass's ``default_factory``) in
    the mapping under its name."""
    for f in dataclasses.fields(schema):
        key, value = f"{where}.{f.name}" if where else f.name, values.get(f.name)
        if CHECK in f.metadata and f.name in values:
            f.metadata[CHECK](key, value)
        elif dataclasses.is_dataclass(f.default_factory) and f.name in values:
            if not isinstance(value, Mapping):
                keys = ", ".join(n.name for n in dataclasses.fields(f.default_factory))
                raise ConfigError(key, value, f"a mapping of some of {keys}")
            check_values(f.default_factory, value, key)


def number(v: Any) -> bool:
    """A finite int or float (not a bool)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def axis(v: Any) -> bool:
    """One axis, or several joined by '+' (a multi-axis smoothing's name)."""
    return isinstance(v, str) and all(a in AXES for a in v.split("+"))


def _list_of(v: Any, holds: Callable[[Any], bool]) -> bool:
    return isinstance(v, list) and len(v) > 0 and all(holds(x) for x in v)


def one_of(*values: str) -> Check:
    """One of ``values`` ("a or b"; "one of a, b, c")."""
    allowed = " or ".join(values) if len(values) == 2 else f"one of {', '.join(values)}"
    return Check(lambda v: v in values, allowed)


POSITIVE = Check(lambda v: number(v) and v > 0, "a finite number > 0")
NON_NEGATIVE = Check(lambda v: number(v) and v >= 0, "a finite number >= 0")
FINITE = Check(number, "a finite number")
POSITIVE_INT = Check(lambda v: integer(v) and v >= 1, "an integer >= 1")
COUNT = Check(lambda v: integer(v) and v >= 0, "an integer >= 0")
PROBABILITY = Check(lambda v: number(v) and 0 < v < 1, "a number strictly between 0 and 1")
FRACTION = Check(lambda v: number(v) and 0 <= v < 1, "a number in [0, 1)")
SEED = Check(lambda v: integer(v) and 0 <= v < 2**32, "an integer in [0, 2**32)")
METRES = Check(lambda v: number(v) and v > 0, "a finite number > 0 (metres)")
METRES_OR_NULL = Check(lambda v: v is None or number(v) and v > 0, "a finite number > 0 (metres), or null")
AXIS = Check(axis, f"one of {', '.join(AXES)} (or several joined by '+')")
AXES_OR_NULL = Check(
    lambda v: v is None or _list_of(v, axis), f"a non-empty list of axes from {', '.join(AXES)} (or null for all)"
)
BACKEND = one_of("auto", "numba", "torch", "triton")
VARIANT = one_of("vanilla", "augmented")
RANGE = Check(
    lambda v: isinstance(v, list) and len(v) == 2 and all(number(x) for x in v) and v[0] <= v[1],
    "a list [low, high] of two finite numbers with low <= high",
)
