"""Classifying a sequence of images that differ from one to the next in a few pixels, by
recomputing only what those pixels reach.

Consecutive images of an enumeration (:mod:`mrcert.core.verification.events`) differ in one to
a few pixels; a convolutional network's activations differ in a small window around them, which
grows by each layer's kernel and shrinks by its stride. :class:`IncrementalNetwork` keeps every
activation of the current image and, for the next one, recomputes each layer on the window its
changed inputs reach (a convolution or pooling over the window's input, zero or minus-infinity
padded where it leaves the tensor, exactly as the layer pads), then the layers after the spatial
ones (global pooling, the linear head) in full. The values are recomputed from the current
inputs, never accumulated as differences, so nothing drifts along a sequence; they equal the
network's own forward pass in exact arithmetic and up to float32 rounding (a different order of
summation) in floats, which is why a margin within rounding of 0 is decided by classifying the
image on its own (:mod:`mrcert.core.methods.enumeration`).

The graph is read with ``torch.fx``. Spatial layers it updates by window: ``Conv2d`` (zero
padding, no dilation; a following ``BatchNorm2d`` in evaluation mode folded in), ``MaxPool2d``
(no dilation, no ceil mode), per-channel affine maps by constants (the input normaliser), ReLU,
batch norm alone, and sums of two spatial tensors (residual connections). Any other layer of a
4-d tensor (adaptive pooling to 1x1, flattening) ends the spatial part; from there every layer is
computed in full, cheaply. A graph with anything else is refused (:func:`IncrementalNetwork.of`
returns None), and the caller classifies whole images instead.
"""

from __future__ import annotations

import copy
import operator
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.fx as fx
import torch.nn.functional as F
from torch import nn

from mrcert.errors import MrcertError

ELEMENTWISE_FUNCTIONS = (torch.relu, F.relu, operator.sub, operator.truediv, operator.mul, operator.add,
                         torch.sub, torch.div, torch.mul, torch.add)  # fmt: skip
SUMS = (operator.add, operator.iadd, torch.add)

FULL_IMAGE = 0.25
"""A change whose window covers more than this share of the image is computed as a whole image."""

NEAR, APART = 64, 8
"""At most ``APART`` changed pixels whose box is larger than ``NEAR`` pixels are changed one at a time."""


@dataclass
class _Node:
    kind: str  # "input", "conv", "pool", "map", "add", "dense"
    inputs: tuple[int, ...]
    fn: object = None  # map/dense: a function of the inputs' values; conv: (weight, bias); pool: kernel
    kernel: int = 1
    stride: int = 1
    padding: int = 0
    spatial: bool = True
    groups: int = 1
    users: list[int] = field(default_factory=list)
    post: list = field(default_factory=list)  # elementwise maps folded in after the layer (a ReLU)
    bounds: object = None  # dense: how intervals pass ("monotone", or a Linear's (weight, bias)); None: they do not


def _pair(value) -> int | None:
    values = value if isinstance(value, (tuple, list)) else (value, value)
    return int(values[0]) if len(set(values)) == 1 else None


class IncrementalNetwork:
    """A classifier's graph as layers that update by window (module docstring)."""

    def __init__(self, nodes: list[_Node], output: int, device):
        self.nodes, self.output, self.device = nodes, output, device
        for k, node in enumerate(nodes):
            for i in node.inputs:
                nodes[i].users.append(k)
        self.values: list[torch.Tensor | None] = [None] * len(nodes)
        # The layer where an affine tail begins (global pooling, the linear head): the margins
        # are then a fixed linear function of its values, and a bound over a few pixels is the
        # current margins plus terms that hold while nothing it read changes (:meth:`bound`).
        dense = [k for k, node in enumerate(nodes) if not node.spatial]
        feeding = {i for k in dense for i in nodes[k].inputs if nodes[i].spatial}
        affine = all(len(nodes[k].inputs) == 1 and nodes[k].bounds is not None and nodes[k].bounds != "monotone"
                     for k in dense)  # fmt: skip
        self.boundary = next(iter(feeding)) if affine and len(feeding) == 1 and output in dense else None
        self._sensitivity: torch.Tensor | None = None
        # Results kept while no step changes what they read (the footprint, per layer a box):
        # a bound's offsets, a variant's change of the logits (:meth:`bound`, :meth:`variant`).
        self._kept: dict[tuple, torch.Tensor] = {}
        self._footprint: dict[int, tuple[int, int, int, int]] = {}
        self.deltas = 0  # the changes of the logits computed (:meth:`delta`), each a variant classified

    # --- reading the graph ---------------------------------------------------------------------
    @classmethod
    def of(cls, model: nn.Module) -> IncrementalNetwork | None:
        """The model's graph as an incremental network, or None where it holds a layer this
        module does not update by window."""
        model = copy.deepcopy(model).eval()
        device = next(iter(model.parameters()), torch.zeros(())).device
        try:
            traced = fx.symbolic_trace(model)
        except Exception:  # noqa: BLE001 - a graph fx cannot read: whole images it is
            return None
        try:
            return cls._read(traced, device)
        except _Refused:
            return None

    @classmethod
    def _read(cls, traced: fx.GraphModule, device) -> IncrementalNetwork:
        nodes: list[_Node] = []
        index: dict[fx.Node, int] = {}
        consts: dict[fx.Node, object] = {}
        output = -1
        graph = list(traced.graph.nodes)
        users = {n: list(n.users) for n in graph}
        for node in graph:
            if node.op == "placeholder":
                if nodes:
                    raise _Refused
                index[node] = len(nodes)
                nodes.append(_Node("input", ()))
                continue
            if node.op == "get_attr":
                obj = traced
                for part in str(node.target).split("."):
                    obj = getattr(obj, part)
                consts[node] = obj
                continue
            if node.op == "output":
                out = node.args[0]
                if not isinstance(out, fx.Node) or out not in index:
                    raise _Refused
                output = index[out]
                continue
            bounded = [a for a in node.all_input_nodes if a in index]
            if not bounded:
                args = fx.node.map_arg(node.args, lambda a: consts[a])
                kwargs = fx.node.map_arg(node.kwargs, lambda a: consts[a])
                consts[node] = _call(traced, node, args, kwargs)
                continue
            inputs = tuple(index[a] for a in bounded)
            spatial = all(nodes[i].spatial for i in inputs)
            made = cls._node(traced, node, inputs, consts, spatial, nodes, index, users)
            if made is None:  # a batch norm folded into the convolution before it
                index[node] = index[bounded[0]]
                continue
            index[node] = len(nodes)
            nodes.append(made)
        if output < 0:
            raise _Refused
        nodes, output = _fused(nodes, output)
        return cls(nodes, output, device)

    @staticmethod
    def _node(traced, node, inputs, consts, spatial, nodes, index, users) -> _Node | None:
        module = traced.get_submodule(str(node.target)) if node.op == "call_module" else None
        dense = _Node("dense", inputs, _dense(traced, node, index, consts), spatial=False)
        dense.bounds = _interval_rule(node, module, consts)
        if not spatial:
            return dense
        if isinstance(module, nn.Conv2d):
            k, s, p, d = (_pair(v) for v in (module.kernel_size, module.stride, module.padding, module.dilation))
            if None in (k, s, p) or d != 1 or module.padding_mode != "zeros" or isinstance(module.padding, str):
                raise _Refused
            weight = module.weight.detach().clone()
            bias = None if module.bias is None else module.bias.detach().clone()
            return _Node("conv", inputs, (weight, bias), k, s, p, groups=module.groups)
        if isinstance(module, nn.BatchNorm2d):
            (x,) = inputs
            producer = nodes[x]
            feeds = [n for n, i in index.items() if i == x]
            if producer.kind == "conv" and all(len(users[n]) == 1 for n in feeds) and not module.training:
                scale = module.weight.detach() / torch.sqrt(module.running_var + module.eps)
                shift = module.bias.detach() - module.running_mean * scale
                weight, bias = producer.fn
                bias = torch.zeros_like(shift) if bias is None else bias
                producer.fn = (weight * scale.reshape(-1, 1, 1, 1), bias * scale + shift)
                return None
            return _Node("map", inputs, lambda v, m=module: F.batch_norm(
                v, m.running_mean, m.running_var, m.weight, m.bias, False, 0.0, m.eps))  # fmt: skip
        if isinstance(module, nn.MaxPool2d):
            k, s, p, d = (_pair(v) for v in (module.kernel_size, module.stride or module.kernel_size,
                                               module.padding, module.dilation))  # fmt: skip
            if None in (k, s, p) or d != 1 or module.ceil_mode or module.return_indices:
                raise _Refused
            return _Node("pool", inputs, None, k, s, p)
        if (
            isinstance(module, nn.ReLU)
            or (node.op == "call_function" and node.target in (torch.relu, F.relu))
            or (node.op == "call_method" and node.target == "relu")
        ):
            return _Node("map", inputs, torch.relu)
        if node.op == "call_function" and node.target in SUMS and len(inputs) == 2 and not node.kwargs:
            return _Node("add", inputs)
        if node.op == "call_function" and node.target in ELEMENTWISE_FUNCTIONS and len(inputs) == 1:
            others = [consts[a] for a in node.all_input_nodes if a not in index]
            if all(not isinstance(o, torch.Tensor) or (o.dim() <= 4 and o.shape[-2:].numel() == 1) for o in others):
                return _Node("map", inputs, _dense(traced, node, index, consts))
        if isinstance(module, (nn.Identity, nn.Dropout)):
            return _Node("map", inputs, lambda v: v)
        # anything else on a 4-d tensor ends the spatial part (global pooling, flattening)
        dense.spatial = False
        if (
            isinstance(module, (nn.AdaptiveAvgPool2d, nn.Flatten, nn.AdaptiveMaxPool2d))
            or (node.op == "call_function" and node.target in (torch.flatten, F.adaptive_avg_pool2d))
            or (node.op == "call_method" and node.target in ("flatten", "mean", "view", "reshape"))
        ):
            return dense
        raise _Refused

    # --- evaluation ----------------------------------------------------------------------------
    def start(self, image: torch.Tensor) -> torch.Tensor:
        """Set the current image (1, C, H, W) and return its logits (1, K)."""
        self._forget()
        for k, node in enumerate(self.nodes):
            if node.kind == "input":
                self.values[k] = image.to(self.device).clone()
            else:
                self.values[k] = self._whole(node)
        return self.values[self.output]

    def _whole(self, node: _Node) -> torch.Tensor:
        return _post(node, self._layer(node))

    def _layer(self, node: _Node) -> torch.Tensor:
        args = [self.values[i] for i in node.inputs]
        if node.kind == "conv":
            weight, bias = node.fn
            return F.conv2d(args[0], weight, bias, node.stride, node.padding, 1, node.groups)
        if node.kind == "pool":
            return F.max_pool2d(args[0], node.kernel, node.stride, node.padding)
        if node.kind == "add":
            return args[0] + args[1]
        return node.fn(*args)

    def step(self, pixels: np.ndarray, values: torch.Tensor, record: dict | None = None) -> torch.Tensor:
        """Change the current image at ``pixels`` (flat indices) to ``values`` (C, len(pixels))
        and return the new image's logits (1, K). With ``record``, the boxes each layer read are
        added to it (layer -> box) and nothing kept is forgotten."""
        x = self.values[0]
        _, C, H, W = x.shape
        rows, cols = pixels // W, pixels % W
        r0, r1, c0, c1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
        if (r1 - r0) * (c1 - c0) > NEAR and len(pixels) <= APART:  # a few pixels far apart: one by one
            for j in range(len(pixels)):
                logits = self.step(pixels[j : j + 1], values[:, j : j + 1], record)
            return logits
        flat = x.view(1, C, H * W)
        flat[0, :, torch.from_numpy(pixels).to(x.device)] = values.to(x.device, x.dtype)
        if (r1 - r0) * (c1 - c0) > FULL_IMAGE * H * W:
            if record is not None:
                record["whole"] = True
            kept, footprint = self._kept, self._footprint
            logits = self.start(x)
            if record is not None:
                self._kept, self._footprint = kept, footprint
            return logits
        regions: list[tuple[int, int, int, int] | None] = [None] * len(self.nodes)  # None: unchanged
        regions[0] = (r0, r1, c0, c1)
        reads = record if record is not None else None
        if reads is not None:
            _widen(reads, 0, regions[0])
        for k, node in enumerate(self.nodes):
            if k == 0:
                continue
            changed = [regions[i] for i in node.inputs if regions[i] is not None]
            if not changed:
                continue
            if not node.spatial:
                self.values[k] = self._whole(node)
                regions[k] = (0, 0, 0, 0)
                continue
            box = _union(changed)
            if node.kind in ("map", "add"):
                r0, r1, c0, c1 = box
                args = [self.values[i][:, :, r0:r1, c0:c1] for i in node.inputs]
                value = args[0] + args[1] if node.kind == "add" else node.fn(*args)
                self.values[k][:, :, r0:r1, c0:c1] = _post(node, value)
                regions[k] = box
                if reads is not None:
                    for i in node.inputs:
                        _widen(reads, i, box)
            else:
                regions[k] = self._window(k, node, box, reads)
            if reads is None and self._kept and regions[k] is not None and k in self._footprint:
                if _meets(regions[k], self._footprint[k]):
                    self._forget()
        if reads is None and self._kept and _meets(regions[0], self._footprint.get(0, (0, 0, 0, 0))):
            self._forget()
        return self.values[self.output]

    def _forget(self) -> None:
        self._kept = {}
        self._footprint = {}

    def variant(self, pixels: np.ndarray, values: torch.Tensor) -> torch.Tensor:
        """The logits (1, K) of the current image changed at ``pixels`` to ``values``; the current
        image is left as it is. Where the tail is affine, the change of the logits is kept while
        no step changes what it read."""
        if self.affine():
            return self.values[self.output] + self.delta(pixels, values)
        nominal = self.values[0].reshape(self.values[0].shape[1], -1)[:, torch.from_numpy(pixels)].clone()
        logits = self.step(pixels, values, {}).clone()
        self.step(pixels, nominal, {})
        return logits

    def delta(self, pixels: np.ndarray, values: torch.Tensor) -> torch.Tensor:
        """(1, K): how the logits change when the current image is changed at ``pixels`` to
        ``values`` (an affine tail: a function of the values near the pixels alone, kept while no
        step changes what it read); the current image is left as it is."""
        key = ("delta", pixels.tobytes(), values.numpy().tobytes())
        if key not in self._kept:
            self.deltas += 1
            now = self.values[self.output].clone()
            nominal = self.values[0].reshape(self.values[0].shape[1], -1)[:, torch.from_numpy(pixels)].clone()
            reads: dict = {}
            changed = self.step(pixels, values, reads) - now
            self.step(pixels, nominal, reads)
            if reads.pop("whole", False):
                return changed
            for i, box in reads.items():
                _widen(self._footprint, i, box)
            self._kept[key] = changed
        return self._kept[key]

    def offsets(self, pixels: np.ndarray, low: torch.Tensor, high: torch.Tensor, c: int) -> torch.Tensor:
        """(K,): per class ``j``, the least change of ``y_c - y_j`` from the current image's over
        the box of :meth:`bound` (an affine tail), kept while no step changes what it read."""
        key = ("bound", pixels.tobytes(), low.numpy().tobytes(), high.numpy().tobytes(), c)
        if key not in self._kept:
            self._kept[key] = self._offsets(pixels, low, high, c)
        return self._kept[key]

    def affine(self) -> bool:
        """Whether the layers after the spatial part are affine (so :meth:`delta` and
        :meth:`offsets` hold); known once an image is set."""
        if self.boundary is not None and self._sensitivity is None:
            self._sensitivity = self._tail_gradients()
            if self._sensitivity is None:
                self.boundary = None
        return self.boundary is not None

    def reach(self) -> tuple[int, int, int, int] | None:
        """The box of input pixels that everything kept depends on: what it read, and what those
        values were computed from, back to the input. A change outside it changes nothing kept."""
        need = dict(self._footprint)
        for k in range(len(self.nodes) - 1, 0, -1):
            node = self.nodes[k]
            if k not in need or not node.spatial:
                continue
            r0, r1, c0, c1 = need[k]
            if node.kind in ("conv", "pool"):
                (i,) = node.inputs
                H, W = self.values[i].shape[2:]
                kk, s, p = node.kernel, node.stride, node.padding
                box = (max(r0 * s - p, 0), min((r1 - 1) * s - p + kk, H),
                       max(c0 * s - p, 0), min((c1 - 1) * s - p + kk, W))  # fmt: skip
                _widen(need, i, box)
            else:
                for i in node.inputs:
                    _widen(need, i, need[k])
        return need.get(0)

    def boundary_box(self, pixels: np.ndarray) -> tuple[int, int, int, int] | None:
        """The box of the affine tail's first layer (the boundary) that a change of the current
        image at ``pixels`` can reach (None: none of it); the values outside it depend on none of
        those pixels. Known once an image is set."""
        W = self.values[0].shape[3]
        rows, cols = pixels // W, pixels % W
        regions: list[tuple[int, int, int, int] | None] = [None] * len(self.nodes)
        regions[0] = (int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1)
        for k, node in enumerate(self.nodes):
            changed = [regions[i] for i in node.inputs if regions[i] is not None]
            if k == 0 or not changed or not node.spatial:
                continue
            box = _union(changed)
            if node.kind in ("map", "add"):
                regions[k] = box
            else:
                reached = self._reached(k, node, box)
                regions[k] = None if reached is None else reached[0]
        return regions[self.boundary] if self.boundary is not None else None

    def bound(self, pixels: np.ndarray, low: torch.Tensor, high: torch.Tensor, c: int) -> float:
        """A lower bound (interval arithmetic, float32) of ``y_c - max_{j != c} y_j`` over every
        image equal to the current one but at ``pixels``, where it lies in ``[low, high]``
        (C, len(pixels)); the current image is left as it is. ``-inf`` where a layer after the
        spatial part passes no interval here."""
        if self.affine():
            logits = self.values[self.output][0]
            margins = logits[c] - logits + self.offsets(pixels, low, high, c)
            margins[c] = torch.inf
            return float(margins.min())
        windows = self._windows(pixels, low, high)
        full: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        for k, node in enumerate(self.nodes):
            if node.spatial or not any(i in windows or i in full for i in node.inputs):
                continue
            if node.bounds is None or len(node.inputs) != 1:
                return -np.inf
            (i,) = node.inputs
            a, b = full[i] if i in full else self._spread(i, windows[i])
            if k == self.output and isinstance(node.bounds, tuple):
                return _margin_lower(node.bounds, a, b, c)
            full[k] = _dense_interval(node, a, b)
        if self.output in full:
            a, b = full[self.output]
            others = b.clone()
            others[:, c] = -torch.inf
            return float(a[0, c] - others.max())
        return -np.inf

    def _windows(self, pixels: np.ndarray, low: torch.Tensor, high: torch.Tensor) -> dict:
        """Interval bounds of every spatial layer that the pixels' box reaches, on the window it
        reaches (node -> (box, lower, upper)); what was read is kept as the footprint."""
        x = self.values[0]
        _, C, H, W = x.shape
        rows, cols = pixels // W, pixels % W
        r0, r1, c0, c1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
        lo, up = x[:, :, r0:r1, c0:c1].clone(), x[:, :, r0:r1, c0:c1].clone()
        local = torch.from_numpy((rows - r0) * (c1 - c0) + (cols - c0)).to(x.device)
        lo.view(1, C, -1)[0, :, local] = low.to(x.device, x.dtype)
        up.view(1, C, -1)[0, :, local] = high.to(x.device, x.dtype)
        _widen(self._footprint, 0, (r0, r1, c0, c1))
        windows: dict[int, tuple[tuple[int, int, int, int], torch.Tensor, torch.Tensor]]
        windows = {0: ((r0, r1, c0, c1), lo, up)}
        for k, node in enumerate(self.nodes):
            if k == 0 or not node.spatial or not any(i in windows for i in node.inputs):
                continue
            box = _union([windows[i][0] for i in node.inputs if i in windows])
            if node.kind in ("map", "add"):
                parts = [self._crop(i, box, windows) for i in node.inputs]
                if node.kind == "add":
                    a, b = parts[0][0] + parts[1][0], parts[0][1] + parts[1][1]
                else:
                    a, b = _monotone(node.fn, parts[0][0], parts[0][1])  # elementwise and monotone
                windows[k] = (box, *_post_interval(node, a, b))
                continue
            made = self._window_interval(k, node, box, windows)
            if made is not None:
                windows[k] = (made[0], *_post_interval(node, made[1], made[2]))
        return windows

    def _offsets(self, pixels: np.ndarray, low: torch.Tensor, high: torch.Tensor, c: int) -> torch.Tensor:
        """Per class ``j``, the least change of ``y_c - y_j`` from the current image's over the
        box (the tail being affine, a fixed linear function of the boundary layer's change)."""
        windows = self._windows(pixels, low, high)
        L = self.boundary
        K = self._sensitivity.shape[0]
        if L not in windows:
            return torch.zeros(K, dtype=self.values[L].dtype, device=self.values[L].device)
        (r0, r1, c0, c1), lo, up = windows[L]
        nominal = self.values[L][:, :, r0:r1, c0:c1]
        _widen(self._footprint, L, (r0, r1, c0, c1))
        g = self._sensitivity[:, :, r0:r1, c0:c1]  # (K, C, h, w)
        spec = g[c : c + 1] - g  # row j: the gradient of y_c - y_j
        down, rise = (lo - nominal), (up - nominal)  # (1, C, h, w): down <= 0 <= rise
        least = torch.minimum(spec * down, spec * rise)
        return least.reshape(K, -1).sum(1)

    def _tail_gradients(self) -> torch.Tensor | None:
        """(K, C, H, W): the gradient of each logit with respect to the boundary layer's values,
        the same at every image (the tail is affine); None where autograd cannot run the tail."""
        L = self.boundary
        try:
            with torch.inference_mode(False), torch.enable_grad():
                a = torch.zeros(self.values[L].shape, dtype=self.values[L].dtype, device=self.values[L].device,
                                requires_grad=True)  # fmt: skip
                vals: dict[int, torch.Tensor] = {L: a}
                for k, node in enumerate(self.nodes):
                    if not node.spatial:
                        vals[k] = node.fn(vals[node.inputs[0]])
                y = vals[self.output].reshape(-1)
                rows = [torch.autograd.grad(y[j], a, retain_graph=True)[0][0] for j in range(len(y))]
        except RuntimeError:
            return None
        return torch.stack(rows).detach()

    def _crop(self, i: int, box, windows) -> tuple[torch.Tensor, torch.Tensor]:
        """Node ``i``'s bounds on ``box``: its current values, its window's bounds where it has one."""
        r0, r1, c0, c1 = box
        _widen(self._footprint, i, tuple(box))
        value = self.values[i][:, :, r0:r1, c0:c1]
        if i not in windows:
            return value, value
        (w0, w1, v0, v1), lo, up = windows[i]
        if (w0, w1, v0, v1) == tuple(box):
            return lo, up
        a, b = value.clone(), value.clone()
        t0, t1, u0, u1 = max(w0, r0), min(w1, r1), max(v0, c0), min(v1, c1)  # the window inside the box
        if t0 < t1 and u0 < u1:
            a[:, :, t0 - r0 : t1 - r0, u0 - c0 : u1 - c0] = lo[:, :, t0 - w0 : t1 - w0, u0 - v0 : u1 - v0]
            b[:, :, t0 - r0 : t1 - r0, u0 - c0 : u1 - c0] = up[:, :, t0 - w0 : t1 - w0, u0 - v0 : u1 - v0]
        return a, b

    def _spread(self, i: int, window) -> tuple[torch.Tensor, torch.Tensor]:
        _, H, W = self.values[i].shape[1:]
        return self._crop(i, (0, H, 0, W), {i: window})

    def _reached(self, k: int, node: _Node, box):
        """The outputs of a convolution or pooling that an input window ``box`` reaches, and the
        input rows and columns they read (outside the tensor where the layer pads); None if none."""
        Ho, Wo = self.values[k].shape[2:]
        kk, s, p = node.kernel, node.stride, node.padding
        r0, r1, c0, c1 = box
        o_r0, o_r1 = max(0, -(-(r0 + p - kk + 1) // s)), min(Ho, (r1 - 1 + p) // s + 1)
        o_c0, o_c1 = max(0, -(-(c0 + p - kk + 1) // s)), min(Wo, (c1 - 1 + p) // s + 1)
        if o_r0 >= o_r1 or o_c0 >= o_c1:
            return None
        rows = (o_r0 * s - p, (o_r1 - 1) * s - p + kk)
        cols = (o_c0 * s - p, (o_c1 - 1) * s - p + kk)
        return (o_r0, o_r1, o_c0, o_c1), (*rows, *cols)

    def _window_interval(self, k: int, node: _Node, box, windows):
        reached = self._reached(k, node, box)
        if reached is None:
            return None
        (o_r0, o_r1, o_c0, o_c1), (i_r0, i_r1, i_c0, i_c1) = reached
        H, W = self.values[node.inputs[0]].shape[2:]
        kk, s = node.kernel, node.stride
        inner = (max(i_r0, 0), min(i_r1, H), max(i_c0, 0), min(i_c1, W))
        lo, up = self._crop(node.inputs[0], inner, windows)
        pads = (max(0, -i_c0), max(0, i_c1 - W), max(0, -i_r0), max(0, i_r1 - H))
        if node.kind == "conv":
            weight, bias = node.fn
            positive, negative = weight.clamp(min=0), weight.clamp(max=0)
            if any(pads):
                lo, up = F.pad(lo, pads), F.pad(up, pads)
            a = F.conv2d(lo, positive, bias, s, 0, 1, node.groups) + F.conv2d(up, negative, None, s, 0, 1, node.groups)
            b = F.conv2d(up, positive, bias, s, 0, 1, node.groups) + F.conv2d(lo, negative, None, s, 0, 1, node.groups)
        else:
            if any(pads):
                lo, up = F.pad(lo, pads, value=-torch.inf), F.pad(up, pads, value=-torch.inf)
            a, b = F.max_pool2d(lo, kk, s, 0), F.max_pool2d(up, kk, s, 0)
        return (o_r0, o_r1, o_c0, o_c1), a, b

    def _window(self, k: int, node: _Node, box, reads: dict | None = None) -> tuple[int, int, int, int] | None:
        """Recompute a convolution's or a pooling's outputs that the input window ``box`` reaches."""
        reached = self._reached(k, node, box)
        if reached is None:  # no output reaches the window
            return None
        (o_r0, o_r1, o_c0, o_c1), (i_r0, i_r1, i_c0, i_c1) = reached
        x, out = self.values[node.inputs[0]], self.values[k]
        H, W = x.shape[2:]
        kk, s = node.kernel, node.stride
        crop = x[:, :, max(i_r0, 0) : min(i_r1, H), max(i_c0, 0) : min(i_c1, W)]
        if reads is not None:
            _widen(reads, node.inputs[0], (max(i_r0, 0), min(i_r1, H), max(i_c0, 0), min(i_c1, W)))
        pads = (max(0, -i_c0), max(0, i_c1 - W), max(0, -i_r0), max(0, i_r1 - H))
        if node.kind == "conv":
            weight, bias = node.fn
            if any(pads):
                crop = F.pad(crop, pads)
            value = F.conv2d(crop, weight, bias, s, 0, 1, node.groups)
        else:
            if any(pads):
                crop = F.pad(crop, pads, value=-torch.inf)
            value = F.max_pool2d(crop, kk, s, 0)
        out[:, :, o_r0:o_r1, o_c0:o_c1] = _post(node, value)
        return (o_r0, o_r1, o_c0, o_c1)

    # --- many sequences at once ----------------------------------------------------------------
    def lanes(self, firsts: torch.Tensor, pixels: np.ndarray, colours: torch.Tensor, shown: np.ndarray) -> torch.Tensor:
        """Logits along ``B`` sequences at once, one changed pixel per sequence and step.

        ``firsts`` (B, C, H, W) are the sequences' first images; at step ``t`` sequence ``b``'s
        pixel ``pixels[b, t]`` (flat; -1: none) takes the colour ``colours[b, t]`` (C,); its
        logits are kept where ``shown[b, t]`` (the step completes an image). Returns (1 + S, K)
        rows per sequence, concatenated in sequence order: its first image's logits, then those
        of each shown step (S of them). The current image of :meth:`step` is left unset."""
        B, T = pixels.shape
        _, C, H, W = firsts.shape
        device = self.device
        halo = self._halos()
        stores: list[torch.Tensor | None] = [None] * len(self.nodes)
        views: list[torch.Tensor | None] = [None] * len(self.nodes)
        with torch.inference_mode():
            for k, node in enumerate(self.nodes):
                if node.kind == "input":
                    value = firsts.to(device)
                else:
                    self.values = views  # _whole reads self.values
                    value = self._whole(node)
                if node.spatial and value.dim() == 4:
                    P, fill = halo[k]
                    store = value.new_full((B, value.shape[1], value.shape[2] + 2 * P, value.shape[3] + 2 * P), fill)
                    store[:, :, P : P + value.shape[2], P : P + value.shape[3]] = value
                    stores[k], views[k] = store, store[:, :, P : P + value.shape[2], P : P + value.shape[3]]
                else:
                    views[k] = value
            out = [views[self.output].float().cpu()]
            lane = torch.arange(B, device=device)
            colours = colours.to(device, firsts.dtype)
            for t in range(T):
                p = pixels[:, t]
                moving = p >= 0
                rows, cols = np.where(moving, p // W, 0), np.where(moving, p % W, 0)
                if moving.any():
                    which = torch.from_numpy(np.nonzero(moving)[0]).to(device)
                    P = halo[0][0]
                    r = torch.from_numpy(rows[moving]).to(device) + P
                    c = torch.from_numpy(cols[moving]).to(device) + P
                    stores[0][which, :, r, c] = colours[which, t]
                regions = {0: (rows, rows + 1, cols, cols + 1)}
                for k, node in enumerate(self.nodes):
                    if k == 0:
                        continue
                    if not node.spatial:
                        self.values = views
                        views[k] = self._whole(node)
                        continue
                    regions[k] = self._lane_window(k, node, regions, stores, views, halo, lane)
                keep = np.nonzero(shown[:, t])[0]
                if len(keep):
                    out.append((views[self.output][torch.from_numpy(keep).to(device)].float().cpu(), keep))
        self.values = [None] * len(self.nodes)
        self._forget()
        first, rest = out[0], out[1:]
        rows_of: list[list[torch.Tensor]] = [[first[b]] for b in range(B)]
        for logits, keep in rest:
            for j, b in enumerate(keep.tolist()):
                rows_of[b].append(logits[j])
        return torch.stack([row for rows in rows_of for row in rows])

    def _halos(self) -> list[tuple[int, float]]:
        """Per layer, the padding its stored values carry for the layers that read it (zeros for
        a convolution, minus infinity for a max pooling), wide enough for each reader's padding."""
        halo = [(0, 0.0)] * len(self.nodes)
        for node in self.nodes:
            if node.kind in ("conv", "pool") and node.padding:
                (i,) = node.inputs
                fill = -torch.inf if node.kind == "pool" else 0.0
                P, old = halo[i]
                if P and old != fill:
                    raise MrcertError("a layer read by a convolution and a padded max pooling")
                halo[i] = (max(P, node.padding), fill)
        return halo

    def _lane_window(self, k, node, regions, stores, views, halo, lane):
        """One step of every sequence at layer ``k``: the window each sequence's change reaches,
        widened to one size for all (recomputing values that did not change is harmless)."""
        out = stores[k]
        P_out = halo[k][0]
        Ho, Wo = views[k].shape[2:]
        if node.kind in ("map", "add"):
            boxes = [regions[i] for i in node.inputs]
            r0 = np.minimum.reduce([b[0] for b in boxes])
            r1 = np.maximum.reduce([b[1] for b in boxes])
            c0 = np.minimum.reduce([b[2] for b in boxes])
            c1 = np.maximum.reduce([b[3] for b in boxes])
            r0, r1 = _one_size(r0, r1, Ho)
            c0, c1 = _one_size(c0, c1, Wo)
            h, w = int(r1[0] - r0[0]), int(c1[0] - c0[0])
            parts = [_gather(stores[i], halo[i][0], r0, h, c0, w, lane) for i in node.inputs]
            value = parts[0] + parts[1] if node.kind == "add" else node.fn(parts[0])
            _scatter(out, P_out, r0, c0, _post(node, value), lane)
            return r0, r1, c0, c1
        (i,) = node.inputs
        kk, s, p = node.kernel, node.stride, node.padding
        r0, r1, c0, c1 = regions[i]
        o_r0, o_r1 = np.maximum(0, -(-(r0 + p - kk + 1) // s)), np.minimum(Ho, (r1 - 1 + p) // s + 1)
        o_c0, o_c1 = np.maximum(0, -(-(c0 + p - kk + 1) // s)), np.minimum(Wo, (c1 - 1 + p) // s + 1)
        o_r0, o_r1 = _one_size(o_r0, o_r1, Ho)
        o_c0, o_c1 = _one_size(o_c0, o_c1, Wo)
        h, w = int(o_r1[0] - o_r0[0]), int(o_c1[0] - o_c0[0])
        crop = _gather(stores[i], halo[i][0], o_r0 * s - p, (h - 1) * s + kk, o_c0 * s - p, (w - 1) * s + kk, lane)
        if node.kind == "conv":
            weight, bias = node.fn
            value = F.conv2d(crop, weight, bias, s, 0, 1, node.groups)
        else:
            value = F.max_pool2d(crop, kk, s, 0)
        _scatter(out, P_out, o_r0, o_c0, _post(node, value), lane)
        return o_r0, o_r1, o_c0, o_c1


class _Refused(Exception):
    """A layer the incremental network does not update by window."""


def _dense_interval(node: _Node, lo: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    if node.bounds in ("affine", "monotone"):
        return node.fn(lo), node.fn(up)
    weight, bias = node.bounds
    centre, radius = (lo + up) / 2, (up - lo) / 2
    mid = F.linear(centre, weight, bias)
    spread = F.linear(radius, weight.abs())
    return mid - spread, mid + spread


def _margin_lower(rule, lo: torch.Tensor, up: torch.Tensor, c: int) -> float:
    """The least ``y_c - y_j`` (j != c) over the box, for a last layer ``y = W x + b``."""
    weight, bias = rule
    spec = weight[c : c + 1] - weight  # (K, n): row j is w_c - w_j
    offset = 0.0 if bias is None else bias[c] - bias
    centre, radius = (lo + up) / 2, (up - lo) / 2
    low = F.linear(centre, spec) - F.linear(radius, spec.abs()) + offset
    low[:, c] = torch.inf
    return float(low.min())


def _post(node: _Node, value: torch.Tensor) -> torch.Tensor:
    for fn in node.post:
        value = fn(value)
    return value


def _monotone(fn, lo: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """An elementwise monotone map's bounds over ``[lo, up]`` (increasing or decreasing)."""
    a, b = fn(lo), fn(up)
    return torch.minimum(a, b), torch.maximum(a, b)


def _post_interval(node: _Node, lo: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    for fn in node.post:
        lo, up = _monotone(fn, lo, up)
    return lo, up


def _fused(nodes: list[_Node], output: int) -> tuple[list[_Node], int]:
    """The layers with each elementwise map folded into the layer before it where that layer
    feeds nothing else (one window written per pair instead of two)."""
    readers = [0] * len(nodes)
    for node in nodes:
        for i in node.inputs:
            readers[i] += 1
    alias = list(range(len(nodes)))
    kept: list[int] = []
    for k, node in enumerate(nodes):
        node.inputs = tuple(alias[i] for i in node.inputs)
        if node.kind == "map" and node.spatial and len(node.inputs) == 1:
            (i,) = node.inputs
            producer = nodes[i]
            if producer.kind in ("conv", "pool", "map", "add") and readers[i] == 1 and i != output:
                producer.post.append(node.fn)
                alias[k] = i
                readers[i] = readers[k]
                continue
        kept.append(k)
    renumber = {old: new for new, old in enumerate(kept)}
    out = []
    for old in kept:
        node = nodes[old]
        node.inputs = tuple(renumber[i] for i in node.inputs)
        out.append(node)
    return out, renumber[alias[output]]


def _one_size(lo: np.ndarray, hi: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Ranges ``[lo, hi)`` per sequence widened to the longest one's length and shifted inside
    ``[0, size)``; an empty range (nothing reached) becomes any range of that length."""
    hi = np.where(hi > lo, hi, lo + 1)
    length = min(int((hi - lo).max()), size)
    lo = np.clip(np.minimum(lo, size - length), 0, None)
    return lo, lo + length


def _gather(store: torch.Tensor, P: int, r0: np.ndarray, h: int, c0: np.ndarray, w: int, lane) -> torch.Tensor:
    """(B, C, h, w): each sequence's window of a stored (halo-padded) layer at its own place."""
    rows, cols = _grid(store, P, r0, h, c0, w)
    return store[lane[:, None, None], :, rows, cols].permute(0, 3, 1, 2)


def _scatter(store: torch.Tensor, P: int, r0: np.ndarray, c0: np.ndarray, value: torch.Tensor, lane) -> None:
    rows, cols = _grid(store, P, r0, value.shape[2], c0, value.shape[3])
    store[lane[:, None, None], :, rows, cols] = value.permute(0, 2, 3, 1)


def _grid(store: torch.Tensor, P: int, r0: np.ndarray, h: int, c0: np.ndarray, w: int):
    device = store.device
    rows = torch.from_numpy(r0 + P).to(device)[:, None] + torch.arange(h, device=device)
    cols = torch.from_numpy(c0 + P).to(device)[:, None] + torch.arange(w, device=device)
    return rows[:, :, None], cols[:, None, :]


def _widen(boxes: dict, i: int, box) -> None:
    """``boxes[i]`` grown to hold ``box``."""
    boxes[i] = _union([boxes[i], tuple(box)]) if i in boxes else tuple(box)


def _meets(a, b) -> bool:
    """Whether two boxes (r0, r1, c0, c1) share a position."""
    return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]


def _union(boxes):
    return (min(b[0] for b in boxes), max(b[1] for b in boxes), min(b[2] for b in boxes), max(b[3] for b in boxes))


AFFINE_MODULES = (nn.AdaptiveAvgPool2d, nn.AvgPool2d, nn.Flatten, nn.Identity, nn.Dropout)
AFFINE_FUNCTIONS = (torch.flatten, F.adaptive_avg_pool2d, F.avg_pool2d, torch.reshape)
AFFINE_METHODS = ("flatten", "view", "reshape", "mean")
MONOTONE_MODULES = (nn.AdaptiveMaxPool2d, nn.MaxPool2d, nn.ReLU)
MONOTONE_FUNCTIONS = (torch.relu, F.relu)


def _interval_rule(node: fx.Node, module, consts):
    """How an interval passes a layer after the spatial part: "affine" (a linear map with
    nonnegative weights: pooling by averages, flattening), "monotone" (each output a
    nondecreasing function of the inputs), a Linear's (weight, bias), or None (not known here)."""
    single = len(node.all_input_nodes) == 1
    if isinstance(module, nn.Linear):
        return (module.weight.detach(), None if module.bias is None else module.bias.detach())
    if isinstance(module, AFFINE_MODULES) or (single and (
        (node.op == "call_function" and node.target in AFFINE_FUNCTIONS)
        or (node.op == "call_method" and node.target in AFFINE_METHODS)
    )):  # fmt: skip
        return "affine"
    if isinstance(module, MONOTONE_MODULES) or (single and (
        (node.op == "call_function" and node.target in MONOTONE_FUNCTIONS)
        or (node.op == "call_method" and node.target == "relu")
    )):  # fmt: skip
        return "monotone"
    return None


def _call(traced, node, args, kwargs):
    if node.op == "call_module":
        return traced.get_submodule(str(node.target))(*args, **kwargs)
    if node.op == "call_method":
        return getattr(args[0], str(node.target))(*args[1:], **kwargs)
    return node.target(*args, **kwargs)


def _dense(traced, node, index, consts):
    """The node as a function of its bounded inputs' values (in ``index`` order), its constant
    arguments resolved once."""
    bounded = [a for a in node.all_input_nodes if a in index]
    if len(bounded) == 1 and not any(isinstance(v, fx.Node) for v in node.kwargs.values()):
        (x,) = bounded
        places = [j for j, a in enumerate(node.args) if a is x]
        plain = all(isinstance(a, fx.Node) or not isinstance(a, (list, tuple, dict)) for a in node.args)
        if len(places) == 1 and plain:
            args = [a if a is x else (consts[a] if isinstance(a, fx.Node) else a) for a in node.args]
            kwargs = dict(node.kwargs)
            j = places[0]
            target = (
                traced.get_submodule(str(node.target)) if node.op == "call_module"
                else node.target if node.op == "call_function" else None
            )  # fmt: skip
            if target is not None:
                before, after = tuple(args[:j]), tuple(args[j + 1 :])
                return lambda v: target(*before, v, *after, **kwargs)

    def fn(*values):
        lookup = dict(zip(bounded, values, strict=True))
        args = fx.node.map_arg(node.args, lambda a: lookup[a] if a in lookup else consts[a])
        kwargs = fx.node.map_arg(node.kwargs, lambda a: lookup[a] if a in lookup else consts[a])
        return _call(traced, node, args, kwargs)

    return fn
