"""Time alignment: video frame t' -> reference frame C(t'), monotone.

Two families, both on a cost matrix ``d (B, T', T)`` (lower is better, e.g. the proposal's
Eq. 24 stick-figure distance):

* :func:`chain_align` -- what registration uses. C is a chain of discrete nodes (one per video
  frame, states = reference frames) with monotone steps ``0 <= C(t'+1) - C(t') <= S``, solved
  exactly by max-product in :mod:`pgm` (O(T' T S), never a dense T x T table).
  :func:`soft_align` is the same chain under a tempered log semiring: a posterior over C(t').
  :func:`coarse_to_fine_align` solves long sequences from a cost *function* in near-linear time.
  :func:`tempo_align` adds a hidden, slowly changing tempo behind the steps (still exact) on
  a band of reference frames per video frame.
* :func:`dtw` -- the proposal's classic DTW (Eq. 26, steps (1,0), (0,1), (1,1), both ends
  fixed), kept for comparison, with its per-t' choice of the most similar reference frame.

Robustness (:func:`robust_cost`): truncating or saturating the cost bounds what a corrupted
stretch of video can cost, so it cannot pull the path off course elsewhere.

Units: frames (integer indices, 0-based) for C; costs in the caller's units.

Device: the dynamic programmes run on the CPU. A cost table on another device (a GPU's pair
fits) is copied to the CPU first -- a ``T' x W`` table, small beside what made it, and the
recursion is sequential in ``t'`` -- so C always comes back as a CPU tensor.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pgm import (
    BandedMonotoneFactor,
    BandedTempoFactor,
    InfeasibleError,
    MonotoneFactor,
    TemperedSemiring,
    chain_inference,
    chain_map,
)

__all__ = [
    "Alignment",
    "AlignmentError",
    "DTWResult",
    "SoftAlignment",
    "TempoPrior",
    "band_mask",
    "chain_align",
    "coarse_to_fine_align",
    "dtw",
    "robust_cost",
    "sequence_cost_fn",
    "slope_step_cost",
    "soft_align",
    "tempo_align",
]

CostFn = Callable[[Tensor, Tensor], Tensor]


class AlignmentError(ValueError):
    """Bad input to an alignment routine (shape, NaN, step size, empty sequence, infeasible)."""


@dataclass
class Alignment:
    """A hard alignment.

    Attributes:
        path: ``(B, T')`` long, C(t') for every video frame.
        cost: ``(B,)`` sum over t' of ``d(t', C(t'))`` (of the cost that was minimised).
    """

    path: Tensor
    cost: Tensor


@dataclass
class SoftAlignment:
    """Posterior over C(t') under ``p(C) ~ exp(-sum d / temperature)``.

    Attributes:
        posterior: ``(B, T', T)`` probabilities, rows sum to 1.
        expected: ``(B, T')`` posterior mean of C(t') (reference frames, float).
        std: ``(B, T')`` posterior standard deviation of C(t') (reference frames).
        log_partition: ``(B,)`` ``temperature * log Z``, minus the free energy (tends to
            ``-min E`` as the temperature tends to 0).
    """

    posterior: Tensor
    expected: Tensor
    std: Tensor
    log_partition: Tensor


@dataclass
class DTWResult:
    """Classic DTW output for one cost matrix.

    Attributes:
        path: ``(L, 2)`` long, the warping path (t', t) from (0, 0) to (T'-1, T-1).
        cost: accumulated cost D(T'-1, T-1) (Eq. 26), a float.
        choice: ``(T',)`` long, the proposal's C: for each t' the path's most similar t.
    """

    path: Tensor
    cost: float
    choice: Tensor


# -- validation --------------------------------------------------------------------------------
def _check_cost(cost: Tensor, name: str = "cost") -> Tensor:
    if not isinstance(cost, Tensor):
        raise AlignmentError(f"{name} must be a torch.Tensor, got {type(cost).__name__}")
    if cost.dim() == 2:
        cost = cost.unsqueeze(0)
    if cost.dim() != 3:
        raise AlignmentError(
            f"{name} must have shape (T', T) or (B, T', T); got {tuple(cost.shape)}"
        )
    if not cost.dtype.is_floating_point:
        raise AlignmentError(f"{name} must be a floating-point tensor; got {cost.dtype}")
    if cost.shape[0] == 0 or cost.shape[1] == 0 or cost.shape[2] == 0:
        raise AlignmentError(f"{name} must be non-empty; got shape {tuple(cost.shape)}")
    cost = cost.cpu()  # the DP runs on the host (see the module's docstring)
    total = cost.sum()  # one pass; only a NaN or an infinity somewhere needs a closer look
    if torch.isfinite(total):
        return cost
    nan = torch.isnan(cost)
    if nan.any():
        b, i, j = (int(x) for x in nan.nonzero()[0])
        raise AlignmentError(
            f"{name} contains NaN ({int(nan.sum())} entries; first at batch {b}, t'={i}, t={j})"
        )
    if torch.isneginf(cost).any():
        raise AlignmentError(f"{name} contains -inf; costs must be finite or +inf (forbidden)")
    return cost


def _check_step(max_step: int | None) -> None:
    if max_step is None:
        return
    if isinstance(max_step, bool) or not isinstance(max_step, int):
        raise AlignmentError(f"max_step (S) must be an int or None; got {max_step!r}")
    if max_step < 1:
        raise AlignmentError(f"max_step (S) must be >= 1; got {max_step}")


# -- cost shaping ------------------------------------------------------------------------------
def robust_cost(cost: Tensor, threshold: float | None = None, mode: str = "truncate") -> Tensor:
    """Bound the cost so that a corrupted stretch of input cannot dominate the alignment.

    Args:
        cost: ``(..., T', T)`` non-negative costs.
        threshold: the cost scale tau; default: twice the median over t' of each row's
            minimum cost (a pair worse than that is treated as an outlier).
        mode: ``"truncate"`` -> ``min(d, tau)``; ``"saturate"`` -> ``tau * (1 - exp(-d / tau))``
            (smooth, same limits).

    Returns:
        the robust cost, shape of ``cost``.
    """
    if threshold is None:
        row_min = cost.amin(-1)
        threshold_t = 2.0 * row_min.median(-1, keepdim=True).values.unsqueeze(-1)
        threshold_t = threshold_t.clamp_min(torch.finfo(cost.dtype).tiny)
    else:
        if not (threshold > 0 and math.isfinite(threshold)):
            raise AlignmentError(f"threshold must be a finite positive number; got {threshold}")
        threshold_t = torch.as_tensor(threshold, dtype=cost.dtype, device=cost.device)
    if mode == "truncate":
        return torch.minimum(cost, threshold_t)
    if mode == "saturate":
        return threshold_t * -torch.expm1(-cost / threshold_t)
    raise AlignmentError(f"mode must be 'truncate' or 'saturate'; got {mode!r}")


def slope_step_cost(max_step: int, slope: float, weight: float) -> Tensor:
    """Quadratic slope prior for :func:`chain_align`: ``weight * ((s - slope) / slope)^2``.

    A time warp that suddenly races ahead and then stalls (what a corrupted stretch of video
    invites) pays for every step away from the expected slope (e.g. the frame-rate ratio).

    Returns:
        ``(S + 1,)`` cost of each step size 0..S, in the units of ``weight``.
    """
    _check_step(max_step)
    if not (slope > 0 and math.isfinite(slope)):
        raise AlignmentError(f"slope must be a finite positive number; got {slope}")
    if weight < 0:
        raise AlignmentError(f"weight must be >= 0; got {weight}")
    steps = torch.arange(max_step + 1, dtype=torch.get_default_dtype(), device="cpu")
    return weight * ((steps - slope) / slope) ** 2


def band_mask(num_video: int, num_ref: int, radius: int) -> Tensor:
    """Sakoe-Chiba band around the straight line from (0, 0) to (T'-1, T-1).

    Returns:
        ``(T', T)`` bool, True inside ``|t - t' (T-1)/(T'-1)| <= radius``.
    """
    if radius < 0:
        raise AlignmentError(f"band radius must be >= 0; got {radius}")
    slope = (num_ref - 1) / max(num_video - 1, 1)
    centre = torch.arange(num_video, dtype=torch.float64) * slope
    t = torch.arange(num_ref, dtype=torch.float64)
    return (t[None, :] - centre[:, None]).abs() <= radius + 1e-9


def _unary(cost: Tensor, band: Tensor | None, fix_start: bool, fix_end: bool) -> Tensor:
    unary = -cost  # a fresh tensor: edited in place below and usable as a work buffer
    if band is not None:
        if band.shape != cost.shape[-2:]:
            raise AlignmentError(
                f"band must have shape {tuple(cost.shape[-2:])}; got {tuple(band.shape)}"
            )
        unary = unary.masked_fill(~band, -math.inf)
    if fix_start:
        unary[:, 0, 1:] = -math.inf
    if fix_end:
        unary[:, -1, :-1] = -math.inf
    return unary


def _step_factor(max_step: int | None, step_cost: Tensor | None) -> MonotoneFactor:
    if step_cost is None:
        return MonotoneFactor(max_step)
    if max_step is None:
        raise AlignmentError("step_cost needs a finite max_step")
    step_cost = torch.as_tensor(step_cost, dtype=torch.get_default_dtype(), device="cpu")
    if step_cost.shape != (max_step + 1,):
        raise AlignmentError(
            f"step_cost must have shape ({max_step + 1},) for max_step={max_step}; "
            f"got {tuple(step_cost.shape)}"
        )
    return MonotoneFactor(max_step, -step_cost)


# -- chain alignment ---------------------------------------------------------------------------
def chain_align(
    cost: Tensor,
    max_step: int | None,
    *,
    fix_start: bool = False,
    fix_end: bool = False,
    band: Tensor | None = None,
    step_cost: Tensor | None = None,
) -> Alignment:
    """Exact monotone alignment minimising ``sum_t' d(t', C(t'))`` (chain Viterbi).

    Args:
        cost: ``(B, T', T)`` or ``(T', T)``; ``+inf`` forbids a pair.
        max_step: S >= 1: ``0 <= C(t'+1) - C(t') <= S``; ``None`` for any non-negative step.
        fix_start: force C(0) = 0.
        fix_end: force C(T'-1) = T-1.
        band: optional ``(T', T)`` bool mask of allowed pairs (see :func:`band_mask`).
        step_cost: optional ``(S + 1,)`` cost added for each step size 0..S (a slope prior).

    Returns:
        :class:`Alignment` with ``path`` (B, T') and ``cost`` (B,) (excluding ``step_cost``).

    Raises:
        AlignmentError: bad shapes, NaN, S < 1, empty input, or no monotone path fits.
    """
    _check_step(max_step)
    cost = _check_cost(cost)
    unary = _unary(cost, band, fix_start, fix_end)
    factor = _step_factor(max_step, step_cost)
    try:
        # unary is our own tensor (made by _unary), so the fused kernel may work in it
        result = chain_map(unary, factor, overwrite=True)
    except InfeasibleError as err:
        raise AlignmentError(
            f"no monotone path with max_step={max_step} fits the constraints "
            f"(T'={cost.shape[1]}, T={cost.shape[2]}, fix_start={fix_start}, fix_end={fix_end})"
        ) from err
    path = result.assignment
    total = cost.gather(-1, path.unsqueeze(-1)).squeeze(-1).sum(-1)
    return Alignment(path, total)


@dataclass(frozen=True)
class TempoPrior:
    """A performer's tempo for :func:`tempo_align`: C(t') follows a phase ``phi`` that
    advances by the tempo ``v`` (reference frames per video frame) each frame, ``C =
    round(phi)``, and ``v`` drifts as a random walk. Rounding the phase, not each step,
    lets a tempo of 4.8 take steps of 5, 5, 5, 5, 4 at no cost.

    Attributes:
        slope: the expected tempo (e.g. the frame-rate ratio).
        slope_weight: nats per video frame of ``((v - slope) / slope)^2`` (the slope prior
            of :func:`slope_step_cost`, on the tempo).
        change_std: the random walk's standard deviation per video frame, relative to
            ``slope``.
        subdivisions: the phase's resolution, ``1 / subdivisions`` reference frame.
    """

    slope: float
    slope_weight: float
    change_std: float
    subdivisions: int = 4

    def __post_init__(self):
        for name in ("slope", "change_std"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise AlignmentError(f"{name} must be a finite positive number; got {value}")
        if not (self.slope_weight >= 0 and math.isfinite(self.slope_weight)):
            raise AlignmentError(
                f"slope_weight must be a finite number >= 0; got {self.slope_weight}"
            )
        m = self.subdivisions
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise AlignmentError(f"subdivisions must be an int >= 1; got {m!r}")

    def factor(self, max_step: int, offsets: Tensor) -> BandedTempoFactor:
        """The chain on the phase grid: positions ``offsets * m + [0, (W - 1) m]``, steps
        of ``0 .. S m`` grid units, one level per step (the tempo), each emitting its own
        step only."""
        m = self.subdivisions
        tempo = torch.arange(max_step * m + 1, dtype=torch.float64, device="cpu") / m
        level_cost = self.slope_weight * ((tempo - self.slope) / self.slope) ** 2
        emission = torch.full(
            (len(tempo), len(tempo)), -math.inf, dtype=torch.float64, device="cpu"
        )
        emission.diagonal().copy_(-level_cost)
        change = (tempo[:, None] - tempo[None, :]) / self.slope
        change = -(change**2) / (2 * self.change_std**2)
        dtype = torch.get_default_dtype()
        return BandedTempoFactor(max_step * m, offsets * m, emission.to(dtype), change.to(dtype))


def _phase_costs(cost: Tensor, m: int) -> Tensor:
    """``(T', W)`` costs at reference frames -> ``(T', (W - 1) m + 1)`` at the phase grid:
    each phase costs what its rounded frame does (what C will be)."""
    phase = torch.arange((cost.shape[1] - 1) * m + 1, device=cost.device)
    return cost[:, torch.div(phase + m // 2, m, rounding_mode="floor")]


def tempo_align(
    cost: Tensor, offsets: Tensor, max_step: int, prior: TempoPrior | None = None
) -> Alignment:
    """Exact monotone alignment on a band under a performer's slowly changing tempo.

    Minimises ``sum_t' d(t', C(t'))`` plus the :class:`TempoPrior`'s costs (the slope prior
    on the tempo, each change of tempo) jointly over monotone paths (each ``C(t')`` in its
    window ``offsets[t'] + [0, W)``, steps in ``[0, S]``) and tempo sequences: a first-order
    chain on (phase, tempo) states on a grid of ``1 / m`` reference frame, solved by
    max-product in :mod:`pgm` (:class:`pgm.BandedTempoFactor`; O(T' W S m^3)), each phase
    costing what its rounded frame does. A first-order chain chooses each step on its own,
    so where the costs hardly differ (the ends of a video, a body half out of view) the path
    stalls or races within the slope prior; the tempo carries the rate the rest of the
    video shows through them. The first frame's tempo is free.

    Args:
        cost: ``(T', W)`` costs of each video frame's window; ``+inf`` forbids a pair.
        offsets: ``(T',)`` non-decreasing long, each window's first reference frame.
        max_step: S >= 1.
        prior: :class:`TempoPrior`; ``None``: any step in ``[0, S]`` alike (the banded
            first-order chain).

    Returns:
        :class:`Alignment` with ``path`` (1, T') absolute reference frames (the phase
        rounded) and ``cost`` (1,) the sum of ``cost`` along it (excluding the prior).

    Raises:
        AlignmentError: bad shapes, NaN, S < 1, or no monotone path fits the windows.
    """
    _check_step(max_step)
    if max_step is None:
        raise AlignmentError("tempo_align needs a finite max_step")
    if isinstance(cost, Tensor) and cost.dim() != 2:
        raise AlignmentError(f"cost must be one (T', W) table; got shape {tuple(cost.shape)}")
    cost = _check_cost(cost)[0]
    n, w = cost.shape
    offsets = torch.as_tensor(offsets, device="cpu")
    if offsets.shape != (n,) or offsets.dtype.is_floating_point or (offsets.diff() < 0).any():
        raise AlignmentError(
            f"offsets must be ({n},) non-decreasing integers; got {tuple(offsets.shape)} "
            f"{offsets.dtype}"
        )
    if prior is None:  # no tempo: the plain banded chain
        m, levels, factor = 1, 1, BandedMonotoneFactor(max_step, offsets.long())
    else:
        m, factor = prior.subdivisions, prior.factor(max_step, offsets.long())
        levels = factor.num_levels
    # the default dtype: T' x W m x L lifted states (7,500 x 193 x 49 for a 5-minute video)
    phase_cost = _phase_costs(cost.to(torch.get_default_dtype()), m)
    unary = -phase_cost.repeat_interleave(levels, dim=-1).unsqueeze(0)
    try:
        result = chain_map(unary, factor)
    except InfeasibleError as err:
        raise AlignmentError(
            f"no monotone path with max_step={max_step} fits the windows (T'={n}, W={w})"
        ) from err
    phase = result.assignment[0] // levels
    index = torch.div(phase + m // 2, m, rounding_mode="floor").clamp(max=w - 1)
    total = cost.gather(-1, index[:, None]).sum()
    return Alignment((offsets + index).unsqueeze(0), total.reshape(1))


def soft_align(
    cost: Tensor,
    max_step: int | None,
    temperature: float = 1.0,
    *,
    fix_start: bool = False,
    fix_end: bool = False,
    band: Tensor | None = None,
    step_cost: Tensor | None = None,
) -> SoftAlignment:
    """Posterior over monotone alignments, ``p(C) ~ exp(-E(C) / temperature)`` (forward-backward).

    Same arguments as :func:`chain_align`, plus ``temperature`` > 0 in cost units; as it tends
    to 0 the posterior concentrates on the :func:`chain_align` path.
    """
    _check_step(max_step)
    cost = _check_cost(cost)
    unary = _unary(cost, band, fix_start, fix_end)
    semiring = TemperedSemiring(temperature)
    result = chain_inference(unary, _step_factor(max_step, step_cost), semiring)
    if not torch.isfinite(result.log_partition).all():
        raise AlignmentError(f"no monotone path with max_step={max_step} fits the constraints")
    posterior = result.log_marginals.exp()
    t = torch.arange(cost.shape[-1], dtype=posterior.dtype)
    mean = (posterior * t).sum(-1)
    var = (posterior * (t - mean.unsqueeze(-1)) ** 2).sum(-1)
    return SoftAlignment(posterior, mean, var.clamp_min(0).sqrt(), result.log_partition)


# -- classic DTW (the proposal's Eq. 26) -------------------------------------------------------
def dtw(cost: Tensor) -> DTWResult:
    """Classic DTW with steps (1, 0), (0, 1), (1, 1) and both ends fixed (proposal Eq. 26).

    ``D(t', t) = d(t', t) + min(D(t'-1, t-1), D(t'-1, t), D(t', t-1))``, ``D(0, 0) = d(0, 0)``.
    Each row is solved in closed form (``D[t] = c[t] + cummin_s (A[s] - c[s-1])`` with ``c``
    the row's cumulative cost), in float64.

    Args:
        cost: ``(T', T)`` finite costs.

    Returns:
        :class:`DTWResult`; ties in backtracking prefer the diagonal step, then (1, 0).
    """
    cost = _check_cost(cost)
    if cost.shape[0] != 1:
        raise AlignmentError(f"dtw takes one (T', T) cost matrix; got {tuple(cost.shape)}")
    if not torch.isfinite(cost.sum()):  # finite costs sum to a finite number
        raise AlignmentError("dtw needs finite costs (use chain_align for forbidden pairs)")
    # A sequential row recursion: NumPy's ufuncs have less per-call overhead than torch ops
    # here, and minimum.accumulate is a cummin without indices.
    d = cost[0].double().numpy()
    n, m = d.shape
    c = np.cumsum(d, 1)  # c[i, t] = sum_{u <= t} d[i, u], all rows at once
    acc = np.empty_like(d)
    acc[0] = c[0]
    a = np.empty(m, dtype=d.dtype)
    for i in range(1, n):
        prev, row, ci = acc[i - 1], acc[i], c[i]
        a[0] = prev[0]
        np.minimum(prev[1:], prev[:-1], out=a[1:])  # A[t] = min(D[i-1, t], D[i-1, t-1])
        np.subtract(a[1:], ci[:-1], out=a[1:])  # A[s] - c[i, s-1]
        np.minimum.accumulate(a, out=row)
        row += ci  # D[i, t] = c[i, t] + min_{s <= t} (A[s] - c[i, s-1])
    path = np.asarray(_dtw_backtrack(acc), dtype=np.int64)
    # The proposal's C: among the path's cells of each t', the most similar reference frame
    # (path rows are non-decreasing; lexsort puts each row's cheapest cell first).
    d_path = d[path[:, 0], path[:, 1]]
    order = np.lexsort((d_path, path[:, 0]))
    _, first = np.unique(path[order, 0], return_index=True)
    choice = torch.from_numpy(path[order[first], 1].copy())
    return DTWResult(torch.from_numpy(path), float(acc[-1, -1]), choice)


def _dtw_backtrack(acc: np.ndarray) -> list[tuple[int, int]]:
    i, j = acc.shape[0] - 1, acc.shape[1] - 1
    path = [(i, j)]
    while i > 0 or j > 0:
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            diag, up, left = acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1]
            if diag <= up and diag <= left:
                i, j = i - 1, j - 1
            elif up <= left:
                i -= 1
            else:
                j -= 1
        path.append((i, j))
    path.reverse()
    return path


# -- long sequences ----------------------------------------------------------------------------
def sequence_cost_fn(video: Tensor, reference: Tensor) -> CostFn:
    """Cost function for :func:`coarse_to_fine_align`: mean squared feature difference.

    Args:
        video: ``(T', F)`` features of the video frames.
        reference: ``(T, F)`` features of the reference frames.

    Returns:
        ``cost_fn(rows (R,), cols (R, W)) -> (R, W)``, ``mean_f (video[r] - reference[c])^2``.
    """
    if video.dim() != 2 or reference.dim() != 2 or video.shape[1] != reference.shape[1]:
        raise AlignmentError(
            "video and reference features must be (T', F) and (T, F) with the same F; got "
            f"{tuple(video.shape)} and {tuple(reference.shape)}"
        )

    def cost_fn(rows: Tensor, cols: Tensor) -> Tensor:
        diff = video[rows].unsqueeze(1) - reference[cols]
        return diff.square().mean(-1)

    return cost_fn


def _evaluate(cost_fn: CostFn, rows: Tensor, cols: Tensor, chunk_cells: int = 4_000_000) -> Tensor:
    """Call ``cost_fn`` on row chunks so that one call sees at most ``chunk_cells`` cells."""
    per = max(1, chunk_cells // max(cols.shape[1], 1))
    parts = [cost_fn(rows[s : s + per], cols[s : s + per]).cpu() for s in range(0, len(rows), per)]
    out = torch.cat(parts)
    if out.shape != cols.shape:
        raise AlignmentError(
            f"cost_fn returned shape {tuple(out.shape)}; expected {tuple(cols.shape)}"
        )
    return out


def coarse_to_fine_align(
    cost_fn: CostFn,
    num_video: int,
    num_ref: int,
    max_step: int,
    *,
    factor: int = 4,
    radius: int | None = None,
    max_cells: int = 2_000_000,
    fix_start: bool = False,
    fix_end: bool = False,
    step_cost: Tensor | None = None,
    robust: str | None = None,
    robust_scale: float = 2.0,
    threshold: float | None = None,
    pool_stride: int | None = None,
    margin: float = 0.0,
    beam: int | None = None,
    prune: float = 0.0,
) -> Alignment:
    """Monotone alignment of long sequences without the full T' x T cost matrix.

    Level ``l`` keeps every ``F = factor**l``-th video frame as its rows and groups the
    reference into cells of F consecutive frames (so the step bound S holds in cells); the
    coarsest level is solved whole, each finer one exactly inside a band derived from the
    coarser solution (a chain whose states are sliding windows,
    :class:`pgm.BandedMonotoneFactor`). Three things keep a periodic motion (a gait cycle
    of a few coarse cells) from aliasing:

    * **Min-pooling.** A cell's cost is the minimum over the reference frames it covers (at
      the row's video frame), not one sample of them, so a coarse cell never hides a good
      match: for any fine path, the coarse path through the cells it visits costs at most
      what the fine path costs on those rows. (Sampling one frame per cell, a cell size near
      half a cycle makes the right phase invisible and a path shifted by cycles look best.)
    * **Max-marginal band.** The next level's band covers every coarse cell on a coarse path
      within ``margin`` of the best (forward-backward max-product), and between two coarse
      rows everything monotone paths through those cells can reach, plus ``radius`` cells
      around the interpolated best path. The band widens exactly where the coarse level
      cannot tell alternatives apart.
    * **Tracking.** The two finest levels, whose rows (at most ``factor`` video frames apart)
      are close enough for the step bound to fix a periodic motion's rate (coarser levels'
      are not: rows half a cycle or more apart see every cycle alike, and tracking there
      only widens the band, multiplying that level's cost evaluations),
      extend their band along their own best partial paths (a forward pass in chunks of
      rows, ``beam`` cells around where each path, continued at its recent slope, goes: the
      best one, and the next best within ``prune``), so the band follows the motion instead
      of forcing the path off phase where the motion drifts out of it. Only the coarser band
      and the beams are evaluated, not the cells between them, so the cost per row stays
      bounded however far (e.g. whole loops of a repeating reference) a beam wanders from
      the coarser band.

    Work: about ``T'`` times the band width cost evaluations per level (a cell of F frames
    costs ``F / g`` evaluations, g the pooling stride), plus ``(T' / F_L) T / g`` at the
    coarsest level L and ``2 T`` to choose g; the band widens only where a level is
    ambiguous. Equal to the full solution on smooth warps, and on long periodic motion with
    distinguishing features (``margin=1``) or the same optimal cost without them (tested
    against the full chain). On a long walk against a reference repeating one gait loop it
    evaluates a small fraction of the pairs and keeps every frame in phase, where classic
    subsampling (one sample per coarse cell, no tracking) loses the phase on many frames
    (``benchmarks/bench_alignment.py``; figures: docs/decisions/004-tuning-evidence.md).

    Args:
        cost_fn: ``cost_fn(rows (R,), cols (R, W)) -> (R, W)`` costs of video frames ``rows``
            against reference frames ``cols`` (e.g. :func:`sequence_cost_fn`).
        num_video, num_ref: T' and T.
        max_step: S >= 1.
        factor: subsampling factor per level (>= 2).
        radius: band half-width in cells around the interpolated coarser path at each level
            (default ``factor * S``).
        max_cells: solve a level whole once that takes at most this many cost evaluations
            (rows x pooled reference frames), or the next level would have fewer than
            ``2 factor`` rows or cells.
        fix_start, fix_end: force C(0) = 0 / C(T'-1) = T-1.
        step_cost: optional ``(S + 1,)`` cost of each step size 0..S (a slope prior, e.g.
            :func:`slope_step_cost`), at every level: subsampling both sequences by the same
            factor keeps step sizes and the slope; a level of cells of F frames counts it F
            times (a step between its rows stands for F steps of the finest level). With
            ``robust``, in units of the threshold.
        robust: ``"truncate"`` or ``"saturate"`` (see :func:`robust_cost`) at every level,
            then divided by the threshold so costs lie in [0, 1].
        robust_scale, threshold: the threshold tau; by default ``robust_scale`` times the
            median over t' of each row's minimum at the coarsest level (whose cells cover
            every reference frame, so with a pooling stride of 1 these are true minima).
        pool_stride: a cell's minimum is over every g-th reference frame, g the largest
            divisor of the cell size up to this: 1 is the exact minimum; larger is cheaper
            and fine when the cost changes little over that many frames; at least
            ``factor**L`` samples one frame per cell, the classic (aliasing) subsampling.
            ``None``: the largest power of 2 whose subsampling raises the minima of cells
            with a plausible match by at most 5 % of tau on average, measured on two probe
            rows against every reference frame.
        margin: how much worse (in units of tau: with ``robust`` one truncated row) a coarse
            path may be and still have its cells in the band. 0 keeps the best path only. A
            margin of about 1 finds the full solution where cycles differ only slightly
            (they tie at the coarse levels); but where cycles are identical (a reference that
            repeats one loop) every cycle ties and the band grows towards the full matrix.
        beam: tracking half-width in cells (default ``radius``); 0 turns tracking off.
        prune: tracking keeps a beam around the next best partial path too where its score is
            within this of the best one's (in units of tau, as ``margin``); 0 (default): around
            the best one only.

    Returns:
        :class:`Alignment` with ``path`` (1, T') and ``cost`` (1,): the sum of the (robust,
        if set) costs along the path, excluding ``step_cost``.
    """
    _check_step(max_step)
    if max_step is None:
        raise AlignmentError("coarse_to_fine_align needs a finite max_step")
    if num_video < 1 or num_ref < 1:
        raise AlignmentError(f"sequences must be non-empty; got T'={num_video}, T={num_ref}")
    if factor < 2:
        raise AlignmentError(f"factor must be >= 2; got {factor}")
    radius = factor * max_step if radius is None else radius
    if radius < 1:
        raise AlignmentError(f"radius must be >= 1; got {radius}")
    if robust not in (None, "truncate", "saturate"):
        raise AlignmentError(f"robust must be None, 'truncate' or 'saturate'; got {robust!r}")
    if not (robust_scale > 0 and math.isfinite(robust_scale)):
        raise AlignmentError(f"robust_scale must be a finite positive number; got {robust_scale}")
    if pool_stride is not None and (
        isinstance(pool_stride, bool) or not isinstance(pool_stride, int) or pool_stride < 1
    ):
        raise AlignmentError(f"pool_stride must be None or an int >= 1; got {pool_stride!r}")
    if not (margin >= 0 and math.isfinite(margin)):
        raise AlignmentError(f"margin must be a finite number >= 0; got {margin}")
    beam = radius if beam is None else beam
    if isinstance(beam, bool) or not isinstance(beam, int) or beam < 0:
        raise AlignmentError(f"beam must be None or an int >= 0; got {beam!r}")
    if not (prune >= 0 and math.isfinite(prune)):
        raise AlignmentError(f"prune must be a finite number >= 0; got {prune}")
    if step_cost is not None:
        step_cost = _step_factor(max_step, step_cost).step_log_potential.neg()  # validated
    levels = _Levels(
        cost_fn,
        num_video,
        num_ref,
        max_step,
        factor,
        radius,
        max_cells,
        fix_start,
        fix_end,
        robust,
        robust_scale,
        step_cost,
        pool_stride,
        margin,
        beam,
        prune,
    )
    path, total = levels.solve(threshold)
    return Alignment(path.unsqueeze(0), total.reshape(1))


def _bucket(count: Tensor) -> Tensor:
    """Counts rounded up to 3 significant bits (at most 12.5 % more): rows of similar
    width share one ``cost_fn`` call."""
    bits = torch.floor(torch.log2(count.clamp_min(1).double())).long()
    unit = torch.pow(2, (bits - 3).clamp_min(0))
    return (count + unit - 1) // unit * unit


def _window_max(prev: np.ndarray, first: int, lo: int, width: int, window_lp: np.ndarray):
    """``max_s prev[p - s] + step_lp[s]`` for positions ``p = lo .. lo + width - 1``, where
    ``prev`` holds positions ``first ..`` (``-inf`` elsewhere) and ``window_lp`` is
    ``step_lp`` reversed (window entry i is the source S - i positions back)."""
    s = len(window_lp) - 1
    work = np.full(width + s, -np.inf)  # positions lo - s .. lo + width - 1
    a, b = max(first, lo - s), min(first + len(prev), lo + width)
    if a < b:
        work[a - lo + s : b - lo + s] = prev[a - first : b - first]
    windows = np.lib.stride_tricks.sliding_window_view(work, s + 1)  # window k: p - S .. p
    return (windows + window_lp).max(-1)


def _banded_forward(unary: np.ndarray, offsets: np.ndarray, step_lp: np.ndarray) -> np.ndarray:
    """Max-product forward scores of a banded monotone chain, each node's unary included.

    Shapes: ``unary`` (N, W) log-potentials of node n's positions ``offsets[n] + [0, W)``,
    ``offsets`` (N,) non-decreasing, ``step_lp`` (S + 1,). Float64 without rescaling: the
    scores are sums of N costs, far from float64's limits.
    """
    alpha = unary.copy()
    window_lp = step_lp[::-1].copy()
    for t in range(1, len(alpha)):
        prev = alpha[t - 1]
        alpha[t] += _window_max(prev, offsets[t - 1], offsets[t], alpha.shape[1], window_lp)
    return alpha


def _max_marginals(unary: np.ndarray, offsets: np.ndarray, step_lp: np.ndarray) -> np.ndarray:
    """``(N, W)`` score of the best path through each state: forward + backward - unary."""
    alpha = _banded_forward(unary, offsets, step_lp)
    # the backward pass is the forward pass of the chain reversed in time and position
    last = offsets + unary.shape[1] - 1
    beta = _banded_forward(unary[::-1, ::-1].copy(), -last[::-1], step_lp)[::-1, ::-1]
    finite = np.isfinite(unary)
    out = np.full_like(alpha, -np.inf)
    out[finite] = alpha[finite] + beta[finite] - unary[finite]
    return out


@dataclass
class _Levels:
    """The settings :func:`coarse_to_fine_align` works with, and its level loop."""

    cost_fn: CostFn
    num_video: int
    num_ref: int
    max_step: int
    factor: int
    radius: int
    max_cells: int
    fix_start: bool
    fix_end: bool
    robust: str | None
    robust_scale: float
    step_cost: Tensor | None
    pool_stride: int | None
    margin: float
    beam: int
    prune: float
    chunk: int = 16  # rows per tracking step
    runs: int = 2  # most partial paths (runs of ends) tracking keeps a beam around

    def estimate_stride(self, threshold: float | None, tolerance: float = 0.05) -> int:
        """The coarsest pooling grid that loses little. Two probe rows (the video frames at
        1/4 and 3/4) are evaluated against every reference frame; for g = 2, 4, 8, ... the
        minimum over every g-th frame of a cell of 4 g frames (each phase of that grid) is
        compared with the cell's true minimum, on the cells holding a plausible match (true
        minimum below tau, at least 4 of them); the largest g whose mean excess is at most
        ``tolerance`` tau is taken (1 if none)."""
        rows = torch.tensor(sorted({self.num_video // 4, 3 * self.num_video // 4}), device="cpu")
        cols = torch.arange(self.num_ref, device="cpu").expand(len(rows), -1)
        raw = _evaluate(self.cost_fn, rows, cols).double()
        tau = threshold
        if tau is None:
            row_min = raw.amin(-1)
            row_min = row_min[torch.isfinite(row_min)]
            tau = self.robust_scale * float(row_min.median()) if len(row_min) else 1.0
        shaped = raw.clamp(max=max(tau, torch.finfo(torch.float64).tiny)) / tau
        g = 1
        while 8 * g <= self.num_ref:
            cand, cell = 2 * g, 8 * g
            cells = shaped[:, : self.num_ref // cell * cell].unflatten(-1, (-1, cell))
            exact = cells.amin(-1)
            plausible = exact < 1
            # every phase of the grid: a loop of a multiple of g frames would otherwise put
            # the best frame of every cycle on the grid or off it, by luck
            excess = sum(cells[..., o::cand].amin(-1) - exact for o in range(cand)) / cand
            if plausible.sum() < 4 or float(excess[plausible].mean()) > tolerance:
                break
            g = cand
        return g

    def stride(self, scale: int) -> int:
        """The pooling grid's stride at a level: the largest divisor of ``scale`` up to
        ``pool_stride``."""
        return max(d for d in range(1, min(self.pool_stride, scale) + 1) if scale % d == 0)

    def scales(self) -> list[int]:
        """Cell sizes F of the levels, finest (1) first: coarser while solving a level whole
        takes more than ``max_cells`` cost evaluations (rows x pooled reference frames) and
        the next level would still have ``2 factor`` rows and cells."""
        f, scales = self.factor, [1]
        while True:
            scale = scales[-1]
            n, m = -(-self.num_video // scale), -(-self.num_ref // scale)
            if n * -(-self.num_ref // self.stride(scale)) <= self.max_cells:
                return scales
            if -(-n // f) < 2 * f or -(-m // f) < 2 * f:
                return scales
            scales.append(scale * f)

    def shape(self, cost: Tensor, threshold: float | None) -> tuple[Tensor, float]:
        """Robust, normalised costs; the threshold is fixed by the first (coarsest) call.
        Without ``robust`` it is computed all the same: it is the unit of ``margin``."""
        if threshold is None:
            row_min = cost.amin(-1)
            finite = row_min[torch.isfinite(row_min)]
            threshold = self.robust_scale * float(finite.median()) if len(finite) else 1.0
            threshold = max(threshold, torch.finfo(torch.float64).tiny)
        if self.robust is None:
            return cost, threshold
        return robust_cost(cost, threshold, self.robust) / threshold, threshold

    def evaluate(
        self, scale: int, rows: Tensor, lo: Tensor, hi: Tensor, one_call: bool = False
    ) -> Tensor:
        """``(R, W)`` costs of cells ``lo..hi`` of level rows ``rows`` in windows
        ``lo + [0, W)`` (``+inf`` outside; rows with ``hi < lo`` are empty). Row v is video
        frame ``v * scale``; cell j is reference frames ``[j scale, (j + 1) scale)`` and costs
        their minimum on a grid of stride g (the largest divisor of ``scale`` up to
        ``pool_stride``)."""
        g = self.stride(scale)
        width = max(1, int((hi - lo).max()) + 1) if len(rows) else 1
        out = torch.full((len(rows), width), math.inf, dtype=torch.float64, device="cpu")
        first = lo * scale
        last = torch.clamp((hi + 1) * scale, max=self.num_ref) - 1
        bucket = _bucket((last - first) // g + 1)  # reference frames evaluated per row
        if one_call:  # every row padded to the widest: one cost_fn call
            bucket = torch.full_like(bucket, int(bucket.max()))
        bucket[hi < lo] = 0
        for size in torch.unique(bucket[bucket > 0]).tolist():
            sel = (bucket == size).nonzero().flatten()
            frames = first[sel, None] + g * torch.arange(size, device="cpu")
            frames = torch.minimum(frames, last[sel, None])  # padding repeats the last frame
            cost = _evaluate(self.cost_fn, rows[sel] * scale, frames).double()
            pooled = torch.full((len(sel), width), math.inf, dtype=torch.float64, device="cpu")
            out[sel] = pooled.scatter_reduce_(1, frames // scale - lo[sel, None], cost, "amin")
        return out

    def band(
        self, num_rows: int, num_cells: int, coarse: Tensor, keep_lo: Tensor, keep_hi: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Cells ``[lo, hi]`` per row of a level from the coarser level's best path and kept
        cells (in coarser cells): where monotone paths through the kept cells of the two
        coarse rows around a row can be, and ``radius`` cells around the interpolated path."""
        f, s, r = self.factor, self.max_step, self.radius
        v = torch.arange(num_rows)
        i = v // f  # the coarse row at or before v
        k = v - i * f  # rows since it
        nxt = (i + 1).clamp(max=len(coarse) - 1)
        has_next = i + 1 < len(coarse)
        lo = keep_lo[i] * f
        hi = (keep_hi[i] + 1) * f - 1 + s * k  # reachable from the kept cells of row i
        lo_next = keep_lo[nxt] * f - s * (f - k)  # reaching the kept cells of row i + 1
        hi_next = (keep_hi[nxt] + 1) * f - 1
        lo = torch.where(has_next, torch.maximum(lo, lo_next), lo)
        hi = torch.where(has_next, torch.minimum(hi, hi_next), hi)
        # radius around the best path, interpolated (past the last coarse row: continued
        # at its last slope)
        centre = coarse.double() * f
        slope = float(centre[-1] - centre[-2]) / f if len(coarse) > 1 else 0.0
        frac = k.double() / f
        mid = (
            torch.where(
                has_next, centre[i] * (1 - frac) + centre[nxt] * frac, centre[i] + slope * k
            )
            .round()
            .long()
        )
        return self.hull(torch.minimum(lo, mid - r), torch.maximum(hi, mid + r), num_cells)

    def hull(self, lo: Tensor, hi: Tensor, num_cells: int) -> tuple[Tensor, Tensor]:
        """A band clamped to the level and reaching fixed ends, without cells no monotone
        path can use (``lo`` non-decreasing; ``hi`` non-decreasing from the end)."""
        lo, hi = lo.clamp(0, num_cells - 1), hi.clamp(0, num_cells - 1)
        if self.fix_start:
            lo[0] = 0
        if self.fix_end:
            hi[-1] = num_cells - 1
        lo = torch.cummax(lo, 0).values
        hi = torch.cummin(hi.flip(0), 0).values.flip(0)
        return lo, torch.maximum(hi, lo)

    def track(
        self, scale: int, raw: Tensor, lo: Tensor, hi: Tensor, m: int, threshold: float
    ) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """The band ``[lo, hi]`` (costs ``raw``) extended along this level's best partial
        paths (:meth:`survivors`): a forward pass over chunks of ``chunk`` rows; before each
        chunk each kept path's ends are continued at the slope the best path had over the
        last chunk, and the chunk's rows get ``beam`` cells either side of them. Returns the
        new band, its costs and which of them were evaluated (``None``: the band did not
        grow): the coarse band and the beams, not the cells between them."""
        n, s, r, h = len(lo), self.max_step, self.beam, self.chunk
        window_lp = self.step_lp(scale)[::-1].copy()
        lo_np, hi_np = lo.numpy(), hi.numpy()
        width0 = hi_np - lo_np + 1
        inside = np.arange(raw.shape[1]) < width0[:, None]
        unary0 = np.where(inside, -self.shape(raw, threshold)[0].numpy(), -np.inf)
        raw_np = raw.numpy()
        new_lo, new_hi = lo_np.copy(), hi_np.copy()
        # (first row, raw costs over the new band, which of them were evaluated)
        tables: list[tuple[int, np.ndarray, np.ndarray]] = []
        grown = False
        alpha = prev_lo = None
        slope = 0.0
        for v0 in range(0, n, h):
            v1 = min(n, v0 + h)
            rows = np.arange(v0, v1)
            beams: list[tuple[np.ndarray, np.ndarray]] = []  # (first, last) cell per row
            if v0 > 0:
                step = np.round(slope * (rows - v0 + 1)).astype(np.int64)
                nlo, nhi = lo_np[rows].copy(), hi_np[rows].copy()
                for a0, a1 in self.survivors(alpha, prev_lo, threshold):
                    # each kept partial path's run of ends, continued at the slope, with
                    # beam cells either side, where it comes within beam / 2 of an edge
                    near_lo = a0 + step - r // 2 < lo_np[rows]
                    near_hi = a1 + step + r // 2 > hi_np[rows]
                    first, last = a0 + step - r, a1 + step + r
                    beams.append((np.where(near_lo | near_hi, first, last + 1), last))
                    nlo = np.where(near_lo, np.minimum(nlo, first), nlo)
                    nhi = np.where(near_hi, np.maximum(nhi, last), nhi)
                nlo = np.maximum(nlo, new_lo[v0 - 1])
                new_lo[rows] = np.maximum.accumulate(np.clip(nlo, 0, m - 1))
                # and no higher than the previous row's band lets a step reach
                reach = np.minimum.accumulate(
                    np.append(new_hi[v0 - 1], nhi) - s * np.arange(len(rows) + 1)
                )[1:] + s * np.arange(1, len(rows) + 1)
                new_hi[rows] = np.clip(reach, new_lo[rows], m - 1)
            nlo, nhi = new_lo[rows], new_hi[rows]
            width = int((nhi - nlo).max()) + 1
            shift = lo_np[rows] - nlo  # where the coarse band starts in the new windows
            cols = shift[:, None] + np.arange(raw.shape[1])
            keep = inside[rows] & (cols < width)
            rr = np.broadcast_to(np.arange(len(rows))[:, None], cols.shape)
            raw_c = np.full((len(rows), width), np.inf)
            raw_c[rr[keep], cols[keep]] = raw_np[rows][keep]
            known_c = np.zeros((len(rows), width), dtype=bool)
            known_c[rr[keep], cols[keep]] = True
            unary = np.full((len(rows), width), -np.inf)
            unary[rr[keep], cols[keep]] = unary0[rows][keep]
            # the new cells: each beam's part left of the coarse band and right of it, in one
            # call; cells between the beams and the coarse band stay out (a path a few loops
            # off the coarse band would otherwise cost every cell between them)
            part_lo, part_hi = [], []
            for first, last in beams:
                first, last = np.maximum(first, nlo), np.minimum(last, nhi)
                part_lo += [first, np.maximum(first, hi_np[rows] + 1)]
                part_hi += [np.minimum(last, lo_np[rows] - 1), last]
            part_lo = np.concatenate(part_lo) if beams else np.zeros(0, dtype=np.int64)
            part_hi = np.concatenate(part_hi) if beams else np.zeros(0, dtype=np.int64)
            sel = np.nonzero(part_hi >= part_lo)[0]
            if len(sel):
                grown = True
                # one call per chunk: pieces of a few cells each in calls of their own cost
                # more in per-call overhead (and, with stage 1's pair fitter, in full-start
                # fits of narrow windows) than the padding does
                got = self.evaluate(
                    scale,
                    torch.from_numpy(np.tile(rows, 2 * len(beams))[sel]),
                    torch.from_numpy(part_lo[sel]),
                    torch.from_numpy(part_hi[sel]),
                    one_call=True,
                )
                shaped = -self.shape(got, threshold)[0].numpy()
                k = np.arange(got.shape[1])
                ok = k[None] <= (part_hi - part_lo)[sel, None]
                ri = np.broadcast_to(sel[:, None] % len(rows), ok.shape)
                cc = (part_lo[sel] - nlo[sel % len(rows)])[:, None] + k
                raw_c[ri[ok], cc[ok]] = got.numpy()[ok]
                unary[ri[ok], cc[ok]] = shaped[ok]
                known_c[ri[ok], cc[ok]] = True
            tables.append((v0, raw_c, known_c))
            if v0 == 0:
                if self.fix_start:
                    unary[0, nlo[0] + np.arange(width) != 0] = -np.inf
                alpha = unary[0]
            else:
                alpha = unary[0] + _window_max(alpha, prev_lo, int(nlo[0]), width, window_lp)
            slope = 0.0
            if len(rows) > 1:  # the fused sweep of pgm.BandedMonotoneFactor.viterbi
                shifts = np.diff(nlo)
                work = np.full(s + width + int(shifts.max()), -np.inf)
                windows = np.lib.stride_tricks.sliding_window_view(work, s + 1)
                back = np.empty((len(rows), width), dtype=np.int64)
                for t in range(1, len(rows)):
                    d = int(shifts[t - 1])
                    work[s : s + width] = alpha
                    cand = windows[d : d + width] + window_lp
                    back[t] = cand.argmax(-1)
                    alpha = unary[t] + cand.max(-1)
                # the slope of the best partial path over this chunk (backtracked)
                j = int(alpha.argmax())
                for t in range(len(rows) - 1, 0, -1):
                    j += int(nlo[t] - nlo[t - 1]) - (s - int(back[t, j]))
                slope = float(
                    np.clip((alpha.argmax() + nlo[-1] - j - nlo[0]) / (len(rows) - 1), 0, s)
                )
            prev_lo = int(nlo[-1])
        if not grown:
            return lo, hi, raw, None
        size = (n, int((new_hi - new_lo).max()) + 1)
        table = torch.full(size, math.inf, dtype=torch.float64)
        known = torch.zeros(size, dtype=torch.bool)
        for v0, raw_c, known_c in tables:
            table[v0 : v0 + len(raw_c), : raw_c.shape[1]] = torch.from_numpy(raw_c)
            known[v0 : v0 + len(raw_c), : raw_c.shape[1]] = torch.from_numpy(known_c)
        return torch.from_numpy(new_lo), torch.from_numpy(new_hi), table, known

    def survivors(self, alpha: np.ndarray, first: int, threshold: float) -> list[tuple[int, int]]:
        """Runs ``(a0, a1)`` of positions (``first`` + index) whose forward score ``alpha``
        is within ``prune`` (units of tau) of the best, runs closer than ``2 beam + 1``
        merged, the ``runs`` best of them (the best one's always): the partial paths
        tracking keeps a beam around."""
        unit = 1.0 if self.robust else threshold
        finite = np.isfinite(alpha)
        if not finite.any():
            return []
        kept = np.nonzero(alpha >= alpha[finite].max() - self.prune * unit)[0]
        cuts = np.nonzero(np.diff(kept) > 2 * self.beam + 1)[0]
        starts = np.concatenate([[0], cuts + 1])
        ends = np.concatenate([cuts, [len(kept) - 1]])
        # identical loop copies tie forever once reached: only the best ``runs`` runs keep
        # a beam, so that the band stays a bounded number of beams wide however long the
        # sequence is
        score = [
            float(alpha[kept[a] : kept[b] + 1].max()) for a, b in zip(starts, ends, strict=True)
        ]
        best = sorted(np.argsort(score, kind="stable")[::-1][: self.runs])
        return [(first + int(kept[starts[i]]), first + int(kept[ends[i]])) for i in best]

    def level_step_cost(self, scale: int) -> Tensor | None:
        """``(S + 1,)`` cost of each step size at the level of cells of ``scale`` frames
        (``None`` without a slope prior): ``scale`` times the step cost, since a step between
        two of its rows stands for ``scale`` steps of the finest level at that slope (the
        least they cost, the step cost being convex). Counted once per row, a level's slope
        prior would be ``scale`` times weaker than the finest's against its costs: where
        those say little (cells of a cycle or more of a periodic motion all match), coarse
        paths would start anywhere and run at any slope, and the finer bands around them drop
        or gain whole cycles to follow. On a long walk against its loop repeated the scaled
        prior keeps more frames in phase on one warp and a few fewer on others, where the
        path changes copy of the loop at places the pair costs hardly tell from the truth
        (docs/decisions/004-tuning-evidence.md; docs/experiments.md, "A long input")."""
        return None if self.step_cost is None else scale * self.step_cost

    def step_lp(self, scale: int) -> np.ndarray:
        """``(S + 1,)`` log-potential of each step size at the level of cells of ``scale``
        frames (:meth:`level_step_cost`)."""
        cost = self.level_step_cost(scale)
        return np.zeros(self.max_step + 1) if cost is None else cost.double().neg().numpy()

    def unary(
        self,
        raw: Tensor,
        lo: Tensor,
        hi: Tensor,
        m: int,
        threshold: float | None,
        known: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, float]:
        """``(1, N, W)`` log-potentials of a band (``-inf`` outside it, at cells not
        ``known`` if given, and off fixed ends), the shaped costs and the threshold."""
        _check_cost(raw)
        cost, threshold = self.shape(raw, threshold)
        cols = torch.arange(raw.shape[1], device="cpu")
        inside = cols <= (hi - lo)[:, None]
        if known is not None:
            inside = inside & known
        unary = torch.where(inside, -cost, -math.inf).unsqueeze(0)
        if self.fix_start:
            unary[:, 0] = unary[:, 0].masked_fill(lo[0] + cols != 0, -math.inf)
        if self.fix_end:
            unary[:, -1] = unary[:, -1].masked_fill(lo[-1] + cols != m - 1, -math.inf)
        return unary, cost, threshold

    def solve(self, threshold: float | None) -> tuple[Tensor, Tensor]:
        """Path ``(T',)`` and its cost, coarsest level first."""
        if self.pool_stride is None:
            self.pool_stride = 1
            if self.num_video * self.num_ref > self.max_cells:  # not solved whole
                self.pool_stride = self.estimate_stride(threshold)
        scales = self.scales()
        coarse = keep_lo = keep_hi = None
        for level in range(len(scales) - 1, -1, -1):
            scale = scales[level]
            n = -(-self.num_video // scale)
            m = -(-self.num_ref // scale)
            if coarse is None:
                lo, hi = (
                    torch.zeros(n, dtype=torch.long, device="cpu"),
                    torch.full((n,), m - 1, device="cpu"),
                )
            else:
                lo, hi = self.band(n, m, coarse, keep_lo, keep_hi)
            raw = self.evaluate(scale, torch.arange(n, device="cpu"), lo, hi)
            known = None
            if coarse is not None and self.beam > 0 and scale <= self.factor:
                lo, hi, raw, known = self.track(scale, raw, lo, hi, m, threshold)
            unary, cost, threshold = self.unary(raw, lo, hi, m, threshold, known)
            cost_of_step = self.level_step_cost(scale)
            step = None if cost_of_step is None else -cost_of_step
            try:
                result = chain_map(
                    unary.clone(), BandedMonotoneFactor(self.max_step, lo, step), overwrite=True
                )
            except InfeasibleError as err:
                raise AlignmentError(
                    "no monotone path fits the band around the coarse path "
                    f"(T'={self.num_video}, T={self.num_ref}, max_step={self.max_step}, "
                    f"fix_start={self.fix_start}, fix_end={self.fix_end}); increase radius"
                ) from err
            offsets = result.assignment[0]
            coarse = lo + offsets
            if level == 0:
                return coarse, cost.gather(-1, offsets.unsqueeze(-1)).sum()
            keep_lo = keep_hi = coarse
            if self.margin > 0:
                marg = _max_marginals(unary[0].numpy(), lo.numpy(), self.step_lp(scale))
                keep = torch.from_numpy(
                    marg >= marg.max() - self.margin * (1.0 if self.robust else threshold)
                )
                cols = torch.arange(keep.shape[1])
                keep_lo = lo + torch.where(keep, cols, keep.shape[1]).amin(-1)
                keep_hi = lo + torch.where(keep, cols, -1).amax(-1)
        raise AssertionError("unreachable")
