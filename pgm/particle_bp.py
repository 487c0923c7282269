"""Particle belief propagation (the proposal's Eqs. 28-35) on the exact engine.

With its particles fixed, a continuous node is a discrete node whose support is its K
particles with log-measure ``-log q(s)``; a pairwise factor evaluated on two particle sets is
a ``(B, E, K, K)`` table. One iteration of particle BP is therefore:

1. **Proposal** (iterations after the first): for every continuous node j, K new particles
   from a mixture of its own previous marginal (resample, then perturb with the state
   space's kernel) and each neighbour's marginal pushed through ``psi_ij`` (resample
   ``x_i``, then ``x_j ~ psi_ij(x_i, .)``); ``q_j(s)``, the mixture's density at each new
   particle, is kept. ``proposal="own"`` uses the node's own marginal only (BPMC-style).
2. **Messages** (Eq. 33) and **marginals** (Eq. 35): exact BP on the particle-discretised
   graph -- :func:`pgm.tree.tree_inference` on a tree, :func:`pgm.loopy.loopy_bp` otherwise --
   with ``unary = log phi_j(s_j, X_-j, z_j)`` and ``log_measure = -log q_j(s_j)`` (0 under
   max-product, which maximises over particle locations and must not favour rare ones). Messages
   into a node exclude the target's own message (prefix/suffix products), which is Eq. 33's
   division by ``omega_ji``; the marginal is ``phi * prod omega / q``, normalised.
3. **Estimates**: weighted mean on the manifold and the best particle per node.

Sum-product or max-product (particle max-product) is the semiring's choice. Pairwise
factors anneal through their :class:`~pgm.schedules.Schedule`; ``restarts`` repeats the whole
iteration sequence from the current particles (the proposal runs 6 iterations twice).

Shapes: ``B`` batch, ``V`` nodes, ``K`` particles (discrete nodes: states, padded to K),
``D`` the widest state. Every random draw uses the given ``torch.Generator``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from pgm.continuous import ContinuousPairwise, UnaryFactor
from pgm.factors import PairwiseFactor, TableFactor
from pgm.graph import FactorGraph, GraphError, NotATreeError
from pgm.loopy import loopy_bp
from pgm.schedules import Constant, Schedule
from pgm.semiring import LogSemiring, Semiring
from pgm.spaces import StateSpace
from pgm.tree import tree_inference

__all__ = ["IterationStats", "ParticleGraph", "ParticleResult", "particle_bp"]


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

    Args:
        num_nodes: V.
        spaces: ``[(space, nodes), ...]`` -- every node in exactly one group.
        pairwise: ``[(edges (E, 2), factor), ...]`` as in :class:`~pgm.graph.FactorGraph`.
        unary: ``[(nodes (N,), factor), ...]`` observation factors (a node may have several).
    """

    def __init__(
        self,
        num_nodes: int,
        spaces: Sequence[tuple[StateSpace, Tensor]],
        pairwise: Sequence[tuple[Tensor, PairwiseFactor]] = (),
        unary: Sequence[tuple[Tensor, UnaryFactor]] = (),
    ):
        if not isinstance(num_nodes, int) or num_nodes < 1:
            raise GraphError(f"num_nodes must be an int >= 1; got {num_nodes!r}")
        self.num_nodes = num_nodes
        owner = torch.full((num_nodes,), -1, dtype=torch.long)
        self.spaces: list[tuple[StateSpace, Tensor]] = []
        for gi, (space, nodes) in enumerate(spaces):
            if not isinstance(space, StateSpace):
                raise GraphError(f"spaces[{gi}] must pair a StateSpace with nodes; got {space!r}")
            nodes = torch.as_tensor(nodes, dtype=torch.long).reshape(-1)
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
        self.pairwise = list(pairwise)
        self.unary = []
        for ui, (nodes, factor) in enumerate(unary):
            nodes = torch.as_tensor(nodes, dtype=torch.long).reshape(-1)
            if nodes.numel() and (nodes.min() < 0 or nodes.max() >= num_nodes):
                raise GraphError(f"unary[{ui}] names nodes outside [0, {num_nodes})")
            if not isinstance(factor, UnaryFactor):
                raise GraphError(
                    f"unary[{ui}] factor must be a UnaryFactor; got {type(factor).__name__}"
                )
            self.unary.append((nodes, factor))
        self.max_dim = max(space.dim for space, _ in self.spaces)
        self.discrete_states = max(
            [getattr(s, "num_states", 0) for s, _ in self.spaces if s.discrete] + [0]
        )
        # Validate the wiring once (shapes, ranges, factor edge counts).
        FactorGraph(torch.zeros(1, num_nodes, 1), self.pairwise)

    def directed_edges(self) -> tuple[list[_Directed], int]:
        """Every factor group in both directions, with the slot each edge takes among its
        target's proposal components (slot 0 is the node's own marginal)."""
        count = [0] * self.num_nodes
        out = []
        for g, (edges, _factor) in enumerate(self.pairwise):
            edges = torch.as_tensor(edges).long()
            for forward in (True, False):
                src, dst = (edges[:, 0], edges[:, 1]) if forward else (edges[:, 1], edges[:, 0])
                slots = []
                for t in dst.tolist():
                    count[t] += 1
                    slots.append(count[t])
                out.append(_Directed(g, forward, src, dst, torch.tensor(slots, dtype=torch.long)))
        return out, max([*count, 0])


def _stats_range(log_w: Tensor) -> Tensor:
    finite = torch.isfinite(log_w)
    hi = torch.where(finite, log_w, -math.inf).amax(-1)
    lo = torch.where(finite, log_w, math.inf).amin(-1)
    return hi - lo


def particle_bp(
    graph: ParticleGraph,
    initial: Tensor,
    *,
    iterations: int = 6,
    restarts: int = 1,
    generator: torch.Generator | None = None,
    semiring: Semiring | None = None,
    proposal: str = "mixture",
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
            ``"own"`` (own marginal only, BPMC-style).
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
        batch_chunk: frames processed together in the proposal and BP steps (default: as
            many as keep ~48 MB of pairwise tables in BP and up to 2^20 particles in the
            proposal on a CPU, 1 GB and 2^24 elsewhere); results do not depend on it except
            through the order of random draws.
        callback: called with each iteration's :class:`IterationStats`.

    Returns:
        :class:`ParticleResult`.

    Raises:
        ValueError / GraphError: mismatched dimensions, non-finite particles or weights, an
            observation factor returning the wrong shape or NaN, a bad option.
    """
    semiring = semiring or LogSemiring()
    if proposal not in ("mixture", "own"):
        raise ValueError(f"proposal must be 'mixture' or 'own'; got {proposal!r}")
    if not 0.0 <= self_weight <= 1.0:
        raise ValueError(f"self_weight must be in [0, 1]; got {self_weight}")
    if iterations < 1 or restarts < 1:
        raise ValueError(f"iterations and restarts must be >= 1; got {iterations}, {restarts}")
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
    scales = _kernel_scales(graph, kernel_scale)
    kernel_schedule = kernel_schedule or Constant()
    dtype, device = initial.dtype, initial.device

    # Supports: continuous nodes start from `initial`, discrete nodes hold their states.
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
    directed, max_in = graph.directed_edges()
    try:
        schedule = FactorGraph(torch.zeros(1, v, 1), graph.pairwise).tree_schedule
        is_tree = True
    except NotATreeError:
        is_tree = False
    # On a tree, store each group's tables in the order BP visits the edges: every level's
    # edges are then a run, and the message products read views instead of copies.
    orders = {}
    if is_tree:
        for g in range(len(graph.pairwise)):
            visits = [op.local_edges for ops in schedule.ops for op in ops if op.group == g]
            if visits:
                orders[g] = torch.cat(visits)

    if batch_chunk is not None and (not isinstance(batch_chunk, int) or batch_chunk < 1):
        raise ValueError(f"batch_chunk must be an int >= 1 or None; got {batch_chunk!r}")
    # Defaults measured on a 2-core CPU: BP takes ~48 MB of (E, K, K) tables per chunk (1 to
    # 3 chunks measured alike, 5 slower: per-op overhead against cache reuse); the proposal
    # is many small ops (its mixture densities are evaluated in cache-sized blocks), so it
    # takes up to 2^20 particles at once. A GPU has no such cache to keep to: chunks there
    # only bound memory (1 GB of tables, 2^24 particles).
    on_cpu = initial.device.type == "cpu"
    table_bytes = max(1, sum(len(e) for e, _ in graph.pairwise)) * k * k * initial.element_size()
    chunks = _chunks(b, batch_chunk or ((48 << 20) if on_cpu else (1 << 30)) // table_bytes)
    proposal_chunks = _chunks(b, batch_chunk or ((1 << 20) if on_cpu else (1 << 24)) // (v * k))

    workspaces: dict = {}  # linear-space tables, reused by every iteration and chunk
    log_w = torch.full((b, v, k), -math.log(k), dtype=dtype, device=device)
    log_w = log_w.masked_fill(torch.isinf(log_q), -math.inf)
    mean = best = None
    history: list[IterationStats] = []
    first = True
    for restart in range(restarts):
        for it in range(iterations):
            for _, factor in graph.pairwise:
                factor.set_iteration(it)
            if not first:
                # Frames are independent here: chunks keep the (B, E, K, K) work in cache.
                parts = [
                    _propose(
                        graph,
                        values[c],
                        log_w[c],
                        directed,
                        max_in,
                        scales,
                        kernel_schedule(it),
                        proposal,
                        self_weight,
                        proposal_centres,
                        generator,
                    )
                    for c in proposal_chunks
                ]
                values = torch.cat([p[0] for p in parts])
                log_q = torch.cat([p[1] for p in parts])
            first = False
            estimates = best if best is not None else _estimate(graph, values, log_w)[0]
            unary = _unary(graph, values, estimates)
            # Max-product (particle max-product) maximises the potentials over the particle
            # locations: the sampling density is no part of the objective, only the support.
            measure = (
                -log_q if not semiring.selects else torch.where(torch.isinf(log_q), -math.inf, 0.0)
            ).to(dtype)
            marginals, change = [], None
            for c in chunks:
                groups = _cached_tables(graph, values[c], k, orders, workspaces)
                # Cached tables carry everything; other factors may read the particles.
                needs_values = any(not isinstance(f, TableFactor) for _, f in groups)
                fg = FactorGraph(
                    unary[c],
                    groups,
                    log_measure=measure[c],
                    values=values[c] if needs_values else None,
                )
                if is_tree:
                    result = tree_inference(fg, semiring)
                else:
                    result = loopy_bp(
                        fg, semiring, max_iters=loopy_iterations, damping=loopy_damping, tol=1e-6
                    )
                    change = max(change or 0.0, result.message_change[-1])
                marginals.append(result.log_marginals)
            result.log_marginals = torch.cat(marginals)
            log_w = torch.log_softmax(result.log_marginals, -1)
            if torch.isnan(log_w).any():
                bad = torch.isnan(log_w).any(-1).nonzero()[0].tolist()
                raise ValueError(
                    f"particle weights became NaN at batch {bad[0]}, node {bad[1]} (every "
                    "particle has zero potential: widen the kernels or the potentials)"
                )
            new_mean, new_best = _estimate(graph, values, log_w)
            est_change = math.nan if mean is None else _max_change(graph, mean, new_mean)
            mean, best = new_mean, new_best
            stats = IterationStats(
                restart,
                it,
                1.0 / log_w.exp().square().sum(-1),
                _stats_range(log_w),
                est_change,
                change,
            )
            history.append(stats)
            if callback is not None:
                callback(stats)
    return ParticleResult(values, log_w, mean, best, history)


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
    return torch.as_tensor(scale) * factor


def _cached_tables(
    graph: ParticleGraph,
    values: Tensor,
    k: int,
    orders: dict[int, Tensor] | None = None,
    workspaces: dict | None = None,
) -> list:
    """Dense factors evaluated once per iteration: tree BP would otherwise evaluate each
    table twice (upward and downward), loopy BP once per inner iteration. ``orders[g]``:
    a permutation of group g's edges to store them in (the marginals do not depend on it).
    ``workspaces``: reusable buffers for the tables' linear-space copies, keyed by group and
    shape, kept by the caller across iterations."""
    groups = []
    for g, (edges, factor) in enumerate(graph.pairwise):
        if isinstance(factor, ContinuousPairwise) or isinstance(
            getattr(factor, "base", None), ContinuousPairwise
        ):
            e = torch.as_tensor(edges).long()
            which = slice(None)
            if orders and g in orders:
                which = orders[g]
                e = e[which]
            xa, xb = values[:, e[:, 0]], values[:, e[:, 1]]
            if workspaces is not None and isinstance(factor, ContinuousPairwise):
                size = values.shape[0] * len(e) * k * k
                table = factor.log_potential_into(
                    which, xa, xb, k, _buffer(workspaces, ("log", g), size, values)
                )
            else:
                table = factor.log_potential(which, xa, xb, k)
            total = float(table.sum())  # one pass: NaN or +inf show in it, and -inf
            if math.isnan(total) or total == math.inf:
                raise ValueError(
                    f"pairwise[{g}] {type(factor).__name__}.log_potential returned NaN or +inf"
                )
            bound = factor.log_potential_bound() if hasattr(factor, "log_potential_bound") else None
            ws = None
            if workspaces is not None and bound is not None:
                ws = _buffer(workspaces, ("linear", g), table.numel(), table)
            groups.append(
                (
                    e,
                    TableFactor(
                        table,
                        validate=False,
                        finite=math.isfinite(total),
                        upper_bound=bound,
                        workspace=ws,
                    ),
                )
            )
        else:
            groups.append((edges, factor))
    return groups


def _buffer(workspaces: dict, key: tuple, numel: int, like: Tensor) -> Tensor:
    """A flat buffer of ``numel`` elements of ``like``'s dtype and device, allocated on the
    first request for that key and size only."""
    key = (*key, numel, like.dtype, like.device)
    if key not in workspaces:
        workspaces[key] = torch.empty(numel, dtype=like.dtype, device=like.device)
    return workspaces[key]


def _unary(graph: ParticleGraph, values: Tensor, estimates: Tensor) -> Tensor:
    b, v, k, _ = values.shape
    total = torch.zeros(b, v, k, dtype=values.dtype, device=values.device)
    for ui, (nodes, factor) in enumerate(graph.unary):
        out = factor.log_potential(values[:, nodes], nodes, estimates)
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


def _estimate(graph: ParticleGraph, values: Tensor, log_w: Tensor) -> tuple[Tensor, Tensor]:
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


def _propose(
    graph,
    values,
    log_w,
    directed,
    max_in,
    scales,
    kernel_mult,
    proposal,
    self_weight,
    proposal_centres,
    generator,
):
    """New particles for every continuous node and their mixture log density ``log q``.

    Each new particle's mixture component is drawn first and only that component is
    sampled (K draws per node, not K per component)."""
    b, v, k, _ = values.shape
    ncomp = 1 + max_in
    comp_logq = values.new_full((b, v, ncomp, k), -math.inf)  # filled after sampling
    weights = values.new_zeros(v, ncomp)
    device = values.device
    continuous = torch.zeros(v, dtype=torch.bool, device=device)
    for space, nodes in graph.spaces:
        if not space.discrete:
            continuous[nodes] = True

    uniform = proposal_centres is not None and proposal_centres < k

    def centres(log_w_rows: Tensor, x_rows: Tensor) -> tuple[Tensor, Tensor]:
        """Kernel centres of a component and their log weights: every particle weighted by
        its marginal, or (with proposal_centres = M) M particles resampled from it, 1/M each
        -- a valid proposal whose exact density costs M / K as much to evaluate."""
        if not uniform:
            return x_rows, log_w_rows
        idx = _resample_index(log_w_rows, proposal_centres, generator)
        flat = torch.full(
            idx.shape, -math.log(proposal_centres), dtype=x_rows.dtype, device=x_rows.device
        )
        return _gather_particles(x_rows, idx), flat

    def chosen(c_x: Tensor, c_w: Tensor, mask: Tensor) -> tuple[Tensor, ...]:
        """Centres resampled for the slots in ``mask`` (B, R, K): their (b, r, k) positions
        and values (n, D)."""
        bi, ri, ki = mask.nonzero(as_tuple=True)
        if uniform:  # equal weights: a uniform index for each slot that needs one
            pick = torch.randint(c_x.shape[-2], bi.shape, generator=generator, device=c_x.device)
        else:
            pick = _resample_index(c_w, k, generator)[bi, ri, ki]
        return bi, ri, ki, c_x[bi, ri, pick]

    # Mixture weights: component 0 is the node's own marginal (resampled and perturbed),
    # components 1.. its neighbours' marginals pushed through psi.
    weights[:, 0] = 1.0
    usable = []
    if proposal == "mixture":
        for de in directed:
            factor = graph.pairwise[de.group][1]
            if getattr(factor, "can_sample", False) and continuous[de.target].any():
                weights[de.target, de.slot] = 1.0
                usable.append(de)
        has_nb = weights[:, 1:].sum(-1) > 0
        nb_count = weights[:, 1:].sum(-1).clamp_min(1)
        weights[:, 1:] = weights[:, 1:] * ((1 - self_weight) / nb_count)[:, None]
        weights[:, 0] = torch.where(
            has_nb, torch.full_like(weights[:, 0], self_weight), weights[:, 0]
        )
    comp = torch.multinomial(
        weights.double().clamp_min(0), b * k, replacement=True, generator=generator
    )
    comp = comp.reshape(v, b, k).permute(1, 0, 2)  # (B, V, K)

    new = values.clone()
    own = {}
    for g, (space, nodes) in enumerate(graph.spaces):
        if space.discrete:
            continue
        c_x, c_w = centres(log_w[:, nodes], values[:, nodes][..., : space.dim])
        own[g] = (c_x, c_w)
        bi, ni, ki, picked = chosen(c_x, c_w, comp[:, nodes] == 0)
        moved = space.perturb(picked, _scaled(scales[g], kernel_mult), generator)
        new[bi, nodes.to(device)[ni], ki, : space.dim] = moved
    pushed = []
    for de in usable:
        factor = graph.pairwise[de.group][1]
        c_x, c_w = centres(log_w[:, de.source], values[:, de.source])
        pushed.append((de, c_x, c_w))
        target = de.target.to(device)
        drawn_here = comp[:, target] == de.slot.to(device)[None, :, None]
        mask = drawn_here & continuous[target][None, :, None]
        bi, ei, ki, x_src = chosen(c_x, c_w, mask)
        if len(bi) == 0:
            continue
        # one flat batch of (source particle, its edge) pairs: E = n, M = 1
        sample = factor.sample_target(x_src[None, :, None], ei, de.forward, generator)[0, :, 0]
        new[bi, target[ei], ki, : sample.shape[-1]] = sample

    # Mixture density of every new particle under every component.
    for g, (space, nodes) in enumerate(graph.spaces):
        if space.discrete:
            continue
        c_x, c_w = own[g]
        comp_logq[:, nodes, 0] = space.log_kernel_mixture(  # (B, N, K)
            new[:, nodes][..., : space.dim], c_x, c_w, _scaled(scales[g], kernel_mult)
        )
    for de, c_x, c_w in pushed:
        factor = graph.pairwise[de.group][1]
        comp_logq[:, de.target, de.slot] = factor.log_target_mixture(
            new[:, de.target], c_x, c_w, slice(None), de.forward
        )
    log_weights = torch.log(weights.to(values.dtype))[None, :, :, None]  # (1, V, C, 1)
    log_q = torch.logsumexp(comp_logq + log_weights, dim=2)
    old_log_q_discrete = torch.where(torch.isinf(log_w), math.inf, 0.0)
    log_q = torch.where(continuous[None, :, None], log_q, old_log_q_discrete)
    return new, log_q
