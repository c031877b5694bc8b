"""Small ONNX graphs written node by node (onnx.helper), and the reference executor
(onnxruntime) that runs them as the file means: shared by the reading tests and the fuzz."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


def tensor(name: str, value) -> TensorProto:
    return numpy_helper.from_array(np.asarray(value, dtype=np.float32), name)


def ints(name: str, value) -> TensorProto:
    return numpy_helper.from_array(np.asarray(value, dtype=np.int64), name)


def model(nodes, shape, initializers=(), output="y", opset: int = OPSET) -> onnx.ModelProto:
    """A graph of ``nodes`` from the input ``x`` of ``shape`` to the output ``output``."""
    graph = helper.make_graph(
        list(nodes), "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(shape))],
        [helper.make_tensor_value_info(output, TensorProto.FLOAT, None)], list(initializers),
    )  # fmt: skip
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], ir_version=8)


def save(m: onnx.ModelProto, path: Path) -> Path:
    path.write_bytes(m.SerializeToString())
    return path


class Reference:
    """onnxruntime on one model: outputs (B, K) of inputs (B, ...), one point at a time."""

    def __init__(self, m: onnx.ModelProto):
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        self.runner = ort.InferenceSession(m.SerializeToString(), options, providers=["CPUExecutionProvider"])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float32)
        rows = [self.runner.run(None, {"x": x[i : i + 1]})[0].reshape(1, -1) for i in range(len(x))]
        return np.concatenate(rows).astype(np.float64)


def vnnlib_text(low, high, conjunctions, outputs: int) -> str:
    """A property: the box [low, high] and the disjunction of conjunctions of ``(>= Y_a Y_b)`` pairs."""
    lines = [f"(declare-const X_{i} Real)" for i in range(len(low))]
    lines += [f"(declare-const Y_{j} Real)" for j in range(outputs)]
    for i, (lo, hi) in enumerate(zip(low, high, strict=True)):
        lines += [f"(assert (>= X_{i} {float(lo)!r}))", f"(assert (<= X_{i} {float(hi)!r}))"]
    terms = " ".join("(and " + " ".join(f"(>= Y_{a} Y_{b})" for a, b in conj) + ")" for conj in conjunctions)
    lines.append(f"(assert (or {terms}))")
    return "\n".join(lines) + "\n"
