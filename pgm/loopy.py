"""Loopy belief propagation: flooding schedule with damping and a message-change report.

Every directed message is updated at once from the previous iteration's messages. Messages
are kept normalised (``semiring.normalize``) and damped in log space. Exactness is not claimed
on graphs with cycles; on a tree the fixed point is the exact answer (tested).

Shapes: ``B`` batch, ``V`` nodes, ``E`` edges, ``K`` states; directed messages are stored as
``(B, 2E + 1, K)``: ``[0, E)`` along each edge (a -> b), ``[E, 2E)`` against it (b -> a), and
one padding row equal to the semiring's ``one``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from pgm.graph import FactorGraph
from pgm.semiring import LogSemiring, Semiring
from pgm.tree import InferenceResult, exclusive_products

__all__ = ["loopy_bp"]


def _incoming_table(graph: FactorGraph) -> tuple[Tensor, Tensor]:
    """``incoming`` (V, max_deg): ids of messages into each node (pad 2E), and for every
    directed message s -> t the slot of the reverse message t -> s in ``incoming[s]``."""
    edges, _, _ = graph.all_edges
    e = edges.shape[0]
    v = graph.num_nodes
    targets = torch.cat([edges[:, 1], edges[:, 0]])  # message d goes into targets[d]
    lists: list[list[int]] = [[] for _ in range(v)]
    for d, t in enumerate(targets.tolist()):
        lists[t].append(d)
    width = max(1, max(len(x) for x in lists))
    incoming = torch.full((v, width), 2 * e, dtype=torch.long)
    slot_of = {}
    for node, ids in enumerate(lists):
        for s, d in enumerate(ids):
            incoming[node, s] = d
            slot_of[d] = s
    reverse = torch.cat([torch.arange(e, 2 * e), torch.arange(0, e)])
    reverse_slot = torch.tensor([slot_of[int(r)] for r in reverse], dtype=torch.long)
    return incoming, reverse_slot


def loopy_bp(
    graph: FactorGraph,
    semiring: Semiring | None = None,
    max_iters: int = 100,
    damping: float = 0.5,
    tol: float = 1e-6,
    callback: Callable[[int, float], None] | None = None,
) -> InferenceResult:
    """Flooding-schedule belief propagation on any pairwise graph.

    Args:
        graph: a :class:`FactorGraph`.
        semiring: log-space semiring (default :class:`LogSemiring`; MaxSemiring for max-product).
        max_iters: iteration cap.
        damping: weight of the old message in ``new = (1 - damping) * new + damping * old``
            (log space), in ``[0, 1)``.
        tol: stop when the max absolute change of any finite message entry falls below it.
        callback: called as ``callback(iteration, change)`` after every iteration.

    Returns:
        :class:`InferenceResult` with ``log_marginals`` (B, V, K), ``message_change`` (one float
        per iteration), ``log_partition`` = ``None`` (no Bethe estimate), and under max-product
        ``assignment`` = per-node argmax of the max-marginals.
    """
    semiring = semiring or LogSemiring()
    if not semiring.log_space:
        raise ValueError(f"loopy_bp needs a log-space semiring; got {semiring!r}")
    if not 0.0 <= damping < 1.0:
        raise ValueError(f"damping must be in [0, 1); got {damping}")
    if max_iters < 1:
        raise ValueError(f"max_iters must be >= 1; got {max_iters}")
    b, v, k = graph.unary.shape
    edges, _, _ = graph.all_edges
    e = edges.shape[0]
    incoming, reverse_slot = _incoming_table(graph)
    sources = torch.cat([edges[:, 0], edges[:, 1]])
    base = semiring.from_log(graph.base_log_potential()).expand(b, v, k)
    dtype, device = base.dtype, base.device
    msgs = torch.full((b, 2 * e + 1, k), semiring.one, dtype=dtype, device=device)
    changes: list[float] = []
    for it in range(max_iters):
        excl = exclusive_products(msgs[:, incoming], 2, semiring)  # (B, V, max_deg, K)
        h_nodes = semiring.mul(base.unsqueeze(2), excl)
        h = h_nodes[:, sources, reverse_slot]  # (B, 2E, K): belief of the source minus target
        new = torch.empty_like(msgs[:, : 2 * e])
        offset = 0
        for g, group in enumerate(graph.groups):
            n = group.edges.shape[0]
            local = slice(0, n)
            xa, xb = graph.edge_values(g, local)
            fwd = slice(offset, offset + n)
            bwd = slice(e + offset, e + offset + n)
            new[:, fwd] = group.factor.message(h[:, fwd], local, True, semiring, xa, xb)
            new[:, bwd] = group.factor.message(h[:, bwd], local, False, semiring, xa, xb)
            offset += n
        new = semiring.normalize(new, -1)
        old = msgs[:, : 2 * e]
        if damping > 0:
            both_finite = torch.isfinite(new) & torch.isfinite(old)
            mixed = (1 - damping) * new + damping * old
            new = torch.where(both_finite, mixed, torch.minimum(new, old))
        diff = torch.where(torch.isfinite(new) & torch.isfinite(old), (new - old).abs(), 0.0)
        mismatch = torch.isfinite(new) != torch.isfinite(old)
        change = float("inf") if mismatch.any() else (float(diff.max()) if diff.numel() else 0.0)
        msgs = torch.cat([new, msgs[:, 2 * e :]], dim=1)
        changes.append(change)
        if callback is not None:
            callback(it, change)
        if change < tol:
            break
    belief = semiring.mul(base, semiring.prod(msgs[:, incoming], dim=2))
    marginals = semiring.normalize(belief, -1)
    assignment = marginals.argmax(-1) if semiring.selects else None
    return InferenceResult(None, marginals, assignment, changes)
