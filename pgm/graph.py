"""Factor graphs over nodes that share one support size K, compiled once into index maps.

A :class:`FactorGraph` holds

* ``unary`` log-potentials ``(B, V, K)`` -- one row per node, ``-inf`` forbids a state;
* optional support ``log_measure`` ``(B, V, K)``: 0 for discrete states, ``-log q(s)`` for
  particles; padding a node with fewer than K states is a ``-inf`` measure;
* optional support ``values`` ``(B, V, K, D)`` for factors that look at state values
  (particles); discrete factors index states and ignore it;
* pairwise factor groups: each an ``(E, 2)`` LongTensor of oriented edges ``(a, b)`` and one
  :class:`~pgm.factors.PairwiseFactor` evaluating all of them in one batched call.

Wiring is compiled once (edge lists, neighbour tables, tree schedules) so inference never loops
over nodes in Python -- only over tree levels and factor groups (compare PGMax).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import torch
from torch import Tensor

from pgm.factors import Capability, PairwiseFactor

__all__ = ["FactorGraph", "GraphError", "NotATreeError", "TreeSchedule", "pairwise_groups"]


class GraphError(ValueError):
    """A factor graph was given inconsistent shapes, indices or values."""


class NotATreeError(GraphError):
    """Exact tree inference was asked of a graph with a cycle."""


@dataclass(frozen=True)
class PairwiseGroup:
    """Edges ``(E, 2)`` (a, b) sharing one factor type."""

    edges: Tensor
    factor: PairwiseFactor


@dataclass
class LevelOp:
    """Edges between one tree level and its parents that belong to one factor group."""

    group: int
    local_edges: Tensor  # (n,) indices into the group's edges
    child_is_a: bool  # upward (child -> parent) message is the factor's forward direction
    child: Tensor  # (n,) child nodes
    parent: Tensor  # (n,) parent nodes
    parent_row: Tensor  # (n,) row of the parent within the previous level's node list
    slot: Tensor  # (n,) position of the child within its parent's children row


@dataclass
class TreeSchedule:
    """Rooted-forest schedule: levels by depth, children tables, per-level edge ops."""

    roots: Tensor  # (R,)
    levels: list[Tensor]  # levels[d] = nodes at depth d
    children: Tensor  # (V, max_children) child ids, padded with V
    ops: list[list[LevelOp]] = field(default_factory=list)  # ops[d] for d >= 1


def _check_log_potential(name: str, x: Tensor) -> None:
    if torch.isnan(x).any():
        raise GraphError(f"{name} contains NaN")
    if torch.isposinf(x).any():
        raise GraphError(f"{name} contains +inf (log-potentials must be finite or -inf)")


def pairwise_groups(
    pairwise: Sequence[tuple[Tensor, PairwiseFactor]], num_nodes: int
) -> list[PairwiseGroup]:
    """Check the wiring of pairwise factor groups over ``num_nodes`` nodes once: each item an
    ``(edges (E, 2) integer, factor)`` pair, edges inside ``[0, V)`` without self-loops, and a
    factor with per-edge parameters for exactly its E edges.

    Raises:
        GraphError: naming the group, with the expected and the actual.
    """
    groups = []
    for gi, item in enumerate(pairwise):
        if not (isinstance(item, tuple | list) and len(item) == 2):
            raise GraphError(f"pairwise[{gi}] must be a pair (edges, factor); got {item!r}")
        edges, factor = item
        edges = torch.as_tensor(edges, device="cpu")
        if edges.dim() != 2 or edges.shape[1] != 2 or edges.dtype.is_floating_point:
            raise GraphError(
                f"pairwise[{gi}] edges must be an integer tensor of shape (E, 2); "
                f"got {tuple(edges.shape)} {edges.dtype}"
            )
        edges = edges.long()
        if edges.numel() and (edges.min() < 0 or edges.max() >= num_nodes):
            raise GraphError(f"pairwise[{gi}] edges reference nodes outside [0, {num_nodes})")
        if (edges[:, 0] == edges[:, 1]).any():
            raise GraphError(f"pairwise[{gi}] has a self-loop edge (a == b)")
        if not isinstance(factor, PairwiseFactor):
            raise GraphError(
                f"pairwise[{gi}] factor must be a PairwiseFactor; got {type(factor).__name__}"
            )
        if factor.num_edges is not None and factor.num_edges != edges.shape[0]:
            raise GraphError(
                f"pairwise[{gi}]: factor {type(factor).__name__} has parameters for "
                f"{factor.num_edges} edges but {edges.shape[0]} edges were given"
            )
        groups.append(PairwiseGroup(edges, factor))
    return groups


class FactorGraph:
    """A pairwise factor graph, batched over ``B`` problems that share its wiring.

    Args:
        unary: ``(B, V, K)`` unary log-potentials (a ``(V, K)`` tensor is taken as B = 1).
        pairwise: sequence of ``(edges, factor)``; ``edges`` is an ``(E, 2)`` integer tensor of
            oriented node pairs ``(a, b)`` matching the factor's ``log_potential[a, b]``.
        log_measure: ``(B, V, K)`` log-measure of each support point (default 0).
        values: ``(B, V, K, D)`` support values (particles), or ``None`` for discrete nodes.
        schedule: the :func:`tree_schedule` of these very edges, when compiled already
            (particle BP builds a graph per iteration over the same wiring).

    Raises:
        GraphError: with the expected and actual shapes, for out-of-range or self-loop edges,
            for a factor whose parameter count disagrees with its edge count, for NaN/+inf.
    """

    def __init__(
        self,
        unary: Tensor,
        pairwise: Sequence[tuple[Tensor, PairwiseFactor]] = (),
        log_measure: Tensor | None = None,
        values: Tensor | None = None,
        schedule: TreeSchedule | None = None,
    ):
        if not isinstance(unary, Tensor):
            raise GraphError(f"unary must be a torch.Tensor, got {type(unary).__name__}")
        if unary.dim() == 2:
            unary = unary.unsqueeze(0)
        if unary.dim() != 3:
            raise GraphError(f"unary must have shape (B, V, K) or (V, K); got {tuple(unary.shape)}")
        if unary.shape[1] == 0 or unary.shape[2] == 0:
            raise GraphError(
                f"unary must have V >= 1 nodes and K >= 1 states; got {tuple(unary.shape)}"
            )
        _check_log_potential("unary", unary)
        self.unary = unary
        b, v, k = unary.shape
        if log_measure is not None:
            if log_measure.dim() == 2:
                log_measure = log_measure.unsqueeze(0)
            if log_measure.shape[1:] != (v, k) or log_measure.shape[0] not in (1, b):
                raise GraphError(
                    f"log_measure must have shape ({b}, {v}, {k}); got {tuple(log_measure.shape)}"
                )
            _check_log_potential("log_measure", log_measure)
        self.log_measure = log_measure
        if values is not None and (values.dim() != 4 or values.shape[1:3] != (v, k)):
            raise GraphError(f"values must have shape (B, {v}, {k}, D); got {tuple(values.shape)}")
        self.values = values
        self.groups = pairwise_groups(pairwise, v)
        if schedule is not None:
            self.__dict__["tree_schedule"] = schedule
        for gi, group in enumerate(self.groups):
            if group.factor.num_states not in (None, k):
                raise GraphError(
                    f"pairwise[{gi}]: {type(group.factor).__name__} has "
                    f"{group.factor.num_states} states per node but the graph has {k}"
                )
        if values is None:
            for gi, group in enumerate(self.groups):
                if Capability.READS_VALUES in group.factor.capabilities:
                    raise GraphError(
                        f"pairwise[{gi}]: factor {type(group.factor).__name__} reads support "
                        f"values (capability '{Capability.READS_VALUES.value}') but the graph "
                        "has no values: pass values (B, V, K, D)"
                    )

    # -- sizes -----------------------------------------------------------------------------
    @property
    def batch_size(self) -> int:
        return self.unary.shape[0]

    @property
    def num_nodes(self) -> int:
        return self.unary.shape[1]

    @property
    def num_states(self) -> int:
        return self.unary.shape[2]

    def base_log_potential(self) -> Tensor:
        """Unary plus support log-measure, ``(B, V, K)``."""
        if self.log_measure is None:
            return self.unary
        return self.unary + self.log_measure

    def edge_values(self, group: int, local_edges: Tensor | slice) -> tuple[Tensor | None, ...]:
        """Support values of both ends of some edges, ``(B, E, K, D)`` each, or ``(None, None)``."""
        if self.values is None:
            return None, None
        e = self.groups[group].edges[local_edges]
        return self.values[:, e[:, 0]], self.values[:, e[:, 1]]

    # -- compiled wiring -------------------------------------------------------------------
    @cached_property
    def all_edges(self) -> tuple[Tensor, Tensor, Tensor]:
        """Concatenated edges: ``(E_tot, 2)`` nodes, ``(E_tot,)`` group id, ``(E_tot,)`` local id."""
        return concatenated_edges(self.groups)

    @cached_property
    def tree_schedule(self) -> TreeSchedule:
        """Root every connected component at its smallest node and order nodes by depth
        (:func:`tree_schedule`; given to the constructor when compiled already).

        Raises:
            NotATreeError: if the edges contain a cycle (or a repeated edge).
        """
        return tree_schedule(self.groups, self.num_nodes)


def concatenated_edges(groups: Sequence[PairwiseGroup]) -> tuple[Tensor, Tensor, Tensor]:
    """All groups' edges: ``(E_tot, 2)`` nodes, ``(E_tot,)`` group id, ``(E_tot,)`` local id."""
    if not groups:
        empty = torch.zeros(0, dtype=torch.long)
        return torch.zeros(0, 2, dtype=torch.long), empty, empty
    edges = torch.cat([g.edges for g in groups])
    gid = torch.cat([torch.full((len(g.edges),), i, device="cpu") for i, g in enumerate(groups)])
    lid = torch.cat([torch.arange(len(g.edges), device="cpu") for g in groups])
    return edges, gid, lid


def tree_schedule(groups: Sequence[PairwiseGroup], num_nodes: int) -> TreeSchedule:
    """Root every connected component at its smallest node and order nodes by depth: the
    wiring of tree BP, which depends on the edges alone (compile it once for graphs that
    share them).

    Raises:
        NotATreeError: if the edges contain a cycle (or a repeated edge).
    """
    v = num_nodes
    edges, gid, lid = concatenated_edges(groups)
    # Union-find: an edge joining two nodes already connected closes a cycle.
    parent_uf = list(range(v))

    def find(x: int) -> int:
        while parent_uf[x] != x:
            parent_uf[x] = parent_uf[parent_uf[x]]
            x = parent_uf[x]
        return x

    adjacency: list[list[tuple[int, int]]] = [[] for _ in range(v)]
    for e, (a, b) in enumerate(edges.tolist()):
        ra, rb = find(a), find(b)
        if ra == rb:
            raise NotATreeError(
                f"the graph is not a tree or forest: edge ({a}, {b}) closes a cycle; "
                "use pgm.loopy_bp for graphs with cycles"
            )
        parent_uf[ra] = rb
        adjacency[a].append((b, e))
        adjacency[b].append((a, e))

    depth = [-1] * v
    par = [-1] * v
    par_edge = [-1] * v
    roots: list[int] = []
    levels: list[list[int]] = []
    for r in range(v):
        if depth[r] >= 0:
            continue
        roots.append(r)
        depth[r] = 0
        frontier = [r]
        d = 0
        while frontier:
            if len(levels) <= d:
                levels.append([])
            levels[d].extend(frontier)
            nxt = []
            for node in frontier:
                for nb, e in adjacency[node]:
                    if depth[nb] < 0:
                        depth[nb] = d + 1
                        par[nb] = node
                        par_edge[nb] = e
                        nxt.append(nb)
            frontier = nxt
            d += 1

    kids: list[list[int]] = [[] for _ in range(v)]
    for node in range(v):
        if par[node] >= 0:
            kids[par[node]].append(node)
    width = max(1, max(len(c) for c in kids))
    children = torch.full((v, width), v, dtype=torch.long, device="cpu")
    slot = [0] * v
    for p, cs in enumerate(kids):
        for s, c in enumerate(cs):
            children[p, s] = c
            slot[c] = s

    level_tensors = [torch.tensor(lv, dtype=torch.long, device="cpu") for lv in levels]
    ops: list[list[LevelOp]] = [[]]
    for d in range(1, len(levels)):
        row_of = {node: i for i, node in enumerate(levels[d - 1])}
        buckets: dict[tuple[int, bool], list[tuple[int, int, int, int, int]]] = {}
        for c in levels[d]:
            e = par_edge[c]
            g = int(gid[e])
            child_is_a = int(edges[e, 0]) == c
            buckets.setdefault((g, child_is_a), []).append(
                (int(lid[e]), c, par[c], row_of[par[c]], slot[c])
            )
        level_ops = []
        for (g, child_is_a), rows in sorted(buckets.items()):
            cols = torch.tensor(rows, dtype=torch.long, device="cpu").T
            level_ops.append(LevelOp(g, cols[0], child_is_a, cols[1], cols[2], cols[3], cols[4]))
        ops.append(level_ops)
    return TreeSchedule(
        torch.tensor(roots, dtype=torch.long, device="cpu"), level_tensors, children, ops
    )
