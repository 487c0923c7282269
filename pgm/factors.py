"""Pairwise factors: a log-potential over two batched supports, optionally a structured kernel.

A pairwise factor ``psi(x_a, x_b)`` sits on oriented edges ``(a, b)``. Message passing sends
along an edge either *forward* (source ``a`` -> target ``b``) or *backward* (``b`` -> ``a``).
The extension surface is deliberately small (compare PyTorch Geometric's ``MessagePassing``):

* :meth:`PairwiseFactor.log_potential` -- the dense table over two supports. Implementing
  this alone is enough: messages, conditionals and backtracking follow generically.
* :meth:`PairwiseFactor.message` -- override with a structured kernel when the dense
  ``(K, K)`` table is too large (see :class:`MonotoneFactor`: O(K * S) per edge, not O(K^2)).
* :meth:`PairwiseFactor.backtrack` -- override to decode MAP assignments in O(S) rather than
  O(K) per edge.

Every optional ability beyond the table is a :class:`Capability` that a factor declares in
``capabilities`` (one registry, :data:`CAPABILITY_METHODS`, lists their methods; each has a
default here), so engines call methods instead of probing for them, graphs check at
construction that each factor can do what its place needs, and :class:`FactorWrapper`
forwards all of them. Structured kernels compute exactly what their dense table computes, in
every semiring (``tests/pgm/test_factor_conformance.py``).

Shapes: ``B`` batch, ``E`` edges of this factor (or a subset of them), ``K`` support size
(states or particles), ``D`` state dimension. Supports are passed as values ``(B, E, K, D)``
or ``None`` for a discrete support (the state index is the value).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pgm.semiring import LogSemiring, Semiring
from pgm.tuning import EXP_FLOOR, MATMUL_MIN_STATES, UNSHIFTED_BOUND_MAX

__all__ = [
    "CAPABILITY_METHODS",
    "AnnealingStep",
    "BandedMonotoneFactor",
    "Capability",
    "FactorWrapper",
    "MissingCapabilityError",
    "MonotoneFactor",
    "PairwiseFactor",
    "TableFactor",
]

EdgeIndex = Tensor | slice


class Capability(enum.Enum):
    """An optional ability of a pairwise factor, declared in its ``capabilities``.

    Every ability has a default on :class:`PairwiseFactor` (so the engine calls the methods
    without probing for them); declaring it says the factor really provides it, which graphs
    check when they are built.
    """

    #: ``log_potential`` reads the support values ``xa``, ``xb`` (particles) rather than
    #: state indices: engines pass values, and particle BP rebuilds its table every iteration
    READS_VALUES = "reads_values"
    #: ``annealed(step)`` returns the factor at an iteration of its annealing schedule
    ANNEALED = "annealed"
    #: ``sample_target`` draws ``x_target ~ psi(x_source, .)``, ``log_target_density`` is
    #: its density and ``log_target_mixture`` the density under a mixture of sources; the
    #: mixture proposal of particle BP needs it on edges into continuous nodes
    SAMPLABLE = "samplable"
    #: ``log_potential_bound()`` is a number no table entry exceeds (BP then normalises one
    #: linear-space table for both message directions)
    BOUNDED = "bounded"
    #: ``log_potential_into(..., out)`` writes the table into a buffer the engine reuses
    BUFFERED = "buffered"
    #: ``viterbi(unary)`` runs a whole chain's MAP sweep in one fused kernel
    FUSED_VITERBI = "fused_viterbi"
    #: ``message``, ``source_given_target`` and ``backtrack`` are structured kernels that
    #: never build the dense ``(K, K)`` table (which may be too large to exist)
    STRUCTURED = "structured"


#: The methods behind each capability: one place, which :class:`FactorWrapper` must forward
#: entirely (checked when this module is imported). ``READS_VALUES`` is a property of
#: ``log_potential`` itself.
CAPABILITY_METHODS: dict[Capability, tuple[str, ...]] = {
    Capability.READS_VALUES: (),
    Capability.ANNEALED: ("annealed",),
    Capability.SAMPLABLE: ("sample_target", "log_target_density", "log_target_mixture"),
    Capability.BOUNDED: ("log_potential_bound",),
    Capability.BUFFERED: ("log_potential_into",),
    Capability.FUSED_VITERBI: ("viterbi",),
    Capability.STRUCTURED: ("message", "source_given_target", "backtrack"),
}
#: what every factor has (``log_potential`` required, the rest generic over the table)
CORE_METHODS = ("log_potential", "message", "source_given_target", "backtrack")
#: the methods a class declaring a capability must implement itself (the others of
#: :data:`CAPABILITY_METHODS` have generic defaults that stay correct)
_REQUIRED = {
    Capability.SAMPLABLE: ("sample_target", "log_target_density"),
    Capability.STRUCTURED: ("message",),
}


@dataclass(frozen=True)
class AnnealingStep:
    """Where the engine is in its iteration sequence; annealed factors read their schedule
    at ``iteration`` (0-based; restarts run the schedule again)."""

    iteration: int = 0
    restart: int = 0


class MissingCapabilityError(NotImplementedError):
    """A factor was asked for an ability it does not declare."""

    def __init__(self, factor: object, capability: Capability):
        methods = ", ".join(CAPABILITY_METHODS[capability])
        super().__init__(
            f"{type(factor).__name__} does not declare the capability "
            f"'{capability.value}' ({methods})"
        )


class PairwiseFactor:
    """Base class of pairwise factors on a group of oriented edges ``(a, b)``.

    Subclasses implement :meth:`log_potential`; optional abilities are the
    :class:`Capability` members listed in ``capabilities``, each with a default here
    (a generic dense kernel, ``None`` for "no fast path", or :class:`MissingCapabilityError`
    for a sampler). A class that declares a capability must override its methods (checked
    when the class is defined).

    Attributes:
        num_edges: number of edges this factor carries parameters for, or ``None`` when the
            parameters are shared by any number of edges (then any ``edges`` index is valid).
        num_states: the number of states per node its tables are made for (a fixed-size
            table), or ``None`` when it works on supports of any size.
        capabilities: the declared :class:`Capability` set.
    """

    num_edges: int | None = None
    num_states: int | None = None
    capabilities: frozenset[Capability] = frozenset()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        declared = cls.__dict__.get("capabilities")
        if not isinstance(declared, (frozenset, set)):
            return  # inherited, or computed per instance (wrappers)
        for capability in declared:
            lacking = [
                m
                for m in _REQUIRED.get(capability, CAPABILITY_METHODS[capability])
                if getattr(cls, m) is getattr(PairwiseFactor, m)
            ]
            if lacking:
                raise TypeError(
                    f"{cls.__name__} declares the capability '{capability.value}' but does "
                    f"not implement {', '.join(lacking)}"
                )

    def log_potential(
        self, edges: EdgeIndex, xa: Tensor | None, xb: Tensor | None, num_states: int
    ) -> Tensor:
        """Dense log-potential table ``log psi(x_a, x_b)``.

        Args:
            edges: which of this factor's edges, a LongTensor ``(E,)`` or a slice.
            xa, xb: support values of the two end nodes, ``(B, E, K, D)``, or ``None`` for
                discrete supports (the state index is the value).
            num_states: K.

        Returns:
            ``(B or 1, E or 1, K, K)`` log-potentials, ``[..., i, j] = log psi(a=i, b=j)``;
            ``-inf`` marks a forbidden pair.
        """
        raise NotImplementedError(f"{type(self).__name__} must implement log_potential")

    # -- annealed ----------------------------------------------------------------------------
    def annealed(self, step: AnnealingStep) -> PairwiseFactor:
        """This factor at an annealing step: a value (``self`` is never modified), so one
        factor may be shared by several graphs. Default: ``self`` (nothing anneals)."""
        return self

    # -- bounded / buffered ------------------------------------------------------------------
    def log_potential_bound(self) -> float | None:
        """A number no entry of :meth:`log_potential` exceeds (e.g. a normalised kernel's
        peak), or ``None`` (the default: unknown)."""
        return None

    def log_potential_into(
        self, edges: EdgeIndex, xa: Tensor, xb: Tensor, num_states: int, out: Tensor
    ) -> Tensor:
        """:meth:`log_potential`, written into ``out`` (a flat buffer the engine reuses
        across iterations, as many elements as the table) where the factor can; the
        default ignores ``out``. Returns the table."""
        return self.log_potential(edges, xa, xb, num_states)

    # -- samplable ---------------------------------------------------------------------------
    def sample_target(
        self, x_source: Tensor, edges: EdgeIndex, forward: bool, generator: torch.Generator | None
    ) -> Tensor:
        """Draw ``x_target ~ psi(x_source, .)`` (normalised as a density of the target):
        the target is ``b`` when ``forward``, else ``a``. Shapes: (B, E, M, D) -> (B, E, M, D_t)."""
        raise MissingCapabilityError(self, Capability.SAMPLABLE)

    def log_target_density(
        self, x_target: Tensor, x_source: Tensor, edges: EdgeIndex, forward: bool
    ) -> Tensor:
        """Log density of :meth:`sample_target`. Shapes: (B, E, K, D_t), (B, E, M, D_s) -> (B, E, K, M)."""
        raise MissingCapabilityError(self, Capability.SAMPLABLE)

    def log_target_mixture(
        self,
        x_target: Tensor,
        x_source: Tensor,
        log_w_source: Tensor,
        edges: EdgeIndex,
        forward: bool,
    ) -> Tensor:
        """``log sum_m w_m psi(x_source_m -> x_target_k)``: the density of each target under
        the mixture of conditionals (the proposal's neighbour component). Default: a
        log-sum-exp over :meth:`log_target_density`. Shapes: (B, E, K, D_t), (B, E, M, D_s),
        (B, E, M) -> (B, E, K)."""
        dens = self.log_target_density(x_target, x_source, edges, forward)
        return torch.logsumexp(dens + log_w_source.unsqueeze(-2), -1)

    # -- fused Viterbi -----------------------------------------------------------------------
    def viterbi(self, unary: Tensor, overwrite: bool = False) -> tuple[Tensor, Tensor] | None:
        """A fused MAP sweep of a chain with this factor on every edge ``(n, n + 1)``:
        score (B,) and states (B, N), or ``None`` (the default) to leave it to the generic
        path. Shapes: ``unary`` (B, N, K)."""
        return None

    # -- messages (structured kernels override these) ----------------------------------------
    def message(
        self,
        h: Tensor,
        edges: EdgeIndex,
        forward: bool,
        semiring: Semiring,
        xa: Tensor | None = None,
        xb: Tensor | None = None,
    ) -> Tensor:
        """Semiring message through the factor.

        ``out[b, e, j] = sum_i psi(i, j) * h[b, e, i]`` (forward, a -> b) or
        ``out[b, e, i] = sum_j psi(i, j) * h[b, e, j]`` (backward), in the semiring's domain.

        Shapes: ``h`` (B, E, K) -> (B, E, K).
        """
        table = semiring.from_log(self.log_potential(edges, xa, xb, h.shape[-1]))
        if forward:
            return semiring.sum(semiring.mul(table, h.unsqueeze(-1)), dim=-2)
        return semiring.sum(semiring.mul(table, h.unsqueeze(-2)), dim=-1)

    def source_given_target(
        self,
        target_state: Tensor,
        edges: EdgeIndex,
        forward: bool,
        num_states: int,
        xa: Tensor | None = None,
        xb: Tensor | None = None,
    ) -> Tensor:
        """Log-potential over the source's states with the target fixed.

        Shapes: ``target_state`` (B, E) long -> (B, E, K).
        """
        table = self.log_potential(edges, xa, xb, num_states)
        b, e = target_state.shape
        table = table.expand(b, e, num_states, num_states)
        if forward:  # source a, target b: column b = target
            idx = target_state[:, :, None, None].expand(b, e, num_states, 1)
            return table.gather(-1, idx).squeeze(-1)
        idx = target_state[:, :, None, None].expand(b, e, 1, num_states)
        return table.gather(-2, idx).squeeze(-2)

    def backtrack(
        self,
        h: Tensor,
        target_state: Tensor,
        edges: EdgeIndex,
        forward: bool,
        xa: Tensor | None = None,
        xb: Tensor | None = None,
    ) -> Tensor:
        """MAP decoding step: ``argmax_i h[b, e, i] + log psi(i -> target_state[b, e])``.

        Shapes: ``h`` (B, E, K), ``target_state`` (B, E) -> (B, E) long.
        """
        cond = self.source_given_target(target_state, edges, forward, h.shape[-1], xa, xb)
        return (h + cond).argmax(-1)


class FactorWrapper(PairwiseFactor):
    """A factor that presents ``base`` differently (e.g. on other edges) and forwards every
    method of the interface -- each capability's methods (:data:`CAPABILITY_METHODS`) and the
    core ones -- with its edges mapped by :meth:`map_edges`. Declares what its base declares
    (less what :meth:`drops` removes). A capability added to the registry without a
    forwarding method here fails at import.
    """

    def __init__(self, base: PairwiseFactor):
        if not isinstance(base, PairwiseFactor):
            raise TypeError(f"base must be a PairwiseFactor; got {type(base).__name__}")
        self.base = base
        # declared sizes are forwarded too (a subclass that changes them sets its own)
        self.num_edges, self.num_states = base.num_edges, base.num_states

    def map_edges(self, edges: EdgeIndex) -> EdgeIndex:
        """This wrapper's edges -> the base's (default: the same)."""
        return edges

    def drops(self) -> frozenset[Capability]:
        """Capabilities of the base that this wrapper cannot offer (default: none)."""
        return frozenset()

    def rewrap(self, base: PairwiseFactor) -> FactorWrapper:
        """The same wrapper around another base (used by :meth:`annealed`)."""
        raise NotImplementedError(f"{type(self).__name__} must implement rewrap")

    @property
    def capabilities(self) -> frozenset[Capability]:  # type: ignore[override]
        return frozenset(self.base.capabilities) - self.drops()

    def log_potential(self, edges, xa, xb, num_states):
        return self.base.log_potential(self.map_edges(edges), xa, xb, num_states)

    def annealed(self, step):
        base = self.base.annealed(step)
        return self if base is self.base else self.rewrap(base)

    def log_potential_bound(self):
        return self.base.log_potential_bound()

    def log_potential_into(self, edges, xa, xb, num_states, out):
        return self.base.log_potential_into(self.map_edges(edges), xa, xb, num_states, out)

    def sample_target(self, x_source, edges, forward, generator):
        return self.base.sample_target(x_source, self.map_edges(edges), forward, generator)

    def log_target_density(self, x_target, x_source, edges, forward):
        return self.base.log_target_density(x_target, x_source, self.map_edges(edges), forward)

    def log_target_mixture(self, x_target, x_source, log_w_source, edges, forward):
        return self.base.log_target_mixture(
            x_target, x_source, log_w_source, self.map_edges(edges), forward
        )

    def viterbi(self, unary, overwrite=False):
        if Capability.FUSED_VITERBI in self.drops():
            return None
        return self.base.viterbi(unary, overwrite)

    def message(self, h, edges, forward, semiring, xa=None, xb=None):
        return self.base.message(h, self.map_edges(edges), forward, semiring, xa, xb)

    def source_given_target(self, target_state, edges, forward, num_states, xa=None, xb=None):
        return self.base.source_given_target(
            target_state, self.map_edges(edges), forward, num_states, xa, xb
        )

    def backtrack(self, h, target_state, edges, forward, xa=None, xb=None):
        return self.base.backtrack(h, target_state, self.map_edges(edges), forward, xa, xb)


def _unforwarded(wrapper: type) -> list[str]:
    """Interface methods a wrapper class does not define itself."""
    names = {*CORE_METHODS, *(m for ms in CAPABILITY_METHODS.values() for m in ms)}
    return sorted(n for n in names if n not in wrapper.__dict__)


if _unforwarded(FactorWrapper):  # pragma: no cover - fails at import, by design
    raise TypeError(f"FactorWrapper does not forward {_unforwarded(FactorWrapper)}")


def _as_slice(edges: EdgeIndex) -> EdgeIndex:
    """A run of consecutive edge indices as a slice, so that selecting table rows is a view
    rather than a copy of ``(B, E, K, K)`` (tree levels of edges stored in level order)."""
    if isinstance(edges, Tensor) and edges.dim() == 1 and len(edges) > 0:
        first, last = int(edges[0]), int(edges[-1])
        if last - first + 1 == len(edges) and (len(edges) == 1 or bool((edges.diff() == 1).all())):
            return slice(first, last + 1)
    return edges


_INDEX_DTYPES = (torch.int64, torch.int32)


def _select_blocks(table: Tensor, edges: Tensor) -> Tensor:
    """``table[:, edges]`` for a ``(B, E, K, K)`` table and ``(n,)`` indices.

    index_select copies whole ``(K, K)`` blocks, ~5x faster on CPU than advanced indexing
    (17 of 120 blocks of 100 x 100). A table whose blocks are stored transposed (a factor
    that built it as ``psi(b, a)``) is gathered in its own layout and handed back
    transposed: index_select into row-major blocks reads it element by element, ~35x
    slower."""
    if table.stride(-1) != 1 and table.stride(-2) == 1:
        return table.transpose(-1, -2).index_select(1, edges).transpose(-1, -2)
    return table.index_select(1, edges)


def _check_step_log_potential(step_log_potential: Tensor, max_step: int) -> None:
    if step_log_potential.shape != (max_step + 1,):
        raise ValueError(
            f"step_log_potential must have shape ({max_step + 1},) for max_step="
            f"{max_step}; got {tuple(step_log_potential.shape)}"
        )
    _check_finite_or_neg_inf("step_log_potential", step_log_potential)


def _check_finite_or_neg_inf(name: str, x: Tensor) -> None:
    if torch.isnan(x).any() or torch.isposinf(x).any():
        raise ValueError(f"{name} must be finite or -inf (forbidden); found NaN or +inf")


class TableFactor(PairwiseFactor):
    """A dense table of log-potentials.

    Args:
        log_table: ``(K, K)`` shared by every edge, ``(E, K, K)`` one table per edge, or
            ``(B, E, K, K)`` per batch item and edge. Entry ``[..., i, j]`` is
            ``log psi(x_a = i, x_b = j)``; ``-inf`` forbids the pair.
        validate: check for NaN / +inf (skip only for tables the caller has checked).
        finite: the caller knows whether the table has no ``-inf`` (saves a pass over it);
            ``None``: found out when first needed.
        upper_bound: a number no entry exceeds (e.g. a normalised kernel's peak). Sum-product
            messages then share one ``exp(T - bound)`` table for both directions instead of
            normalising rows and columns separately (half the passes over the table).
        workspace: a float tensor with the table's number of elements that the linear-space
            table may be written into (a caller that rebuilds same-sized tables every
            iteration saves allocating -- and first touching -- a new one each time).
    """

    def __init__(
        self,
        log_table: Tensor,
        validate: bool = True,
        finite: bool | None = None,
        upper_bound: float | None = None,
        workspace: Tensor | None = None,
    ):
        if not isinstance(log_table, Tensor):
            raise TypeError(f"log_table must be a torch.Tensor, got {type(log_table).__name__}")
        if log_table.dim() not in (2, 3, 4) or log_table.shape[-1] != log_table.shape[-2]:
            raise ValueError(
                "log_table must have shape (K, K), (E, K, K) or (B, E, K, K); "
                f"got {tuple(log_table.shape)}"
            )
        if validate:
            _check_finite_or_neg_inf("log_table", log_table)
        while log_table.dim() < 4:
            log_table = log_table.unsqueeze(0)
        self.table = log_table  # (B or 1, E or 1, K, K)
        self.num_edges = self.table.shape[1] if self.table.shape[1] > 1 else None
        self.num_states = self.table.shape[-1]
        self._finite = finite
        self.upper_bound = upper_bound
        self.workspace = workspace
        if upper_bound is not None:
            self.capabilities = frozenset({Capability.BOUNDED})

    def log_potential_bound(self) -> float | None:
        return self.upper_bound

    def message(self, h, edges, forward, semiring, xa=None, xb=None):
        # Sum-product messages through a large dense table are a batched mat-vec in linear
        # space: exp(T - max) is computed once per direction and reused by every call
        # (tree BP asks each edge twice, loopy BP once per sweep), instead of a fresh
        # log-sum-exp over (B, E, K, K) each time.
        if type(semiring) is LogSemiring and self.table.shape[-1] >= MATMUL_MIN_STATES:
            return self._matmul_message(h, edges, forward)
        return super().message(h, edges, forward, semiring, xa, xb)

    def _scaled_exp(self, forward: bool) -> tuple[Tensor, Tensor | float, float]:
        """``exp(T - peak)`` stored edge-major ``(E, B, K, K)`` (so that a run of edges is a
        view that flattens to a batched matrix without a copy), ``peak``: ``(B, E, K)`` per
        column (forward) or row (backward), or one number for both under an upper bound;
        and the value the smallest entries were raised to."""
        cache = self.__dict__.setdefault("_exp_cache", {})
        key = None if self.upper_bound is not None else forward
        if key not in cache:
            t = self.table.transpose(0, 1)
            ws = self.workspace
            if (
                key is None
                and ws is not None
                and ws.numel() == t.numel()
                and ws.dtype == t.dtype
                and ws.device == t.device
            ):
                scaled = ws.view(t.shape)
            else:
                scaled = torch.empty(t.shape, dtype=t.dtype, device=t.device)
            # exp() of arguments below -87 (float32 underflow) takes a scalar slow path, ~40x
            # slower: raise them to -87 (1.6e-38) after the shift; where that floor could
            # matter the message is recomputed exactly (_matmul_message). Forbidden pairs
            # (-inf) stay exactly 0.
            if self._finite is None:
                self._finite = bool(self.table.amin() > -math.inf)
            forbidden = None if self._finite else torch.isneginf(t)
            if self.upper_bound is not None:
                bound = float(self.upper_bound)
                # A bound in [0, UNSHIFTED_BOUND_MAX] needs no shift (one pass fewer over
                # the table; see pgm.tuning).
                shift = 0.0 if 0.0 <= bound <= UNSHIFTED_BOUND_MAX else bound
                peak = shift
                torch.clamp(t, min=bound + EXP_FLOOR, out=scaled)
                if shift:
                    scaled.sub_(shift)
                floor = math.exp(bound + EXP_FLOOR - shift)
            else:
                dim = -2 if forward else -1  # forward sums over a (rows), backward over b
                peak = self.table.amax(dim, keepdim=True)
                peak = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))
                torch.sub(t, peak.transpose(0, 1), out=scaled)  # written edge-major
                scaled.clamp_(min=EXP_FLOOR)
                peak = peak.squeeze(dim)
                floor = math.exp(EXP_FLOOR)
            scaled.exp_()
            if forbidden is not None:
                scaled.masked_fill_(forbidden, 0.0)
            cache[key] = (scaled, peak, floor)
        return cache[key]

    def _matmul_message(self, h: Tensor, edges: EdgeIndex, forward: bool) -> Tensor:
        scaled, peak, floor = self._scaled_exp(forward)
        edges = _as_slice(edges)
        if self.table.shape[1] > 1:
            scaled = scaled[edges]
            if isinstance(peak, Tensor):
                peak = peak[:, edges]
        h_peak = h.amax(-1, keepdim=True)
        h_peak = torch.where(torch.isfinite(h_peak), h_peak, torch.zeros_like(h_peak))
        b, e, k = h.shape
        w = (h - h_peak).exp().transpose(0, 1)  # (E, B, K), as the tables
        scaled = scaled.expand(e, b, k, k).reshape(e * b, k, k)
        rows = w.reshape(e * b, 1, k)
        # Both directions stream the table row by row: a row vector times the matrix
        # (forward, sum over a) and row-wise dot products (backward, sum over b) are 2-3x
        # faster on CPU than torch's batched matrix-vector product, which walks columns.
        s = torch.bmm(rows, scaled) if forward else torch.linalg.vecdot(scaled, rows)
        s = s.reshape(e, b, k).transpose(0, 1)
        out = torch.log(s) + h_peak
        if isinstance(peak, Tensor) or peak:
            out = out + peak
        # Redo exactly what the floor could have decided: all mass underflowed (or truly
        # none), or -- against a shared bound, which no entry need reach -- a sum within a
        # factor 1e6 of the floor's own largest contribution (so it is off by < 1e-6).
        lost = s == 0
        if self.upper_bound is not None:
            lost |= s <= (floor * 1e6) * w.sum(-1).transpose(0, 1).unsqueeze(-1)
        if lost.any():
            table = self.table if self.table.shape[1] == 1 else self.table[:, edges]
            table = table.expand(h.shape[0], h.shape[1], *table.shape[-2:])
            b, e, j = lost.nonzero(as_tuple=True)
            rows = table[b, e, :, j] if forward else table[b, e, j, :]
            out[b, e, j] = torch.logsumexp(rows + h[b, e], -1)
        return out

    def log_potential(self, edges, xa, xb, num_states):
        if self.table.shape[-1] != num_states:
            raise ValueError(
                f"TableFactor has {self.table.shape[-1]} states per node but the graph has "
                f"{num_states}"
            )
        if self.table.shape[1] == 1:
            return self.table
        edges = _as_slice(edges)
        if isinstance(edges, Tensor) and edges.dim() == 1 and edges.dtype in _INDEX_DTYPES:
            return _select_blocks(self.table, edges)
        return self.table[:, edges]


class MonotoneFactor(PairwiseFactor):
    """Monotone transition ``0 <= x_b - x_a <= max_step`` over discrete states.

    This is the time-warping constraint of a correspondence chain (C(t'+1) - C(t') in
    ``[0, S]``). Its message is a trailing window semiring-sum of width ``S + 1`` (O(K * S),
    and a fused ``max_pool1d`` under max-product); with ``max_step=None`` the step is
    unbounded and the message is a prefix semiring-sum (O(K)). The dense ``(K, K)`` table is
    never built for inference (it is available through :meth:`log_potential` for tests).

    Args:
        max_step: S >= 1, or ``None`` for any non-negative step.
        step_log_potential: optional ``(S + 1,)`` log-potential of each step size 0..S (e.g.
            a penalty for leaving the expected slope); needs a finite ``max_step``.
    """

    capabilities = frozenset({Capability.STRUCTURED, Capability.FUSED_VITERBI})

    def __init__(self, max_step: int | None, step_log_potential: Tensor | None = None):
        if max_step is not None:
            if isinstance(max_step, bool) or not isinstance(max_step, int):
                raise TypeError(f"max_step must be an int or None, got {type(max_step).__name__}")
            if max_step < 1:
                raise ValueError(f"max_step (S) must be >= 1, got {max_step}")
        if step_log_potential is not None:
            if max_step is None:
                raise ValueError("step_log_potential needs a finite max_step")
            _check_step_log_potential(step_log_potential, max_step)
        self.max_step = max_step
        self.step_log_potential = step_log_potential
        if max_step is None or step_log_potential is not None:  # no fused sweep for these
            self.capabilities = frozenset({Capability.STRUCTURED})

    def log_potential(self, edges, xa, xb, num_states):
        i = torch.arange(num_states)
        step = i[None, :] - i[:, None]  # [a, b] -> b - a
        hi = num_states if self.max_step is None else self.max_step
        allowed = (step >= 0) & (step <= hi)
        table = torch.full((num_states, num_states), -math.inf, dtype=torch.get_default_dtype())
        if self.step_log_potential is None:
            table[allowed] = 0.0
        else:
            table = table.to(self.step_log_potential.dtype)
            table[allowed] = self.step_log_potential[step[allowed]]
        return table[None, None]

    def message(self, h, edges, forward, semiring, xa=None, xb=None):
        # Backward (b -> a) is the forward kernel on the reversed state axis.
        x = h if forward else h.flip(-1)
        if self.max_step is None:
            out = semiring.cumsum(x, dim=-1)
        elif self.step_log_potential is None:
            out = semiring.window_sum(x, self.max_step + 1)
        else:
            out = self._weighted_window(x, semiring)
        return out if forward else out.flip(-1)

    def _weighted_window(self, x: Tensor, semiring: Semiring) -> Tensor:
        s = self.max_step
        w = semiring.from_log(self.step_log_potential.to(x.dtype))
        padded = F.pad(x, (s, 0), value=semiring.zero)
        windows = padded.unfold(-1, s + 1, 1)  # (..., K, S+1); window[j, m] = x[j - S + m]
        return semiring.sum(semiring.mul(windows, w.flip(0)), dim=-1)

    def viterbi(
        self, unary: Tensor, overwrite: bool = False, rescale_every: int = 32
    ) -> tuple[Tensor, Tensor] | None:
        """Fused chain Viterbi with this factor on every edge (the time-alignment hot path).

        Each step is one centred ``max_pool1d`` (read as a trailing window by an offset of
        ``S - ceil(S / 2)``), one ``cummax`` of that many head entries, and in-place adds
        into the unary buffer; rows are shifted to max 0 every ``rescale_every`` steps so
        float32 keeps its precision over any length; backtracking reads S + 1 entries per
        step in NumPy. Same result as the generic path (tested), ties going to the smaller step.

        Args:
            unary: ``(B, N, K)`` log-potentials.
            overwrite: use ``unary`` as the work buffer (saves a copy; its values are lost).

        Returns:
            score (B,), states (B, N) long; or ``None`` when this kernel does not apply
            (step potentials, no step bound, or K <= S), leaving it to the generic path.
        """
        s = self.max_step
        b, n, k = unary.shape
        if s is None or self.step_log_potential is not None or k <= s:
            return None
        alpha = unary if overwrite else unary.clone()
        pad = (s + 1) // 2  # max_pool1d allows padding <= kernel / 2
        head = s - pad  # pooled[c] covers [c - pad, c - pad + S] = trailing window of c + head
        log_scale = torch.zeros(b, dtype=torch.float64, device=unary.device)
        for t in range(1, n):
            prev = alpha[:, t - 1 : t]
            row = alpha[:, t : t + 1]
            pooled = F.max_pool1d(prev, kernel_size=s + 1, stride=1, padding=pad)
            row[..., head:].add_(pooled[..., : k - head])
            if head:
                row[..., :head].add_(torch.cummax(prev[..., :head], -1).values)
            if t % rescale_every == 0:
                c = row.amax(-1, keepdim=True)
                c = torch.where(torch.isfinite(c), c, torch.zeros_like(c))
                row.sub_(c)
                log_scale += c.flatten().double()
        last = alpha[:, -1]
        score = (last.amax(-1).double() + log_scale).to(unary.dtype)
        states = np.empty((b, n), dtype=np.int64)
        rows = alpha.detach().cpu().numpy()
        end = last.argmax(-1).cpu().numpy()
        for bi in range(b):
            rows_b = rows[bi]
            j = int(end[bi])
            states[bi, n - 1] = j
            for t in range(n - 2, -1, -1):
                lo = max(0, j - s)
                # reversed window: argmax returns the first maximum = the smallest step
                j -= int(rows_b[t, lo : j + 1][::-1].argmax())
                states[bi, t] = j
        return score, torch.from_numpy(states).to(unary.device)

    def source_given_target(self, target_state, edges, forward, num_states, xa=None, xb=None):
        k = torch.arange(num_states, device=target_state.device)
        step = target_state.unsqueeze(-1) - k if forward else k - target_state.unsqueeze(-1)
        hi = num_states if self.max_step is None else self.max_step
        allowed = (step >= 0) & (step <= hi)
        dtype = torch.get_default_dtype()
        if self.step_log_potential is None:
            return torch.where(allowed, 0.0, -math.inf).to(dtype)
        w = self.step_log_potential[step.clamp(0, hi)]
        return torch.where(allowed, w, torch.full_like(w, -math.inf))

    def backtrack(self, h, target_state, edges, forward, xa=None, xb=None):
        if self.max_step is None:
            return super().backtrack(h, target_state, edges, forward, xa, xb)
        # Only the S + 1 states a step can come from are looked at: O(S) per edge.
        s = self.max_step
        k = h.shape[-1]
        offs = torch.arange(s + 1, device=h.device)
        cand = target_state.unsqueeze(-1) - offs if forward else target_state.unsqueeze(-1) + offs
        valid = (cand >= 0) & (cand < k)
        vals = h.gather(-1, cand.clamp(0, k - 1))
        if self.step_log_potential is not None:
            vals = vals + self.step_log_potential.to(vals.dtype)
        vals = torch.where(valid, vals, torch.full_like(vals, -math.inf))
        return cand.gather(-1, vals.argmax(-1, keepdim=True)).squeeze(-1)


class BandedMonotoneFactor(PairwiseFactor):
    """Monotone transition between nodes whose states are sliding windows of one integer axis.

    Node ``n`` has ``W`` states standing for the absolute positions ``offsets[n] + i``
    (``i`` in ``[0, W)``); the factor allows ``0 <= pos_b - pos_a <= max_step``. This is the
    band of a coarse-to-fine time alignment: each video frame keeps only a window of reference
    frames around the upsampled coarse path. O(W * S) per edge.

    Edges must be consecutive pairs ``(n, n + 1)``, addressed by ``n`` (as in
    :func:`pgm.chain.chain_map`): edge ``n`` joins node ``n`` (a) to node ``n + 1`` (b).

    Args:
        max_step: S >= 1.
        offsets: ``(N,)`` long, first absolute position of each node's window.
        step_log_potential: optional ``(S + 1,)`` log-potential of each step size 0..S (a
            slope prior), as :class:`MonotoneFactor`'s.
    """

    capabilities = frozenset({Capability.STRUCTURED, Capability.FUSED_VITERBI})

    def __init__(self, max_step: int, offsets: Tensor, step_log_potential: Tensor | None = None):
        if isinstance(max_step, bool) or not isinstance(max_step, int) or max_step < 1:
            raise ValueError(f"max_step (S) must be an int >= 1, got {max_step!r}")
        if offsets.dim() != 1 or offsets.dtype.is_floating_point:
            raise ValueError(f"offsets must be a 1-D integer tensor; got {tuple(offsets.shape)}")
        self.max_step = max_step
        self.offsets = offsets.long()
        self.num_edges = offsets.shape[0] - 1
        if step_log_potential is None:
            step_log_potential = torch.zeros(
                max_step + 1, dtype=torch.get_default_dtype(), device=offsets.device
            )
        _check_step_log_potential(step_log_potential, max_step)
        # beside the offsets: the messages run on their device
        self.step_log_potential = step_log_potential.to(offsets.device)

    def viterbi(self, unary: Tensor, overwrite: bool = False) -> tuple[Tensor, Tensor] | None:
        """Fused chain Viterbi over the band, in NumPy on the CPU (windows are short, so
        per-call overhead dominates and NumPy's is ~10x lower than torch's).

        Shapes: ``unary`` (B, N, W) -> score (B,), states (B, N) long (window offsets).
        Returns ``None`` off the CPU (the generic path handles it).
        """
        if unary.device.type != "cpu" or unary.requires_grad:
            return None
        b, n, w = unary.shape
        if n != self.offsets.shape[0]:
            raise ValueError(f"unary has {n} nodes but offsets has {self.offsets.shape[0]}")
        s = self.max_step
        shifts = (self.offsets[1:] - self.offsets[:-1]).tolist()
        alpha = unary.detach().numpy() if overwrite else unary.detach().numpy().copy()
        alpha = alpha.astype(np.float64, copy=False)
        step_lp = self.step_log_potential.double().cpu().numpy()
        # window index k reads the source S - k positions back: a step of S - k
        window_lp = step_lp[::-1].copy()
        plain = not step_lp.any()
        log_scale = np.zeros(b)
        work = np.full((b, s + w + max([0, *shifts])), -np.inf)
        windows = np.lib.stride_tricks.sliding_window_view(work, s + 1, axis=1)  # a view
        for t in range(1, n):
            d = shifts[t - 1]
            work[:, s : s + w] = alpha[:, t - 1]
            # target j reads source positions j + d - S .. j + d (window of `work` at j + d)
            if plain:
                alpha[:, t] += windows[:, d : d + w].max(-1)
            else:
                alpha[:, t] += (windows[:, d : d + w] + window_lp).max(-1)
            if t % 32 == 0:
                c = alpha[:, t].max(-1)
                c = np.where(np.isfinite(c), c, 0.0)
                alpha[:, t] -= c[:, None]
                log_scale += c
        score = alpha[:, -1].max(-1) + log_scale
        states = np.zeros((b, n), dtype=np.int64)
        for bi in np.isfinite(score).nonzero()[0]:  # an infeasible item has no path to trace
            j = int(alpha[bi, -1].argmax())
            states[bi, -1] = j
            for t in range(n - 2, -1, -1):
                hi = j + shifts[t]  # same absolute position in node t's window
                lo = max(0, hi - s)
                top = min(hi, w - 1)
                # reversed: argmax takes the first maximum = the smallest step
                cand = alpha[bi, t, lo : top + 1][::-1] + step_lp[hi - top : hi - lo + 1]
                j = top - int(cand.argmax())
                states[bi, t] = j
        return torch.from_numpy(score).to(unary.dtype), torch.from_numpy(states)

    def _shift(self, edges: EdgeIndex) -> Tensor:
        n = torch.arange(self.num_edges, device=self.offsets.device)[edges]
        return self.offsets[n + 1] - self.offsets[n]  # (E,)

    def log_potential(self, edges, xa, xb, num_states):
        d = self._shift(edges)  # pos_b - pos_a = d + j - i
        i = torch.arange(num_states, device=d.device)
        step = d[:, None, None] + i[None, None, :] - i[None, :, None]
        allowed = (step >= 0) & (step <= self.max_step)
        lp = self.step_log_potential[step.clamp(0, self.max_step)]
        return torch.where(allowed, lp, -math.inf).unsqueeze(0)

    def _gather_index(self, edges: EdgeIndex, width: int, forward: bool) -> tuple[Tensor, Tensor]:
        # Every edge's index once per (width, direction), then the edges asked for: loopy BP
        # sends through the same edges every iteration, and building the index was a dozen
        # small tensor operations per message.
        cache = self.__dict__.setdefault("_index_cache", {})
        if (width, forward) not in cache:
            d = self._shift(slice(None))[:, None, None]
            i = torch.arange(width, device=d.device)[None, :, None]
            s = torch.arange(self.max_step + 1, device=d.device)[None, None, :]
            # forward: target j collects source i = j + d - s; backward: target i collects
            # j = i - d + s
            src = i + d - s if forward else i - d + s
            valid = (src >= 0) & (src < width)
            cache[width, forward] = (src.clamp(0, width - 1), valid)  # (E, W, S+1)
        src, valid = cache[width, forward]
        return src[edges], valid[edges]

    def message(self, h, edges, forward, semiring, xa=None, xb=None):
        b, e, w = h.shape
        src, valid = self._gather_index(edges, w, forward)
        vals = h.unsqueeze(2).expand(b, e, w, w).gather(-1, src.unsqueeze(0).expand(b, -1, -1, -1))
        # the last axis is the step: its potential enters through the semiring's product
        steps = semiring.from_log(self.step_log_potential.to(vals.dtype))
        vals = semiring.mul(vals, steps)
        vals = torch.where(valid, vals, torch.full_like(vals, semiring.zero))
        return semiring.sum(vals, dim=-1)

    def source_given_target(self, target_state, edges, forward, num_states, xa=None, xb=None):
        d = self._shift(edges)[None, :, None]
        i = torch.arange(num_states, device=d.device)[None, None, :]
        t = target_state.unsqueeze(-1)
        step = t + d - i if forward else i + d - t
        allowed = (step >= 0) & (step <= self.max_step)
        lp = self.step_log_potential[step.clamp(0, self.max_step)]
        return torch.where(allowed, lp, -math.inf)

    def backtrack(self, h, target_state, edges, forward, xa=None, xb=None):
        d = self._shift(edges)[None, :, None]
        s = torch.arange(self.max_step + 1, device=d.device)[None, None, :]
        t = target_state.unsqueeze(-1)
        cand = t + d - s if forward else t - d + s
        w = h.shape[-1]
        valid = (cand >= 0) & (cand < w)
        vals = h.gather(-1, cand.clamp(0, w - 1)) + self.step_log_potential.to(h.dtype)
        vals = torch.where(valid, vals, torch.full_like(vals, -math.inf))
        return cand.gather(-1, vals.argmax(-1, keepdim=True)).squeeze(-1)


class BandedTempoFactor(PairwiseFactor):
    """:class:`BandedMonotoneFactor` with a hidden tempo: a monotone chain whose steps are
    emitted by a level that itself changes slowly (an HMM over the step), as a first-order
    chain on lifted states.

    Node ``n`` has ``K = W L`` states, pairs ``(i, l)`` at index ``i L + l``: absolute
    position ``offsets[n] + i`` and tempo level ``l``. Edge ``n`` joins ``(i, l)`` to
    ``(j, l')`` with the step ``s = offsets[n + 1] + j - offsets[n] - i``, allowed in
    ``[0, S]``, and log-potential ``change_log_potential[l', l] +
    emission_log_potential[l', s]``: the new level given the old, and the step given the new
    level (e.g. a fractional tempo rounded to the steps either side, a slope prior folded
    in). With ``L = S + 1`` levels that emit their own step only, this is a second-order
    chain on positions (a prior on the change of step). The chain's MAP is exact dynamic
    programming; structured messages cost O(W L (L + R)) per edge, R the most steps a level
    allows (one or two for a rounded tempo), the dense table
    (``K x K``) exists for tests and small chains only. States past ``W L`` (a node padded
    to a particle count) are forbidden.

    Edges must be consecutive pairs ``(n, n + 1)``, addressed by ``n``, as for
    :class:`BandedMonotoneFactor`.

    Args:
        max_step: S >= 1.
        offsets: ``(N,)`` long, first absolute position of each node's window.
        emission_log_potential: ``(L, S + 1)`` log-potential of each step given a level.
        change_log_potential: ``(L, L)`` log-potential of level ``l'`` after level ``l``,
            indexed ``[l', l]``.
    """

    capabilities = frozenset({Capability.STRUCTURED})

    def __init__(
        self,
        max_step: int,
        offsets: Tensor,
        emission_log_potential: Tensor,
        change_log_potential: Tensor,
    ):
        if isinstance(max_step, bool) or not isinstance(max_step, int) or max_step < 1:
            raise ValueError(f"max_step (S) must be an int >= 1, got {max_step!r}")
        if offsets.dim() != 1 or offsets.dtype.is_floating_point:
            raise ValueError(f"offsets must be a 1-D integer tensor; got {tuple(offsets.shape)}")
        levels = emission_log_potential.shape[0] if emission_log_potential.dim() == 2 else 0
        if levels < 1 or emission_log_potential.shape != (levels, max_step + 1):
            raise ValueError(
                f"emission_log_potential must have shape (L, {max_step + 1}) for "
                f"max_step={max_step}; got {tuple(emission_log_potential.shape)}"
            )
        if change_log_potential.shape != (levels, levels):
            raise ValueError(
                f"change_log_potential must have shape ({levels}, {levels}) for L={levels} "
                f"levels; got {tuple(change_log_potential.shape)}"
            )
        _check_finite_or_neg_inf("emission_log_potential", emission_log_potential)
        _check_finite_or_neg_inf("change_log_potential", change_log_potential)
        self.max_step = max_step
        self.offsets = offsets.long()
        self.num_edges = offsets.shape[0] - 1
        self.num_levels = levels
        self.emission_log_potential = emission_log_potential
        self.change_log_potential = change_log_potential
        # each level's allowed steps, padded to the most any level has (a rounded tempo
        # emits one or two): messages then cost O(W L R), not O(W L S)
        allowed = torch.isfinite(emission_log_potential)
        rank = max(1, int(allowed.sum(1).max()))
        order = torch.sort(allowed.long(), dim=1, descending=True, stable=True).indices
        self._steps = order[:, :rank]  # (L, R)
        self._step_ok = allowed.gather(1, self._steps)  # (L, R)

    def width(self, num_states: int) -> int:
        """W, the positions per node, of a node with ``num_states`` states."""
        return num_states // self.num_levels

    def _lifted(self, num_states: int) -> tuple[Tensor, Tensor]:
        """Each state's position index and level ``(K,)``, ``-1`` on padding."""
        L, w = self.num_levels, self.width(num_states)
        dev = self.offsets.device
        pos = torch.full((num_states,), -1, dtype=torch.long, device=dev)
        level = torch.full((num_states,), -1, dtype=torch.long, device=dev)
        pos[: w * L] = torch.arange(w, device=dev).repeat_interleave(L)
        level[: w * L] = torch.arange(L, device=dev).repeat(w)
        return pos, level

    def _shift(self, edges: EdgeIndex) -> Tensor:
        n = torch.arange(self.num_edges, device=self.offsets.device)[edges]
        return self.offsets[n + 1] - self.offsets[n]  # (E,)

    def _pair(self, step: Tensor, new: Tensor, old: Tensor, real: Tensor) -> Tensor:
        """Log-potential of steps with new and old levels (broadcastable; ``real`` marks
        pairs of real states), ``-inf`` where the step is outside ``[0, S]``."""
        ok = real & (step >= 0) & (step <= self.max_step)
        new, old = new.clamp(min=0), old.clamp(min=0)
        emit = self.emission_log_potential[new, step.clamp(0, self.max_step)]
        lp = self.change_log_potential[new, old] + emit
        return torch.where(ok, lp, -math.inf)

    def log_potential(self, edges, xa, xb, num_states):
        d = self._shift(edges)[:, None, None]
        pos, level = self._lifted(num_states)
        step = d + pos[None, None, :] - pos[None, :, None]  # (E, K_a, K_b)
        real = (level[:, None] >= 0) & (level[None, :] >= 0)
        return self._pair(step, level[None, None, :], level[None, :, None], real).unsqueeze(0)

    def _positions(self, grid: Tensor, src: Tensor) -> tuple[Tensor, Tensor]:
        """``grid`` ``(B, E, W, L)`` read at positions ``src`` ``(E, W, L, R)`` of the same
        level -> ``(B, E, W, L, R)`` and the mask of positions inside the window."""
        b, e, w, L = grid.shape
        r = src.shape[-1]
        valid = (src >= 0) & (src < w)
        flat = (
            src.clamp(0, w - 1) * L + torch.arange(L, device=src.device)[:, None]
        )  # index into (W L)
        vals = grid.reshape(b, e, w * L).gather(2, flat.reshape(1, e, -1).expand(b, e, -1))
        return vals.reshape(b, e, w, L, r), valid

    def message(self, h, edges, forward, semiring, xa=None, xb=None):
        b, e, k = h.shape
        L, w = self.num_levels, self.width(k)
        grid = h[..., : w * L].reshape(b, e, w, L)
        d = self._shift(edges)[:, None, None, None]  # (E, 1, 1, 1)
        pos = torch.arange(w, device=h.device)[None, :, None, None]
        steps = self._steps[None, None]  # (.., L, R)
        change = semiring.from_log(self.change_log_potential.to(h.dtype))  # [l', l]
        emit = self.emission_log_potential.gather(1, self._steps)  # (L, R)
        emit = semiring.from_log(emit.to(h.dtype))
        zero = torch.full((), semiring.zero, dtype=h.dtype, device=h.device)
        if forward:
            # each source position's levels moved to the new level, then the step emitted
            moved = semiring.sum(semiring.mul(grid[..., None, :], change), dim=-1)  # [i, l']
            vals, valid = self._positions(moved, pos + d - steps)  # [j, l', r]: i = j + d - s
            ok = (valid & self._step_ok)[None]
            out = semiring.sum(torch.where(ok, semiring.mul(vals, emit), zero), dim=-1)
        else:
            vals, valid = self._positions(grid, pos - d + steps)  # [i, l', r]: j = i - d + s
            ok = (valid & self._step_ok)[None]
            emitted = semiring.sum(torch.where(ok, semiring.mul(vals, emit), zero), dim=-1)
            out = semiring.sum(semiring.mul(emitted[..., :, None], change), dim=-2)  # [i, l]
        out = out.reshape(b, e, w * L)
        return torch.nn.functional.pad(out, (0, k - w * L), value=semiring.zero)

    def source_given_target(self, target_state, edges, forward, num_states, xa=None, xb=None):
        d = self._shift(edges)[None, :, None]
        lifted = self._lifted(num_states)
        pos, level = (x[None, None, :] for x in lifted)  # the source's
        t_pos, t_level = (x[target_state].unsqueeze(-1) for x in lifted)
        real = (level >= 0) & (t_level >= 0)
        if forward:  # source (i, l) -> target (j, l')
            return self._pair(d + t_pos - pos, t_level, level, real)
        return self._pair(d + pos - t_pos, level, t_level, real)  # target (i, l) <- (j, l')
