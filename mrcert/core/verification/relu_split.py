"""Branch and bound on ReLU splits: a box that bound propagation leaves open is divided by the
sign of one unstable neuron's pre-activation at a time (``z >= 0``: the ReLU is the identity;
``z <= 0``: it is zero), each part bounded again with that assumption
(:meth:`~mrcert.core.verification.network.BoundNetwork.split_lower`), until every part is
ruled out. The parts cover the box (every input lies in one of them), so a property verified on
every part holds on the box; a part whose assumptions contradict its bounds is empty.

The neuron split is the one of largest score (its coefficient in the backward relaxation times
its chord's intercept: what its relaxation costs the bound), as BaBSR (Bunel et al. 2020) scores
them. A part the default relaxation leaves open is bounded again with optimised ReLU slopes and
split multipliers (``steps`` gradient steps: alpha- and beta-CROWN)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from mrcert.core.verification.network import BoundNetwork

Split = dict[int, tuple[frozenset, frozenset]]
"""Per ReLU layer, the flat indices of its neurons assumed active and inactive."""


def verify_by_relu_splits(
    network: BoundNetwork,
    low: torch.Tensor,
    high: torch.Tensor,
    spec: torch.Tensor,
    offset: torch.Tensor,
    groups: list[torch.Tensor],
    late: Callable[[], bool],
    max_domains: int,
    batch: int = 8,
    steps: int = 0,
) -> tuple[bool, int, float]:
    """Whether every part of the box ``[low, high]`` (batch 1) rules out every disjunct (rows of
    ``spec`` by ``groups``: a disjunct is ruled out where one of its rows' bounds of
    ``spec . y - offset`` is positive), how many parts were bounded and the least margin by which
    a part was ruled out; False as soon as a
    part has no unstable neuron left to split, ``max_domains`` parts are bounded or ``late()``."""
    shapes: dict[int, tuple] = {}
    everything = frozenset(range(len(groups)))
    queue: list[tuple[Split, frozenset]] = [({}, everything)]  # a part and its disjuncts still open
    bounded, least = 0, float("inf")
    while queue:
        if late() or bounded >= max_domains:
            return False, bounded, least
        part, queue = queue[:batch], queue[batch:]
        got = _bounded(network, low, high, spec, part, groups, shapes, 0)
        if got is None:
            return False, bounded, least
        bound, scores = got
        bounded += len(part)
        bound = bound - offset
        hard = [j for j, (_, open_) in enumerate(part) if any(not bound[j, groups[d]].max() > 0 for d in open_)]
        if steps > 0 and hard:  # only the parts the default slopes leave open get optimised ones
            tighter, better = _bounded(network, low, high, spec, [part[j] for j in hard], groups, shapes, steps)
            for i, j in enumerate(hard):
                bound[j], scores[j] = torch.maximum(bound[j], tighter[i] - offset), better[i]
        for j, (split, open_) in enumerate(part):
            ruled = {d: float(bound[j, groups[d]].max()) for d in open_}
            left = frozenset(d for d, m in ruled.items() if not m > 0)
            least = min([least, *(m for m in ruled.values() if m > 0)])
            if not left:
                continue
            best = None
            for k, score in scores[j].items():
                shapes.setdefault(k, tuple(score.shape[1:]))
                flat = score.flatten()
                i = int(flat.argmax())
                if flat[i] > 0 and (best is None or flat[i] > best[0]):
                    best = (float(flat[i]), k, i)
            if best is None:  # nothing left to split: the relaxation is exact here and still open
                return False, bounded, least
            _, k, i = best
            active, inactive = split.get(k, (frozenset(), frozenset()))
            queue += [(split | {k: (active | {i}, inactive)}, left), (split | {k: (active, inactive | {i})}, left)]
    return True, bounded, least


def _bounded(network: BoundNetwork, low, high, spec, part, groups, shapes: dict, steps: int):
    """The bounds of ``spec . y`` on each part of the batch (its open disjuncts' rows) and their
    split scores (:meth:`~mrcert.core.verification.network.BoundNetwork.split_lower`)."""
    masks = _masks([p for p, _ in part], shapes, low.device) if shapes else {}
    rows = [torch.nonzero(sum(groups[d] for d in open_))[:, 0] for _, open_ in part]
    n = len(part)
    return network.split_lower(low.expand(n, *low.shape[1:]), high.expand(n, *high.shape[1:]), spec, masks, rows, steps)


def _masks(part: list[Split], shapes: dict[int, tuple], device) -> dict:
    """The splits of a batch of parts as the masks (B, *shape) bound propagation takes."""
    masks = {}
    for k, shape in shapes.items():
        active = torch.zeros((len(part), *shape), dtype=torch.bool, device=device)
        inactive = torch.zeros_like(active)
        for b, split in enumerate(part):
            on, off = split.get(k, ((), ()))
            active.view(len(part), -1)[b, list(on)] = True
            inactive.view(len(part), -1)[b, list(off)] = True
        masks[k] = (active, inactive)
    return masks
