"""Bound propagation through a classifier: from a box of inputs (a lowest and a highest value
per pixel and channel) to sound bounds on its logits and on their differences.

:class:`BoundNetwork` reads the classifier's graph with ``torch.fx`` (our small CNN, ResNet-18
and ResNet-50 as torchvision builds them, the networks :mod:`mrcert.formats.onnx_model` reads)
into layers of four kinds: affine maps of one input (convolution, linear, batch norm in
evaluation mode, average pooling, zero padding, flattening, reshaping, adding or scaling by a constant), the
sum of two inputs (residual additions), ReLU and max pooling. It bounds them in float64:

* **interval bounds** (IBP) pass ``[lo, up]`` layer by layer: an affine map sends the centre
  through the map and the radius through its absolute value; ReLU and max pooling are monotone;
* **a backward linear relaxation** (CROWN, Zhang et al. 2018) bounds a linear function of a
  layer -- here the margins ``y_c - y_j`` -- as a linear function of the input box, passing its
  coefficients backwards: through an affine map by its transpose, through ReLU by the two lines
  between its pre-activation bounds (upper: the chord; lower: slope 1 when ``up > -lo``, else 0),
  through max pooling by ``max >= x_j*`` (the input of largest lower bound) and ``max <= max up``
  (or ``= x_j*`` when that input's lower bound beats every other's upper bound). The same
  backward pass tightens the pre-activation bounds of the ReLU layers small enough to afford it
  (``crown_neurons``); the others keep their interval bounds;
* **linear bounds carried forwards** in the inputs a box perturbs: where a box leaves all but a few
  inputs fixed (``forward_inputs`` at most), every layer's value is bounded by two affine functions
  of those inputs alone, ``L x + l <= z <= U x + u``, passed forwards with the same relaxations
  (an affine map ``W`` sends them to ``W (L + U)/2 -+ |W| (U - L)/2``; ReLU and max pooling by the
  lines above); the fixed inputs are constants folded into ``l`` and ``u``, and a neuron no
  perturbed input reaches keeps coefficients zero. Every layer's bounds are the tighter of these
  and the interval bounds, at the cost of about twice as many forward passes as inputs perturbed,
  where the backward pass that tightens a layer costs two per neuron.

Every bound holds for every input of the box for the network in exact arithmetic; it is
computed in float64, whose rounding is many orders below the margins it decides on.
"""

from __future__ import annotations

import copy
import functools
import operator
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.fx as fx
import torch.nn.functional as F
from torch import nn

from mrcert.errors import MrcertError

LAMBDA_BUDGET = 2.5e7
"""The most coefficients (float64) one backward pass that tightens a layer's bounds may hold."""


@dataclass
class Layer:
    kind: str  # "input", "affine", "add", "relu", "maxpool"
    inputs: tuple[int, ...] = ()
    fn: Callable | None = None  # affine: x -> A x + b, batch-polymorphic
    magnitude: Callable | None = None  # affine: r -> |A| r
    pool: tuple[int, int, int] = (0, 0, 0)  # maxpool: kernel, stride, padding
    name: str = ""


def _with_weight(target, weight, rest, kwargs, x):
    """``target(x, weight, None, *rest, **kwargs)``: a convolution or linear map without its bias."""
    return target(x, weight, None, *rest, **kwargs)


def _scaled(scale, shift, x):
    return x * scale + shift


def _pair(value, name: str) -> int:
    values = value if isinstance(value, (tuple, list)) else (value, value)
    if len(set(values)) != 1:
        raise MrcertError(f"bound propagation needs square {name}s, got {tuple(values)}")
    return int(values[0])


def _unsupported(node: fx.Node, what: str) -> MrcertError:
    return MrcertError(f"bound propagation does not support {what} (layer {node.name})")


RELU_FUNCTIONS = (torch.relu, F.relu)
SUMS = (operator.add, operator.iadd, torch.add)
SHIFTS = (*SUMS, operator.sub, operator.isub, torch.sub, operator.neg, torch.neg)
SCALES = (operator.mul, operator.imul, torch.mul)
DIVISIONS = (operator.truediv, operator.itruediv, torch.div)
POSITIVE = (torch.flatten, F.avg_pool2d, F.adaptive_avg_pool2d, torch.reshape)
POSITIVE_METHODS = ("flatten", "view", "reshape", "mean")
POSITIVE_MODULES = (nn.AvgPool2d, nn.AdaptiveAvgPool2d, nn.Flatten, nn.Identity, nn.Dropout)


def _relu_lines(lo: torch.Tensor, up: torch.Tensor):
    """ReLU's relaxation between its pre-activation bounds (module docstring): the lower line's
    slope (1 or 0), the upper line's slope and its intercept (the chord's, where unstable)."""
    active, unstable = lo >= 0, (lo < 0) & (up > 0)
    width = torch.where(unstable, up - lo, torch.ones_like(up))
    upper = torch.where(active, 1.0, torch.where(unstable, up / width, 0.0))
    lower = torch.where(active | (unstable & (up > -lo)), 1.0, 0.0)
    return lower, upper, torch.where(unstable, -upper * lo, 0.0)


def _pool_choice(layer: Layer, lo: torch.Tensor, up: torch.Tensor):
    """Max pooling's relaxation (module docstring) over its windows: a function giving a tensor's
    windows (padded with a fill), the input of largest lower bound in each window, whether it is
    decided (its lower bound beats every other input's upper bound) and the greatest upper bound."""
    k, stride, pad = layer.pool
    c = lo.shape[1]

    def windows(t: torch.Tensor, fill: float = -torch.inf) -> torch.Tensor:
        t = F.pad(t, (pad, pad, pad, pad), value=fill)
        return F.unfold(t, k, stride=stride).reshape(len(t), c, k * k, -1)

    lw, uw = windows(lo), windows(up)
    best = lw.argmax(2, keepdim=True)  # (n, c, 1, L)
    others = uw.scatter(2, best, -torch.inf).amax(2)
    decided = lw.gather(2, best)[:, :, 0] >= others  # (n, c, L)
    return windows, best, decided, uw.amax(2)


class BoundNetwork:
    """A classifier as layers that bounds pass through (module docstring); built once per
    model, on the model's device, in float64."""

    def __init__(self, model: nn.Module, crown_neurons: int = 2048, forward_inputs: int = 0):
        with torch.inference_mode(False):  # its weights take part in the backward pass
            model = copy.deepcopy(model).to(torch.float64, memory_format=torch.contiguous_format).eval()
            for p in model.parameters():
                p.requires_grad_(False)
            try:
                self.traced = fx.symbolic_trace(model)
            except Exception as exc:  # noqa: BLE001 - control flow that depends on values, say
                raise MrcertError(f"bound propagation cannot read the model's graph: {exc}") from None
            self.crown_neurons = int(crown_neurons)
            self.forward_inputs = int(forward_inputs)
            self.layers: list[Layer] = []
            self.output = -1
            self._outputs: int | None = None
            self._build()

    # --- reading the graph ---------------------------------------------------------------------
    def _build(self) -> None:
        index: dict[fx.Node, int] = {}
        consts: dict[fx.Node, object] = {}
        for node in self.traced.graph.nodes:
            if node.op == "placeholder":
                if any(layer.kind == "input" for layer in self.layers):
                    raise _unsupported(node, "a second input")
                index[node] = self._add(Layer("input", name=node.name))
            elif node.op == "get_attr":
                consts[node] = self._attr(str(node.target))
            elif node.op == "output":
                out = node.args[0]
                if not isinstance(out, fx.Node) or out not in index:
                    raise _unsupported(node, "an output that is not one tensor of the graph")
                self.output = index[out]
            else:
                bounded = [a for a in node.all_input_nodes if a in index]
                if not bounded:  # a constant computed from constants
                    args = fx.node.map_arg(node.args, lambda a: consts[a])
                    kwargs = fx.node.map_arg(node.kwargs, lambda a: consts[a])
                    consts[node] = self._call(node, args, kwargs)
                    continue
                index[node] = self._add(self._layer(node, bounded, index, consts))
        if self.output < 0:
            raise MrcertError("bound propagation found no output in the model's graph")

    def _attr(self, target: str):
        obj = self.traced
        for part in target.split("."):
            obj = getattr(obj, part)
        return obj

    def _call(self, node: fx.Node, args, kwargs):
        if node.op == "call_module":
            return self.traced.get_submodule(str(node.target))(*args, **kwargs)
        if node.op == "call_method":
            return getattr(args[0], str(node.target))(*args[1:], **kwargs)
        return node.target(*args, **kwargs)

    def _add(self, layer: Layer) -> int:
        self.layers.append(layer)
        return len(self.layers) - 1

    def _layer(self, node: fx.Node, bounded: list[fx.Node], index: dict, consts: dict) -> Layer:
        inputs = tuple(index[a] for a in bounded)
        name = node.name
        if node.op == "call_module":
            return self._module_layer(node, self.traced.get_submodule(str(node.target)), inputs)
        target = node.target
        if len(bounded) == 2 and node.op == "call_function" and target in SUMS and not node.kwargs:
            return Layer("add", inputs, name=name)
        if len(bounded) != 1 or sum(a is bounded[0] for a in node.args) > 1:
            raise _unsupported(node, f"{getattr(target, '__name__', target)} of {len(bounded)} bounded tensors")
        (x,) = bounded
        if (node.op == "call_function" and target in RELU_FUNCTIONS) or (node.op == "call_method" and target == "relu"):
            return Layer("relu", inputs, name=name)
        if node.op == "call_function" and target is F.max_pool2d:
            args = list(node.args[1:]) + [None] * 6
            dilation = node.kwargs.get("dilation", args[3] if args[3] is not None else 1)
            ceil, indices = (node.kwargs.get(k, v) for k, v in (("ceil_mode", args[4]), ("return_indices", args[5])))
            if _pair(dilation, "dilation") != 1 or ceil or indices:
                raise _unsupported(node, "max pooling with dilation, ceil_mode or indices")
            kernel = node.kwargs.get("kernel_size", args[0])
            stride = node.kwargs.get("stride", args[1]) or kernel
            padding = node.kwargs.get("padding", args[2] or 0)
            return Layer(
                "maxpool",
                inputs,
                pool=(_pair(kernel, "kernel"), _pair(stride, "stride"), _pair(padding, "padding")),
                name=name,
            )

        def fn(value, node=node):
            args = fx.node.map_arg(node.args, lambda a: value if a is x else consts[a])
            kwargs = fx.node.map_arg(node.kwargs, lambda a: value if a is x else consts[a])
            if node.op == "call_method" and node.target in ("view", "reshape"):  # keep the batch
                shape = args[1] if len(args) == 2 and isinstance(args[1], (tuple, list)) else args[1:]
                return value.reshape(value.shape[0], *shape[1:])
            if node.op == "call_function" and node.target is torch.reshape:
                return value.reshape(value.shape[0], *args[1][1:])
            return self._call(node, args, kwargs)

        others = [consts[a] for a in node.all_input_nodes if a is not x]
        if node.op == "call_function" and target in SHIFTS:
            return Layer("affine", inputs, fn, lambda r: r, name=name)
        if node.op == "call_function" and target in SCALES and len(others) <= 1:
            factor = others[0] if others else next(a for a in node.args if not isinstance(a, fx.Node))
            return Layer("affine", inputs, fn, lambda r, f=factor: r * abs(f), name=name)
        if node.op == "call_function" and target in DIVISIONS and node.args[0] is x:
            divisor = node.args[1] if not isinstance(node.args[1], fx.Node) else consts[node.args[1]]
            return Layer("affine", inputs, fn, lambda r, d=divisor: r / abs(d), name=name)
        if node.op == "call_function" and target is F.pad:
            rest = list(node.args[2:]) + [None, None]
            mode, value = node.kwargs.get("mode", rest[0] or "constant"), node.kwargs.get("value", rest[1])
            if mode != "constant" or value not in (None, 0, 0.0):
                raise _unsupported(node, f"padding by mode {mode!r} with value {value!r} (zeros only)")
            return Layer("affine", inputs, fn, fn, name=name)
        if (node.op == "call_function" and target in POSITIVE) or (
            node.op == "call_method" and target in POSITIVE_METHODS
        ):
            return Layer("affine", inputs, fn, fn, name=name)
        if node.op == "call_function" and target in (F.conv2d, F.linear) and node.args[0] is x:
            weight = consts[node.args[1]] if isinstance(node.args[1], fx.Node) else node.args[1]
            kwargs = {k: v for k, v in node.kwargs.items() if k != "bias"}
            magnitude = functools.partial(_with_weight, target, weight.abs(), tuple(node.args[3:]), kwargs)
            return Layer("affine", inputs, fn, magnitude, name=name)
        raise _unsupported(node, f"{node.op} {getattr(target, '__name__', target)}")

    def _module_layer(self, node: fx.Node, module: nn.Module, inputs: tuple[int, ...]) -> Layer:
        name = node.name
        if isinstance(module, nn.ReLU):
            return Layer("relu", inputs, name=name)
        if isinstance(module, nn.MaxPool2d):
            if _pair(module.dilation, "dilation") != 1 or module.ceil_mode or module.return_indices:
                raise _unsupported(node, "max pooling with dilation, ceil_mode or indices")
            stride = module.stride or module.kernel_size
            pool = (_pair(module.kernel_size, "kernel"), _pair(stride, "stride"), _pair(module.padding, "padding"))
            return Layer("maxpool", inputs, pool=pool, name=name)
        if isinstance(module, nn.Conv2d):
            if module.padding_mode != "zeros":
                raise _unsupported(node, f"convolution with padding_mode={module.padding_mode}")
            rest = (module.stride, module.padding, module.dilation, module.groups)
            magnitude = functools.partial(_with_weight, F.conv2d, module.weight.abs(), rest, {})
            return Layer("affine", inputs, module, magnitude, name=name)
        if isinstance(module, nn.Linear):
            magnitude = functools.partial(_with_weight, F.linear, module.weight.abs(), (), {})
            return Layer("affine", inputs, module, magnitude, name=name)
        if isinstance(module, nn.BatchNorm2d):
            if module.running_mean is None:
                raise _unsupported(node, "batch norm without running statistics")
            scale = torch.rsqrt(module.running_var + module.eps)
            if module.weight is not None:
                scale = scale * module.weight
            shift = -module.running_mean * scale + (module.bias if module.bias is not None else 0.0)
            scale, shift = scale.reshape(1, -1, 1, 1), shift.reshape(1, -1, 1, 1)
            fn = functools.partial(_scaled, scale, shift)
            return Layer("affine", inputs, fn, functools.partial(_scaled, scale.abs(), 0.0), name=name)
        if isinstance(module, POSITIVE_MODULES):
            return Layer("affine", inputs, module, module, name=name)
        raise _unsupported(node, type(module).__name__)

    # --- bounds ----------------------------------------------------------------------------------
    def forward(self, x: torch.Tensor, every: bool = False):
        """The network's logits in float64 through the layers themselves (with ``every``: the
        list of every layer's value)."""
        values: list[torch.Tensor | None] = []
        for layer in self.layers:
            ins = [values[i] for i in layer.inputs]
            if layer.kind == "input":
                values.append(x.to(torch.float64))
            elif layer.kind == "affine":
                values.append(layer.fn(ins[0]))
            elif layer.kind == "add":
                values.append(ins[0] + ins[1])
            elif layer.kind == "relu":
                values.append(torch.relu(ins[0]))
            else:
                k, s, p = layer.pool
                values.append(F.max_pool2d(ins[0], k, s, p))
        return values if every else values[self.output]

    def interval(
        self, low: torch.Tensor, high: torch.Tensor, tighten: bool = False
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Bounds ``(lo, up)`` of every layer over the box ``[low, high]`` (B, ...): interval bounds,
        and with ``tighten`` the pre-activation bounds of small ReLU layers by the backward pass."""
        with torch.inference_mode(False):
            return self._interval(low.to(torch.float64).clone(), high.to(torch.float64).clone(), tighten)

    def _interval(
        self, low: torch.Tensor, high: torch.Tensor, tighten: bool, splits: dict | None = None
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        if tighten and self.forward_inputs > 0:
            carried = self._carried(low, high, splits)
            if carried is not None:
                return carried
        if splits:
            raise ValueError("ReLU splits need linear bounds carried forwards (forward_inputs)")
        return self._propagated(low, high, tighten)

    def _propagated(
        self, low: torch.Tensor, high: torch.Tensor, tighten: bool
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        bounds: list[tuple[torch.Tensor, torch.Tensor]] = []
        exact = set()  # layers IBP bounds exactly: affine maps of the input alone
        for k, layer in enumerate(self.layers):
            if layer.kind == "input":
                bounds.append((low, high))
                exact.add(k)
                continue
            ins = [bounds[i] for i in layer.inputs]
            with torch.no_grad():
                if layer.kind == "affine":
                    (lo, up) = ins[0]
                    centre, radius = layer.fn((lo + up) / 2), layer.magnitude((up - lo) / 2)
                    bounds.append((centre - radius, centre + radius))
                    if layer.inputs[0] in exact:  # an affine map of the input alone: IBP is exact
                        exact.add(k)
                elif layer.kind == "add":
                    bounds.append((ins[0][0] + ins[1][0], ins[0][1] + ins[1][1]))
                elif layer.kind == "relu":
                    (lo, up) = ins[0]
                    source = layer.inputs[0]
                    if tighten and source not in exact and self._affordable(source, bounds):
                        lo, up = self._tightened(source, bounds)
                        bounds[source] = (lo, up)
                    bounds.append((torch.relu(lo), torch.relu(up)))
                else:
                    k_, s, p = layer.pool
                    bounds.append((F.max_pool2d(ins[0][0], k_, s, p), F.max_pool2d(ins[0][1], k_, s, p)))
        return bounds

    def _carried(
        self, low: torch.Tensor, high: torch.Tensor, splits: dict | None = None
    ) -> list[tuple[torch.Tensor, torch.Tensor]] | None:
        """Every layer's bounds over the boxes ``[low, high]`` (B, ...) by linear bounds carried
        forwards in the inputs some box perturbs (module docstring), met with the interval
        bounds; None where more than ``forward_inputs`` inputs are perturbed or the coefficients
        would pass ``LAMBDA_BUDGET``. ``splits``: ``{layer: (active, inactive)}``, masks (B, *shape)
        of the pre-activations of ReLU layer ``layer`` that box b assumes at least (at most) 0:
        the bounds then hold on the part of the box where every assumption does."""
        with torch.no_grad():
            free = torch.nonzero((high > low).flatten(1).any(0))[:, 0]
            p, b = len(free), len(low)
            if p > self.forward_inputs:
                return None
            intervals = self._propagated(low, high, tighten=False)
            widest = max(lo[0].numel() for lo, _ in intervals)
            if 2 * b * max(p, 1) * widest > LAMBDA_BUDGET:
                return None
            lo_p, hi_p = low.flatten(1)[:, free], high.flatten(1)[:, free]  # (B, p)

            def concrete(coef, const, upper):
                """The least (or greatest) value of ``coef . x + const`` over the boxes."""
                first, second = (hi_p, lo_p) if upper else (lo_p, hi_p)
                flat = coef.flatten(2)
                value = (flat.clamp(min=0) * first[..., None] + flat.clamp(max=0) * second[..., None]).sum(1)
                return const + value.reshape(const.shape)

            lines: list[tuple | None] = []  # per layer: (L coef, l, U coef, u); coef (B, p, *shape)
            bounds: list[tuple[torch.Tensor, torch.Tensor]] = []
            for k, layer in enumerate(self.layers):
                if layer.kind == "input":
                    eye = torch.zeros(p, low[0].numel(), dtype=torch.float64, device=low.device)
                    eye[torch.arange(p), free] = 1.0
                    coef = eye.reshape(1, p, *low.shape[1:]).expand(b, *eye.shape[:1], *low.shape[1:])
                    const = low.clone()
                    const.view(b, -1)[:, free] = 0.0
                    lines.append((coef, const, coef, const))
                    bounds.append((low, high))
                    continue
                ins = [lines[i] for i in layer.inputs]
                if layer.kind == "affine":
                    lc, l0, uc, u0 = ins[0]
                    shape = l0.shape[1:]
                    zero = layer.fn(torch.zeros((1, *shape), dtype=torch.float64, device=low.device))

                    def linear(v, zero=zero, layer=layer):
                        return layer.fn(v) - zero

                    cc = linear(((lc + uc) / 2).reshape(b * p, *shape))
                    rc = layer.magnitude(((uc - lc) / 2).reshape(b * p, *shape))
                    c0, r0 = layer.fn((l0 + u0) / 2), layer.magnitude((u0 - l0) / 2)
                    cc, rc = cc.reshape(b, p, *cc.shape[1:]), rc.reshape(b, p, *rc.shape[1:])
                    line = (cc - rc, c0 - r0, cc + rc, c0 + r0)
                elif layer.kind == "add":
                    line = tuple(x + y for x, y in zip(ins[0], ins[1], strict=True))
                elif layer.kind == "relu":
                    lc, l0, uc, u0 = ins[0]
                    lo, up = bounds[layer.inputs[0]]
                    if splits and k in splits:  # the part of the box where these signs hold
                        active_, inactive_ = splits[k]
                        lo, up = torch.where(active_, lo.clamp(min=0), lo), torch.where(inactive_, up.clamp(max=0), up)
                        bounds[layer.inputs[0]] = (lo, up)
                    lower, slope, intercept = _relu_lines(lo, up)
                    line = (lc * lower[:, None], l0 * lower, uc * slope[:, None], u0 * slope + intercept)
                else:
                    line = self._pool_forward(layer, ins[0], *bounds[layer.inputs[0]])
                lines.append(line)
                lo_k = concrete(line[0], line[1], upper=False)
                up_k = concrete(line[2], line[3], upper=True)
                ilo, iup = intervals[k]
                bounds.append((torch.maximum(lo_k, ilo), torch.minimum(up_k, iup)))
            return bounds

    @staticmethod
    def _pool_forward(layer: Layer, line, lo: torch.Tensor, up: torch.Tensor):
        """Max pooling's relaxation (module docstring) applied to linear bounds carried forwards:
        below, the input of largest lower bound; above, that input where it is decided, else the
        window's greatest upper bound (a constant)."""
        k, stride, pad = layer.pool
        n, c, h, w = lo.shape
        lc, l0, uc, u0 = line
        p = lc.shape[1]
        windows, best, decided, top = _pool_choice(layer, lo, up)
        oh, ow = (h + 2 * pad - k) // stride + 1, (w + 2 * pad - k) // stride + 1

        def pick(coef, const):
            chosen_c = windows(coef.reshape(n * p, c, h, w), 0.0).reshape(n, p, c, k * k, -1)
            chosen_c = chosen_c.gather(3, best[:, None].expand(n, p, c, 1, -1))[:, :, :, 0]
            chosen_0 = windows(const, 0.0).gather(2, best)[:, :, 0]
            return chosen_c, chosen_0

        lcc, l00 = pick(lc, l0)
        ucc, u00 = pick(uc, u0)
        ucc = torch.where(decided[:, None], ucc, 0.0)
        u00 = torch.where(decided, u00, top)
        return (lcc.reshape(n, p, c, oh, ow), l00.reshape(n, c, oh, ow),
                ucc.reshape(n, p, c, oh, ow), u00.reshape(n, c, oh, ow))  # fmt: skip

    def _affordable(self, source: int, bounds) -> bool:
        neurons = bounds[source][0][0].numel()
        widest = max(b[0][0].numel() for b in bounds[: source + 1])
        return neurons <= self.crown_neurons and 2 * neurons * widest <= LAMBDA_BUDGET

    def _tightened(self, source: int, bounds) -> tuple[torch.Tensor, torch.Tensor]:
        """Layer ``source``'s bounds by the backward pass (one sample at a time), met with its own."""
        l_old, u_old = bounds[source]
        shape = l_old.shape[1:]
        m = l_old[0].numel()
        eye = torch.eye(m, dtype=torch.float64, device=l_old.device)
        lam = torch.cat([eye, -eye]).reshape(1, 2 * m, *shape)
        lows, highs = [], []
        for b in range(len(l_old)):
            one = [(lo[b : b + 1], hi[b : b + 1]) for lo, hi in bounds]
            lower = self._backward(one, source, lam)[0]
            lows.append(lower[:m].reshape(shape))
            highs.append(-lower[m:].reshape(shape))
        return torch.maximum(l_old, torch.stack(lows)), torch.minimum(u_old, torch.stack(highs))

    def margins(
        self, low: torch.Tensor, high: torch.Tensor, target: torch.Tensor | int, relaxation: str = "crown", upto=0.0
    ):
        """Lower bounds (B, K) of ``y_target - y_j`` for every class ``j`` over each box of
        ``[low, high]`` (B, ...), +inf at ``j = target``: interval bounds alone
        (``relaxation="interval"``) or the better of them and the backward relaxation (``"crown"``)
        for the margins interval bounds leave at most ``upto``."""
        b = len(low)
        k = self.output_size(low)  # the same at every call: a forward pass the first time only
        target = torch.as_tensor(target).expand(b).long()
        spec = -torch.eye(k, dtype=torch.float64).expand(b, k, k).clone()
        spec[torch.arange(b), :, target] += 1.0
        result = self.linear_lower(low, high, spec, relaxation, upto)
        result[torch.arange(b), target.to(result.device)] = torch.inf
        return result

    def output_size(self, low: torch.Tensor) -> int:
        """The number of logits (read from one forward pass of ``low``'s first box, once)."""
        if self._outputs is None:
            with torch.inference_mode(False), torch.no_grad():
                self._outputs = int(self.forward(low[:1].to(torch.float64)).shape[1])
        return self._outputs

    def linear_lower(self, low, high, spec: torch.Tensor, relaxation: str = "crown", upto: float = 0.0):
        """Lower bounds (B, S) of ``spec . y`` (``spec``: (B, S, K) or (S, K)) over each box of
        ``[low, high]``: from the logits' interval bounds, and with ``"crown"`` the better of
        that and the backward relaxation, which runs only for the boxes and rows whose interval
        bound is at most ``upto`` (0: those a property's sign still depends on; inf: all)."""
        if relaxation not in ("interval", "crown"):
            raise ValueError(f"relaxation {relaxation!r} is not one of interval, crown")
        with torch.inference_mode(False):
            low, high = low.to(torch.float64).clone(), high.to(torch.float64).clone()
            bounds = self._interval(low, high, tighten=relaxation == "crown")
            l_out, u_out = bounds[self.output]
            spec = spec.to(torch.float64).to(l_out.device).expand(len(l_out), *spec.shape[-2:]).clone()
            pos, neg = spec.clamp(min=0), spec.clamp(max=0)
            result = (pos * l_out[:, None]).sum(-1) + (neg * u_out[:, None]).sum(-1)
            open_ = (result <= upto) & (spec != 0).any(-1)  # the backward pass's work
            for box in torch.nonzero(open_.any(1))[:, 0].tolist() if relaxation == "crown" else ():
                rows = torch.nonzero(open_[box])[:, 0]  # one box at a time, only its open rows
                some = [(lo[box : box + 1], up[box : box + 1]) for lo, up in bounds]
                tighter = self._backward(some, self.output, spec[box : box + 1, rows])[0]
                result[box, rows] = torch.maximum(result[box, rows], tighter)
            return result.detach()

    def split_lower(
        self, low: torch.Tensor, high: torch.Tensor, spec: torch.Tensor, splits: dict, rows=None, steps: int = 0
    ):
        """Lower bounds (B, S) of ``spec . y`` (``spec``: (S, K)) by the backward relaxation over
        the part of each box of ``[low, high]`` where its ReLU splits hold (``splits``: as
        :meth:`_carried` takes them; +inf for a part shown empty), and per box, per ReLU layer, a
        score (1, *shape) of each neuron left unstable there: its coefficient times its chord's
        intercept, what splitting it may gain. ``rows``: per box, the rows of ``spec`` to bound
        (the others +inf); all when not given. ``steps``: gradient steps on the lower lines' slopes
        of the unstable neurons and on a multiplier per split neuron (:meth:`_optimised`), the best
        bound of any step kept: each slope in [0, 1] and multiplier >= 0 gives a sound bound. None
        where bounds cannot be carried forwards."""
        with torch.inference_mode(False), torch.no_grad():
            low, high = low.to(torch.float64).clone(), high.to(torch.float64).clone()
            bounds = self._carried(low, high, splits) if self.forward_inputs > 0 else None
            if bounds is None:
                return None
            empty = torch.zeros(len(low), dtype=torch.bool, device=low.device)
            for lo, up in bounds:
                empty |= (lo > up).flatten(1).any(1)
            spec = spec.to(torch.float64).to(low.device)
            result = torch.full((len(low), len(spec)), torch.inf, dtype=torch.float64, device=low.device)
            scores: list[dict] = []
            for b in range(len(low)):
                relus: dict = {}
                chosen = torch.arange(len(spec), device=low.device) if rows is None else rows[b]
                if not empty[b] and len(chosen):
                    some = [(lo[b : b + 1], up[b : b + 1]) for lo, up in bounds]
                    signs = {k: (inactive_[b : b + 1].double() - active_[b : b + 1].double())[:, None]
                             for k, (active_, inactive_) in splits.items()}  # fmt: skip
                    slopes, betas = self._optimised(some, spec[None, chosen], steps, signs=signs)
                    result[b, chosen] = self._backward(
                        some, self.output, spec[None, chosen], relus=relus, slopes=slopes, betas=betas
                    )[0]
                scores.append(relus)
            return result, scores

    def _optimised(self, bounds, lam: torch.Tensor, steps: int, start: int | None = None, signs: dict | None = None):
        """Lower lines' slopes and split multipliers for the backward relaxation of ``lam . y_start``
        (the output when not given) over one box, by ``steps`` steps of Adam (learning rate 0.1) on
        the sum of its rows' lower bounds, each row's best kept. Slopes (alpha-CROWN, Xu et al.
        2021): per ReLU layer, (1, S, *shape), from the default ones, projected on [0, 1] after
        every step (any of them is a line below ReLU). Multipliers (beta-CROWN, Wang et al. 2021):
        ``signs`` gives per ReLU layer the sign (1, 1, *shape) of each neuron split in this part (+1 where ``z <= 0`` is
        assumed, -1 where ``z >= 0``, 0 elsewhere); ``beta >= 0`` times it is added to the
        pre-activation's coefficient (``beta s z <= 0`` on the part, so the bound stays below the
        function there). Returns the pair of dicts :meth:`_backward` takes."""
        start = self.output if start is None else start
        signs = signs or {}
        slopes, betas = {}, {}
        for k, layer in enumerate(self.layers[:start]):
            if layer.kind == "relu":
                lo, up = bounds[layer.inputs[0]]
                lower = _relu_lines(lo[:, None], up[:, None])[0]
                slopes[k] = lower.expand(1, lam.shape[1], *lower.shape[2:]).clone().requires_grad_(True)
                if k in signs and bool((signs[k] != 0).any()):
                    betas[k] = torch.zeros_like(slopes[k], requires_grad=True)
        free = [*slopes.values(), *betas.values()]
        best = ({k: v.detach().clone() for k, v in slopes.items()}, {k: v.detach().clone() for k, v in betas.items()})
        if not free or steps <= 0:
            return best[0], self._signed(best[1], signs)
        top = torch.full(lam.shape[:2], -torch.inf, dtype=torch.float64, device=lam.device)
        moments = [(torch.zeros_like(v), torch.zeros_like(v)) for v in free]
        for step in range(1, steps + 1):
            with torch.enable_grad():
                value = self._backward(bounds, start, lam, slopes=slopes, betas=self._signed(betas, signs))
                grads = torch.autograd.grad(value.sum(), free, allow_unused=True)
            better = value.detach() > top
            top = torch.where(better, value.detach(), top)
            for kept, now in zip(best, (slopes, betas), strict=True):
                for k, v in now.items():
                    kept[k] = torch.where(better[0].reshape(-1, *([1] * (v.dim() - 2))), v.detach(), kept[k])
            with torch.no_grad():  # one step of Adam (Kingma and Ba 2015) up the bound, projected
                for v, g, (m, r) in zip(free, grads, moments, strict=True):
                    if g is None:
                        continue
                    m.mul_(0.9).add_(g, alpha=0.1)
                    r.mul_(0.999).addcmul_(g, g, value=0.001)
                    v.add_(0.1 * (m / (1 - 0.9**step)) / ((r / (1 - 0.999**step)).sqrt() + 1e-8))
                for v in slopes.values():
                    v.clamp_(0.0, 1.0)
                for v in betas.values():
                    v.clamp_(min=0.0)
        return best[0], self._signed(best[1], signs)

    @staticmethod
    def _signed(betas: dict, signs: dict) -> dict:
        return {k: v * signs[k] for k, v in betas.items()}

    def input_weights(self, low: torch.Tensor, high: torch.Tensor, spec: torch.Tensor) -> torch.Tensor:
        """(B, S, *input shape): each input's coefficient in the backward relaxation of ``spec . y``
        over the box (its width times the coefficient's size is what it costs the bound: where
        splitting the box helps most)."""
        with torch.inference_mode(False):
            bounds = self._interval(low.to(torch.float64).clone(), high.to(torch.float64).clone(), tighten=True)
            spec = spec.to(torch.float64).to(low.device).expand(len(low), *spec.shape[-2:]).clone()
            weights: list[torch.Tensor] = []
            self._backward(bounds, self.output, spec, weights)
            return weights[0].detach()

    def _backward(
        self,
        bounds,
        start: int,
        lam: torch.Tensor,
        weights: list | None = None,
        relus: dict | None = None,
        slopes: dict | None = None,
        betas: dict | None = None,
    ) -> torch.Tensor:
        """A lower bound (B, S) of ``lam . y_start`` over the box, ``lam`` (B, S, *shape of layer
        ``start``): the coefficients passed backwards through every layer to the input (appended
        to ``weights`` when given; ``relus``: filled with each ReLU layer's split scores, as
        :meth:`split_lower` gives them; ``slopes``: per ReLU layer, the lower lines' slopes of its
        unstable neurons, (B or 1, S, *shape) in [0, 1], instead of 0 or 1; ``betas``: per ReLU layer,
        (B or 1, S, *shape) added to its pre-activation's coefficients, as :meth:`_optimised` makes them)."""
        coeffs: dict[int, torch.Tensor] = {start: lam}
        const = torch.zeros(lam.shape[:2], dtype=torch.float64, device=lam.device)
        for k in range(start, -1, -1):
            if k not in coeffs:
                continue
            lam = coeffs.pop(k)
            layer = self.layers[k]
            n, s = lam.shape[:2]
            if layer.kind == "input":
                lo, up = bounds[k]
                const += (lam.clamp(min=0) * lo[:, None] + lam.clamp(max=0) * up[:, None]).flatten(2).sum(-1)
                if weights is not None:
                    weights.append(lam)
                continue
            source = layer.inputs[0]
            lo, up = bounds[source]
            if layer.kind == "affine":
                passed, offset = self._transpose(layer, lam, lo.shape[1:])
                const += offset
            elif layer.kind == "add":
                self._accumulate(coeffs, layer.inputs[1], lam)
                passed = lam
            elif layer.kind == "relu":
                lower, upper, intercept = _relu_lines(lo[:, None], up[:, None])
                if slopes is not None and k in slopes:  # any slope in [0, 1] is a line below ReLU
                    lower = torch.where((lo[:, None] < 0) & (up[:, None] > 0), slopes[k], lower)
                pos, neg = lam.clamp(min=0), lam.clamp(max=0)
                if relus is not None:  # per unstable neuron, its coefficient times its chord's intercept
                    relus[k] = (lam.abs() * intercept).sum(1)
                passed = pos * lower + neg * upper
                if betas is not None and k in betas:
                    passed = passed + betas[k]
                const = const + (neg * intercept).flatten(2).sum(-1)
            else:
                passed, offset = self._pool_backward(layer, lam, lo, up)
                const += offset
            self._accumulate(coeffs, source, passed)
        return const

    @staticmethod
    def _accumulate(coeffs: dict, k: int, lam: torch.Tensor) -> None:
        coeffs[k] = coeffs[k] + lam if k in coeffs else lam

    @staticmethod
    def _transpose(layer: Layer, lam: torch.Tensor, shape) -> tuple[torch.Tensor, torch.Tensor]:
        """``lam A`` and ``lam . b`` for the affine layer ``x -> A x + b``."""
        n, s = lam.shape[:2]
        zero = torch.zeros((n * s, *shape), dtype=torch.float64, device=lam.device, requires_grad=True)
        with torch.enable_grad():
            out = layer.fn(zero)  # linear in lam: differentiable in it when lam is (optimised slopes)
            # The gradient of the scalar <out, lam>, not a vector-Jacobian product with lam given
            # as the output's gradient: the same numbers, without the imports torch makes for that.
            total = (out * lam.reshape(n * s, *lam.shape[2:])).sum()
            (passed,) = torch.autograd.grad(total, zero, create_graph=lam.requires_grad)
        offset = (lam * out.detach()[:1].reshape(1, 1, *lam.shape[2:])).flatten(2).sum(-1)
        return passed.reshape(n, s, *shape), offset

    @staticmethod
    def _pool_backward(layer: Layer, lam: torch.Tensor, lo: torch.Tensor, up: torch.Tensor):
        """Max pooling's relaxation (module docstring) passed backwards."""
        k, stride, pad = layer.pool
        n, c, h, w = lo.shape
        s = lam.shape[1]
        _, best, decided, top = _pool_choice(layer, lo, up)
        lam = lam.reshape(n, s, c, -1)
        pos, neg = lam.clamp(min=0), lam.clamp(max=0)
        decided = decided[:, None]
        chosen = pos + torch.where(decided, neg, 0.0)
        offset = (torch.where(decided, 0.0, neg) * top[:, None]).flatten(2).sum(-1)
        spread = torch.zeros(n, s, c, k * k, lam.shape[-1], dtype=torch.float64, device=lam.device)
        spread.scatter_(3, best[:, None].expand(n, s, c, 1, -1), chosen[:, :, :, None])
        folded = F.fold(spread.reshape(n * s, c * k * k, -1), (h + 2 * pad, w + 2 * pad), k, stride=stride)
        passed = folded[:, :, pad : pad + h, pad : pad + w].reshape(n, s, c, h, w)
        return passed, offset
