"""ONNX classifiers as torch modules, and our classifiers as ONNX files.

:func:`read_onnx` turns an ONNX graph of the operators feed-forward image classifiers use
(:data:`ATTRIBUTES`: the VNN-COMP MetaRoom CNNs, and what :func:`write_onnx` writes) into an
:class:`OnnxNetwork`, a module whose forward pass applies the graph's nodes in order with torch
functions, so that it runs on any device and :class:`~mrcert.core.verification.network.BoundNetwork` can
read it. The network is the file's or none:

* every attribute of every operator read is either implemented, with the ONNX specification's
  default where the file gives none, or refused in one line naming the node, the attribute and
  its value (:data:`ATTRIBUTES` lists the attributes each operator may carry); so is any other
  operator, a node of another domain, and an output of a node that the graph uses but mrcert
  does not compute (a max pooling's indices, a dropout's mask);
* what depends on the shapes (``auto_pad``, a pooling's ``ceil_mode``, a reshape's 0 and -1) is
  resolved once when the file is read, from one pass of a zero input;
* the tensors a file claims (its initializers, external data included) are counted before any
  is loaded, and a file beyond ``max_bytes`` is refused (:data:`MAX_MODEL_BYTES`);
* :class:`ReferenceCheck` runs the file itself with an independent executor (onnxruntime) on
  points of a property's box, and refuses a network whose outputs differ from mrcert's beyond
  float tolerance (``task=verify`` does so for every instance before it answers).

A gzipped file (``.onnx.gz``, or any file that starts as gzip does) is read as it is.
"""

from __future__ import annotations

import gzip
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mrcert.errors import MrcertError

MAX_MODEL_BYTES = 512 * 2**20
"""The most bytes of tensors (initializers, external data included) a model may claim by default."""

# Every operator read, with the attributes it may carry (any other is refused naming it).
ATTRIBUTES: dict[str, tuple[str, ...]] = {
    "Conv": ("auto_pad", "dilations", "group", "kernel_shape", "pads", "strides"),
    "Gemm": ("alpha", "beta", "transA", "transB"),
    "MatMul": (),
    "Add": (),
    "Sub": (),
    "Mul": (),
    "Div": (),
    "Relu": (),
    "Flatten": ("axis",),
    "Reshape": ("allowzero",),
    "MaxPool": ("auto_pad", "ceil_mode", "dilations", "kernel_shape", "pads", "storage_order", "strides"),
    "AveragePool": ("auto_pad", "ceil_mode", "count_include_pad", "dilations", "kernel_shape", "pads", "strides"),
    "GlobalAveragePool": (),
    "BatchNormalization": ("epsilon", "momentum", "training_mode", "spatial", "is_test"),
    "Constant": ("value", "value_float", "value_floats", "value_int", "value_ints"),
    "Identity": (),
    "Dropout": ("ratio", "seed", "is_test"),
}
OPERATORS = tuple(ATTRIBUTES)
REFUSED: dict[str, str] = {
    "Conv": "other than 2-D; a weight or bias the graph computes; kernel_shape other than the weight's; auto_pad "
    "beside pads",
    "Gemm": "transA=1; B or C computed by the graph; C that does not broadcast to (1, K)",
    "MatMul": "a right operand computed by the graph or not 2-D",
    "Add": "a constant that broadcasts the batch; two computed tensors of different shapes",
    "Sub": "a constant that broadcasts the batch; two computed tensors",
    "Mul": "a constant that broadcasts the batch; two computed tensors",
    "Div": "a computed divisor; a constant divisor with zeros",
    "Flatten": "axis other than 1",
    "Reshape": "a shape the graph computes; one that does not keep the batch first; allowzero=1 with a 0",
    "MaxPool": "dilations other than 1; unequal pads on two sides (after auto_pad); ceil_mode=1 where it adds a "
    "window; its Indices output used",
    "AveragePool": "dilations other than 1; unequal pads with count_include_pad=0; ceil_mode=1 where it adds a window",
    "GlobalAveragePool": "other than (N, C, H, W)",
    "BatchNormalization": "training_mode=1; spatial=0; statistics the graph computes; its running outputs used",
    "Constant": "sparse_value, value_string(s), value_float(s)/value_int(s) beside value",
    "Identity": "",
    "Dropout": "training_mode=True; its mask used",
    "Relu": "",
}
"""What each operator is refused for beyond an attribute it does not carry (docs/verification.md)."""

ITEM_BYTES = {1: 4, 2: 1, 3: 1, 4: 2, 5: 2, 6: 4, 7: 8, 9: 1, 10: 2, 11: 8, 12: 4, 13: 8, 16: 2}


def _onnx():
    try:
        import onnx
    except ImportError:  # pragma: no cover - a dependency
        raise MrcertError("reading ONNX needs the onnx package (pip install onnx)") from None
    return onnx


class OnnxNetwork(nn.Module):
    """An ONNX graph as a module: ``steps`` are (operator, inputs, output, parameters), applied in
    order, every parameter resolved when the file was read; constants are buffers (``c0``, ...).
    Its output is (N, K): the graph's output flattened after the batch."""

    def __init__(self, steps: list[tuple], constants: dict[str, np.ndarray], input_name: str, output: str, shape):
        super().__init__()
        self.names: dict[str, str] = {}
        for k, (name, value) in enumerate(constants.items()):
            self.register_buffer(f"c{k}", torch.from_numpy(np.array(value)))
            self.names[name] = f"c{k}"
        self.steps, self.input_name, self.output, self.input_shape = steps, input_name, output, tuple(shape)
        self.source: bytes | None = None  # the file's model, as the reference executor reads it

    def constant(self, name: str) -> torch.Tensor:
        return getattr(self, self.names[name])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        values = {self.input_name: x}
        for op, inputs, output, params in self.steps:
            args = [(values[i] if i in values else self.constant(i)) if i else None for i in inputs]
            values[output] = _apply(op, args, params)
        return torch.flatten(values[self.output], 1)


def _apply(op: str, args: list, p: dict):
    """One node on its (already resolved) parameters ``p``."""
    x = args[0]
    if op in ("Identity", "Dropout"):
        return x
    if op == "Relu":
        return torch.relu(x)
    if op == "Conv":
        if p["pre_pad"] is not None:
            x = F.pad(x, p["pre_pad"])
        return F.conv2d(x, args[1], args[2] if len(args) > 2 else None, p["stride"], p["padding"], p["dilation"],
                        p["groups"])  # fmt: skip
    if op in ("Gemm", "MatMul"):
        out = F.linear(x, args[1])
        return out + args[2] if len(args) > 2 and args[2] is not None else out
    if op == "Add":
        return torch.add(args[0], args[1])
    if op == "Sub":
        return torch.sub(args[0], args[1])
    if op == "Mul":
        return torch.mul(args[0], args[1])
    if op == "Div":
        return torch.div(args[0], args[1])
    if op == "Flatten":
        return torch.flatten(x, 1)
    if op == "Reshape":
        return x.reshape(-1, *p["shape"])
    if op == "MaxPool":
        return F.max_pool2d(x, p["kernel"], p["stride"], p["padding"])
    if op == "AveragePool":
        if p["pre_pad"] is not None:
            x = F.pad(x, p["pre_pad"])
        return F.avg_pool2d(x, p["kernel"], p["stride"], p["padding"], False, p["count_include_pad"])
    if op == "GlobalAveragePool":
        return F.adaptive_avg_pool2d(x, 1)
    if op == "BatchNormalization":
        return x * args[1] + args[2]
    raise MrcertError(f"ONNX operator {op} is not supported")  # pragma: no cover - refused when read


@dataclass
class _Node:
    """One node being read: its attributes, the shapes and constants known so far."""

    path: str
    node: Any
    attrs: dict
    constants: dict[str, np.ndarray]
    shapes: dict[str, tuple[int, ...]]
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # constants this node adds

    @property
    def label(self) -> str:
        name = self.node.name or self.node.output[0]
        return f"{self.path}: ONNX node {name!r} ({self.node.op_type})"

    def refuse(self, what: str) -> MrcertError:
        return MrcertError(f"{self.label} {what}")

    def attribute(self, name: str, value) -> MrcertError:
        return self.refuse(f"has {name}={value!r}, which mrcert does not read")

    def get(self, name: str, default):
        value = self.attrs.get(name, default)
        return value.decode() if isinstance(value, bytes) else value

    def inputs(self) -> list[str]:
        return list(self.node.input)

    def is_constant(self, k: int) -> bool:
        names = self.inputs()
        return k < len(names) and names[k] in self.constants

    def constant(self, k: int, what: str) -> np.ndarray:
        if not self.is_constant(k):
            raise self.refuse(f"needs its {what} (input {k + 1}) to be a constant of the file")
        return self.constants[self.inputs()[k]]

    def shape(self, k: int) -> tuple[int, ...]:
        name = self.inputs()[k]
        return tuple(self.constants[name].shape) if name in self.constants else self.shapes[name]

    def add_constant(self, suffix: str, value: np.ndarray) -> str:
        name = f"{self.node.output[0]}::{suffix}"
        self.extra[name] = np.ascontiguousarray(value, dtype=np.float32)
        return name


def _ints(value, n: int, what: str, node: _Node) -> tuple[int, ...]:
    values = tuple(int(v) for v in value)
    if len(values) != n:
        raise node.attribute(what, list(values))
    return values


def _window(node: _Node, hw: tuple[int, int], kernel, strides, dilations) -> tuple[int, int, int, int]:
    """ONNX pads ``(top, left, bottom, right)`` after ``auto_pad`` (the specification's rule)."""
    auto = node.get("auto_pad", "NOTSET")
    if auto not in ("NOTSET", "VALID", "SAME_UPPER", "SAME_LOWER"):
        raise node.attribute("auto_pad", auto)
    if auto != "NOTSET" and "pads" in node.attrs:
        raise node.refuse(f"has both auto_pad={auto!r} and pads, which the ONNX specification excludes")
    if auto == "NOTSET":
        pads = _ints(node.attrs.get("pads", [0, 0, 0, 0]), 4, "pads", node)
        if min(pads) < 0:
            raise node.attribute("pads", list(pads))
        return pads
    if auto == "VALID":
        return (0, 0, 0, 0)
    begin, end = [], []
    for size, k, s, d in zip(hw, kernel, strides, dilations, strict=True):
        total = max((math.ceil(size / s) - 1) * s + (k - 1) * d + 1 - size, 0)
        small, large = total // 2, total - total // 2
        begin.append(small if auto == "SAME_UPPER" else large)
        end.append(large if auto == "SAME_UPPER" else small)
    return (begin[0], begin[1], end[0], end[1])


def _pool_common(node: _Node) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int, int, int]]:
    """A pooling's kernel, strides (default 1) and pads; dilations other than 1, a ceil_mode
    that changes the output size and unequal pads on two sides are refused."""
    shape = node.shape(0)
    if len(shape) != 4:
        raise node.refuse(f"pools a tensor of shape {list(shape)}; mrcert reads 2-D pooling of (N, C, H, W)")
    if "kernel_shape" not in node.attrs:
        raise node.refuse("has no kernel_shape, which the ONNX specification requires")
    kernel = _ints(node.attrs["kernel_shape"], 2, "kernel_shape", node)
    strides = _ints(node.attrs.get("strides", [1, 1]), 2, "strides", node)
    dilations = _ints(node.attrs.get("dilations", [1, 1]), 2, "dilations", node)
    if dilations != (1, 1):
        raise node.attribute("dilations", list(dilations))
    for name, values in (("kernel_shape", kernel), ("strides", strides)):
        if min(values) < 1:
            raise node.attribute(name, list(values))
    pads = _window(node, shape[2:], kernel, strides, dilations)
    ceil = int(node.attrs.get("ceil_mode", 0))
    if ceil not in (0, 1):
        raise node.attribute("ceil_mode", ceil)
    if ceil:
        for size, k, s, a, b in zip(shape[2:], kernel, strides, pads[:2], pads[2:], strict=True):
            span = size + a + b - k
            if span % s:  # the ceiling adds a window the floor does not: refused
                raise node.refuse(
                    f"has ceil_mode=1, which changes its output size here ({span // s + 2} instead of "
                    f"{span // s + 1}); mrcert reads ceil_mode only where it changes nothing"
                )
    return kernel, strides, pads


def _conv(node: _Node) -> dict:
    shape, weight = node.shape(0), node.constant(1, "weight")
    if len(shape) != 4 or weight.ndim != 4:
        raise node.refuse(f"convolves a tensor of shape {list(shape)}; mrcert reads 2-D convolutions of (N, C, H, W)")
    kernel = _ints(node.attrs.get("kernel_shape", weight.shape[2:]), 2, "kernel_shape", node)
    if kernel != tuple(weight.shape[2:]):
        raise node.attribute("kernel_shape", list(kernel))
    strides = _ints(node.attrs.get("strides", [1, 1]), 2, "strides", node)
    dilations = _ints(node.attrs.get("dilations", [1, 1]), 2, "dilations", node)
    group = int(node.attrs.get("group", 1))
    if group < 1 or shape[1] != weight.shape[1] * group or weight.shape[0] % group:
        raise node.attribute("group", group)
    for name, values in (("strides", strides), ("dilations", dilations)):
        if min(values) < 1:
            raise node.attribute(name, list(values))
    if len(node.inputs()) > 2 and node.inputs()[2]:
        bias = node.constant(2, "bias")
        if bias.shape != (weight.shape[0],):
            raise node.refuse(f"has a bias of shape {list(bias.shape)} for {weight.shape[0]} output channels")
    pads = _window(node, shape[2:], kernel, strides, dilations)
    symmetric = pads[:2] == pads[2:]
    return {
        "stride": strides, "dilation": dilations, "groups": group,
        "padding": pads[:2] if symmetric else (0, 0),
        "pre_pad": None if symmetric else (pads[1], pads[3], pads[0], pads[2]),
    }  # fmt: skip


def _max_pool(node: _Node) -> dict:
    kernel, strides, pads = _pool_common(node)
    if pads[:2] != pads[2:]:
        raise node.refuse(f"pads {list(pads)} unequally on two sides, which mrcert's max pooling does not read")
    order = int(node.attrs.get("storage_order", 0))
    if order not in (0, 1):
        raise node.attribute("storage_order", order)
    return {"kernel": kernel, "stride": strides, "padding": pads[:2]}


def _average_pool(node: _Node) -> dict:
    kernel, strides, pads = _pool_common(node)
    include = int(node.attrs.get("count_include_pad", 0))
    if include not in (0, 1):
        raise node.attribute("count_include_pad", include)
    symmetric = pads[:2] == pads[2:]
    if not symmetric and not include:
        raise node.refuse(
            f"pads {list(pads)} unequally on two sides with count_include_pad=0, which mrcert does not read"
        )
    return {
        "kernel": kernel, "stride": strides, "padding": pads[:2] if symmetric else (0, 0),
        "pre_pad": None if symmetric else (pads[1], pads[3], pads[0], pads[2]), "count_include_pad": bool(include),
    }  # fmt: skip


def _linear(node: _Node) -> tuple[dict, list[str]]:
    """Gemm and MatMul as ``x W^T + b``: the weight (and bias) resolved into new constants."""
    shape = node.shape(0)
    if node.is_constant(0) or not node.is_constant(1):
        raise node.refuse("multiplies by a tensor the network computes; mrcert reads x @ W with W a constant")
    b = node.constants[node.inputs()[1]]
    if node.node.op_type == "MatMul":
        if b.ndim != 2 or len(shape) < 2 or shape[-1] != b.shape[0]:
            raise node.refuse(f"multiplies shapes {list(shape)} and {list(b.shape)}; mrcert reads (..., n) @ (n, m)")
        return {}, [node.inputs()[0], node.add_constant("weight", b.T)]
    if int(node.attrs.get("transA", 0)) != 0:
        raise node.attribute("transA", int(node.attrs["transA"]))
    trans_b = int(node.attrs.get("transB", 0))
    if trans_b not in (0, 1):
        raise node.attribute("transB", trans_b)
    alpha, beta = float(node.attrs.get("alpha", 1.0)), float(node.attrs.get("beta", 1.0))
    weight = (b if trans_b else b.T).astype(np.float64)
    if len(shape) != 2 or b.ndim != 2 or weight.shape[1] != shape[1]:
        raise node.refuse(f"multiplies shapes {list(shape)} and {list(b.shape)} (transB={trans_b})")
    names = [node.inputs()[0], node.add_constant("weight", weight * alpha if alpha != 1.0 else weight)]
    if len(node.inputs()) > 2 and node.inputs()[2]:
        c = node.constant(2, "bias C").astype(np.float64)
        try:
            bias = np.broadcast_to(c, (1, weight.shape[0]))[0]
        except ValueError:
            raise node.refuse(f"has a bias C of shape {list(c.shape)} for (N, {weight.shape[0]})") from None
        names.append(node.add_constant("bias", bias * beta if beta != 1.0 else bias))
    return {}, names


def _elementwise(node: _Node) -> dict:
    op, names = node.node.op_type, node.inputs()
    tensors = [k for k in (0, 1) if not node.is_constant(k)]
    if len(tensors) == 2:
        if op != "Add" or node.shape(0) != node.shape(1):
            raise node.refuse("of two computed tensors is read only as Add of two tensors of one shape")
        return {}
    (k,) = tensors
    other = node.constants[names[1 - k]]
    try:
        out = np.broadcast_shapes(node.shape(k), other.shape)
    except ValueError:
        raise node.refuse(f"broadcasts shapes {list(node.shape(0))} and {list(node.shape(1))}") from None
    if out != node.shape(k):
        raise node.refuse(f"broadcasts its input {list(node.shape(k))} to {list(out)}; mrcert keeps the batch as it is")
    if op == "Div" and k == 1:
        raise node.refuse("divides a constant by a computed tensor, which is not affine")
    if op == "Div" and not np.all(other != 0):
        raise node.refuse("divides by a constant that has zeros")
    return {}


def _reshape(node: _Node) -> dict:
    shape = node.shape(0)
    out = _reshaped(node, shape, [int(v) for v in node.constant(1, "shape").reshape(-1)])
    if out[0] != shape[0]:
        raise node.refuse(f"reshapes {list(shape)} to {list(out)}: the batch is not kept as the first axis")
    return {"shape": tuple(int(v) for v in out[1:])}


def _flatten(node: _Node) -> dict:
    rank = len(node.shape(0))
    axis = int(node.attrs.get("axis", 1))
    if (axis + rank if axis < 0 else axis) != 1:
        raise node.attribute("axis", axis)
    return {}


def _batch_norm(node: _Node) -> tuple[dict, list[str]]:
    shape = node.shape(0)
    if int(node.attrs.get("training_mode", 0)) != 0:
        raise node.attribute("training_mode", int(node.attrs["training_mode"]))
    if int(node.attrs.get("spatial", 1)) != 1:
        raise node.attribute("spatial", int(node.attrs["spatial"]))
    if len(shape) < 2:
        raise node.refuse(f"normalises a tensor of shape {list(shape)}; it needs (N, C, ...)")
    scale, bias, mean, var = (node.constant(k, w).astype(np.float64) for k, w in
                              enumerate(("scale", "bias", "mean", "variance"), start=1))  # fmt: skip
    if any(t.shape != (shape[1],) for t in (scale, bias, mean, var)):
        raise node.refuse(f"has statistics of shapes other than ({shape[1]},), its channels")
    epsilon = float(node.attrs.get("epsilon", 1e-5))
    if not (var + epsilon > 0).all():
        raise node.refuse(f"has a variance plus epsilon={epsilon!r} that is not positive")
    factor = scale / np.sqrt(var + epsilon)
    broadcast = (1, shape[1]) + (1,) * (len(shape) - 2)
    names = [node.inputs()[0], node.add_constant("factor", factor.reshape(broadcast)),
             node.add_constant("shift", (bias - mean * factor).reshape(broadcast))]  # fmt: skip
    return {}, names


def _dropout(node: _Node) -> dict:
    names = node.inputs()
    if len(names) > 2 and names[2]:
        mode = node.constant(2, "training_mode")
        if bool(np.asarray(mode).reshape(-1)[0]):
            raise node.refuse("has training_mode=True, which drops at random")
    return {}


def _constant_value(node: _Node) -> np.ndarray:
    from onnx import numpy_helper

    (name,) = node.attrs if len(node.attrs) == 1 else (None,)
    if name == "value":
        return numpy_helper.to_array(node.attrs["value"])
    if name in ("value_float", "value_floats"):
        return np.asarray(node.attrs[name], dtype=np.float32)
    if name in ("value_int", "value_ints"):
        return np.asarray(node.attrs[name], dtype=np.int64)
    raise node.refuse(f"has attributes {sorted(node.attrs)}; mrcert reads a Constant of one value, value_float(s) "
                      "or value_int(s)")  # fmt: skip


def _reshaped(node: _Node, shape: tuple[int, ...], target: list[int]) -> tuple[int, ...]:
    """The shape ``target`` gives a tensor of ``shape`` (0: the input's size, unless allowzero; -1: the rest)."""
    allow = int(node.attrs.get("allowzero", 0))
    if allow not in (0, 1) or (allow and 0 in target):
        raise node.attribute("allowzero", allow)
    target = [shape[i] if v == 0 and i < len(shape) else v for i, v in enumerate(target)]
    try:
        return np.empty(shape, dtype=np.uint8).reshape(target).shape
    except ValueError:
        raise node.refuse(f"reshapes {list(shape)} to {target}, which does not fit") from None


def _fold(node: _Node) -> np.ndarray:
    """A node whose inputs are all constants of the file, computed once when it is read."""
    op, args = node.node.op_type, [node.constants[n] for n in node.inputs() if n]
    if op in ("Identity", "Dropout"):
        return args[0]
    if op == "Relu":
        return np.maximum(args[0], 0)
    if op in ("Add", "Sub", "Mul", "Div") and len(args) == 2:
        if op == "Div" and (args[0].dtype.kind in "iub" or not np.all(args[1] != 0)):
            raise node.refuse("divides constants that are integers or zeros")
        try:
            return {"Add": np.add, "Sub": np.subtract, "Mul": np.multiply, "Div": np.divide}[op](*args)
        except ValueError:
            raise node.refuse(f"broadcasts shapes {[list(a.shape) for a in args]}, which do not fit") from None
    if op == "Reshape" and len(args) == 2:
        return args[0].reshape(_reshaped(node, args[0].shape, [int(v) for v in args[1].reshape(-1)]))
    raise node.refuse("computes from constants alone, which mrcert reads only for Identity, Dropout, Relu, Add, "
                      "Sub, Mul, Div and Reshape")  # fmt: skip


def _read_node(node: _Node) -> tuple[dict, list[str]]:
    """A node's resolved parameters and the input names it is applied to."""
    op = node.node.op_type
    names = node.inputs()
    if op in ("Conv",):
        return _conv(node), names
    if op in ("Gemm", "MatMul"):
        return _linear(node)
    if op == "BatchNormalization":
        return _batch_norm(node)
    readers = {
        "MaxPool": _max_pool, "AveragePool": _average_pool, "Add": _elementwise, "Sub": _elementwise,
        "Mul": _elementwise, "Div": _elementwise, "Reshape": _reshape, "Flatten": _flatten, "Dropout": _dropout,
    }  # fmt: skip
    if op in readers:
        params = readers[op](node)
        return params, names[:1] if op in ("Reshape", "Dropout") else names
    if op == "GlobalAveragePool" and len(node.shape(0)) != 4:
        raise node.refuse(f"pools a tensor of shape {list(node.shape(0))}; mrcert reads (N, C, H, W)")
    return {}, names[:1]


def _load(path: Path, max_bytes: int):
    """The ModelProto of ``path`` (gzipped or not), its tensors counted before any is loaded."""
    onnx = _onnx()
    from onnx import external_data_helper

    try:
        with path.open("rb") as f:
            head = f.read(2)
    except OSError as exc:
        raise MrcertError(f"cannot read ONNX model {str(path)!r}: {exc.strerror}") from None
    limit = max_bytes + 64 * 2**20  # the graph itself beside its tensors
    if head == b"\x1f\x8b":
        with gzip.open(path, "rb") as f:
            data = f.read(limit + 1)
    else:
        if path.stat().st_size > limit:
            raise MrcertError(f"{path}: {path.stat().st_size} bytes, beyond the {limit} an ONNX model may have here "
                              "(task.max_model_mb)")  # fmt: skip
        data = path.read_bytes()
    if len(data) > limit:
        raise MrcertError(f"{path}: more than {limit} bytes once unzipped, beyond what an ONNX model may have here "
                          "(task.max_model_mb)")  # fmt: skip
    try:
        model = onnx.load_model_from_string(data)
    except Exception as exc:  # noqa: BLE001 - a truncated or foreign file
        raise MrcertError(f"cannot read ONNX model {str(path)!r}: {exc}") from None
    tensors = list(model.graph.initializer) + [
        a.t for node in model.graph.node for a in node.attribute if a.type == onnx.AttributeProto.TENSOR
    ]
    claimed = sum(math.prod(t.dims) * ITEM_BYTES.get(t.data_type, 8) for t in tensors)
    if claimed > max_bytes:
        raise MrcertError(f"{path}: its tensors claim {claimed} bytes, beyond the {max_bytes} a model may have "
                          "here (task.max_model_mb)")  # fmt: skip
    folder = path.resolve().parent
    for t in tensors:
        if not external_data_helper.uses_external_data(t):
            continue
        info = {e.key: e.value for e in t.external_data}
        target = (folder / info.get("location", "")).resolve()
        if folder not in target.parents or not target.is_file():
            raise MrcertError(f"{path}: tensor {t.name!r} names external data {info.get('location')!r} outside "
                              "the model's folder or absent")  # fmt: skip
        size = target.stat().st_size - int(info.get("offset", 0))
        need = math.prod(t.dims) * ITEM_BYTES.get(t.data_type, 8)
        if int(info.get("length", need)) != need or size < need:
            raise MrcertError(f"{path}: tensor {t.name!r} claims {need} bytes of external data where its file "
                              f"holds {size} from its offset")  # fmt: skip
    try:
        external_data_helper.load_external_data_for_model(model, str(folder))
    except Exception as exc:  # noqa: BLE001 - a file the checks above let through that onnx refuses
        raise MrcertError(f"{path}: cannot load its external data: {exc}") from None
    return model


def read_onnx(path: Path | str, max_bytes: int = MAX_MODEL_BYTES) -> OnnxNetwork:
    """The classifier of an ONNX file (one image input of shape (1, C, H, W) or (N, C, H, W),
    one output of logits), in float32 evaluation mode; refused in one line unless every node is
    read as the ONNX specification defines it (module docstring)."""
    onnx = _onnx()
    from onnx import numpy_helper

    path = Path(path)
    model = _load(path, int(max_bytes))
    graph = model.graph
    constants: dict[str, np.ndarray] = {}
    for t in graph.initializer:
        constants[t.name] = _typed(numpy_helper.to_array(t))
    inputs = [i for i in graph.input if i.name not in constants]
    if len(inputs) != 1 or len(graph.output) != 1:
        raise MrcertError(
            f"{path}: an ONNX classifier needs one input and one output, got {len(inputs)} and {len(graph.output)}"
        )
    kind = inputs[0].type.tensor_type
    if kind.elem_type not in (1,):
        raise MrcertError(f"{path}: input {inputs[0].name!r} has element type {kind.elem_type}; mrcert reads float32")
    dims = [d.dim_value or 1 for d in kind.shape.dim]
    if len(dims) < 2:
        raise MrcertError(f"{path}: input {inputs[0].name!r} has shape {dims}; it needs a batch axis and features")
    used = {name for node in graph.node for name in node.input} | {o.name for o in graph.output}
    shapes: dict[str, tuple[int, ...]] = {inputs[0].name: (1, *dims[1:])}
    values: dict[str, torch.Tensor] = {inputs[0].name: torch.zeros(1, *dims[1:])}
    steps = []
    for k, proto in enumerate(graph.node):
        label = proto.name or proto.output[0] or f"#{k}"
        if proto.domain not in ("", "ai.onnx"):
            raise MrcertError(f"{path}: ONNX node {label!r} is operator {proto.op_type} of domain {proto.domain!r}; "
                              "mrcert reads the standard operators only")  # fmt: skip
        if proto.op_type not in ATTRIBUTES:
            raise MrcertError(
                f"{path}: ONNX operator {proto.op_type} (node {label!r}) is not supported "
                f"(supported: {', '.join(OPERATORS)})"
            )
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in proto.attribute}
        node = _Node(str(path), proto, attrs, constants, shapes)
        for name in sorted(set(attrs) - set(ATTRIBUTES[proto.op_type])):
            raise node.attribute(name, attrs[name])
        for extra in proto.output[1:]:
            if extra and extra in used:
                raise node.refuse(f"has its output {extra!r} used by the graph; mrcert computes only the first")
        if proto.op_type == "Constant":
            constants[proto.output[0]] = _typed(_constant_value(node))
            continue
        if proto.input and all(not n or n in constants for n in proto.input):
            constants[proto.output[0]] = _typed(_fold(node))  # computed from constants alone
            continue
        missing = [n for n in proto.input[:1] if n not in values and n not in constants]
        if missing or not proto.input:
            raise node.refuse(f"reads {missing[0] if missing else 'no input'!r}, which no node before it computes")
        params, names = _read_node(node)
        constants.update(node.extra)
        for name in names:
            if name and name not in values and name not in constants:
                raise node.refuse(f"reads {name!r}, which no node before it computes")
        step = (proto.op_type, names, proto.output[0], params)
        try:
            with torch.no_grad():
                out = _apply(proto.op_type, [_value(n, values, constants) for n in names], params)
        except (RuntimeError, ValueError) as exc:
            raise node.refuse(f"cannot be applied to its inputs: {str(exc).splitlines()[0]}") from None
        values[proto.output[0]], shapes[proto.output[0]] = out, tuple(out.shape)
        steps.append(step)
    output = graph.output[0].name
    if output not in values:
        raise MrcertError(f"{path}: output {output!r} is not computed from the input")
    kept = {n for _, names, _, _ in steps for n in names if n in constants}
    net = OnnxNetwork(steps, {n: v for n, v in constants.items() if n in kept}, inputs[0].name, output, dims)
    net.source = model.SerializeToString()
    return net.eval()


def _typed(value: np.ndarray) -> np.ndarray:
    """Floating tensors as float32, integer ones (shapes) as int64."""
    value = np.asarray(value)
    if value.dtype.kind in "iub":
        return value.astype(np.int64)
    return value.astype(np.float32)


def _value(name: str, values: dict, constants: dict):
    if not name:
        return None
    return values[name] if name in values else torch.from_numpy(np.array(constants[name]))


class ReferenceCheck:
    """The file's network run by an independent executor (onnxruntime) beside mrcert's reading of
    it: :meth:`check` refuses, in one line, a network whose outputs differ from the executor's
    beyond float tolerance at the points it is given (a node read otherwise than the file means)."""

    RTOL = 1e-4
    """Tolerance relative to the largest output (plus :data:`ATOL`): float32 rounding is far below it."""
    ATOL = 1e-5

    def __init__(self, net: OnnxNetwork, label: str):
        try:
            import onnxruntime as ort
        except ImportError:  # pragma: no cover - a dependency
            raise MrcertError("checking an ONNX network needs onnxruntime (pip install onnxruntime)") from None
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.log_severity_level = 3
        try:
            self.runner = ort.InferenceSession(net.source, options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - a file onnxruntime refuses is no network to answer about
            raise MrcertError(f"{label}: the reference executor (onnxruntime) cannot run it: "
                              f"{str(exc).splitlines()[0]}") from None  # fmt: skip
        self.net, self.label = net, label
        self.name = self.runner.get_inputs()[0].name

    def reference(self, x: np.ndarray) -> np.ndarray:
        """The executor's outputs (B, K) at the inputs ``x`` (B, ...), one point at a time."""
        rows = [self.runner.run(None, {self.name: x[i : i + 1].astype(np.float32)})[0] for i in range(len(x))]
        return np.concatenate([r.reshape(1, -1) for r in rows])

    def check(self, x: torch.Tensor, *networks) -> float:
        """The largest difference between the executor and each of ``networks`` (callables on a
        (B, ...) tensor) at ``x``; one line refuses the network when it is beyond tolerance."""
        want = self.reference(x.detach().cpu().numpy())
        scale = self.ATOL + self.RTOL * float(np.abs(want).max(initial=0.0))
        worst = 0.0
        for network in networks:
            with torch.no_grad():
                got = network(x).detach().double().cpu().reshape(len(x), -1).numpy()
            if got.shape != want.shape:
                raise MrcertError(f"{self.label}: mrcert's reading gives {got.shape[1]} outputs where the reference "
                                  f"executor (onnxruntime) gives {want.shape[1]}")  # fmt: skip
            diff = float(np.abs(got - want).max(initial=0.0)) if np.isfinite(got).all() else math.inf
            if not diff <= scale:
                raise MrcertError(
                    f"{self.label}: mrcert's reading of the network differs from the reference executor "
                    f"(onnxruntime) by {diff:.3g} (tolerance {scale:.3g}) inside the box; it is not answered"
                )
            worst = max(worst, diff)
        return worst


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
