"""VNN-LIB as the standard says: top-level assertions hold together, a disjunction of input boxes
is answered box by box, every name is checked against the declarations and the network, NaN and
infinities are refused, every malformed file is one line naming the file and the line, and a
benchmark answers its other instances when one cannot be."""

from __future__ import annotations

import gzip
import time

import pandas as pd
import pytest

from mrcert.errors import MrcertError
from mrcert.formats.vnnlib import read_cases, read_vnnlib
from mrcert.tasks.verify import Settings, verify_instance
from tests.conftest import run_cli
from tests.onnx_graphs import Reference, model, save, tensor, vnnlib_text
from tests.test_onnx_reading import misread, node

# One input x in [0, 1]; outputs (0, x - 0.6, 0.4 - x): y_1 >= y_0 exactly when x >= 0.6, y_2 >= y_0
# exactly when x <= 0.4 -- each is possible in the box, both together are not.
LINE = model(
    [node("Gemm", ["x", "g", "b"], "y")], (1, 1), [tensor("g", [[0.0, 1.0, -1.0]]), tensor("b", [0, -0.6, 0.4])]
)
DECLARE = "(declare-const X_0 Real)\n(declare-const Y_0 Real)\n(declare-const Y_1 Real)\n(declare-const Y_2 Real)\n"
BOX = "(assert (>= X_0 0.0))\n(assert (<= X_0 1.0))\n"


def answer(tmp_path, text: str, net=LINE, name="p.vnnlib"):
    onnx = save(net, tmp_path / "net.onnx")
    (tmp_path / name).write_text(text)
    return verify_instance(onnx, tmp_path / name, 30.0, Settings())


def test_top_level_assertions_hold_together(tmp_path):
    both = answer(tmp_path, DECLARE + BOX + "(assert (>= Y_1 Y_0))\n(assert (>= Y_2 Y_0))\n")[0]
    conj = answer(tmp_path, DECLARE + BOX + "(assert (and (>= Y_1 Y_0) (>= Y_2 Y_0)))\n")[0]
    either = answer(tmp_path, DECLARE + BOX + "(assert (or (>= Y_1 Y_0) (>= Y_2 Y_0)))\n")[0]
    assert (both.result, conj.result, either.result) == ("unsat", "unsat", "sat")
    y = Reference(LINE)(either.x.reshape(1, 1))[0]
    assert y[1] >= y[0] or y[2] >= y[0]


@pytest.mark.parametrize(("upper", "result"), [(0.3, "sat"), (0.45, "unsat")])
def test_a_disjunction_of_input_boxes_is_answered_box_by_box(upper, result, tmp_path):
    text = DECLARE + (
        f"(assert (or (and (>= X_0 0.0) (<= X_0 {upper}) (>= Y_2 Y_0) (>= Y_1 Y_0))\n"
        f"            (and (>= X_0 {upper}) (<= X_0 1.0) (>= Y_2 Y_0))))\n"
    )
    (tmp_path / "p.vnnlib").write_text(text)
    cases = read_cases(tmp_path / "p.vnnlib")
    boxes = [(c.low.tolist(), c.high.tolist(), len(c.unsafe)) for c in cases]
    assert boxes == [([0.0], [upper], 1), ([upper], [1.0], 1)]
    verdict = answer(tmp_path, text)[0]
    assert verdict.result == result
    if result == "sat":  # in the second box, where x <= 0.4
        assert upper <= float(verdict.x.ravel()[0]) <= 0.4


def test_linear_terms_read_as_their_sums(tmp_path):
    (tmp_path / "p.vnnlib").write_text(DECLARE + BOX + "(assert (<= (+ Y_0 (* -2 Y_1) (- Y_2 3.5)) (- 1)))\n")
    prop = read_vnnlib(tmp_path / "p.vnnlib", 1, 3)
    ((c, d),) = prop.unsafe[0]  # -(y0 - 2 y1 + y2 - 3.5) - 1 >= 0
    assert c.tolist() == [-1.0, 2.0, -1.0] and d == 2.5


MALFORMED = [
    ("(assert)", 5, "expected (assert FORMULA) with one formula, got 0"),
    ("(assert (and))", 5, "(and) needs at least one formula"),
    ("(assert (or (and) (>= Y_1 Y_0)))", 5, "(and) needs at least one formula"),
    ("(assert (>= Y_1 nan))", 5, "the number 'nan' is not finite"),
    ("(assert (<= X_0 nan))", 5, "the number 'nan' is not finite"),
    ("(assert (>= Y_1 1e999))", 5, "the number '1e999' is not finite"),
    ("(assert (>= Y_99 Y_0))", 5, "Y_99 is used but not declared"),
    ("(assert (<= X_7 1))", 5, "X_7 is used but not declared"),
    ("(assert (>= Y_1 1.2.3))", 5, "expected a number or a declared variable, got '1.2.3'"),
    ("(assert (= Y_1 Y_0))", 5, "expected <=, >=, and or or, got '='"),
    ("(assert (>= Y_1 Y_0 Y_2))", 5, "expected (>= A B)"),
    ("(assert (>= X_0 Y_0))", 5, "a comparison of inputs with outputs is not supported"),
    ("(check-sat)", 5, "expected (declare-const ...) or (assert ...), got (check-sat ...)"),
    ("(declare-const Z_0 Real)", 5, "expected (declare-const X_i Real)"),
    ("(declare-const Y_0 Real)", 5, "Y_0 is declared twice"),
    ("(assert (>= Y_1 Y_0)", 5, "this '(' is never closed"),
    ("(assert (>= Y_1 Y_0)))", 5, "a ')' closes nothing"),
]


@pytest.mark.parametrize(("line", "number", "words"), MALFORMED, ids=[m[0] for m in MALFORMED])
def test_a_malformed_property_is_one_line_naming_its_file_and_line(line, number, words, tmp_path):
    text = DECLARE + line + "\n" + BOX + "(assert (>= Y_1 Y_0))\n"
    (tmp_path / "p.vnnlib").write_text(text)
    with pytest.raises(MrcertError) as caught:
        read_cases(tmp_path / "p.vnnlib")
    assert str(caught.value).startswith(f"{tmp_path / 'p.vnnlib'}:{number}: ") and words in str(caught.value)
    verdict, reason = answer(tmp_path, text)  # no traceback: the instance is an error with its reason
    assert verdict.result == "error" and reason == str(caught.value)


@pytest.mark.parametrize(
    ("declarations", "words"),
    [
        ("(declare-const X_0 Real)\n(declare-const X_2 Real)\n", "X_2 is declared but X_1 is not"),
        ("(declare-const X_0 Real)\n(declare-const X_1 Real)\n", "declares 2 inputs where the network has 1"),
        ("(declare-const X_0 Real)\n", "declares 2 outputs where the network has 3"),
    ],
)
def test_sizes_are_checked_against_the_declarations_and_the_network(declarations, words, tmp_path):
    outputs = "(declare-const Y_0 Real)\n(declare-const Y_1 Real)\n"
    text = declarations + (outputs if "outputs" in words else outputs + "(declare-const Y_2 Real)\n")
    text += "".join(f"(assert (>= X_{i} 0))\n(assert (<= X_{i} 1))\n" for i in (0, 1, 2) if f"X_{i} " in text)
    verdict, reason = answer(tmp_path, text + "(assert (>= Y_1 Y_0))\n")
    assert verdict.result == "error" and words in reason


def test_a_property_beyond_the_size_limit_is_refused_before_it_is_parsed(tmp_path):
    text = DECLARE + BOX * 20_000 + "(assert (>= Y_1 Y_0))\n"  # 900 kB
    (tmp_path / "big.vnnlib").write_text(text)
    (tmp_path / "big.vnnlib.gz").write_bytes(gzip.compress(text.encode()))
    for name in ("big.vnnlib", "big.vnnlib.gz"):
        start = time.perf_counter()
        with pytest.raises(MrcertError, match="beyond .*task.max_property_mb"):
            read_cases(tmp_path / name, max_bytes=100_000)
        assert time.perf_counter() - start < 1.0  # refused on its size, not after parsing it
    assert len(read_cases(tmp_path / "big.vnnlib.gz", 1, 3)) == 1  # within the default limit it is read


def test_a_benchmark_answers_its_other_instances_when_one_cannot_be(tmp_path):
    """instances.csv: a good instance, a malformed property, a network read otherwise than its file,
    another good one. The run finishes; the bad ones are ``error`` with their reasons."""
    bench = tmp_path / "bench"
    bench.mkdir()
    save(LINE, bench / "line.onnx")
    m, centre, _ = misread("maxpool dilations")
    save(m, bench / "dilated.onnx")
    (bench / "good.vnnlib").write_text(DECLARE + BOX + "(assert (>= Y_1 Y_0))\n(assert (>= Y_2 Y_0))\n")
    (bench / "bad.vnnlib").write_text(DECLARE + BOX + "(assert (>= Y_1 nan))\n")
    (bench / "dilated.vnnlib").write_text(vnnlib_text(centre - 1e-6, centre + 1e-6, [[(0, 1)]], 3))
    rows = ["line.onnx,good.vnnlib,30", "line.onnx,bad.vnnlib,30", "dilated.onnx,dilated.vnnlib,30",
            "line.onnx,good.vnnlib,30"]  # fmt: skip
    (bench / "instances.csv").write_text("\n".join(rows) + "\n")
    done = run_cli(["task=verify", f"task.instances={bench / 'instances.csv'}"], tmp_path / "out")
    assert done.returncode == 0, done.stderr[-2000:]
    (run,) = sorted((tmp_path / "out" / "runs" / "verify").iterdir())
    log = pd.read_csv(run / "verify.tsv", sep="\t", keep_default_na=False)
    assert log["result"].tolist() == ["unsat", "error", "error", "unsat"]
    assert "bad.vnnlib:7: the number 'nan' is not finite" in log["reason"][1]
    assert "dilations=[2, 2], which mrcert does not read" in log["reason"][2]
    files = [(run / "results" / f"{i}.txt").read_text() for i in range(4)]
    assert files == ["unsat\n", "error\n", "error\n", "unsat\n"]
    assert "error: instance 1 (line.onnx, bad.vnnlib)" in done.stderr
