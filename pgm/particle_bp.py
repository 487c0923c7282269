"""Particle belief propagation (the proposal's Eqs. 28-35) on the exact engine.

With its particles fixed, a continuous node is a discrete node whose support is its K
particles with log-measure ``-log q(s)``; a pairwise factor evaluated on two particle sets is
a ``(B, E, K, K)`` table. One iteration of particle BP is therefore:

1. **Proposal** (iterations after the first): for every continuous node j, K new particles
   from a mixture of its own previous marginal (resample, then perturb with the state
   space's kernel) and each neighbour's marginal pushed through ``psi_ij`` (resample
   ``x_i``, then ``x_j ~ psi_ij(x_i, .)``); ``q_j(s)``, the mixture's density at each new
   particle, is kept. ``proposal="own"`` uses the node's own marginal only (BPMC-style).
2. **Tables**: every factor that reads particle values is evaluated once on the new
   particles (cached ``TableFactor`` s, in the order BP visits their edges).
3. **Messages** (Eq. 33) and **marginals** (Eq. 35): exact BP on the particle-discretised
   graph -- :func:`pgm.tree.tree_inference` on a tree, :func:`pgm.loopy.loopy_bp` otherwise --
   with ``unary = log phi_j(s_j, X_-j, z_j)`` and ``log_measure = -log q_j(s_j)`` (0 under
   max-product, which maximises over particle locations and must not favour rare ones). Messages
   into a node exclude the target's own message (prefix/suffix products), which is Eq. 33's
   division by ``omega_ji``; the marginal is ``phi * prod omega / q``, normalised.
4. **Diagnostics and estimates**: weighted mean on the manifold, the best particle per node,
   effective sample sizes, and a clear error where every particle lost its weight.

Sum-product or max-product (particle max-product) is the semiring's choice. Factors anneal
through their :class:`~pgm.schedules.Schedule`: each iteration the engine asks every factor for
its value at that step (``factor.annealed(step)``), never modifying the graph, so one factor or
graph may be shared. ``restarts`` repeats the whole iteration sequence from the current
particles (the proposal runs 6 iterations twice). What each factor must be able to do is checked
when the :class:`ParticleGraph` is built; the wiring is compiled once per call (a
:class:`_Plan`); chunk and block sizes live in :mod:`pgm.tuning`.

Shapes: ``B`` batch, ``V`` nodes, ``K`` particles (discrete nodes: states, padded to K),
``D`` the widest state. Every random draw uses the given ``torch.Generator``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from pgm.continuous import UnaryFactor
from pgm.factors import (
    AnnealingStep,
    Capability,
    EdgeIndex,
    FactorWrapper,
    PairwiseFactor,
    TableFactor,
)
from pgm.graph import (
    FactorGraph,
    GraphError,
    NotATreeError,
    PairwiseGroup,
    TreeSchedule,
    pairwise_groups,
    tree_schedule,
)
from pgm.loopy import loopy_bp
from pgm.schedules import Constant, Schedule
from pgm.semiring import LogSemiring, Semiring
from pgm.spaces import StateSpace
from pgm.tree import tree_inference
from pgm.tuning import budget_for

__all__ = ["PROPOSALS", "IterationStats", "ParticleGraph", "ParticleResult", "particle_bp"]

#: proposal kinds: neighbours' marginals pushed through the factors too, or the own only
PROPOSALS = ("mixture", "own")


@dataclass
class IterationStats:
    """Diagnostics of one particle-BP iteration.

    Attributes:
        restart, iteration: position in the schedule.
        ess: ``(B, V)`` effective sample size ``1 / sum pi^2`` of each node's marginal.
        log_weight_range: ``(B, V)`` max minus min of the finite log-weights.
        estimate_change: max over nodes of the change of the mean estimate since the last
            iteration (in the state space's distance); ``nan`` at the first.
        message_change: last message change of loopy BP inside the iteration (``None`` on trees).
    """

    restart: int
    iteration: int
    ess: Tensor
    log_weight_range: Tensor
    estimate_change: float
    message_change: float | None


@dataclass
class ParticleResult:
    """Output of :func:`particle_bp`.

    Attributes:
        particles: ``(B, V, K, D)`` final particles (discrete nodes: their states).
        log_weights: ``(B, V, K)`` normalised log marginal weights (``-inf`` on padding).
        mean: ``(B, V, D)`` weighted mean on each node's manifold.
        best: ``(B, V, D)`` highest-weight particle.
        history: one :class:`IterationStats` per iteration.
    """

    particles: Tensor
    log_weights: Tensor
    mean: Tensor
    best: Tensor
    history: list[IterationStats] = field(default_factory=list)


@dataclass
class _Directed:
    """One direction of one factor group's edges, in the proposal's bookkeeping."""

    group: int
    forward: bool
    source: Tensor  # (E,) nodes
    target: Tensor  # (E,) nodes
    slot: Tensor  # (E,) 1 + position among the target's incoming components


class ParticleGraph:
    """A factor graph over continuous (and discrete) nodes, for :func:`particle_bp`.

    Checked here, once, rather than during inference: the wiring (shapes, ranges, per-edge
    parameter counts); that a factor joining a continuous node reads particle values
    (a table over state indices cannot follow particles that move); that a factor over a
    fixed number of states joins discrete nodes with exactly that many; and, for the
    ``"mixture"`` proposal, that every factor on an edge into a continuous node can sample
    it (:attr:`~pgm.factors.Capability.SAMPLABLE`). Each error names the group, the factor
    type and the missing ability.

    Args:
        num_nodes: V.
        spaces: ``[(space, nodes), ...]`` -- every node in exactly one group.
        pairwise: ``[(edges (E, 2), factor), ...]`` as in :class:`~pgm.graph.FactorGraph`.
        unary: ``[(nodes (N,), factor), ...]`` observation factors (a node may have several).
        proposal: how :func:`particle_bp` draws new particles by default: ``"mixture"`` (own
            marginal and neighbours' pushed through the factors) or ``"own"`` (BPMC-style).
    """

    def __init__(
        self,
        num_nodes: int,
        spaces: Sequence[tuple[StateSpace, Tensor]],
        pairwise: Sequence[tuple[Tensor, PairwiseFactor]] = (),
        unary: Sequence[tuple[Tensor, UnaryFactor]] = (),
        proposal: str = "mixture",
    ):
        if isinstance(num_nodes, bool) or not isinstance(num_nodes, int) or num_nodes < 1:
            raise GraphError(f"num_nodes must be an int >= 1; got {num_nodes!r}")
        if proposal not in PROPOSALS:
            raise GraphError(f"proposal must be one of {PROPOSALS}; got {proposal!r}")
        self.num_nodes = num_nodes
        self.proposal = proposal
        owner = torch.full((num_nodes,), -1, dtype=torch.long, device="cpu")
        self.spaces: list[tuple[StateSpace, Tensor]] = []
        for gi, (space, nodes) in enumerate(spaces):
            if not isinstance(space, StateSpace):
                raise GraphError(f"spaces[{gi}] must pair a StateSpace with nodes; got {space!r}")
            nodes = torch.as_tensor(nodes, dtype=torch.long, device="cpu").reshape(-1)
            if nodes.numel() and (nodes.min() < 0 or nodes.max() >= num_nodes):
                raise GraphError(f"spaces[{gi}] names nodes outside [0, {num_nodes})")
            if (owner[nodes] >= 0).any() or len(set(nodes.tolist())) != len(nodes):
                raise GraphError(f"spaces[{gi}] names a node that already has a space")
            owner[nodes] = gi
            self.spaces.append((space, nodes))
        if (owner < 0).any():
            missing = (owner < 0).nonzero().flatten().tolist()
            raise GraphError(f"nodes {missing[:10]} have no state space")
        self.space_of = owner
        self.groups: list[PairwiseGroup] = pairwise_groups(pairwise, num_nodes)
        self.pairwise = [(g.edges, g.factor) for g in self.groups]
        self.unary = []
        for ui, (nodes, factor) in enumerate(unary):
            nodes = torch.as_tensor(nodes, dtype=torch.long, device="cpu").reshape(-1)
            if nodes.numel() and (nodes.min() < 0 or nodes.max() >= num_nodes):
                raise GraphError(f"unary[{ui}] names nodes outside [0, {num_nodes})")
            if not isinstance(factor, UnaryFactor):
                raise GraphError(
                    f"unary[{ui}] factor must be a UnaryFactor; got {type(factor).__name__}"
                )
            self.unary.append((nodes, factor))
        self.max_dim = max(space.dim for space, _ in self.spaces)
        self.discrete_states = max([s.num_states for s, _ in self.spaces if s.discrete] + [0])
        self.continuous = torch.tensor(
            [not self.spaces[g][0].discrete for g in owner.tolist()], device="cpu"
        )
        self._check_factor_places()
        if proposal == "mixture":
            check_samplable(self)

    def _check_factor_places(self) -> None:
        for gi, group in enumerate(self.groups):
            name = type(group.factor).__name__
            ends = group.edges.reshape(-1)
            if self.continuous[ends].any() and (
                Capability.READS_VALUES not in group.factor.capabilities
            ):
                node = int(ends[self.continuous[ends]][0])
                raise GraphError(
                    f"pairwise[{gi}]: {name} joins continuous node {node} but does not read "
                    f"particle values (capability '{Capability.READS_VALUES.value}'): a factor "
                    "over state indices belongs between discrete nodes"
                )
            states = group.factor.num_states
            if states is None:
                continue
            for node in ends.unique().tolist():
                space = self.spaces[int(self.space_of[node])][0]
                if space.discrete and space.num_states != states:
                    raise GraphError(
                        f"pairwise[{gi}]: {name} has {states} states per node but node {node} "
                        f"is {space!r}"
                    )

    def directed_edges(self) -> tuple[list[_Directed], int]:
        """Every factor group in both directions, with the slot each edge takes among its
        target's proposal components (slot 0 is the node's own marginal)."""
        count = [0] * self.num_nodes
        out = []
        for g, (edges, _factor) in enumerate(self.pairwise):
            for forward in (True, False):
                src, dst = (edges[:, 0], edges[:, 1]) if forward else (edges[:, 1], edges[:, 0])
                slots = []
                for t in dst.tolist():
                    count[t] += 1
                    slots.append(count[t])
                out.append(
                    _Directed(
                        g, forward, src, dst, torch.tensor(slots, dtype=torch.long, device="cpu")
                    )
                )
        return out, max([*count, 0])

    def proposing_directions(self) -> list[_Directed]:
        """The directions whose targets include continuous nodes: the neighbour components
        of the mixture proposal."""
        directed, _ = self.directed_edges()
        return [de for de in directed if self.continuous[de.target].any()]


def check_samplable(graph: ParticleGraph) -> None:
    """Raise :class:`GraphError` unless every factor on an edge into a continuous node can
    sample it, as the ``"mixture"`` proposal needs."""
    for de in graph.proposing_directions():
        factor = graph.pairwise[de.group][1]
        if Capability.SAMPLABLE not in factor.capabilities:
            end = "b" if de.forward else "a"
            node = int(de.target[graph.continuous[de.target]][0])
            raise GraphError(
                f"pairwise[{de.group}]: {type(factor).__name__} lacks the capability "
                f"'{Capability.SAMPLABLE.value}', but the mixture proposal draws continuous "
                f"node {node} (end {end}) through it; implement sample_target and "
                "log_target_density and declare Capability.SAMPLABLE, or use proposal='own'"
            )


@dataclass(frozen=True)
class _Proposal:
    """How new particles are drawn (compiled once per call; see :func:`particle_bp`)."""

    kind: str
    self_weight: float
    centres: int | None  # None: kernels on all K particles; M: on M resampled centres
    scales: dict[int, object]  # space group -> perturbation kernel scale
    kernel_schedule: Schedule
    pushed: list[_Directed]  # the neighbour components (empty for "own")
    weights: Tensor  # (V, 1 + max_in) mixture weight of each component


@dataclass
class _Plan:
    """Everything :func:`particle_bp` derives from its arguments once, before iterating.

    Attributes:
        bp_edges: each group's edges as BP stores them: value-reading groups permuted into
            the order tree BP visits them (every level's edges a run: views, not copies).
        bp_order: the permutation of each such group (``slice(None)`` where unchanged).
        schedule: the tree schedule over ``bp_edges``, or ``None`` on a graph with cycles.
        chunks, proposal_chunks: frame slices processed together (pgm.tuning's budgets).
    """

    graph: ParticleGraph
    semiring: Semiring
    proposal: _Proposal
    batch: int
    num_particles: int
    iterations: int
    restarts: int
    bp_edges: list[Tensor]
    bp_order: list[EdgeIndex]
    schedule: TreeSchedule | None
    chunks: list[slice]
    proposal_chunks: list[slice]
    loopy_iterations: int
    loopy_damping: float

    def steps(self) -> Iterator[AnnealingStep]:
        for restart in range(self.restarts):
            for it in range(self.iterations):
                yield AnnealingStep(iteration=it, restart=restart)


def particle_bp(
    graph: ParticleGraph,
    initial: Tensor,
    *,
    iterations: int = 6,
    restarts: int = 1,
    generator: torch.Generator | None = None,
    semiring: Semiring | None = None,
    proposal: str | None = None,
    self_weight: float = 0.5,
    proposal_centres: int | None = None,
    kernel_scale: float | Sequence | dict | None = None,
    kernel_schedule: Schedule | None = None,
    initial_log_density: Tensor | None = None,
    loopy_iterations: int = 30,
    loopy_damping: float = 0.0,
    batch_chunk: int | None = None,
    callback: Callable[[IterationStats], None] | None = None,
) -> ParticleResult:
    """Run particle belief propagation.

    Args:
        graph: a :class:`ParticleGraph`.
        initial: ``(B, V, K, D)`` initial particles (values of discrete nodes are ignored);
            ``D`` is the widest space's width; narrower spaces use the leading columns.
        iterations: weighting passes per restart (the first restart's first pass weights the
            initial particles; every other pass resamples first).
        restarts: how often the iteration sequence (and its annealing schedules) is run.
        generator: source of every random draw.
        semiring: :class:`~pgm.semiring.LogSemiring` (default, marginals) or
            :class:`~pgm.semiring.MaxSemiring` (particle max-product).
        proposal: ``"mixture"`` (own marginal and neighbours' pushed through ``psi``) or
            ``"own"`` (own marginal only, BPMC-style); default: the graph's.
        self_weight: mixture weight of the own-marginal component (``"mixture"`` only).
        proposal_centres: ``None`` (default): each component is a kernel mixture over all K
            particles weighted by their marginal; ``M``: over M particles resampled from it
            (weights 1/M) -- still an exact proposal density, at M / K of the cost.
        kernel_scale: perturbation kernel scale (see each space; SE3 takes ``(metres,
            radians)``): one scale for every continuous group (a float, tuple or tensor), a
            *list* in the order of ``graph.spaces`` (``None`` for discrete groups), or
            ``{group index: scale}``; required when the graph has continuous nodes.
        kernel_schedule: multiplier of ``kernel_scale`` per iteration (default constant 1).
        initial_log_density: ``(B, V, K)`` log density the initial particles were drawn
            from (default: uniform, i.e. the initial particles are taken as a grid).
        loopy_iterations, loopy_damping: inner loopy-BP settings when the graph has cycles.
        batch_chunk: frames processed together in the proposal and BP steps (default: the
            budgets of :mod:`pgm.tuning` for the particles' device); results do not depend
            on it except through the order of random draws.
        callback: called with each iteration's :class:`IterationStats`.

    Returns:
        :class:`ParticleResult`.

    Raises:
        ValueError / GraphError: mismatched dimensions, non-finite particles or weights, an
            observation factor returning the wrong shape or NaN, a bad option.
    """
    plan = _compile(
        graph,
        initial,
        iterations=iterations,
        restarts=restarts,
        semiring=semiring or LogSemiring(),
        proposal=graph.proposal if proposal is None else proposal,
        self_weight=self_weight,
        proposal_centres=proposal_centres,
        kernel_scale=kernel_scale,
        kernel_schedule=kernel_schedule or Constant(),
        loopy_iterations=loopy_iterations,
        loopy_damping=loopy_damping,
        batch_chunk=batch_chunk,
    )
    values, log_q = _initial_supports(graph, initial, initial_log_density)
    k = plan.num_particles
    log_w = torch.full_like(log_q, -math.log(k)).masked_fill(torch.isinf(log_q), -math.inf)
    workspaces: dict = {}  # table buffers, reused by every iteration and chunk
    mean = best = None
    history: list[IterationStats] = []
    for n, step in enumerate(plan.steps()):
        pairwise = [factor.annealed(step) for _, factor in graph.pairwise]
        if n > 0:
            values, log_q = _propose(plan, pairwise, values, log_w, step, generator)
        # the observation contract (UnaryFactor): the starting mean first, then the best
        estimates = best if best is not None else _estimate(graph, values, log_w)[0]
        unary = _unary(graph, step, values, estimates)
        log_marginals, change = _weigh(plan, pairwise, values, unary, log_q, workspaces)
        log_w = _normalised(log_marginals)
        new_mean, best = _estimate(graph, values, log_w)
        est_change = math.nan if mean is None else _max_change(graph, mean, new_mean)
        mean = new_mean
        stats = IterationStats(
            step.restart, step.iteration, _ess(log_w), _stats_range(log_w), est_change, change
        )
        history.append(stats)
        if callback is not None:
            callback(stats)
    return ParticleResult(values, log_w, mean, best, history)


# -- compiling the plan ------------------------------------------------------------------------
def _compile(
    graph: ParticleGraph,
    initial: Tensor,
    *,
    iterations: int,
    restarts: int,
    semiring: Semiring,
    proposal: str,
    self_weight: float,
    proposal_centres: int | None,
    kernel_scale,
    kernel_schedule: Schedule,
    loopy_iterations: int,
    loopy_damping: float,
    batch_chunk: int | None,
) -> _Plan:
    """Validate the call and compile its wiring: proposal components, BP edge order and
    schedule, chunk policy."""
    if proposal not in PROPOSALS:
        raise ValueError(f"proposal must be 'mixture' or 'own'; got {proposal!r}")
    if proposal == "mixture" and graph.proposal != "mixture":
        check_samplable(graph)
    if not 0.0 <= self_weight <= 1.0:
        raise ValueError(f"self_weight must be in [0, 1]; got {self_weight}")
    if iterations < 1 or restarts < 1:
        raise ValueError(f"iterations and restarts must be >= 1; got {iterations}, {restarts}")
    if batch_chunk is not None and (not isinstance(batch_chunk, int) or batch_chunk < 1):
        raise ValueError(f"batch_chunk must be an int >= 1 or None; got {batch_chunk!r}")
    if not isinstance(initial, Tensor) or initial.dim() != 4:
        shape = tuple(initial.shape) if isinstance(initial, Tensor) else type(initial).__name__
        raise ValueError(f"initial must have shape (B, V, K, D); got {shape}")
    b, v, k, d = initial.shape
    if v != graph.num_nodes or d != graph.max_dim:
        raise ValueError(
            f"initial must have shape (B, {graph.num_nodes}, K, {graph.max_dim}); got {tuple(initial.shape)}"
        )
    if graph.discrete_states > k:
        raise ValueError(
            f"K = {k} particles is fewer than the {graph.discrete_states} states of a discrete "
            "node; use K >= the largest discrete state count"
        )
    bp_edges, bp_order, schedule = _bp_wiring(graph)
    budget = budget_for(initial.device)
    table_bytes = max(1, sum(len(e) for e, _ in graph.pairwise)) * k * k * initial.element_size()
    return _Plan(
        graph=graph,
        semiring=semiring,
        proposal=_compile_proposal(
            graph, proposal, self_weight, proposal_centres, kernel_scale, kernel_schedule
        ),
        batch=b,
        num_particles=k,
        iterations=iterations,
        restarts=restarts,
        bp_edges=bp_edges,
        bp_order=bp_order,
        schedule=schedule,
        chunks=_chunks(b, batch_chunk or budget.bp_table_bytes // table_bytes),
        proposal_chunks=_chunks(b, batch_chunk or budget.proposal_particles // (v * k)),
        loopy_iterations=loopy_iterations,
        loopy_damping=loopy_damping,
    )


def _bp_wiring(graph: ParticleGraph) -> tuple[list[Tensor], list[EdgeIndex], TreeSchedule | None]:
    """On a tree, store each value-reading group's tables in the order BP visits its edges:
    every level's edges are then a run, and the message products read views instead of
    copies. Returns the edges as stored, the permutations, and the schedule over them."""
    try:
        original = tree_schedule(graph.groups, graph.num_nodes)
    except NotATreeError:
        return [e for e, _ in graph.pairwise], [slice(None)] * len(graph.pairwise), None
    edges, orders = [], []
    for g, (e, factor) in enumerate(graph.pairwise):
        visits = [op.local_edges for ops in original.ops for op in ops if op.group == g]
        if visits and Capability.READS_VALUES in factor.capabilities:
            order = torch.cat(visits)
            edges.append(e[order])
            orders.append(order)
        else:
            edges.append(e)
            orders.append(slice(None))
    groups = [PairwiseGroup(e, f) for e, (_, f) in zip(edges, graph.pairwise, strict=True)]
    return edges, orders, tree_schedule(groups, graph.num_nodes)


def _compile_proposal(
    graph: ParticleGraph,
    kind: str,
    self_weight: float,
    centres: int | None,
    kernel_scale,
    kernel_schedule: Schedule,
) -> _Proposal:
    """Mixture weights: component 0 is the node's own marginal (resampled and perturbed),
    components 1.. its neighbours' marginals pushed through the factors (``"mixture"``)."""
    _, max_in = graph.directed_edges()
    weights = torch.zeros(graph.num_nodes, 1 + max_in, dtype=torch.float64, device="cpu")
    weights[:, 0] = 1.0
    pushed = graph.proposing_directions() if kind == "mixture" else []
    if pushed:
        for de in pushed:
            weights[de.target, de.slot] = 1.0
        neighbours = weights[:, 1:].sum(-1)
        weights[:, 1:] = weights[:, 1:] * ((1 - self_weight) / neighbours.clamp_min(1))[:, None]
        weights[:, 0] = torch.where(neighbours > 0, self_weight, 1.0)
    return _Proposal(
        kind,
        self_weight,
        centres,
        _kernel_scales(graph, kernel_scale),
        kernel_schedule,
        pushed,
        weights,
    )


def _initial_supports(
    graph: ParticleGraph, initial: Tensor, initial_log_density: Tensor | None
) -> tuple[Tensor, Tensor]:
    """Continuous nodes start from ``initial``; discrete nodes hold their states (padding
    past their count has density +inf, i.e. measure -inf). Returns values and ``log q``."""
    b, v, k, _ = initial.shape
    dtype, device = initial.dtype, initial.device
    values = initial.clone()
    log_q = torch.zeros(b, v, k, dtype=dtype, device=device)
    if initial_log_density is not None:
        if initial_log_density.shape != (b, v, k):
            raise ValueError(
                f"initial_log_density must have shape ({b}, {v}, {k}); got {tuple(initial_log_density.shape)}"
            )
        if torch.isnan(initial_log_density).any() or torch.isposinf(initial_log_density).any():
            raise ValueError("initial_log_density contains NaN or +inf")
        log_q = initial_log_density.to(dtype).clone()
    for space, nodes in graph.spaces:
        if space.discrete:
            n = space.num_states
            values[:, nodes] = 0.0
            values[:, nodes, :n, :1] = space.support(dtype).to(device)
            log_q[:, nodes] = 0.0
            log_q[:, nodes, n:] = math.inf  # measure -inf: padding
        else:
            space.validate(initial[:, nodes][..., : space.dim], "initial particles")
    return values, log_q


def _chunks(size: int, largest: int) -> list[slice]:
    """``range(size)`` in equal-sized slices of at most ``largest`` (no small last one)."""
    largest = max(1, largest)
    step = -(-size // -(-size // largest))
    return [slice(s, min(s + step, size)) for s in range(0, size, step)]


def _kernel_scales(graph: ParticleGraph, kernel_scale) -> dict[int, object]:
    continuous = [g for g, (s, _) in enumerate(graph.spaces) if not s.discrete]
    if kernel_scale is None:
        if continuous:
            raise ValueError("kernel_scale is required for continuous spaces")
        return {}
    if isinstance(kernel_scale, dict):
        scales = dict(kernel_scale)
    elif isinstance(kernel_scale, (int, float, tuple, Tensor)):
        scales = dict.fromkeys(continuous, kernel_scale)
    else:
        if len(kernel_scale) != len(graph.spaces):
            raise ValueError(
                f"kernel_scale has {len(kernel_scale)} entries; the graph has {len(graph.spaces)} space groups"
            )
        scales = dict(enumerate(kernel_scale))
    missing = [g for g in continuous if scales.get(g) is None]
    if missing:
        raise ValueError(f"kernel_scale missing for space groups {missing}")
    return scales


def _scaled(scale, factor: float):
    if isinstance(scale, Tensor):
        return scale * factor
    return torch.as_tensor(scale, device="cpu") * factor  # numbers: a host constant


# -- step 1: proposal --------------------------------------------------------------------------
def _propose(
    plan: _Plan,
    pairwise: list[PairwiseFactor],
    values: Tensor,
    log_w: Tensor,
    step: AnnealingStep,
    generator: torch.Generator | None,
) -> tuple[Tensor, Tensor]:
    """New particles of every continuous node and their proposal log density, in frame
    chunks (frames are independent here; the chunks bound the proposal's memory)."""
    kernel_mult = plan.proposal.kernel_schedule(step.iteration)
    parts = [
        _propose_chunk(plan, pairwise, values[c], log_w[c], kernel_mult, generator)
        for c in plan.proposal_chunks
    ]
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


def _resample_index(log_w: Tensor, count: int, generator) -> Tensor:
    """``count`` indices per row drawn from ``softmax(log_w)`` by inverting each row's CDF
    (``searchsorted``: half the time of ``torch.multinomial`` here). Shapes: (..., K) ->
    (..., count)."""
    k = log_w.shape[-1]
    cdf = torch.softmax(log_w.reshape(-1, k), -1).cumsum_(-1)
    u = torch.rand(cdf.shape[0], count, generator=generator, dtype=cdf.dtype, device=cdf.device)
    idx = torch.searchsorted(cdf, u.mul_(cdf[:, -1:])).clamp_(max=k - 1)
    return idx.reshape(*log_w.shape[:-1], count)


def _gather_particles(x: Tensor, idx: Tensor) -> Tensor:
    """x (..., K, D), idx (..., M) -> (..., M, D)."""
    return x.gather(-2, idx.unsqueeze(-1).expand(*idx.shape, x.shape[-1]))


@dataclass
class _Centres:
    """Kernel centres of one proposal component and their log weights ``(..., M, D)``,
    ``(..., M)``; ``uniform`` when they are M resampled particles of weight 1/M."""

    x: Tensor
    log_w: Tensor
    uniform: bool

    @classmethod
    def of(cls, x: Tensor, log_w: Tensor, count: int | None, generator) -> _Centres:
        """Every particle weighted by its marginal, or (``count`` = M < K) M particles
        resampled from it, 1/M each -- a valid proposal whose exact density costs M / K as
        much to evaluate."""
        if count is None or count >= x.shape[-2]:
            return cls(x, log_w, False)
        idx = _resample_index(log_w, count, generator)
        flat = torch.full(idx.shape, -math.log(count), dtype=x.dtype, device=x.device)
        return cls(_gather_particles(x, idx), flat, True)

    def draw(self, mask: Tensor, k: int, generator) -> tuple[Tensor, ...]:
        """Centres resampled for the slots in ``mask`` (B, R, K): their (b, r, k) positions
        and values (n, D)."""
        bi, ri, ki = mask.nonzero(as_tuple=True)
        if self.uniform:  # equal weights: a uniform index for each slot that needs one
            pick = torch.randint(
                self.x.shape[-2], bi.shape, generator=generator, device=self.x.device
            )
        else:
            pick = _resample_index(self.log_w, k, generator)[bi, ri, ki]
        return bi, ri, ki, self.x[bi, ri, pick]


def _propose_chunk(
    plan: _Plan,
    pairwise: list[PairwiseFactor],
    values: Tensor,
    log_w: Tensor,
    kernel_mult: float,
    generator: torch.Generator | None,
) -> tuple[Tensor, Tensor]:
    """New particles for every continuous node and their mixture log density ``log q``.

    Each new particle's mixture component is drawn first and only that component is
    sampled (K draws per node, not K per component)."""
    graph, spec = plan.graph, plan.proposal
    b, v, k, _ = values.shape
    device = values.device
    continuous = graph.continuous.to(device)
    weights = spec.weights.to(values)
    comp = torch.multinomial(
        weights.double().clamp_min(0), b * k, replacement=True, generator=generator
    )
    comp = comp.reshape(v, b, k).permute(1, 0, 2)  # (B, V, K)

    new = values.clone()
    own = {}
    for g, (space, nodes) in enumerate(graph.spaces):
        if space.discrete:
            continue
        centres = _Centres.of(
            values[:, nodes][..., : space.dim], log_w[:, nodes], spec.centres, generator
        )
        own[g] = centres
        bi, ni, ki, picked = centres.draw(comp[:, nodes] == 0, k, generator)
        moved = space.perturb(picked, _scaled(spec.scales[g], kernel_mult), generator)
        new[bi, nodes.to(device)[ni], ki, : space.dim] = moved
    pushed = []
    for de in spec.pushed:
        factor = pairwise[de.group]
        centres = _Centres.of(values[:, de.source], log_w[:, de.source], spec.centres, generator)
        pushed.append((de, centres))
        target = de.target.to(device)
        drawn_here = comp[:, target] == de.slot.to(device)[None, :, None]
        bi, ei, ki, x_src = centres.draw(
            drawn_here & continuous[target][None, :, None], k, generator
        )
        if len(bi) == 0:
            continue
        # one flat batch of (source particle, its edge) pairs: E = n, M = 1
        sample = factor.sample_target(x_src[None, :, None], ei, de.forward, generator)[0, :, 0]
        new[bi, target[ei], ki, : sample.shape[-1]] = sample

    # Mixture density of every new particle under every component.
    comp_logq = values.new_full((b, v, weights.shape[1], k), -math.inf)
    for g, centres in own.items():
        space, nodes = graph.spaces[g]
        comp_logq[:, nodes, 0] = space.log_kernel_mixture(  # (B, N, K)
            new[:, nodes][..., : space.dim],
            centres.x,
            centres.log_w,
            _scaled(spec.scales[g], kernel_mult),
        )
    for de, centres in pushed:
        comp_logq[:, de.target, de.slot] = pairwise[de.group].log_target_mixture(
            new[:, de.target], centres.x, centres.log_w, slice(None), de.forward
        )
    log_weights = torch.log(weights)[None, :, :, None]  # (1, V, C, 1)
    log_q = torch.logsumexp(comp_logq + log_weights, dim=2)
    old_log_q_discrete = torch.where(torch.isinf(log_w), math.inf, 0.0)
    log_q = torch.where(continuous[None, :, None], log_q, old_log_q_discrete)
    return new, log_q


# -- step 2: observations ----------------------------------------------------------------------
def _unary(graph: ParticleGraph, step: AnnealingStep, values: Tensor, estimates: Tensor) -> Tensor:
    """Sum of every observation factor at this step, ``(B, V, K)``, shape- and NaN-checked."""
    b, v, k, _ = values.shape
    total = torch.zeros(b, v, k, dtype=values.dtype, device=values.device)
    for ui, (nodes, factor) in enumerate(graph.unary):
        out = factor.annealed(step).log_potential(values[:, nodes], nodes, estimates)
        expected = (b, len(nodes), k)
        if not isinstance(out, Tensor) or tuple(out.shape) != expected:
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"unary[{ui}] {type(factor).__name__}.log_potential returned {got}; expected {expected}"
            )
        if torch.isnan(out).any() or torch.isposinf(out).any():
            raise ValueError(
                f"unary[{ui}] {type(factor).__name__}.log_potential returned NaN or +inf"
            )
        total.index_add_(1, nodes.to(total.device), out.to(total.dtype))
    return total


# -- steps 3 and 4: tables, messages, marginals ------------------------------------------------
def _weigh(
    plan: _Plan,
    pairwise: list[PairwiseFactor],
    values: Tensor,
    unary: Tensor,
    log_q: Tensor,
    workspaces: dict,
) -> tuple[Tensor, float | None]:
    """Exact BP on the particle-discretised graph, in frame chunks: unnormalised log
    marginals ``(B, V, K)`` and loopy BP's last message change (``None`` on a tree)."""
    semiring = plan.semiring
    # Max-product (particle max-product) maximises the potentials over the particle
    # locations: the sampling density is no part of the objective, only the support.
    if semiring.selects:
        measure = torch.where(torch.isinf(log_q), -math.inf, 0.0).to(log_q.dtype)
    else:
        measure = -log_q
    marginals, change = [], None
    for c in plan.chunks:
        groups = _tables(plan, pairwise, values[c], workspaces)
        fg = FactorGraph(unary[c], groups, log_measure=measure[c], schedule=plan.schedule)
        if plan.schedule is not None:
            result = tree_inference(fg, semiring)
        else:
            result = loopy_bp(
                fg,
                semiring,
                max_iters=plan.loopy_iterations,
                damping=plan.loopy_damping,
                tol=1e-6,
            )
            change = max(change or 0.0, result.message_change[-1])
        marginals.append(result.log_marginals)
    return torch.cat(marginals), change


def _tables(
    plan: _Plan, pairwise: list[PairwiseFactor], values: Tensor, workspaces: dict
) -> list[tuple[Tensor, PairwiseFactor]]:
    """BP's factor groups for one chunk of frames. Value-reading factors become dense
    tables, evaluated once (tree BP would otherwise evaluate each table twice, loopy BP once
    per inner iteration) into reusable buffers where the factor can write them; factors
    over state indices are used as they are, padded to the K-row supports."""
    k = plan.num_particles
    groups = []
    for g, factor in enumerate(pairwise):
        edges = plan.bp_edges[g]
        if Capability.READS_VALUES not in factor.capabilities:
            if factor.num_states is not None and factor.num_states < k:
                factor = _Padded(factor, k)
            groups.append((edges, factor))
            continue
        xa, xb = values[:, edges[:, 0]], values[:, edges[:, 1]]
        size = values.shape[0] * len(edges) * k * k
        if Capability.BUFFERED in factor.capabilities:
            out = _buffer(workspaces, ("log", g), size, values)
            table = factor.log_potential_into(plan.bp_order[g], xa, xb, k, out)
        else:
            table = factor.log_potential(plan.bp_order[g], xa, xb, k)
        total = float(table.sum())  # one pass: NaN or +inf show in it, and -inf
        if math.isnan(total) or total == math.inf:
            raise ValueError(
                f"pairwise[{g}] {type(factor).__name__}.log_potential returned NaN or +inf"
            )
        bound = factor.log_potential_bound()
        linear = None if bound is None else _buffer(workspaces, ("linear", g), table.numel(), table)
        cached = TableFactor(
            table, validate=False, finite=math.isfinite(total), upper_bound=bound, workspace=linear
        )
        groups.append((edges, cached))
    return groups


class _Padded(FactorWrapper):
    """A factor over ``S`` states on supports of ``K > S`` rows (a discrete node padded to
    the particle count; its padding has measure -inf, so it carries no mass)."""

    def __init__(self, base: PairwiseFactor, num_states: int):
        super().__init__(base)
        self.size, self.num_states, self.num_edges = base.num_states, num_states, base.num_edges

    def rewrap(self, base):
        return _Padded(base, self.num_states)

    def _pad(self, x: Tensor, value: float, dims: int) -> Tensor:
        pad = [0, self.num_states - self.size] * dims
        return torch.nn.functional.pad(x, pad, value=value)

    def log_potential(self, edges, xa, xb, num_states):
        table = self.base.log_potential(edges, xa, xb, self.size)
        return self._pad(table, -math.inf, 2)

    def message(self, h, edges, forward, semiring, xa=None, xb=None):
        out = self.base.message(h[..., : self.size], edges, forward, semiring, xa, xb)
        return self._pad(out, semiring.zero, 1)

    def source_given_target(self, target_state, edges, forward, num_states, xa=None, xb=None):
        out = self.base.source_given_target(
            target_state.clamp(max=self.size - 1), edges, forward, self.size, xa, xb
        )
        return self._pad(out, -math.inf, 1)

    def backtrack(self, h, target_state, edges, forward, xa=None, xb=None):
        return self.base.backtrack(h[..., : self.size], target_state, edges, forward, xa, xb)


def _buffer(workspaces: dict, key: tuple, numel: int, like: Tensor) -> Tensor:
    """A flat buffer of ``numel`` elements of ``like``'s dtype and device, allocated on the
    first request for that key and size only."""
    key = (*key, numel, like.dtype, like.device)
    if key not in workspaces:
        workspaces[key] = torch.empty(numel, dtype=like.dtype, device=like.device)
    return workspaces[key]


def _normalised(log_marginals: Tensor) -> Tensor:
    """Normalised log weights, with the place named where every particle lost its weight."""
    log_w = torch.log_softmax(log_marginals, -1)
    if torch.isnan(log_w).any():
        bad = torch.isnan(log_w).any(-1).nonzero()[0].tolist()
        raise ValueError(
            f"particle weights became NaN at batch {bad[0]}, node {bad[1]} (every "
            "particle has zero potential: widen the kernels or the potentials)"
        )
    return log_w


# -- estimates and diagnostics -----------------------------------------------------------------
def _estimate(graph: ParticleGraph, values: Tensor, log_w: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted mean on each node's manifold and the highest-weight particle, ``(B, V, D)``."""
    mean = torch.zeros(
        values.shape[0], values.shape[1], values.shape[3], dtype=values.dtype, device=values.device
    )
    idx = log_w.argmax(-1)  # (B, V)
    best = values.gather(2, idx[:, :, None, None].expand(-1, -1, 1, values.shape[-1])).squeeze(2)
    for space, nodes in graph.spaces:
        x = values[:, nodes][..., : space.dim]
        mean[:, nodes, : space.dim] = space.weighted_mean(x, log_w[:, nodes])
    return mean, best


def _max_change(graph: ParticleGraph, old: Tensor, new: Tensor) -> float:
    worst = 0.0
    for space, nodes in graph.spaces:
        dist = space.distance(old[:, nodes][..., : space.dim], new[:, nodes][..., : space.dim])
        worst = max(worst, float(dist.max()))
    return worst


def _ess(log_w: Tensor) -> Tensor:
    return 1.0 / log_w.exp().square().sum(-1)


def _stats_range(log_w: Tensor) -> Tensor:
    finite = torch.isfinite(log_w)
    hi = torch.where(finite, log_w, -math.inf).amax(-1)
    lo = torch.where(finite, log_w, math.inf).amin(-1)
    return hi - lo
