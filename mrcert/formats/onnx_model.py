"""ONNX classifiers as torch modules, and our classifiers as ONNX files.

:func:`read_onnx` turns an ONNX graph of the operators feed-forward image classifiers use
(:data:`OPERATORS`: the VNN-COMP MetaRoom CNNs, and what :func:`write_onnx` writes) into an
:class:`OnnxNetwork`, a module whose forward pass applies the graph's nodes in order with torch
functions, so that it runs on any device and :class:`~mrcert.core.propagation.BoundNetwork` can
read it. Any other operator is refused in one line naming it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mrcert.errors import MrcertError

OPERATORS = (
    "Conv", "Gemm", "MatMul", "Add", "Sub", "Mul", "Div", "Relu", "Flatten", "Reshape", "MaxPool",
    "AveragePool", "GlobalAveragePool", "BatchNormalization", "Constant", "Identity", "Dropout",
)  # fmt: skip


def _onnx():
    try:
        import onnx
    except ImportError:  # pragma: no cover - a dependency
        raise MrcertError("reading ONNX needs the onnx package (pip install onnx)") from None
    return onnx


class OnnxNetwork(nn.Module):
    """An ONNX graph as a module: ``steps`` are (operator, inputs, output, attributes), applied in
    order; initializers are buffers (``c0``, ``c1``, ...)."""

    def __init__(self, steps: list[tuple], constants: dict[str, np.ndarray], input_name: str, output: str, shape):
        super().__init__()
        self.names: dict[str, str] = {}
        for k, (name, value) in enumerate(constants.items()):
            self.register_buffer(f"c{k}", torch.from_numpy(np.array(value)))
            self.names[name] = f"c{k}"
        self.steps, self.input_name, self.output, self.input_shape = steps, input_name, output, tuple(shape)

    def constant(self, name: str) -> torch.Tensor:
        return getattr(self, self.names[name])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        values = {self.input_name: x}

        def get(name):
            return values[name] if name in values else self.constant(name)

        for op, inputs, output, attrs in self.steps:
            values[output] = _apply(op, [get(i) if i else None for i in inputs], attrs, inputs, self)
        return values[self.output]


def _apply(op: str, args: list, attrs: dict, names: list[str], net: OnnxNetwork):
    x = args[0]
    if op in ("Identity", "Dropout"):
        return x
    if op == "Relu":
        return torch.relu(x)
    if op == "Conv":
        pads = attrs.get("pads", [0, 0, 0, 0])
        if pads[: len(pads) // 2] != pads[len(pads) // 2 :]:
            raise MrcertError(f"ONNX Conv with asymmetric pads {pads} is not supported")
        return F.conv2d(
            x, args[1], args[2] if len(args) > 2 else None,
            stride=tuple(attrs.get("strides", [1, 1])), padding=tuple(pads[: len(pads) // 2]),
            dilation=tuple(attrs.get("dilations", [1, 1])), groups=int(attrs.get("group", 1)),
        )  # fmt: skip
    if op == "Gemm":
        if attrs.get("transA", 0):
            raise MrcertError("ONNX Gemm with transA=1 is not supported")
        weight = args[1] if attrs.get("transB", 0) else args[1].t()
        bias = args[2] * attrs.get("beta", 1.0) if len(args) > 2 and args[2] is not None else None
        return F.linear(x, weight * attrs.get("alpha", 1.0), bias)
    if op == "MatMul":
        return F.linear(x, args[1].t())
    if op in ("Add", "Sub", "Mul", "Div"):
        fn = {"Add": torch.add, "Sub": torch.sub, "Mul": torch.mul, "Div": torch.div}[op]
        return fn(args[0], args[1])
    if op == "Flatten":
        if int(attrs.get("axis", 1)) != 1:
            raise MrcertError("ONNX Flatten with axis other than 1 is not supported")
        return torch.flatten(x, 1)
    if op == "Reshape":
        shape = [int(v) for v in args[1].tolist()] if isinstance(args[1], torch.Tensor) else list(args[1])
        rest = shape[1:]
        if rest == [-1]:
            return torch.flatten(x, 1)
        if any(v <= 0 for v in rest):
            raise MrcertError(f"ONNX Reshape to {shape} is not supported (the batch first, then known sizes)")
        return x.reshape(-1, *rest)
    if op == "MaxPool":
        pads = attrs.get("pads", [0, 0, 0, 0])
        if attrs.get("ceil_mode", 0) or pads[:2] != pads[2:]:
            raise MrcertError("ONNX MaxPool with ceil_mode or asymmetric pads is not supported")
        kernel = tuple(attrs["kernel_shape"])
        return F.max_pool2d(x, kernel, tuple(attrs.get("strides", kernel)), tuple(pads[:2]))
    if op == "AveragePool":
        pads = attrs.get("pads", [0, 0, 0, 0])
        kernel = tuple(attrs["kernel_shape"])
        return F.avg_pool2d(
            x, kernel, tuple(attrs.get("strides", kernel)), tuple(pads[:2]),
            count_include_pad=bool(attrs.get("count_include_pad", 0)),
        )  # fmt: skip
    if op == "GlobalAveragePool":
        return F.adaptive_avg_pool2d(x, 1)
    if op == "BatchNormalization":
        scale, bias, mean, var = (net.constant(n) for n in names[1:5])
        factor = (scale / torch.sqrt(var + attrs.get("epsilon", 1e-5))).reshape(1, -1, 1, 1)
        return x * factor + (bias.reshape(1, -1, 1, 1) - mean.reshape(1, -1, 1, 1) * factor)
    raise MrcertError(f"ONNX operator {op} is not supported")  # pragma: no cover - refused when read


def read_onnx(path: Path | str) -> OnnxNetwork:
    """The classifier of an ONNX file (one image input of shape (1, C, H, W) or (N, C, H, W),
    one output of logits), in float32 evaluation mode."""
    onnx = _onnx()
    from onnx import numpy_helper

    path = Path(path)
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # noqa: BLE001 - a truncated or foreign file
        raise MrcertError(f"cannot read ONNX model {str(path)!r}: {exc}") from None
    graph = model.graph
    constants = {t.name: numpy_helper.to_array(t).astype(np.float32, copy=False) for t in graph.initializer}
    inputs = [i for i in graph.input if i.name not in constants]
    if len(inputs) != 1 or len(graph.output) != 1:
        raise MrcertError(
            f"{path}: an ONNX classifier needs one input and one output, got {len(inputs)} and {len(graph.output)}"
        )
    dims = [d.dim_value or 1 for d in inputs[0].type.tensor_type.shape.dim]
    steps = []
    for node in graph.node:
        if node.op_type not in OPERATORS:
            raise MrcertError(
                f"{path}: ONNX operator {node.op_type} is not supported (supported: {', '.join(OPERATORS)})"
            )
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        if node.op_type == "Constant":
            constants[node.output[0]] = numpy_helper.to_array(attrs["value"])
            continue
        steps.append((node.op_type, list(node.input), node.output[0], attrs))
    for name, value in list(constants.items()):  # integer tensors (shapes) stay integers
        if value.dtype.kind in "iu":
            constants[name] = value.astype(np.int64)
    net = OnnxNetwork(steps, constants, inputs[0].name, graph.output[0].name, dims)
    return net.eval()


def write_onnx(model: nn.Module, shape: tuple[int, ...], path: Path | str) -> Path:
    """``model`` (a classifier of images ``shape`` = (C, H, W)) as an ONNX file with batch size 1
    (opset 14, the competition's), float32; its class comes back identical through :func:`read_onnx`."""
    _onnx()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = model.float().eval().cpu()
    example = torch.zeros(1, *shape)
    with torch.inference_mode(False), torch.no_grad():
        torch.onnx.export(
            model, (example,), str(path), input_names=["input"], output_names=["output"], opset_version=14,
            dynamo=False, do_constant_folding=True,
        )  # fmt: skip
    return path
