"""VNN-LIB properties: an input box and an unsafe output region, read and written.

A property declares inputs ``X_i`` and outputs ``Y_j``, bounds every input
(``(assert (<= X_i u))``, ``(assert (>= X_i l))``) and states the unsafe region as a disjunction
of conjunctions of linear comparisons between outputs or an output and a constant
(``(assert (or (and (>= Y_1 Y_0)) ...))``, or a single comparison or conjunction). The property
holds (``unsat``) when no input of the box gives outputs in the unsafe region. One box of inputs
is supported (a disjunction over inputs is refused in one line).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mrcert.errors import MrcertError

TOKEN = re.compile(r"\(|\)|[^\s()]+")


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


def _parse(text: str) -> list:
    text = re.sub(r";[^\n]*", "", text)
    stack: list[list] = [[]]
    for tok in TOKEN.findall(text):
        if tok == "(":
            stack.append([])
        elif tok == ")":
            if len(stack) == 1:
                raise MrcertError("VNN-LIB: unbalanced parentheses")
            done = stack.pop()
            stack[-1].append(done)
        else:
            stack[-1].append(tok)
    if len(stack) != 1:
        raise MrcertError("VNN-LIB: unbalanced parentheses")
    return stack[0]


def read_vnnlib(path: Path | str) -> Property:
    """The property of a VNN-LIB file (module docstring)."""
    path = Path(path)
    try:
        forms = _parse(path.read_text())
    except OSError as exc:
        raise MrcertError(f"cannot read VNN-LIB property {str(path)!r}: {exc.strerror}") from None
    names = {"X": [], "Y": []}
    for form in forms:
        if form and form[0] == "declare-const":
            kind, _, index = form[1].partition("_")
            if kind not in names or not index.isdigit():
                raise MrcertError(f"{path}: variable {form[1]} is neither X_i nor Y_j")
            names[kind].append(int(index))
    n_in, n_out = len(names["X"]), len(names["Y"])
    low, high = np.full(n_in, -np.inf), np.full(n_in, np.inf)
    unsafe: list[list[tuple[np.ndarray, float]]] = []

    def term(tok) -> tuple[str, int | float]:
        if isinstance(tok, str) and re.fullmatch(r"[XY]_\d+", tok):
            return tok[0], int(tok[2:])
        try:
            return "c", float(tok)
        except (TypeError, ValueError):
            raise MrcertError(f"{path}: {tok!r} is not a variable or a number") from None

    def comparison(form) -> tuple[np.ndarray, float]:
        """``c . Y + d >= 0`` for ``(>= A B)`` or ``(<= A B)``."""
        if len(form) != 3 or form[0] not in (">=", "<="):
            raise MrcertError(f"{path}: expected (>= A B) or (<= A B), got {form}")
        c, d = np.zeros(n_out), 0.0
        sign = 1.0 if form[0] == ">=" else -1.0
        for side, s in ((form[1], sign), (form[2], -sign)):
            kind, value = term(side)
            if kind == "X":
                raise MrcertError(f"{path}: a constraint mixing inputs and outputs is not supported")
            if kind == "Y":
                c[value] += s
            else:
                d += s * value
        return c, d

    def conjunction(form) -> list[tuple[np.ndarray, float]]:
        if form[0] == "and":
            return [comparison(f) for f in form[1:]]
        return [comparison(form)]

    for form in forms:
        if not form or form[0] != "assert":
            continue
        body = form[1]
        variables = {t[0] for t in _flatten(body) if isinstance(t, str) and re.fullmatch(r"[XY]_\d+", t)}
        if variables == {"X"}:
            if body[0] not in (">=", "<=") or len(body) != 3:
                raise MrcertError(f"{path}: input constraints must be bounds (<= X_i c), (>= X_i c); got {body[0]}")
            (ka, va), (kb, vb) = term(body[1]), term(body[2])
            if {ka, kb} != {"X", "c"}:
                raise MrcertError(f"{path}: input constraints must compare one input with a number")
            index, value = (va, vb) if ka == "X" else (vb, va)
            upper = (body[0] == "<=") == (ka == "X")
            if upper:
                high[index] = min(high[index], value)
            else:
                low[index] = max(low[index], value)
        elif variables == {"Y"}:
            if body[0] == "or":
                unsafe += [conjunction(f) for f in body[1:]]
            else:
                unsafe.append(conjunction(body))
        else:
            raise MrcertError(
                f"{path}: an assertion over both inputs and outputs (several input boxes) is not supported"
            )
    if not np.isfinite(low).all() or not np.isfinite(high).all():
        raise MrcertError(f"{path}: every input needs a lower and an upper bound")
    if (low > high).any():
        raise MrcertError(f"{path}: an input's lower bound exceeds its upper bound (X_{int(np.argmax(low > high))})")
    if not unsafe:
        raise MrcertError(f"{path}: no output constraint (the unsafe region)")
    return Property(low, high, unsafe, n_out)


def _flatten(form):
    if isinstance(form, list):
        for f in form:
            yield from _flatten(f)
    else:
        yield form


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
