"""Loopy belief propagation: flooding schedule with damping and a message-change report.

Every directed message is updated at once from the previous iteration's messages. Messages
are kept normalised (``semiring.normalize``) and damped in log space. Exactness is not claimed
on graphs with cycles; on a tree the fixed point is the exact answer (tested).

Under a batch-invariant semiring (max-product: ``Semiring.batch_invariant``) only the
messages that can change are recomputed. A message ``s -> t`` is a function of the messages
into ``s`` but ``t -> s`` (and, when damped, of its own old value), so once none of those
changed, recomputing it would give back its stored value bit for bit. On registration's
body graphs over a third of the message updates are skipped so (late iterations often touch
a tenth of the messages: most of the graph has settled, a few loops oscillate), and the
result is identical to updating every message every iteration.

Shapes: ``B`` batch, ``V`` nodes, ``E`` edges, ``K`` states, ``D`` the largest degree;
directed messages are stored as ``(B, 2E + 1, K)``: ``[0, E)`` along each edge (a -> b),
``[E, 2E)`` against it (b -> a), and one padding row equal to the semiring's ``one``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from pgm.graph import FactorGraph
from pgm.semiring import LogSemiring, Semiring
from pgm.tree import InferenceResult, exclusive_products

__all__ = ["loopy_bp"]

#: recompute every message (views of the tables, no gathers) when at least this fraction of
#: them may change; below it, gather and recompute those only (measured on registration's
#: body graphs: 0.45 to 0.9 are all within noise, 0.3 is slower)
_SUBSET_MAX_FRACTION = 0.5


@dataclass(frozen=True)
class _Wiring:
    """Index maps of the directed messages, compiled once per call.

    Attributes:
        incoming: ``(V, D)`` ids of the messages into each node, padded with ``2E``.
        sources: ``(2E,)`` the node each message leaves.
        targets: ``(2E,)`` the node each message enters.
        reverse_slot: ``(2E,)`` for a message ``s -> t``, the slot of ``t -> s`` in
            ``incoming[s]``.
        reverse: ``(2E,)`` the id of each message's reverse.
        degree: ``(V,)`` the number of messages into each node.
        blocks: nodes of similar degree, ``(rows, width)``: ``rows`` ``(N * width,)`` their
            ``incoming`` rows cut to ``width`` (the products of the messages into a node
            need no padding beyond its degree).
        source_slot: ``(2E,)`` where each message's exclusive product sits among the
            blocks' products, flattened and concatenated.
        runs: per factor group and direction, ``(group, forward, first id, end id)``: the
            messages of a group form one run of ids in each direction.
    """

    incoming: Tensor
    sources: Tensor
    targets: Tensor
    reverse_slot: Tensor
    reverse: Tensor
    degree: Tensor
    blocks: tuple[tuple[Tensor, int], ...]
    source_slot: Tensor
    runs: tuple[tuple[int, bool, int, int], ...]


def _incoming_table(graph: FactorGraph) -> tuple[Tensor, Tensor]:
    """``incoming`` (V, max_deg): ids of messages into each node (pad 2E), in increasing id
    order, and for every directed message s -> t the slot of the reverse message t -> s in
    ``incoming[s]``."""
    edges, _, _ = graph.all_edges
    e = edges.shape[0]
    v = graph.num_nodes
    targets = torch.cat([edges[:, 1], edges[:, 0]])  # message d goes into targets[d]
    ids = torch.arange(2 * e, device="cpu")
    counts = torch.bincount(targets, minlength=v)
    first = counts.cumsum(0) - counts  # where each node's run starts in target order
    order = torch.sort(targets, stable=True).indices  # by target, then by id
    slot = torch.empty_like(ids)
    slot[order] = ids - first[targets[order]]
    width = max(1, int(counts.max()))
    incoming = torch.full((v, width), 2 * e, dtype=torch.long, device="cpu")
    incoming[targets, slot] = ids
    reverse = torch.cat([torch.arange(e, 2 * e, device="cpu"), torch.arange(0, e, device="cpu")])
    return incoming, slot[reverse]


def _wiring(graph: FactorGraph, device: torch.device) -> _Wiring:
    """The graph's :class:`_Wiring`, its tensors on ``device``."""
    edges, _, _ = graph.all_edges
    e = edges.shape[0]
    incoming, reverse_slot = _incoming_table(graph)
    runs, offset = [], 0
    for g, group in enumerate(graph.groups):
        n = group.edges.shape[0]
        runs += [(g, True, offset, offset + n), (g, False, e + offset, e + offset + n)]
        offset += n
    runs.sort(key=lambda run: run[2])  # in id order, so a sorted id list splits into runs
    sources = torch.cat([edges[:, 0], edges[:, 1]])
    degree = (incoming < 2 * e).sum(1)
    blocks, first_slot = [], torch.zeros_like(degree)  # where each node's products start
    done = 0
    for nodes, width in _degree_blocks(degree):
        blocks.append((incoming[nodes, :width].flatten().to(device), width))
        first_slot[nodes] = done + width * torch.arange(len(nodes), device="cpu")
        done += width * len(nodes)
    return _Wiring(
        incoming=incoming.to(device),
        sources=sources.to(device),
        targets=torch.cat([edges[:, 1], edges[:, 0]]).to(device),
        reverse_slot=reverse_slot.to(device),
        reverse=torch.cat(
            [torch.arange(e, 2 * e, device=device), torch.arange(0, e, device=device)]
        ),
        degree=degree.to(device),
        blocks=tuple(blocks),
        source_slot=(first_slot[sources] + reverse_slot).to(device),
        runs=tuple(runs),
    )


def _degree_blocks(degree: Tensor) -> list[tuple[Tensor, int]]:
    """The nodes in one or two blocks by degree, ``(nodes, width)`` each.

    Exclusive products run over a ``(B, N, width, K)`` table of incoming messages padded to
    the widest node. A few hubs (registration's C nodes: one edge per body part) beside
    many nodes of low degree would pad it several-fold, so the nodes are split at the
    degree that pads least, when that saves at least a quarter of the table.
    """
    v, top = len(degree), max(1, int(degree.max()))
    best, cut = v * top, None
    for width in degree.unique().tolist():
        low = int((degree <= width).sum())
        cells = low * width + (v - low) * top
        if 0 < width < top and cells < best:
            best, cut = cells, width
    if cut is None or best > 0.75 * v * top:
        return [(torch.arange(v), top)]
    low = degree <= cut
    return [(low.nonzero().squeeze(1), cut), ((~low).nonzero().squeeze(1), top)]


def _new_messages(
    graph: FactorGraph,
    wiring: _Wiring,
    semiring: Semiring,
    msgs: Tensor,
    base_out: Tensor,
    ids: Tensor | None,
) -> Tensor:
    """The unnormalised messages ``ids`` (all ``2E`` when ``None``).

    Args:
        msgs: ``(B, 2E + 1, K)`` the current messages.
        base_out: ``(B, 2E, K)`` the base potential of each message's source.
        ids: ``(M,)`` sorted message ids, or ``None``.

    Returns:
        ``(B, M, K)`` (``M = 2E`` when ``ids`` is ``None``).
    """
    b, _, k = msgs.shape
    # index_select rather than advanced indexing throughout: the same copy, several times
    # faster on CPU for these small gathers. Exclusive products are exact whatever the
    # padding (it is the semiring's ``one``), so blocks and subsets give the same bits.
    if ids is None:
        parts = []
        for rows, width in wiring.blocks:
            into = msgs.index_select(1, rows).view(b, -1, width, k)
            parts.append(exclusive_products(into, 2, semiring).flatten(1, 2))
        excl = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
        # h: belief of the source without the target's message, (B, 2E, K)
        h = semiring.mul(base_out, excl.index_select(1, wiring.source_slot))
        bounds = [run[2:] for run in wiring.runs]
    else:
        # the products over the sources' incoming messages, each source once
        nodes, row = torch.unique(wiring.sources[ids], return_inverse=True)
        width = max(1, int(wiring.degree[nodes].max()))  # no padding beyond their degree
        rows = wiring.incoming[nodes, :width].flatten()
        into = msgs.index_select(1, rows).view(b, -1, width, k)
        excl = exclusive_products(into, 2, semiring).flatten(1, 2)  # (B, N * width, K)
        slot = row * width + wiring.reverse_slot[ids]
        h = semiring.mul(base_out.index_select(1, ids), excl.index_select(1, slot))
        ends = [end for run in wiring.runs for end in run[2:]]
        cuts = torch.searchsorted(ids, ids.new_tensor(ends)).tolist()
        bounds = list(zip(cuts[0::2], cuts[1::2], strict=True))
    new = torch.empty_like(h)
    for (g, forward, first, _), (lo, hi) in zip(wiring.runs, bounds, strict=True):
        if lo == hi:
            continue
        # edges within the group: a slice (a view of a dense table) when all are updated
        local = slice(0, hi - lo) if ids is None else ids[lo:hi] - first
        xa, xb = graph.edge_values(g, local)
        factor = graph.groups[g].factor
        new[:, lo:hi] = factor.message(h[:, lo:hi], local, forward, semiring, xa, xb)
    return new


def _stale(wiring: _Wiring, moved: Tensor, damped: bool) -> Tensor:
    """Sorted ids of the messages that may change in the next iteration, given the ``moved``
    ``(n,)`` ids of those that changed in this one.

    A message ``s -> t`` reads every message into ``s`` but ``t -> s``; under damping it also
    mixes in its own old value. Any other message would come back bit for bit.
    """
    changed = torch.zeros_like(wiring.sources)
    changed[moved] = 1
    into = torch.zeros_like(wiring.degree)  # (V,) changed messages into each node
    into.index_add_(0, wiring.targets[moved], torch.ones_like(moved))
    # changes into the source, less the one from the target itself
    stale = into[wiring.sources] > changed[wiring.reverse]
    if damped:
        stale |= changed.bool()
    return stale.nonzero().squeeze(1)


def _change(new: Tensor, old: Tensor) -> float:
    """Max absolute change of the entries finite in both; ``inf`` where an entry became
    finite or stopped being finite; 0 for no entries. Shapes: (B, M, K) each."""
    finite_new, finite_old = torch.isfinite(new), torch.isfinite(old)
    # the finiteness masks once each (isfinite is several passes); where they agree,
    # finite in both is finite in ``new``
    if (finite_new != finite_old).any():
        return float("inf")
    if not new.numel():
        return 0.0
    return float(torch.where(finite_new, (new - old).abs(), 0.0).max())


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
    wiring = _wiring(graph, graph.unary.device)
    m = wiring.sources.shape[0]  # 2E directed messages
    base = semiring.from_log(graph.base_log_potential()).expand(b, v, k)
    base_out = base.index_select(1, wiring.sources)  # (B, 2E, K), constant over the iterations
    dtype, device = base.dtype, base.device
    msgs = torch.full((b, m + 1, k), semiring.one, dtype=dtype, device=device)
    # Skipping the messages that cannot change gives the same bits only where recomputing a
    # few messages rounds as recomputing all of them does (no exp / log).
    subsets = semiring.batch_invariant
    changes: list[float] = []
    ids: Tensor | None = None  # the messages that may change; None: all
    for it in range(max_iters):
        if ids is not None and ids.numel() == 0:
            change = 0.0  # a fixed point: every message would come back bit for bit
        else:
            new = semiring.normalize(_new_messages(graph, wiring, semiring, msgs, base_out, ids))
            old = msgs[:, :m] if ids is None else msgs.index_select(1, ids)
            if damping > 0:
                both_finite = torch.isfinite(new) & torch.isfinite(old)
                mixed = (1 - damping) * new + damping * old
                new = torch.where(both_finite, mixed, torch.minimum(new, old))
            change = _change(new, old)
            moved = (new != old).any(-1).any(0).nonzero().squeeze(1) if subsets else None
            if ids is None:
                msgs[:, :m] = new  # in place: no reallocation of the messages
            else:
                msgs.index_copy_(1, ids, new)
            if subsets:
                ids = _stale(wiring, moved if ids is None else ids[moved], damping > 0)
                if ids.numel() >= _SUBSET_MAX_FRACTION * m:
                    ids = None
        changes.append(change)
        if callback is not None:
            callback(it, change)
        if change < tol:
            break
    belief = semiring.mul(base, semiring.prod(msgs[:, wiring.incoming], dim=2))
    marginals = semiring.normalize(belief, -1)
    assignment = marginals.argmax(-1) if semiring.selects else None
    return InferenceResult(None, marginals, assignment, changes)
