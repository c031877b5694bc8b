"""A box of a network's inputs verified or falsified against a VNN-LIB property's unsafe region:
falsification first, then bound propagation (:mod:`.network`) with input splitting."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from mrcert.core.verification.network import BoundNetwork
from mrcert.core.verification.relu_split import verify_by_relu_splits


@dataclass
class BoxVerdict:
    """What :func:`verify_box` found: ``unsat`` (verified), ``sat`` (with an input ``x`` and its
    outputs ``y``), ``unknown`` or ``timeout``; ``margin``: the least, over the disjuncts still
    open, of the best lower bound by which one of its conjuncts fails (positive when verified)."""

    result: str
    margin: float
    boxes: int
    forward_passes: int
    x: np.ndarray | None = None
    y: np.ndarray | None = None


def verify_box(
    model: torch.nn.Module,
    network: BoundNetwork,
    low: torch.Tensor,
    high: torch.Tensor,
    unsafe: list[list[tuple[np.ndarray, float]]],
    timeout: float,
    relaxation: str = "crown",
    max_boxes: int = 4096,
    batch: int = 8,
    seed: int = 0,
    relu_domains: int = 0,
    bound_steps: int = 0,
) -> BoxVerdict:
    """Whether some input of the box ``[low, high]`` (shaped as the model's input, batch 1) gives
    outputs in the unsafe region (a VNN-LIB property's disjunction of conjunctions ``c . y + d >= 0``).

    The box's centre first; unless it is unsafe, one bound of the whole box (most properties are
    verified by it); then falsification (the box's corners, seeded random points, then
    signed-gradient steps towards the unsafe disjunct nearest to holding), then bound propagation
    with splitting -- first, with ``relu_domains``, on the signs of unstable ReLUs
    (:mod:`.relu_split`, for at most half the time left; each part's bound with ``bound_steps``
    gradient steps on its ReLU slopes and split multipliers), then on the inputs: a disjunct is ruled
    out on a box when one of its conjuncts' upper bound is negative; a box where some
    disjunct stays open is split in two along the input whose width costs the bound of its
    worst disjunct most (width times the backward relaxation's coefficient; with interval
    bounds alone, the widest input), until every box is verified (``unsat``), a point is
    found (``sat``), ``max_boxes`` boxes are bounded (``unknown``) or ``timeout`` seconds pass."""
    start = time.perf_counter()
    device = next(iter(network.traced.buffers()), torch.zeros(0)).device
    low, high = low.to(torch.float64).to(device), high.to(torch.float64).to(device)
    rows = [(c, d) for conj in unsafe for c, d in conj]
    spec = torch.tensor(np.array([-c for c, _ in rows]), dtype=torch.float64)
    offset = torch.tensor([d for _, d in rows], dtype=torch.float64, device=device)
    owner = np.repeat(np.arange(len(unsafe)), [len(conj) for conj in unsafe])
    groups = [torch.from_numpy(owner == k).to(device) for k in range(len(unsafe))]  # each disjunct's rows
    forwards = 0

    def outputs(x: torch.Tensor) -> np.ndarray:
        nonlocal forwards
        forwards += len(x)
        with torch.inference_mode():
            return (
                model(x.to(device=device, dtype=next(model.parameters(), next(model.buffers())).dtype))
                .double()
                .cpu()
                .numpy()
            )

    def violation(y: np.ndarray) -> np.ndarray:
        """Per point, the least over disjuncts of the worst conjunct's slack (<= 0: unsafe holds)."""
        slack = -(y @ np.array([c for c, _ in rows]).T + offset.cpu().numpy())  # > 0: conjunct fails
        per = np.full((len(y), len(unsafe)), -np.inf)
        for k in range(len(unsafe)):
            per[:, k] = slack[:, owner == k].max(1)
        return per.min(1)

    def bounded(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per box, each conjunct's lower bound of failing, and per disjunct the best of them."""
        bound = network.linear_lower(lo, hi, spec, relaxation) - offset  # > 0: the conjunct fails throughout
        return bound, torch.stack([bound[:, rows_of].max(1).values for rows_of in groups], 1)

    centre = (low + high) / 2
    yc = outputs(centre)
    if violation(yc)[0] <= 0:
        return BoxVerdict("sat", float(violation(yc)[0]), 0, forwards, centre[0].cpu().numpy(), yc[0])
    first = bounded(low, high)
    if float(first[1].min()) > 0:  # verified by its first bound
        return BoxVerdict("unsat", float(first[1].min()), 1, forwards)
    g = torch.Generator().manual_seed(seed)
    width = high - low
    points = [low, high, centre]
    points += [low + width * torch.rand(low.shape, generator=g, dtype=torch.float64).to(device) for _ in range(32)]
    xs = torch.cat(points)
    ys = np.concatenate([outputs(xs[:2]), yc, outputs(xs[3:])])
    v = violation(ys)
    best = int(np.argmin(v))
    x = xs[best : best + 1].clone()
    for step in range(20):  # signed gradient steps on the float64 network
        if v[best] <= 0 or not (width > 0).any():
            break
        x.requires_grad_(True)
        with torch.inference_mode(False), torch.enable_grad():
            y = network.forward(x)
            slack = y @ spec.to(device).T - offset  # -(c . y + d): > 0 where the conjunct fails
            per = torch.stack([slack[:, m].max(1).values for m in groups], 1)
            (grad,) = torch.autograd.grad(per.min(), x)
        x = torch.minimum(torch.maximum(x.detach() - width * 0.25 * 0.8**step * grad.sign(), low), high)
        yx = outputs(x)
        vx = violation(yx)[0]
        if vx < v[best]:
            xs[best : best + 1], ys[best], v[best] = x, yx[0], vx
    if v[best] <= 0:
        return BoxVerdict("sat", float(v[best]), 0, forwards, xs[best].cpu().numpy(), ys[best])
    boxes, worst = 1, np.inf

    def late() -> bool:
        return time.perf_counter() - start > timeout

    if relaxation == "crown" and relu_domains > 0:  # branch on ReLU signs first, for half the time left
        half = start + (timeout + time.perf_counter() - start) / 2
        verified, parts, least = verify_by_relu_splits(
            network, low, high, spec, offset, groups, lambda: late() or time.perf_counter() > half, relu_domains, batch,
            bound_steps,
        )  # fmt: skip
        boxes += parts
        if verified:
            return BoxVerdict("unsat", least, boxes, forwards)
    queue: list[tuple[torch.Tensor, torch.Tensor]] = []
    done = (low, high, *first)  # the whole box, bounded above

    while queue or done is not None:
        if late():
            return BoxVerdict("timeout", -np.inf, boxes, forwards)
        if done is not None:
            (lo, hi, bound, per), done = done, None
        else:
            if boxes >= max_boxes:
                return BoxVerdict("unknown", -np.inf, boxes, forwards)
            part, queue = queue[:batch], queue[batch:]
            lo, hi = torch.cat([p[0] for p in part]), torch.cat([p[1] for p in part])
            bound, per = bounded(lo, hi)
            boxes += len(part)
        margin = per.min(1).values.cpu().numpy()
        for j, m in enumerate(margin):
            if late():
                return BoxVerdict("timeout", -np.inf, boxes, forwards)
            if m > 0:
                worst = min(worst, float(m))
                continue
            wide = (hi[j] - lo[j]).flatten()
            cost = wide
            if (wide > 0).any() and relaxation == "crown":  # split where width costs the bound most
                weakest = groups[int(per[j].argmin())]
                row = int(torch.nonzero(weakest)[int(bound[j, weakest].argmax())])
                weight = network.input_weights(lo[j : j + 1], hi[j : j + 1], spec[row : row + 1])[0, 0].flatten()
                cost = wide * weight.abs() if (wide * weight.abs() > 0).any() else wide
            if not (wide > 0).any():  # a point whose bound does not decide: the network is evaluated there
                y = outputs(lo[j : j + 1])
                if violation(y)[0] <= 0:
                    return BoxVerdict("sat", float(violation(y)[0]), boxes, forwards, lo[j].cpu().numpy(), y[0])
                return BoxVerdict("unknown", float(m), boxes, forwards)
            k = int(torch.argmax(cost))
            mid = (lo[j].flatten()[k] + hi[j].flatten()[k]) / 2
            left_hi, right_lo = hi[j : j + 1].clone(), lo[j : j + 1].clone()
            left_hi.view(-1)[k], right_lo.view(-1)[k] = mid, mid
            queue += [(lo[j : j + 1], left_hi), (right_lo, hi[j : j + 1])]
    return BoxVerdict("unsat", worst, boxes, forwards)
