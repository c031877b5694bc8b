"""The network in the file, or a refusal: every attribute of every operator mrcert reads is either
computed as onnxruntime computes it (the reference executor) and bounded soundly, or refused in
one line naming the node, the attribute and its value; a network mrcert would read otherwise
than the file means is never answered ``unsat``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from onnx import helper

from mrcert.core.verification.network import BoundNetwork
from mrcert.errors import MrcertError
from mrcert.formats.onnx_model import ATTRIBUTES, ReferenceCheck, read_onnx
from mrcert.tasks.verify import Settings, verify_instance
from tests.onnx_graphs import Reference, ints, model, save, tensor, vnnlib_text

RNG = np.random.default_rng(7)
W = RNG.normal(size=(4, 2, 3, 3))
W2 = RNG.normal(size=(4, 2, 2, 2))
WG = RNG.normal(size=(4, 1, 3, 3))
STATS = [RNG.uniform(0.5, 1.5, 2), RNG.normal(size=2), RNG.normal(size=2), RNG.uniform(0.5, 1.5, 2)]
BN = [tensor(n, v) for n, v in zip(("s", "b", "m", "v"), STATS, strict=True)]


def node(op, inputs, output="h", **attrs):
    return helper.make_node(op, inputs, [output], name=f"the_{op.lower()}", **attrs)


FLAT = node("Flatten", ["h"], "y")


def conv(**attrs):
    return [node("Conv", ["x", "w"], **attrs), FLAT], [tensor("w", W)]


def pool(op, **attrs):
    return [node(op, ["x"], **attrs), FLAT], []


# (id, nodes and initializers, input shape, None: read as the file means / a refusal's words)
CASES = [
    ("conv", conv(), (1, 2, 5, 6), None),
    ("conv pads", conv(pads=[1, 1, 1, 1]), (1, 2, 5, 6), None),
    ("conv asymmetric pads", conv(pads=[0, 1, 2, 0]), (1, 2, 5, 6), None),
    ("conv SAME_UPPER", conv(auto_pad="SAME_UPPER"), (1, 2, 5, 6), None),
    ("conv SAME_UPPER even kernel", ([node("Conv", ["x", "w"], auto_pad="SAME_UPPER"), FLAT], [tensor("w", W2)]),
     (1, 2, 5, 6), None),
    ("conv SAME_LOWER even kernel", ([node("Conv", ["x", "w"], auto_pad="SAME_LOWER"), FLAT], [tensor("w", W2)]),
     (1, 2, 5, 6), None),
    ("conv SAME_UPPER strided", conv(auto_pad="SAME_UPPER", strides=[2, 2]), (1, 2, 6, 7), None),
    ("conv VALID", conv(auto_pad="VALID"), (1, 2, 5, 6), None),
    ("conv strides dilations", conv(strides=[2, 1], dilations=[2, 2], pads=[1, 2, 1, 2]), (1, 2, 7, 7), None),
    ("conv group and bias", ([node("Conv", ["x", "w", "b"], group=2), FLAT],
                             [tensor("w", WG), tensor("b", RNG.normal(size=4))]), (1, 2, 5, 5), None),
    ("conv kernel_shape not the weight's", conv(kernel_shape=[2, 2]), (1, 2, 5, 6), "kernel_shape=[2, 2]"),
    ("conv auto_pad unknown", conv(auto_pad="SAME"), (1, 2, 5, 6), "auto_pad='SAME'"),
    ("conv auto_pad and pads", conv(auto_pad="SAME_UPPER", pads=[1, 1, 1, 1]), (1, 2, 5, 6), "both auto_pad"),
    ("maxpool default strides are 1", pool("MaxPool", kernel_shape=[2, 2]), (1, 2, 5, 6), None),
    ("maxpool strided", pool("MaxPool", kernel_shape=[2, 2], strides=[2, 2]), (1, 2, 6, 6), None),
    ("maxpool pads", pool("MaxPool", kernel_shape=[3, 3], pads=[1, 1, 1, 1]), (1, 2, 5, 6), None),
    ("maxpool SAME_UPPER odd", pool("MaxPool", kernel_shape=[3, 3], auto_pad="SAME_UPPER"), (1, 2, 5, 6), None),
    ("maxpool SAME_UPPER even", pool("MaxPool", kernel_shape=[2, 2], auto_pad="SAME_UPPER"), (1, 2, 5, 6),
     "unequally"),
    ("maxpool dilations", pool("MaxPool", kernel_shape=[2, 2], dilations=[2, 2]), (1, 2, 5, 6), "dilations=[2, 2]"),
    ("maxpool ceil_mode idle", pool("MaxPool", kernel_shape=[2, 2], strides=[2, 2], ceil_mode=1), (1, 2, 6, 6),
     None),
    ("maxpool ceil_mode", pool("MaxPool", kernel_shape=[2, 2], strides=[2, 2], ceil_mode=1), (1, 2, 5, 6),
     "ceil_mode=1"),
    ("maxpool storage_order", pool("MaxPool", kernel_shape=[2, 2], storage_order=1), (1, 2, 4, 4), None),
    ("maxpool indices used", ([helper.make_node("MaxPool", ["x"], ["p", "i"], name="mp", kernel_shape=[2, 2]),
                               node("Cast", ["i"], "c", to=1), node("Add", ["p", "c"]), FLAT], []), (1, 2, 4, 4),
     "output 'i'"),
    ("avgpool", pool("AveragePool", kernel_shape=[2, 2], strides=[2, 2]), (1, 2, 6, 6), None),
    ("avgpool pads", pool("AveragePool", kernel_shape=[3, 3], pads=[1, 1, 1, 1]), (1, 2, 5, 6), None),
    ("avgpool pads counted", pool("AveragePool", kernel_shape=[3, 3], pads=[1, 1, 1, 1], count_include_pad=1),
     (1, 2, 5, 6), None),
    ("avgpool asymmetric counted", pool("AveragePool", kernel_shape=[2, 2], auto_pad="SAME_UPPER",
                                        count_include_pad=1), (1, 2, 5, 6), None),
    ("avgpool asymmetric", pool("AveragePool", kernel_shape=[2, 2], auto_pad="SAME_LOWER"), (1, 2, 5, 6),
     "count_include_pad=0"),
    ("avgpool ceil_mode", pool("AveragePool", kernel_shape=[2, 2], strides=[2, 2], ceil_mode=1), (1, 2, 5, 5),
     "ceil_mode=1"),
    ("avgpool ceil_mode idle", pool("AveragePool", kernel_shape=[3, 3], strides=[2, 2], ceil_mode=1),
     (1, 2, 5, 5), None),
    ("avgpool dilations", pool("AveragePool", kernel_shape=[2, 2], dilations=[2, 1]), (1, 2, 5, 6),
     "dilations=[2, 1]"),
    ("global avgpool", pool("GlobalAveragePool"), (1, 2, 5, 6), None),
    ("batchnorm", ([node("BatchNormalization", ["x", "s", "b", "m", "v"], epsilon=1e-3), FLAT], BN), (1, 2, 3, 4),
     None),
    ("batchnorm of (N, C)", ([node("BatchNormalization", ["x", "s", "b", "m", "v"], "y")], BN), (1, 2), None),
    ("batchnorm training", ([node("BatchNormalization", ["x", "s", "b", "m", "v"], training_mode=1), FLAT], BN),
     (1, 2, 3, 4), "training_mode=1"),
    ("gemm", ([node("Gemm", ["x", "g", "c"], "y", alpha=0.5, beta=2.0)],
              [tensor("g", RNG.normal(size=(6, 3))), tensor("c", RNG.normal(size=3))]), (1, 6), None),
    ("gemm transB, C of (1, K)", ([node("Gemm", ["x", "g", "c"], "y", transB=1)],
                                  [tensor("g", RNG.normal(size=(3, 6))), tensor("c", RNG.normal(size=(1, 3)))]),
     (1, 6), None),
    ("gemm transA", ([node("Gemm", ["x", "g"], "y", transA=1)], [tensor("g", RNG.normal(size=(1, 3)))]), (1, 6),
     "transA=1"),
    ("matmul", ([node("MatMul", ["x", "g"], "y")], [tensor("g", RNG.normal(size=(6, 3)))]), (1, 6), None),
    ("matmul by the input", ([node("MatMul", ["g", "x"], "y")], [tensor("g", RNG.normal(size=(1, 1)))]), (1, 6),
     "multiplies by a tensor"),
    ("constant minus input", ([node("Sub", ["c", "x"], "y")], [tensor("c", RNG.normal(size=6))]), (1, 6), None),
    ("scaled, shifted, divided", ([node("Mul", ["x", "a"], "u"), node("Add", ["u", "c"], "v"),
                                   node("Div", ["v", "d"], "y")],
                                  [tensor("a", RNG.normal(size=6)), tensor("c", RNG.normal(size=(1, 6))),
                                   tensor("d", RNG.uniform(1, 2, size=6))]), (1, 6), None),
    ("divided by zero", ([node("Div", ["x", "d"], "y")], [tensor("d", [1, 0, 1, 1, 1, 1])]), (1, 6), "zeros"),
    ("broadcast over the batch", ([node("Add", ["x", "c"], "y")], [tensor("c", np.zeros((3, 6)))]), (1, 6),
     "keeps the batch"),
    ("flatten axis 2", ([node("Flatten", ["x"], "y", axis=2)], []), (1, 2, 3, 4), "axis=2"),
    ("reshape 0 and -1", ([node("Reshape", ["x", "s"], "y")], [ints("s", [0, -1])]), (1, 2, 3, 4), None),
    ("reshape through the batch", ([node("Reshape", ["x", "s"], "y")], [ints("s", [2, -1])]), (1, 2, 3, 4),
     "batch"),
    ("constant node", ([helper.make_node("Constant", [], ["c"], value_floats=[1.0, -2.0, 3.0, 0.5, 1.5, -1.0]),
                        node("Add", ["x", "c"], "y")], []), (1, 6), None),
    ("dropout with its ratio", ([node("Dropout", ["x", "r"], "y")], [tensor("r", 0.3)]), (1, 6), None),
    ("dropout training", ([node("Dropout", ["x", "r", "t"], "y")],
                          [tensor("r", 0.3), helper.make_tensor("t", 9, [], [True])]), (1, 6), "training_mode"),
    ("identity and relu", ([node("Identity", ["x"], "u"), node("Relu", ["u"], "y")], []), (1, 6), None),
    ("an attribute no operator has", ([node("Relu", ["x"], "y", alpha=0.1)], []), (1, 6), "alpha=0.1"),
    ("an operator it does not read", ([node("Tanh", ["x"], "y")], []), (1, 6), "Tanh"),
    ("another domain", ([helper.make_node("Relu", ["x"], ["y"], name="r", domain="com.example")], []), (1, 6),
     "domain 'com.example'"),
]  # fmt: skip


@pytest.mark.parametrize(("graph", "shape", "refusal"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_each_attribute_is_read_as_the_reference_executor_runs_it_or_refused(graph, shape, refusal, tmp_path):
    nodes, inits = graph
    m = model(nodes, shape, inits)
    path = save(m, tmp_path / "net.onnx")
    if refusal is not None:
        with pytest.raises(MrcertError) as caught:
            read_onnx(path)
        line = str(caught.value)
        assert refusal in line and "\n" not in line, line
        return
    net = read_onnx(path)
    bounds = BoundNetwork(net)
    g = torch.Generator().manual_seed(0)
    centre = torch.rand(1, *shape[1:], generator=g)
    x = centre + 0.2 * (torch.rand(64, *shape[1:], generator=g) - 0.5)
    want = Reference(m)(x.numpy())
    with torch.no_grad():
        got32, got64 = net(x).double().numpy(), bounds.forward(x.double()).numpy()
    tol = 1e-5 + 1e-5 * np.abs(want).max()
    assert np.abs(got32 - want).max() <= tol and np.abs(got64 - want).max() <= tol
    # Every output's bounds over the box hold at every sampled point (interval and backward relaxation).
    k = want.shape[1]
    spec = torch.cat([torch.eye(k), -torch.eye(k)]).double()
    low, high = centre - 0.1, centre + 0.1
    for relaxation in ("interval", "crown"):
        lower = bounds.linear_lower(low.double(), high.double(), spec, relaxation, upto=np.inf)[0].numpy()
        assert (want >= lower[:k] - tol).all() and (want <= -lower[k:] + tol).all(), relaxation


def test_the_cases_cover_every_operator_read():
    ops = {n.op_type for _, (nodes, _), _, refusal in CASES if refusal is None for n in nodes}
    assert ops == set(ATTRIBUTES)


def test_a_gzipped_model_is_read_as_it_is(tmp_path):
    import gzip

    nodes, inits = CASES[1][1]
    m = model(nodes, (1, 2, 5, 6), inits)
    (tmp_path / "net.onnx.gz").write_bytes(gzip.compress(m.SerializeToString()))
    net = read_onnx(tmp_path / "net.onnx.gz")
    x = torch.rand(2, 2, 5, 6, generator=torch.Generator().manual_seed(1))
    assert np.allclose(net(x).numpy(), Reference(m)(x.numpy()), atol=1e-5)


def test_a_model_claiming_more_tensor_bytes_than_allowed_is_refused_before_loading(tmp_path):
    import onnx
    from onnx import TensorProto

    big = onnx.TensorProto(name="w", data_type=TensorProto.FLOAT, dims=[2**28])  # 1 GiB claimed, none given
    big.data_location = TensorProto.EXTERNAL
    for key, value in (("location", "w.bin"), ("length", str(2**30))):
        big.external_data.add(key=key, value=value)
    m = model([node("Add", ["x", "w"], "y")], (1, 2**28), [big])
    path = save(m, tmp_path / "net.onnx")
    (tmp_path / "w.bin").write_bytes(b"\0" * 16)
    with pytest.raises(MrcertError, match=r"claim 1073741824 bytes, beyond the 536870912"):
        read_onnx(path)
    with pytest.raises(MrcertError, match="claims 1073741824 bytes of external data where its file holds 16"):
        read_onnx(path, max_bytes=2**31)


# The three networks that mrcert read otherwise than their files: an attribute before a global
# average pooling, where the shapes still fit whatever the attribute does.
BODIES = {
    "conv SAME_UPPER": ([node("Conv", ["x", "w"], "c", auto_pad="SAME_UPPER"), node("Relu", ["c"], "r")],
                        (4, 2, 3, 3), (1, 2, 4, 4)),
    "maxpool dilations": ([node("Conv", ["x", "w"], "c"), node("Relu", ["c"], "q"),
                           node("MaxPool", ["q"], "r", kernel_shape=[2, 2], dilations=[2, 2])],
                          (4, 2, 1, 1), (1, 2, 5, 5)),
    "avgpool ceil_mode": ([node("Conv", ["x", "w"], "c"), node("Relu", ["c"], "q"),
                           node("AveragePool", ["q"], "r", kernel_shape=[2, 2], strides=[2, 2], ceil_mode=1)],
                          (4, 2, 1, 1), (1, 2, 5, 5)),
}  # fmt: skip


def pooled_as_ignored(name: str, weight: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The pooled features (B, 4) with the attribute ``name`` names ignored, as mrcert once read them."""
    import torch.nn.functional as F

    h = torch.relu(F.conv2d(torch.from_numpy(x).float(), torch.from_numpy(weight).float()))  # conv: no padding
    if name == "maxpool dilations":
        h = F.max_pool2d(h, 2, 2)  # no dilation, and strides as the kernel
    elif name == "avgpool ceil_mode":
        h = F.avg_pool2d(h, 2, 2)  # the floor's windows only
    return h.mean((2, 3)).double().numpy()


def misread(name: str):
    """The network ``name`` and a point where its output 0 is above output 1 (the file's reading)
    and below it with the attribute ignored, by as much: the head is ``d . pooled + o`` along the
    difference ``d`` of the two readings' pooled features there."""
    body, kernel, shape = BODIES[name]
    weight = np.random.default_rng(5).normal(size=kernel).astype(np.float32)
    centre = np.random.default_rng(3).uniform(size=int(np.prod(shape)))
    x = centre.reshape(1, *shape[1:])
    prefix = model([*body, node("GlobalAveragePool", ["r"], "p"), node("Flatten", ["p"], "y")], shape,
                   [tensor("w", weight)])  # fmt: skip
    true, ignored = Reference(prefix)(x)[0], pooled_as_ignored(name, weight, x)[0]
    d = true - ignored
    head, bias = np.zeros((4, 3)), np.array([-float(d @ (true + ignored)) / 2, 0.0, -10.0])
    head[:, 0] = d
    pooled = [node("GlobalAveragePool", ["r"], "p"), node("Flatten", ["p"], "f")]
    nodes = [*body, *pooled, node("Gemm", ["f", "g", "b"], "y")]
    m = model(nodes, shape, [tensor("w", weight), tensor("g", head), tensor("b", bias)])
    return m, centre, shape


@pytest.mark.parametrize("name", list(BODIES))
def test_a_network_read_otherwise_than_its_file_is_never_verified(name, tmp_path):
    """Unsafe: ``y_0 >= y_1`` on a tiny box around the point of :func:`misread`. With the
    attribute ignored it is verified (``unsat``); the answer is ``sat`` with a counterexample the
    executor confirms, or ``error`` naming the attribute."""
    m, centre, shape = misread(name)
    assert np.diff(Reference(m)(centre.reshape(1, *shape[1:]))[0][:2]) < -1e-4  # the file: y_0 above y_1
    save(m, tmp_path / "net.onnx")
    (tmp_path / "p.vnnlib").write_text(vnnlib_text(centre - 1e-6, centre + 1e-6, [[(0, 1)]], 3))
    verdict, reason = verify_instance(tmp_path / "net.onnx", tmp_path / "p.vnnlib", 30.0, Settings())
    assert verdict.result in ("sat", "error"), (verdict.result, reason)
    if verdict.result == "error":
        assert "\n" not in reason and ("mrcert does not read" in reason or "ceil_mode=1" in reason), reason
    else:
        y = Reference(m)(verdict.x.reshape(1, *shape[1:]))[0]
        assert y[0] >= y[1] and np.abs(verdict.x.ravel() - centre).max() <= 1e-6 + 1e-12


def test_a_reading_that_differs_from_the_executor_is_refused(tmp_path):
    """The cross-check itself: a network whose module computes otherwise than its file (here a
    ReLU dropped after reading) is refused naming the difference."""
    m = model([node("Gemm", ["x", "g"], "h"), node("Relu", ["h"], "y")], (1, 4), [tensor("g", -np.ones((4, 2)))])
    net = read_onnx(save(m, tmp_path / "net.onnx"))
    x = torch.rand(3, 4, generator=torch.Generator().manual_seed(0))
    check = ReferenceCheck(net, "net.onnx")
    assert check.check(x, net) <= 1e-6
    net.steps = net.steps[:-1] + [("Identity", net.steps[-1][1], net.steps[-1][2], {})]
    with pytest.raises(MrcertError, match=r"net.onnx: mrcert's reading of the network differs from the reference"):
        check.check(x, net)
