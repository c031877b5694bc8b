"""VNN-LIB properties: input boxes and unsafe output regions, read and written.

A property declares inputs ``X_i`` and outputs ``Y_j`` (``(declare-const X_0 Real)``, each
index from 0 up without a gap) and asserts formulas over them. As the standard says, the
top-level assertions hold together (a conjunction): the property is ``sat`` when some input
satisfies every one of them with the network's outputs. A formula is a comparison
(``(<= A B)``, ``(>= A B)``, ``A`` and ``B`` linear terms: numbers, variables, ``(+ ...)``,
``(- ...)``, ``(* c t)``) or an ``(and ...)`` / ``(or ...)`` of formulas; a comparison is over
inputs alone (then a bound of one input) or over outputs alone. :func:`read_cases` turns the
assertions into their disjunctive normal form grouped by input box: a list of :class:`Property`
(one box each, with the disjunction of conjunctions over outputs that is unsafe there); the
property is ``unsat`` when every box is. The usual file (bounds on every input, one ``(or (and
...))`` over outputs) is one box.

The file is read as a stream of top-level forms (gzipped or not); a file beyond ``max_bytes``
(:data:`MAX_PROPERTY_BYTES`) is refused before it is parsed, and every malformed file in one
line naming the file, the line and what was expected: an undeclared or out-of-range variable,
a number that is not finite (NaN, infinities), a form that is not one of the above, a
disjunctive normal form beyond :data:`MAX_DISJUNCTS` disjuncts.
"""

from __future__ import annotations

import gzip
import io
import itertools
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mrcert.errors import MrcertError

TOKEN = re.compile(r"\(|\)|[^\s()]+")
NAME = re.compile(r"([XY])_(\d+)")
BOUND = re.compile(r"\s*\(\s*assert\s+\(\s*(<=|>=)\s+(X_\d+)\s+([^\s();]+)\s*\)\s*\)\s*")
"""A line that asserts one bound of one input, the bulk of a property: read without tokens."""
MAX_PROPERTY_BYTES = 64 * 2**20
"""The largest property file (unzipped) read by default."""
MAX_DISJUNCTS = 10_000
"""The most disjuncts a property's assertions may expand to (their disjunctive normal form)."""


@dataclass
class Property:
    """``low <= X <= high`` (flat), and the unsafe region: a list of disjuncts, each a list of
    conjuncts ``(c, d)`` meaning ``c . Y + d >= 0`` (``c`` over the outputs)."""

    low: np.ndarray
    high: np.ndarray
    unsafe: list[list[tuple[np.ndarray, float]]]
    outputs: int

    def violated(self, y: np.ndarray) -> bool:
        """Whether the outputs ``y`` lie in the unsafe region."""
        return any(all(float(c @ y) + d >= 0 for c, d in conj) for conj in self.unsafe)

    def contains(self, x: np.ndarray) -> bool:
        x = np.asarray(x, np.float64).ravel()
        return bool(((x >= self.low) & (x <= self.high)).all())


class Form(list):
    """A parenthesised form, with the line it starts on."""

    line: int = 0


class _Reader:
    """One file's forms, read as a stream (module docstring)."""

    def __init__(self, path: Path, max_bytes: int):
        self.path, self.max_bytes = path, int(max_bytes)
        self.line = 0

    def fail(self, line: int, what: str) -> MrcertError:
        return MrcertError(f"{self.path}:{line}: {what}")

    def _lines(self) -> Iterator[str]:
        try:
            with self.path.open("rb") as probe:
                zipped = probe.read(2) == b"\x1f\x8b"
            if not zipped and self.path.stat().st_size > self.max_bytes:
                raise MrcertError(
                    f"{self.path}: {self.path.stat().st_size} bytes, beyond the {self.max_bytes} a property "
                    "may have here (task.max_property_mb)"
                )
            raw = gzip.open(self.path, "rb") if zipped else self.path.open("rb")
        except OSError as exc:
            raise MrcertError(f"cannot read VNN-LIB property {str(self.path)!r}: {exc.strerror}") from None
        read = 0
        with raw, io.TextIOWrapper(raw, encoding="utf-8", errors="strict") as text:
            try:
                for line in text:
                    read += len(line)
                    if read > self.max_bytes:
                        raise MrcertError(f"{self.path}: more than {self.max_bytes} bytes once unzipped, beyond "
                                          "what a property may have here (task.max_property_mb)")  # fmt: skip
                    yield line
            except (UnicodeDecodeError, OSError, EOFError) as exc:
                raise MrcertError(f"{self.path}: not a readable text file ({exc})") from None

    def forms(self) -> Iterator[Form]:
        """The top-level forms, one at a time."""
        stack: list[Form] = []
        for number, line in enumerate(self._lines(), start=1):
            self.line = number
            simple = None if stack else BOUND.fullmatch(line)
            if simple is not None:  # (assert (<= X_i c)): most lines of a property, read whole
                inner = Form(simple.group(1, 2, 3))
                outer = Form(["assert", inner])
                inner.line = outer.line = number
                yield outer
                continue
            for tok in TOKEN.findall(line.split(";", 1)[0]):
                if tok == "(":
                    form = Form()
                    form.line = number
                    stack.append(form)
                elif tok == ")":
                    if not stack:
                        raise self.fail(number, "unbalanced parentheses: a ')' closes nothing")
                    done = stack.pop()
                    if stack:
                        stack[-1].append(done)
                    else:
                        yield done
                elif not stack:
                    raise self.fail(number, f"expected '(' to open a command, got {tok!r}")
                else:
                    stack[-1].append(tok)
        if stack:
            raise self.fail(stack[-1].line, "unbalanced parentheses: this '(' is never closed")


@dataclass
class _Disjunct:
    """One conjunction of the disjunctive normal form: input bounds and output comparisons."""

    bounds: tuple  # ((index, is_upper, value), ...)
    outputs: tuple  # (({j: coefficient}, constant), ...): sum + constant >= 0


def _tighten(low: dict, high: dict, bounds) -> None:
    """Input bounds ``(index, is_upper, value)`` met with those ``low`` and ``high`` hold."""
    for index, upper, value in bounds:
        if upper:
            high[index] = min(high.get(index, value), value)
        else:
            low[index] = max(low.get(index, value), value)


def read_cases(
    path: Path | str, inputs: int | None = None, outputs: int | None = None, max_bytes: int = MAX_PROPERTY_BYTES
) -> list[Property]:
    """The property of a VNN-LIB file as its input boxes, each with the unsafe region there
    (module docstring); ``inputs`` and ``outputs``, when given, are the network's sizes, which
    the declarations must match."""
    path = Path(path)
    reader = _Reader(path, max_bytes)
    declared: dict[str, set[int]] = {"X": set(), "Y": set()}
    low: dict[int, float] = {}
    high: dict[int, float] = {}
    common: list[tuple[dict, float]] = []  # output comparisons asserted on their own
    compound: list[list[_Disjunct]] = []  # the other assertions, each as its normal form
    size = 1

    def number(tok: str, line: int) -> float:
        try:
            value = float(tok)
        except ValueError:
            raise reader.fail(line, f"expected a number or a declared variable, got {tok!r}") from None
        if not math.isfinite(value):
            raise reader.fail(line, f"the number {tok!r} is not finite")
        return value

    def variable(tok: str, line: int) -> tuple[str, int] | None:
        m = NAME.fullmatch(tok)
        if m is None:
            return None
        kind, index = m.group(1), int(m.group(2))
        if index not in declared[kind]:
            raise reader.fail(line, f"{tok} is used but not declared (declare-const {tok} Real)")
        return kind, index

    def term(form, line: int) -> tuple[dict[tuple[str, int], float], float]:
        """A linear term: coefficients by variable, and a constant."""
        if isinstance(form, str):
            var = variable(form, line)
            return ({var: 1.0}, 0.0) if var else ({}, number(form, line))
        line = form.line
        if not form or not isinstance(form[0], str) or form[0] not in ("+", "-", "*") or len(form) < 2:
            raise reader.fail(line, f"expected a number, a variable or (+ ...), (- ...), (* c t), got {_show(form)}")
        parts = [term(f, line) for f in form[1:]]
        if form[0] == "*":
            if len(parts) != 2 or (parts[0][0] and parts[1][0]):
                raise reader.fail(line, f"expected (* c t) with c a number, got {_show(form)}")
            (ca, ka), (cb, kb) = parts
            coeffs, factor, const = (cb, ka, kb) if not ca else (ca, kb, ka)
            return {v: c * factor for v, c in coeffs.items()}, const * factor
        signs = [1.0] + [(-1.0 if form[0] == "-" else 1.0)] * (len(parts) - 1)
        if form[0] == "-" and len(parts) == 1:
            signs = [-1.0]
        coeffs: dict = {}
        const = 0.0
        for s, (c, k) in zip(signs, parts, strict=True):
            for v, a in c.items():
                coeffs[v] = coeffs.get(v, 0.0) + s * a
            const += s * k
        return coeffs, const

    def comparison(form: Form) -> _Disjunct:
        """``(<= A B)`` / ``(>= A B)`` as an input bound or an output comparison."""
        if len(form) != 3:
            raise reader.fail(form.line, f"expected ({form[0]} A B), got {_show(form)}")
        (ca, ka), (cb, kb) = term(form[1], form.line), term(form[2], form.line)
        sign = 1.0 if form[0] == ">=" else -1.0  # sign * (A - B) >= 0
        coeffs = {v: sign * (ca.get(v, 0.0) - cb.get(v, 0.0)) for v in set(ca) | set(cb)}
        coeffs = {v: c for v, c in coeffs.items() if c != 0.0}
        const = sign * (ka - kb)
        kinds = {v[0] for v in coeffs}
        if kinds == {"X", "Y"}:
            raise reader.fail(form.line, f"a comparison of inputs with outputs is not supported: {_show(form)}")
        if not kinds:
            raise reader.fail(form.line, f"a comparison of numbers alone: {_show(form)}")
        if kinds == {"X"}:
            if len(coeffs) != 1:
                raise reader.fail(form.line, f"an input comparison must bound one input: {_show(form)}")
            [((_, index), a)] = coeffs.items()
            return _Disjunct(((index, a < 0, -const / a),), ())  # a X + const >= 0
        return _Disjunct((), (({j: c for (_, j), c in coeffs.items()}, const),))

    def normal_form(form) -> list[_Disjunct]:
        if isinstance(form, str) or not form or not isinstance(form[0], str):
            line = form.line if isinstance(form, Form) else reader.line
            raise reader.fail(line, f"expected a formula (<= A B), (>= A B), (and ...) or (or ...), got {_show(form)}")
        head = form[0]
        if head in ("<=", ">="):
            return [comparison(form)]
        if head not in ("and", "or"):
            raise reader.fail(form.line, f"expected <=, >=, and or or, got {head!r}")
        if len(form) < 2:
            raise reader.fail(form.line, f"({head}) needs at least one formula")
        parts = [normal_form(f) for f in form[1:]]
        if head == "or":
            out = [d for p in parts for d in p]
        else:
            out = conjoin(parts, form.line)
        if len(out) > MAX_DISJUNCTS:
            raise reader.fail(form.line, f"the formula expands to more than {MAX_DISJUNCTS} disjuncts")
        return out

    def conjoin(parts: list[list[_Disjunct]], line: int) -> list[_Disjunct]:
        total = math.prod(len(p) for p in parts)
        if total > MAX_DISJUNCTS:
            raise reader.fail(line, f"the assertions expand to {total} disjuncts, more than {MAX_DISJUNCTS}")
        return [
            _Disjunct(tuple(b for d in combo for b in d.bounds), tuple(o for d in combo for o in d.outputs))
            for combo in itertools.product(*parts)
        ]

    for form in reader.forms():
        if not form or not isinstance(form[0], str):
            raise reader.fail(form.line, f"expected (declare-const ...) or (assert ...), got {_show(form)}")
        if form[0] == "declare-const":
            m = NAME.fullmatch(form[1]) if len(form) == 3 and isinstance(form[1], str) else None
            if m is None or form[2] != "Real":
                raise reader.fail(form.line, f"expected (declare-const X_i Real) or (declare-const Y_j Real), "
                                             f"got {_show(form)}")  # fmt: skip
            kind, index = m.group(1), int(m.group(2))
            if index in declared[kind]:
                raise reader.fail(form.line, f"{form[1]} is declared twice")
            declared[kind].add(index)
            continue
        if form[0] != "assert":
            raise reader.fail(form.line, f"expected (declare-const ...) or (assert ...), got ({form[0]} ...)")
        if len(form) != 2:
            raise reader.fail(form.line, f"expected (assert FORMULA) with one formula, got {len(form) - 1}")
        bound = form[1]
        if len(bound) == 3 and bound[0] in ("<=", ">=") and isinstance(bound[1], str) and isinstance(bound[2], str):
            var = variable(bound[1], bound.line)
            if var is not None and var[0] == "X" and NAME.fullmatch(bound[2]) is None:  # X_i <= c or X_i >= c
                _tighten(low, high, ((var[1], bound[0] == "<=", number(bound[2], bound.line)),))
                continue
        dnf = normal_form(form[1])
        if len(dnf) == 1:  # a conjunction: its bounds and comparisons hold throughout
            _tighten(low, high, dnf[0].bounds)
            common.extend(dnf[0].outputs)
            continue
        size *= len(dnf)
        if size > MAX_DISJUNCTS:
            raise reader.fail(form.line, f"the assertions expand to more than {MAX_DISJUNCTS} disjuncts")
        compound.append(dnf)

    for kind, what in (("X", "inputs"), ("Y", "outputs")):
        indices = declared[kind]
        if indices != set(range(len(indices))):
            gap = min(set(range(len(indices))) - indices)
            raise MrcertError(f"{path}: {kind}_{max(indices)} is declared but {kind}_{gap} is not (the {what} "
                              f"are numbered from 0 without a gap)")  # fmt: skip
    n_in, n_out = len(declared["X"]), len(declared["Y"])
    for have, want, what in ((n_in, inputs, "inputs"), (n_out, outputs, "outputs")):
        if want is not None and have != want:
            raise MrcertError(f"{path}: declares {have} {what} where the network has {want}")
    if not n_in or not n_out:
        raise MrcertError(f"{path}: declares {n_in} inputs and {n_out} outputs; a property needs both")
    dnf = conjoin(compound, reader.line) if compound else [_Disjunct((), ())]
    boxes: dict[tuple, Property] = {}
    for d in dnf:
        lo, hi = dict(low), dict(high)
        _tighten(lo, hi, d.bounds)
        missing = [i for i in range(n_in) if i not in lo or i not in hi]
        if missing:
            raise MrcertError(f"{path}: every input needs a lower and an upper bound (X_{missing[0]} has "
                              f"{'no lower' if missing[0] not in lo else 'no upper'})")  # fmt: skip
        l_arr = np.array([lo[i] for i in range(n_in)], np.float64)
        h_arr = np.array([hi[i] for i in range(n_in)], np.float64)
        if (l_arr > h_arr).any():
            first = int(np.argmax(l_arr > h_arr))
            raise MrcertError(f"{path}: an input's lower bound exceeds its upper bound (X_{first})")
        rows = [*common, *d.outputs]
        if not rows:
            raise MrcertError(f"{path}: no output constraint (the unsafe region)")
        conj = []
        for coeffs, const in rows:
            c = np.zeros(n_out)
            for j, a in coeffs.items():
                c[j] += a
            conj.append((c, float(const)))
        key = (l_arr.tobytes(), h_arr.tobytes())
        if key not in boxes:
            boxes[key] = Property(l_arr, h_arr, [], n_out)
        boxes[key].unsafe.append(conj)
    return list(boxes.values())


def read_vnnlib(
    path: Path | str, inputs: int | None = None, outputs: int | None = None, max_bytes: int = MAX_PROPERTY_BYTES
) -> Property:
    """The property of a VNN-LIB file with one input box (:func:`read_cases`; several are refused)."""
    cases = read_cases(path, inputs, outputs, max_bytes)
    if len(cases) != 1:
        raise MrcertError(f"{path}: a disjunction of {len(cases)} input boxes, where one is read here")
    return cases[0]


def _show(form, limit: int = 60) -> str:
    text = form if isinstance(form, str) else "(" + " ".join(_show(f, limit) for f in form) + ")"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def write_vnnlib(
    path: Path | str, low: np.ndarray, high: np.ndarray, label: int, outputs: int, comment: str = ""
) -> Path:
    """The competition's robustness property: every input within ``[low, high]`` gives class
    ``label`` the largest output (unsafe: some other output at least as large)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    low, high = np.asarray(low, np.float64).ravel(), np.asarray(high, np.float64).ravel()
    lines = [f"; {comment}" if comment else "; a robustness property", ""]
    lines += [f"(declare-const X_{i} Real)" for i in range(len(low))] + [""]
    lines += [f"(declare-const Y_{j} Real)" for j in range(outputs)] + [""]
    for i, (lo, hi) in enumerate(zip(low, high, strict=True)):  # repr: the values round-trip exactly
        lines += [f"(assert (<= X_{i} {float(hi)!r}))", f"(assert (>= X_{i} {float(lo)!r}))"]
    lines += ["", "(assert (or"] + [f"\t(and (>= Y_{j} Y_{label}))" for j in range(outputs) if j != label] + ["))", ""]
    path.write_text("\n".join(lines))
    return path


def counterexample_text(x: np.ndarray, y: np.ndarray) -> str:
    """A counterexample as the competition's result files give it after ``sat``."""
    entries = [f"(X_{i} {float(v)!r})" for i, v in enumerate(np.asarray(x, np.float64).ravel())]
    entries += [f"(Y_{j} {float(v)!r})" for j, v in enumerate(np.asarray(y, np.float64).ravel())]
    return "(" + "\n ".join(entries) + ")\n"
