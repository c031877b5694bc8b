"""Soundness on small random networks over every operator and attribute the ONNX reader accepts:
against the exact truth of a mixed-integer program (:mod:`tests.fuzz_networks`), ``task=verify``
never answers ``unsat`` where a counterexample exists, and every ``sat`` carries a counterexample
that the reference executor (onnxruntime) confirms inside the box."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from mrcert.formats.onnx_model import ATTRIBUTES
from mrcert.tasks.verify import Settings, verify_instance
from tests.fuzz_networks import CLASSES, Oracle, random_network
from tests.onnx_graphs import Reference, save, vnnlib_text

TOLERANCE = 1e-5
"""Below this, in either direction, the exact truth is too close to call in float32."""
LEGACY = {("Dropout", "ratio"), ("Dropout", "seed"), ("Dropout", "is_test"), ("BatchNormalization", "spatial"),
          ("BatchNormalization", "is_test"), ("Constant", "value_float"), ("Constant", "value_int"),
          ("Constant", "value_ints"), ("MaxPool", "dilations"), ("AveragePool", "dilations")}  # fmt: skip
"""Attributes random networks of opset 17 leave out: older opsets' and those read only at their default."""


def fuzz(count: int, seed: int, tmp_path) -> tuple[Counter, list[str], set]:
    """Answers of ``count`` random instances, the problems found, and the (operator, attribute) pairs used."""
    answers: Counter = Counter()
    problems: list[str] = []
    used: set = set()
    for i in range(count):
        rng = np.random.default_rng([seed, i])
        net = random_network(rng)
        m = net.onnx()
        used |= {(n.op_type, a.name) for n in m.graph.node for a in n.attribute} | {
            (n.op_type, "") for n in m.graph.node
        }
        reference = Reference(m)
        centre = rng.uniform(size=int(np.prod(net.shape)))
        label = int(np.argmax(reference(centre.reshape(net.shape))[0]))
        eps = 10 ** rng.uniform(-3, -0.3)
        low, high = centre - eps, centre + eps
        save(m, tmp_path / "net.onnx")
        pairs = [[(j, label)] for j in range(CLASSES) if j != label]
        (tmp_path / "p.vnnlib").write_text(vnnlib_text(low, high, pairs, CLASSES))
        verdict, reason = verify_instance(tmp_path / "net.onnx", tmp_path / "p.vnnlib", 10.0, Settings(max_boxes=2000))
        answers[verdict.result] += 1
        truth, bound = Oracle(net).worst(low, high, label)
        answers["exact truth undecided"] += not (truth > TOLERANCE or bound < -TOLERANCE)
        where = (
            f"network {i} ({net.kind}, seed {seed}): {verdict.result}, exact worst margin in [{truth:.3g}, {bound:.3g}]"
        )
        if verdict.result == "unsat" and truth > TOLERANCE:
            problems.append(f"unsound: {where}")
        if verdict.result == "sat":
            x = verdict.x.reshape(net.shape)
            y = reference(x)[0]
            inside = ((x.ravel() >= low) & (x.ravel() <= high)).all()
            if not inside or not any(y[j] >= y[label] for j in range(CLASSES) if j != label):
                problems.append(f"invalid counterexample: {where}")
            if bound < -1e-3:
                problems.append(f"sat where the exact truth is unsat: {where}")
        if verdict.result == "error":
            problems.append(f"refused: {where}: {reason}")
    return answers, problems, used


def check(count: int, seed: int, tmp_path) -> Counter:
    answers, problems, used = fuzz(count, seed, tmp_path)
    assert not problems, "\n".join(problems)
    return answers


def test_random_networks_are_never_verified_where_a_counterexample_exists(tmp_path):
    answers = check(40, 0, tmp_path)
    assert answers["unsat"] >= 5 and answers["sat"] >= 5, answers  # both kinds of truth are met


@pytest.mark.slow
def test_four_hundred_random_networks_over_every_accepted_attribute(tmp_path):
    answers, problems, used = fuzz(420, 1, tmp_path)
    assert not problems, "\n".join(problems)
    wanted = {(op, a) for op, attrs in ATTRIBUTES.items() for a in ("", *attrs)} - LEGACY
    assert wanted <= used, sorted(wanted - used)
    print(dict(answers))
