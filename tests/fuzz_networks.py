"""Small random ONNX networks over every operator and attribute mrcert reads, and the exact truth
of a robustness property on them by mixed-integer linear programming (scipy.optimize.milp,
big-M ReLU and max), built from the file alone: every affine node's matrix is read off the
reference executor (onnxruntime) on the basis vectors, every max pooling's windows on one-hot
inputs, so the oracle shares nothing with mrcert's reading of the file."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from onnx import TensorProto, helper, numpy_helper

from tests.onnx_graphs import OPSET, model, tensor

CLASSES = 3


@dataclass
class Network:
    nodes: list
    initializers: list
    shape: tuple[int, ...]
    kind: str

    def onnx(self):
        return model(self.nodes, self.shape, self.initializers)


class _Builder:
    def __init__(self, rng: np.random.Generator, shape):
        self.rng, self.nodes, self.inits, self.k = rng, [], [], 0
        self.shape = tuple(shape)

    def name(self, stem: str) -> str:
        self.k += 1
        return f"{stem}{self.k}"

    def const(self, value) -> str:
        name = self.name("c")
        self.inits.append(tensor(name, value))
        return name

    def add(self, op: str, inputs, **attrs) -> str:
        out = self.name("t")
        self.nodes.append(helper.make_node(op, list(inputs), [out], name=self.name(op.lower()), **attrs))
        return out


def _conv_attrs(rng, h: int, w: int) -> tuple[dict, int]:
    """Random Conv attributes that keep a 2-D output of at least 1 x 1; the kernel size."""
    k = int(rng.integers(1, 4))
    choice = rng.integers(0, 6)
    attrs: dict = {}
    if choice == 1:
        attrs["pads"] = [int(v) for v in rng.integers(0, 2, 4)]
    elif choice == 2:
        attrs["auto_pad"] = ["SAME_UPPER", "SAME_LOWER", "VALID"][int(rng.integers(0, 3))]
    if rng.uniform() < 0.3:
        attrs["strides"] = [int(v) for v in rng.integers(1, 3, 2)]
    if rng.uniform() < 0.2 and k > 1 and min(h, w) >= 2 * k:
        attrs["dilations"] = [2, 2]
    if rng.uniform() < 0.3:
        attrs["kernel_shape"] = [k, k]
    return attrs, k


def _fits(h: int, w: int, k: int, attrs: dict) -> bool:
    d = attrs.get("dilations", [1, 1])
    pads = attrs.get("pads", [0, 0, 0, 0])
    if attrs.get("auto_pad", "").startswith("SAME"):
        return True
    return all((size + pads[i] + pads[i + 2] - (k - 1) * d[i] - 1) >= 0 for i, size in enumerate((h, w)))


def _pool(b: _Builder, x: str, h: int, w: int) -> str:
    rng = b.rng
    k = int(rng.integers(2, 4))
    if min(h, w) < k:
        return x
    stride = int(rng.integers(1, 3))
    attrs: dict = {"kernel_shape": [k, k], "strides": [stride, stride]}
    op = "MaxPool" if rng.uniform() < 0.6 else "AveragePool"
    choice = rng.integers(0, 4)
    if choice == 1 and k == 3:
        attrs["pads"] = [1, 1, 1, 1]
    elif choice == 2 and k == 3 and stride == 1:
        attrs["auto_pad"] = "SAME_UPPER"
    elif choice == 3 and op == "AveragePool":
        attrs["auto_pad"] = "SAME_LOWER"
        attrs["count_include_pad"] = 1
    if op == "AveragePool" and "count_include_pad" not in attrs and rng.uniform() < 0.5:
        attrs["count_include_pad"] = int(rng.integers(0, 2))
    pads = attrs.get("pads", [0, 0, 0, 0])
    if "auto_pad" not in attrs and all((size + 2 * pads[0] - k) % stride == 0 for size in (h, w)):
        attrs["ceil_mode"] = 1  # where the ceiling changes nothing
    if op == "MaxPool" and rng.uniform() < 0.2:
        attrs["storage_order"] = 1
    return b.add(op, [x], **attrs)


def random_network(rng: np.random.Generator) -> Network:
    """One random network (MLP, CNN or residual CNN) of at most 32 inputs and 3 outputs."""
    kind = ["mlp", "cnn", "residual"][int(rng.integers(0, 3))]
    if kind == "mlp":
        n = int(rng.integers(2, 9))
        b = _Builder(rng, (1, n))
        x, width = "x", n
        for _ in range(int(rng.integers(1, 3))):
            hidden = int(rng.integers(3, 9))
            x, width = _dense(b, x, width, hidden), hidden
            if rng.uniform() < 0.3:
                stats = [rng.uniform(0.5, 1.5, hidden), rng.normal(size=hidden), rng.normal(size=hidden),
                         rng.uniform(0.5, 1.5, hidden)]  # fmt: skip
                x = b.add("BatchNormalization", [x, *(b.const(v) for v in stats)], **_norm_attrs(rng))
            x = _scalar_ops(b, x, (1, width))
            x = b.add("Relu", [x])
        _dense(b, x, width, CLASSES, out="y")
        return Network(b.nodes, b.inits, b.shape, kind)
    c = int(rng.integers(1, 3))
    h, w = int(rng.integers(3, 6)), int(rng.integers(3, 6))
    b = _Builder(rng, (1, c, h, w))
    x = "x"
    if kind == "cnn":
        attrs, k = _conv_attrs(rng, h, w)
        while not _fits(h, w, k, attrs):
            attrs, k = _conv_attrs(rng, h, w)
        out_c = int(rng.integers(2, 5))
        group = 2 if c == 2 and out_c % 2 == 0 and rng.uniform() < 0.3 else 1
        weight = rng.normal(size=(out_c, c // group, k, k))
        inputs = [x, b.const(weight)] + ([b.const(rng.normal(size=out_c))] if rng.uniform() < 0.7 else [])
        x = b.add("Conv", inputs, group=group, **attrs)
    else:
        out_c = c
        weight = rng.normal(size=(c, c, 3, 3)) * 0.5
        first = b.add("Conv", [x, b.const(weight), b.const(rng.normal(size=c))], pads=[1, 1, 1, 1])
        first = b.add("Relu", [first])
        second = b.add("Conv", [first, b.const(rng.normal(size=(c, c, 3, 3)) * 0.5)], auto_pad="SAME_UPPER")
        x = b.add("Add", [second, x])
    shape = _shape(b, x)
    if rng.uniform() < 0.4:
        stats = [
            rng.uniform(0.5, 1.5, out_c),
            rng.normal(size=out_c),
            rng.normal(size=out_c),
            rng.uniform(0.5, 1.5, out_c),
        ]
        x = b.add("BatchNormalization", [x, *(b.const(v) for v in stats)], **_norm_attrs(rng))
    x = b.add("Relu", [x])
    if rng.uniform() < 0.6:
        x = _pool(b, x, shape[2], shape[3])
    if rng.uniform() < 0.2:
        x = b.add("Identity", [x])
    if rng.uniform() < 0.2:
        x = b.add("Dropout", [x, b.const(0.25)])
    end = rng.integers(0, 3)
    if end == 0:
        x = b.add("Flatten", [x], **({"axis": 1} if rng.uniform() < 0.5 else {}))
    elif end == 1:
        shape_name = b.name("s")
        b.inits.append(numpy_helper.from_array(np.array([0, -1], dtype=np.int64), shape_name))
        x = b.add("Reshape", [x, shape_name], **({"allowzero": 0} if rng.uniform() < 0.5 else {}))
    else:
        x = b.add("Flatten", [b.add("GlobalAveragePool", [x])])
    width = int(np.prod(_shape(b, x)[1:]))
    x = _scalar_ops(b, x, (1, width))
    _dense(b, x, width, CLASSES, out="y")
    return Network(b.nodes, b.inits, b.shape, kind)


def _dense(b: _Builder, x: str, n: int, m: int, out: str | None = None) -> str:
    rng = b.rng
    if rng.uniform() < 0.3:  # MatMul then Add
        y = b.add("MatMul", [x, b.const(rng.normal(size=(n, m)))])
        node = helper.make_node("Add", [y, b.const(rng.normal(size=m))], [out or b.name("t")], name=b.name("add"))
    else:
        trans = int(rng.integers(0, 2))
        weight = rng.normal(size=(m, n) if trans else (n, m))
        attrs = {"transB": trans, **({"transA": 0} if rng.uniform() < 0.3 else {})}
        if rng.uniform() < 0.3:
            attrs["alpha"] = float(rng.uniform(0.5, 2))
        if rng.uniform() < 0.3:
            attrs["beta"] = float(rng.uniform(0.5, 2))
        bias = rng.normal(size=(1, m) if rng.uniform() < 0.5 else m)
        node = helper.make_node("Gemm", [x, b.const(weight), b.const(bias)], [out or b.name("t")], name=b.name("gemm"),
                                **attrs)  # fmt: skip
    b.nodes.append(node)
    return node.output[0]


def _scalar_ops(b: _Builder, x: str, shape) -> str:
    rng = b.rng
    if rng.uniform() < 0.25:
        x = b.add("Mul", [x, b.const(rng.normal(size=shape[1:]))])
    if rng.uniform() < 0.2:
        x = b.add("Sub", [b.const(rng.normal(size=shape[1:])), x])
    if rng.uniform() < 0.2:
        x = b.add("Div", [x, b.const(rng.uniform(0.5, 2.0))])
    if rng.uniform() < 0.2:
        out = b.name("k")
        value = rng.normal(size=shape[1:])
        attrs = {"value": tensor(out, value)} if rng.uniform() < 0.5 else {"value_floats": [float(v) for v in value]}
        b.nodes.append(helper.make_node("Constant", [], [out], name=b.name("constant"), **attrs))
        x = b.add("Add", [x, out])
    return x


def _norm_attrs(rng) -> dict:
    attrs: dict = {}
    if rng.uniform() < 0.5:
        attrs["epsilon"] = float(rng.uniform(1e-5, 1e-2))
    if rng.uniform() < 0.3:
        attrs["momentum"] = 0.9
    if rng.uniform() < 0.3:
        attrs["training_mode"] = 0
    return attrs


def _shape(b: _Builder, name: str) -> tuple[int, ...]:
    """The shape of ``name`` in the graph built so far (the reference executor on a zero input)."""
    m = model(b.nodes, b.shape, b.inits, output=name)
    return tuple(_run(m, np.zeros(b.shape, np.float32)).shape)


def _run(m, x: np.ndarray, inputs: dict | None = None) -> np.ndarray:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.log_severity_level = 3
    runner = ort.InferenceSession(m.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return runner.run(None, inputs or {"x": x})[0]


class Oracle:
    """The network of a file as a mixed-integer program; :meth:`worst` is the exact largest
    ``y_j - y_c`` over a box (each node's map read off the reference executor)."""

    def __init__(self, net: Network):
        self.net = net
        consts = {t.name: numpy_helper.to_array(t) for t in net.initializers}
        for node in net.nodes:
            if node.op_type == "Constant":
                a = node.attribute[0]
                consts[node.output[0]] = (
                    numpy_helper.to_array(a.t) if a.name == "value" else np.array(a.floats, np.float32)
                )
        self.consts = consts
        self.steps = []  # (kind, inputs, output, data)
        shapes = {"x": net.shape}
        for node in net.nodes:
            if node.op_type == "Constant":
                continue
            tensors = [i for i in node.input if i and i not in consts]
            if node.op_type == "Relu":
                self.steps.append(("relu", tensors, node.output[0], None))
                shapes[node.output[0]] = shapes[tensors[0]]
            elif node.op_type == "Add" and len(tensors) == 2:
                self.steps.append(("sum", tensors, node.output[0], None))
                shapes[node.output[0]] = shapes[tensors[0]]
            else:
                (source,) = tensors
                single = self._single(node, source, shapes[source])
                n = int(np.prod(shapes[source]))
                zero = _run(single, None, {source: np.zeros(shapes[source], np.float32)})
                shapes[node.output[0]] = zero.shape
                if node.op_type == "MaxPool":
                    windows = []
                    for i in range(n):
                        v = -np.ones(n, np.float32)
                        v[i] = 1.0
                        windows.append(_run(single, None, {source: v.reshape(shapes[source])}).ravel() == 1.0)
                    self.steps.append(("max", tensors, node.output[0], np.array(windows).T))  # (out, in)
                else:
                    columns = []
                    for i in range(n):
                        v = np.zeros(n, np.float32)
                        v[i] = 1.0
                        out = _run(single, None, {source: v.reshape(shapes[source])}).astype(np.float64)
                        columns.append(out.ravel() - zero.ravel())
                    self.steps.append(("affine", tensors, node.output[0], (np.array(columns).T, zero.ravel())))
        self.output = net.nodes[-1].output[0]

    def _single(self, node, source: str, shape):
        inits = [numpy_helper.from_array(np.asarray(self.consts[i]), i) for i in node.input if i in self.consts]
        graph = helper.make_graph(
            [node], "one", [helper.make_tensor_value_info(source, TensorProto.FLOAT, list(shape))],
            [helper.make_tensor_value_info(node.output[0], TensorProto.FLOAT, None)], inits,
        )  # fmt: skip
        return helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], ir_version=8)

    def worst(self, low: np.ndarray, high: np.ndarray, label: int, seconds: float = 20.0) -> tuple[float, float]:
        """Bounds on max over the box and over j != label of y_j - y_label (> 0: a counterexample
        exists): equal when the programs are solved, the best point found and the best bound
        otherwise (``seconds`` each)."""
        from scipy.optimize import LinearConstraint, milp
        from scipy.sparse import lil_matrix

        index: dict[str, np.ndarray] = {}
        lo: list[float] = []
        up: list[float] = []
        integral: list[int] = []
        rows: list[tuple[dict, float, float]] = []

        def new(lows, ups, binary=False) -> np.ndarray:
            start = len(lo)
            lo.extend(lows)
            up.extend(ups)
            integral.extend([1 if binary else 0] * len(lows))
            return np.arange(start, len(lo))

        def bounds(ids):
            return np.array([lo[i] for i in ids]), np.array([up[i] for i in ids])

        index["x"] = new(low.ravel(), high.ravel())
        for kind, inputs, output, data in self.steps:
            if kind == "affine":
                a, b = data
                l_in, u_in = bounds(index[inputs[0]])
                l_out = a.clip(min=0) @ l_in + a.clip(max=0) @ u_in + b
                u_out = a.clip(min=0) @ u_in + a.clip(max=0) @ l_in + b
                slack = 1e-6 * (1 + np.abs(l_out) + np.abs(u_out))
                ids = new(l_out - slack, u_out + slack)
                for j, y in enumerate(ids):  # y - A x = b
                    coeffs = {y: 1.0}
                    for i, v in zip(index[inputs[0]], -a[j], strict=True):
                        if v != 0:
                            coeffs[int(i)] = coeffs.get(int(i), 0.0) + v
                    rows.append((coeffs, b[j], b[j]))
            elif kind == "sum":
                (l1, u1), (l2, u2) = bounds(index[inputs[0]]), bounds(index[inputs[1]])
                ids = new(l1 + l2, u1 + u2)
                for y, p, q in zip(ids, index[inputs[0]], index[inputs[1]], strict=True):
                    rows.append(({int(y): 1.0, int(p): -1.0, int(q): -1.0}, 0.0, 0.0))
            elif kind == "relu":
                l_in, u_in = bounds(index[inputs[0]])
                ids = new(np.maximum(l_in, 0), np.maximum(u_in, 0))
                for y, x, lx, ux in zip(ids, index[inputs[0]], l_in, u_in, strict=True):
                    y, x = int(y), int(x)
                    if lx >= 0:
                        rows.append(({y: 1.0, x: -1.0}, 0.0, 0.0))
                    elif ux <= 0:
                        rows.append(({y: 1.0}, 0.0, 0.0))
                    else:
                        (z,) = new([0.0], [1.0], binary=True)
                        rows.append(({y: 1.0, x: -1.0}, 0.0, np.inf))  # y >= x
                        rows.append(({y: 1.0, x: -1.0, int(z): -lx}, -np.inf, -lx))  # y <= x - lx (1 - z)
                        rows.append(({y: 1.0, int(z): -ux}, -np.inf, 0.0))  # y <= ux z
            else:  # max over each window
                l_in, u_in = bounds(index[inputs[0]])
                windows = data
                ids = new([l_in[w].max() for w in windows], [u_in[w].max() for w in windows])
                for y, w in zip(ids, windows, strict=True):
                    members = index[inputs[0]][w]
                    top = u_in[w].max()
                    zs = new([0.0] * len(members), [1.0] * len(members), binary=True)
                    rows.append(({int(z): 1.0 for z in zs}, 1.0, 1.0))
                    for x, z, lx in zip(members, zs, l_in[w], strict=True):
                        rows.append(({int(y): 1.0, int(x): -1.0}, 0.0, np.inf))  # y >= x
                        rows.append(({int(y): 1.0, int(x): -1.0, int(z): top - lx}, -np.inf, top - lx))
            index[output] = ids
        matrix = lil_matrix((len(rows), len(lo)))
        lower, upper = np.empty(len(rows)), np.empty(len(rows))
        for r, (coeffs, a, b) in enumerate(rows):
            for i, v in coeffs.items():
                matrix[r, i] = v
            lower[r], upper[r] = a, b
        constraint = LinearConstraint(matrix.tocsr(), lower, upper)
        from scipy.optimize import Bounds

        box = Bounds(np.array(lo), np.array(up))
        out = index[self.output]
        found, bound = -np.inf, -np.inf
        for j in range(CLASSES):
            if j == label:
                continue
            c = np.zeros(len(lo))
            c[out[j]], c[out[label]] = -1.0, 1.0  # minimise y_label - y_j
            res = milp(c, constraints=constraint, integrality=np.array(integral), bounds=box,
                       options={"mip_rel_gap": 0.0, "time_limit": seconds})  # fmt: skip
            if res.status not in (0, 1):
                raise RuntimeError(f"the MILP did not solve: {res.message}")
            if res.fun is not None:
                found = max(found, -float(res.fun))
            dual = getattr(res, "mip_dual_bound", None)
            bound = max(bound, -float(res.fun) if res.status == 0 else -float(dual) if dual is not None else np.inf)
        return found, bound
