"""Spatiotemporal templates: a per-frame graph replicated along a time axis.

A body (or any articulated object) is defined once for one frame -- P nodes, a few factor
groups of edges between them -- and replicated over T frames with temporal edges joining
node p of frame t to node p of frame t + 1. Nodes are numbered ``t * P + p``; each factor
group stays one group (its edges are tiled along time as one tensor), and factors with
per-edge parameters are reused through :class:`TiledFactor` instead of being copied T times.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from pgm.factors import Capability, EdgeIndex, FactorWrapper, PairwiseFactor

__all__ = ["SpatioTemporalTemplate", "TiledFactor"]


class TiledFactor(FactorWrapper):
    """Reuse a factor with parameters for ``E`` edges on ``tiles`` copies of those edges.

    Edge ``i`` of the tiled group uses the base factor's edge ``i % E``. Every method of the
    interface is forwarded with the edges mapped (:class:`~pgm.factors.FactorWrapper`), so the
    tiled factor declares what its base declares -- except a fused Viterbi sweep over more
    than one tile (the base's kernel covers one copy of its edges; the generic path is
    exact).
    """

    def __init__(self, base: PairwiseFactor, tiles: int):
        super().__init__(base)
        if base.num_edges is None:
            raise ValueError("TiledFactor needs a factor with per-edge parameters (num_edges set)")
        if isinstance(tiles, bool) or not isinstance(tiles, int) or tiles < 1:
            raise ValueError(f"tiles must be an int >= 1; got {tiles!r}")
        self.tiles = tiles
        self.period = base.num_edges
        self.num_edges = base.num_edges * tiles

    def map_edges(self, edges: EdgeIndex) -> Tensor:
        if isinstance(edges, Tensor):
            if edges.numel() and (edges.min() < 0 or edges.max() >= self.num_edges):
                raise IndexError(f"edge index outside [0, {self.num_edges})")
            return edges % self.period
        return torch.arange(self.num_edges)[edges] % self.period

    def drops(self) -> frozenset[Capability]:
        return frozenset({Capability.FUSED_VITERBI}) if self.tiles > 1 else frozenset()

    def rewrap(self, base: PairwiseFactor) -> TiledFactor:
        return TiledFactor(base, self.tiles)

    def __repr__(self) -> str:
        return f"TiledFactor({type(self.base).__name__}, tiles={self.tiles})"


@dataclass
class SpatioTemporalTemplate:
    """A graph over ``num_parts`` nodes per frame, to be replicated over frames.

    Args:
        num_parts: P nodes per frame.
        frame_pairwise: ``[(edges (E, 2) over 0..P-1, factor), ...]`` within one frame; a
            factor may have parameters for its E edges (tiled over frames) or shared ones.
        temporal: factor between node p at t (a) and node p at t + 1 (b), with shared
            parameters or ``P`` per-part ones; ``None`` for independent frames.
        temporal_parts: which parts get temporal edges (default: all).
    """

    num_parts: int
    frame_pairwise: Sequence[tuple[Tensor, PairwiseFactor]] = ()
    temporal: PairwiseFactor | None = None
    temporal_parts: Tensor | None = None

    def __post_init__(self):
        if not isinstance(self.num_parts, int) or self.num_parts < 1:
            raise ValueError(f"num_parts must be an int >= 1; got {self.num_parts!r}")
        for i, (edges, _) in enumerate(self.frame_pairwise):
            edges = torch.as_tensor(edges)
            if edges.dim() != 2 or edges.shape[1] != 2:
                raise ValueError(
                    f"frame_pairwise[{i}] edges must have shape (E, 2); got {tuple(edges.shape)}"
                )
            if edges.numel() and (edges.min() < 0 or edges.max() >= self.num_parts):
                raise ValueError(
                    f"frame_pairwise[{i}] edges reference parts outside [0, {self.num_parts})"
                )

    def node(self, t: Tensor | int, p: Tensor | int) -> Tensor:
        """Node index of part ``p`` in frame ``t`` (broadcasts)."""
        return torch.as_tensor(t) * self.num_parts + torch.as_tensor(p)

    def frame_and_part(self, nodes: Tensor) -> tuple[Tensor, Tensor]:
        """Inverse of :meth:`node`: ``(t, p)`` of each node."""
        return nodes // self.num_parts, nodes % self.num_parts

    def build(self, num_frames: int) -> list[tuple[Tensor, PairwiseFactor]]:
        """Pairwise groups of the T-frame graph (V = T * P nodes), one group per template group.

        Returns:
            ``[(edges (T * E, 2), factor), ..., (temporal edges ((T - 1) * P', 2), factor)]``,
            edges ordered frame-major, so edge ``t * E + e`` is edge ``e`` of frame ``t``.
        """
        if not isinstance(num_frames, int) or num_frames < 1:
            raise ValueError(f"num_frames must be an int >= 1; got {num_frames!r}")
        p = self.num_parts
        t = torch.arange(num_frames, device="cpu")
        groups: list[tuple[Tensor, PairwiseFactor]] = []
        for edges, factor in self.frame_pairwise:
            edges = torch.as_tensor(edges).long()
            tiled = (edges[None] + (t * p)[:, None, None]).reshape(-1, 2)
            if factor.num_edges is not None:
                if factor.num_edges != len(edges):
                    raise ValueError(
                        f"{type(factor).__name__} has parameters for {factor.num_edges} edges but "
                        f"the frame group has {len(edges)}"
                    )
                factor = TiledFactor(factor, num_frames)
            groups.append((tiled, factor))
        if self.temporal is not None and num_frames > 1:
            parts = (
                torch.arange(p, device="cpu")
                if self.temporal_parts is None
                else torch.as_tensor(self.temporal_parts).long()
            )
            a = (t[:-1, None] * p + parts[None]).reshape(-1)
            edges = torch.stack([a, a + p], 1)
            factor = self.temporal
            if factor.num_edges is not None:
                if factor.num_edges != len(parts):
                    raise ValueError(
                        f"temporal factor has parameters for {factor.num_edges} edges; expected "
                        f"one per part with temporal edges ({len(parts)})"
                    )
                factor = TiledFactor(factor, num_frames - 1)
            groups.append((edges, factor))
        return groups
