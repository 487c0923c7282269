"""Time alignment: video frame t' -> reference frame C(t'), monotone.

Two families, both on a cost matrix ``d (B, T', T)`` (lower is better, e.g. the proposal's
Eq. 24 stick-figure distance):

* :func:`chain_align` -- what registration uses. C is a chain of discrete nodes (one per video
  frame, states = reference frames) with monotone steps ``0 <= C(t'+1) - C(t') <= S``, solved
  exactly by max-product in :mod:`pgm` (O(T' T S), never a dense T x T table).
  :func:`soft_align` is the same chain under a tempered log semiring: a posterior over C(t').
  :func:`coarse_to_fine_align` solves long sequences from a cost *function* in near-linear time.
* :func:`dtw` -- the proposal's classic DTW (Eq. 26, steps (1,0), (0,1), (1,1), both ends
  fixed), kept for comparison, with its per-t' choice of the most similar reference frame.

Robustness (:func:`robust_cost`): truncating or saturating the cost bounds what a corrupted
stretch of video can cost, so it cannot pull the path off course elsewhere.

Units: frames (integer indices, 0-based) for C; costs in the caller's units.
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
    "band_mask",
    "chain_align",
    "coarse_to_fine_align",
    "dtw",
    "robust_cost",
    "sequence_cost_fn",
    "slope_step_cost",
    "soft_align",
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
        threshold_t = torch.as_tensor(threshold, dtype=cost.dtype)
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
    steps = torch.arange(max_step + 1, dtype=torch.get_default_dtype())
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
    step_cost = torch.as_tensor(step_cost, dtype=torch.get_default_dtype())
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
    parts = [cost_fn(rows[s : s + per], cols[s : s + per]) for s in range(0, len(rows), per)]
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
    pool_stride: int = 1,
    margin: float = 1.0,
) -> Alignment:
    """Monotone alignment of long sequences without the full T' x T cost matrix.

    Levels: level ``l`` keeps every ``factor**l``-th video frame (its rows) and groups the
    reference into cells of ``F = factor**l`` consecutive frames (which keeps the step bound
    S in level units); the coarsest level (at most ``max_cells`` cells) is solved whole, each
    finer one inside a band derived from the coarser solution, by a chain whose states are
    sliding windows (:class:`pgm.BandedMonotoneFactor`).

    * A cell's cost is the **minimum** of the costs of the reference frames it covers (at
      the row's video frame), not one sample: a coarse cell never hides a good match, so a
      periodic motion (a gait cycle shorter than a few cells) cannot alias, and the coarse
      cost of the projection of any fine path is at most that path's cost on those rows.
    * The band keeps every coarse cell on a coarse path whose cost is within ``margin`` of
      the best (max-marginals, forward-backward max-product), i.e. it widens exactly where
      the coarse level cannot tell alternatives apart (cycles of a periodic motion, a
      stretch of bad frames), plus ``radius`` cells either side of the best coarse path.
      Between two coarse rows it is the parallelogram that monotone paths through their
      kept cells can reach.

    Work: ``T'`` rows times the band's width per level (a cell of F frames costs F / g
    evaluations, g = ``pool_stride``): ``O(T' (width) levels)`` cost evaluations, a small
    fraction of ``T' x T`` where the coarse levels are unambiguous; only ambiguity widens it.
    On smooth warps the result equals the full solution (tested), and on a long periodic
    motion too (tested against the full chain).

    Args:
        cost_fn: ``cost_fn(rows (R,), cols (R, W)) -> (R, W)`` costs of video frames ``rows``
            against reference frames ``cols`` (e.g. :func:`sequence_cost_fn`).
        num_video, num_ref: T' and T.
        max_step: S >= 1.
        factor: subsampling factor per level (>= 2).
        radius: band half-width in cells around the upsampled coarser path at each level
            (default ``factor * S``).
        max_cells: solve directly once a level has at most this many cells.
        fix_start, fix_end: force C(0) = 0 / C(T'-1) = T-1.
        step_cost: optional ``(S + 1,)`` cost of each step size 0..S (a slope prior, e.g.
            :func:`slope_step_cost`), at every level: subsampling both sequences by the same
            factor keeps step sizes and the slope. With ``robust``, in units of the threshold.
        robust: ``"truncate"`` or ``"saturate"`` (see :func:`robust_cost`) at every level,
            then divided by the threshold so costs lie in [0, 1].
        robust_scale, threshold: the threshold tau; by default ``robust_scale`` times the
            median over t' of each row's minimum at the coarsest level (the only full
            matrix; with ``pool_stride=1`` its rows are the exact row minima of those frames).
        pool_stride: a cell's minimum is taken over every g-th reference frame, g the largest
            divisor of the cell size not above this (1: the exact minimum; ``>= factor**L``
            samples one frame per cell, the classic subsampling, which aliases periodic
            motion). Larger is cheaper when the cost is smooth over g reference frames.
        margin: band threshold on a coarse path's excess cost, in units of tau (with
            ``robust`` the truncation level, i.e. one outlier row; without, ``robust_scale``
            times the median row minimum). 0 keeps only the best coarse path (and ties).

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
    if radius < 0:
        raise AlignmentError(f"radius must be >= 0; got {radius}")
    if robust not in (None, "truncate", "saturate"):
        raise AlignmentError(f"robust must be None, 'truncate' or 'saturate'; got {robust!r}")
    if not (robust_scale > 0 and math.isfinite(robust_scale)):
        raise AlignmentError(f"robust_scale must be a finite positive number; got {robust_scale}")
    if isinstance(pool_stride, bool) or not isinstance(pool_stride, int) or pool_stride < 1:
        raise AlignmentError(f"pool_stride must be an int >= 1; got {pool_stride!r}")
    if not (margin >= 0 and math.isfinite(margin)):
        raise AlignmentError(f"margin must be a finite number >= 0; got {margin}")
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
    )
    path, total = levels.solve(threshold)
    return Alignment(path.unsqueeze(0), total.reshape(1))


def _bucket(k: Tensor) -> Tensor:
    """Round counts up to 3 significant bits (at most 12.5 % more), so rows of similar width
    share one ``cost_fn`` call."""
    bits = torch.floor(torch.log2(k.clamp_min(1).double())).long()
    unit = torch.pow(2, (bits - 3).clamp_min(0))
    return (k + unit - 1) // unit * unit


def _banded_forward(unary: np.ndarray, shifts: np.ndarray, step_lp: np.ndarray) -> np.ndarray:
    """Max-product forward messages of a banded monotone chain, including each node's unary.

    Shapes: ``unary`` (N, W) log-potentials of node n's window ``offsets[n] + [0, W)``,
    ``shifts`` (N-1,) ``offsets[n+1] - offsets[n] >= 0``, ``step_lp`` (S+1,). Float64 without
    rescaling: scores are sums of N costs, far from float64's limits.
    """
    n, w = unary.shape
    s = len(step_lp) - 1
    alpha = unary.copy()
    window_lp = step_lp[::-1].copy()  # window index k reads the source S - k positions back
    work = np.full(s + w + int(max(0, *shifts.tolist())) if n > 1 else s + w, -np.inf)
    windows = np.lib.stride_tricks.sliding_window_view(work, s + 1)
    for t in range(1, n):
        d = int(shifts[t - 1])
        work[s : s + w] = alpha[t - 1]
        alpha[t] += (windows[d : d + w] + window_lp).max(-1)
    return alpha


def _max_marginals(unary: np.ndarray, offsets: np.ndarray, step_lp: np.ndarray) -> np.ndarray:
    """``(N, W)`` best score of a path through each state (forward + backward - unary)."""
    shifts = np.diff(offsets)
    alpha = _banded_forward(unary, shifts, step_lp)
    # the backward pass is the forward pass of the reversed chain on the reversed axis
    beta = _banded_forward(unary[::-1, ::-1].copy(), shifts[::-1].copy(), step_lp)[::-1, ::-1]
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
    pool_stride: int
    margin: float
    max_expand: int = 6
    expand_bad: bool = True
    double: int = 1

    def scales(self) -> list[int]:
        """Cell sizes F of the levels, finest (1) first: coarser until one fits max_cells."""
        f, scales = self.factor, [1]
        while True:
            n = -(-self.num_video // scales[-1])
            m = -(-self.num_ref // scales[-1])
            if n * m <= self.max_cells or n < 2 * f or m < 2 * f:
                return scales
            scales.append(scales[-1] * f)

    def shape(self, cost: Tensor, threshold: float | None) -> tuple[Tensor, float]:
        """Robust, normalised costs; the threshold is fixed by the first (coarsest) call.
        Without ``robust`` the threshold is still computed: it is the unit of ``margin``."""
        if threshold is None:
            row_min = cost.amin(-1)
            finite = row_min[torch.isfinite(row_min)]
            threshold = self.robust_scale * float(finite.median()) if len(finite) else 1.0
            threshold = max(threshold, torch.finfo(torch.float64).tiny)
        if self.robust is None:
            return cost, threshold
        return robust_cost(cost, threshold, self.robust) / threshold, threshold

    def evaluate(self, scale: int, rows: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        """``(R, W)`` costs of level cells ``lo..hi`` of level rows ``rows`` (``R``) in windows
        ``lo + [0, W)`` (``+inf`` outside); row v is video frame ``v * scale``, cell j the
        reference frames ``[j scale, (j + 1) scale)``, its cost their minimum on a grid of
        stride g (the largest divisor of ``scale`` up to ``pool_stride``)."""
        g = max(d for d in range(1, min(self.pool_stride, scale) + 1) if scale % d == 0)
        width = int((hi - lo).max()) + 1 if len(rows) else 1
        out = torch.full((len(rows), width), math.inf, dtype=torch.float64)
        if not len(rows):
            return out
        first = lo * scale
        last = torch.clamp((hi + 1) * scale, max=self.num_ref) - 1
        bucket = _bucket((last - first) // g + 1)  # reference frames evaluated per row
        for size in torch.unique(bucket).tolist():
            sel = (bucket == size).nonzero().flatten()
            frames = first[sel, None] + g * torch.arange(size)
            frames = torch.minimum(frames, last[sel, None])  # padding repeats the last frame
            cost = _evaluate(self.cost_fn, rows[sel] * scale, frames)
            cell = frames // scale - lo[sel, None]
            pooled = torch.full((len(sel), width), math.inf, dtype=torch.float64)
            out[sel] = pooled.scatter_reduce_(1, cell, cost.double(), "amin")
        return out

    def extend(
        self, scale: int, table: Tensor, lo: Tensor, hi: Tensor, new_lo: Tensor, new_hi: Tensor
    ) -> Tensor:
        """The costs of band ``[new_lo, new_hi]`` (containing ``[lo, hi]``, whose costs are
        ``table``): only the new cells are evaluated."""
        n = len(lo)
        width = int((new_hi - new_lo).max()) + 1
        out = torch.full((n, width), math.inf, dtype=torch.float64)
        k = torch.arange(table.shape[1])
        col = (lo - new_lo)[:, None] + k
        valid = (k <= (hi - lo)[:, None]) & (col < width)
        r = torch.arange(n)[:, None].expand_as(col)
        out[r[valid], col[valid]] = table[valid]
        for part_lo, part_hi, at in ((new_lo, lo - 1, 0), (hi + 1, new_hi, None)):
            rows = (part_hi >= part_lo).nonzero().flatten()
            if not len(rows):
                continue
            vals = self.evaluate(scale, rows, part_lo[rows], part_hi[rows])
            start = torch.zeros_like(rows) if at == 0 else (hi + 1 - new_lo)[rows]
            kk = torch.arange(vals.shape[1])
            col = start[:, None] + kk
            ok = kk <= (part_hi - part_lo)[rows, None]
            rr = rows[:, None].expand_as(col)
            out[rr[ok], col[ok]] = vals[ok]
        return out

    def band(
        self, num_rows: int, num_cells: int, coarse: Tensor, keep_lo: Tensor, keep_hi: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Per-row cell range ``[lo, hi]`` at a level from the coarser level's best path and
        kept cells (all in coarser cells): where monotone paths through kept cells of two
        consecutive coarse rows can be, and ``radius`` cells around the interpolated path."""
        f, s, r = self.factor, self.max_step, self.radius
        v = torch.arange(num_rows)
        i = v // f  # the coarse row at or before v
        k = v - i * f  # rows since it
        nc = len(coarse)
        nxt = (i + 1).clamp(max=nc - 1)
        has_next = i + 1 < nc
        lo = keep_lo[i] * f
        hi = (keep_hi[i] + 1) * f - 1 + s * k  # reachable from the kept cells at row i
        lo_next = keep_lo[nxt] * f - s * (f - k)  # reaching the kept cells at row i + 1
        hi_next = (keep_hi[nxt] + 1) * f - 1
        lo = torch.where(has_next, torch.maximum(lo, lo_next), lo)
        hi = torch.where(has_next, torch.minimum(hi, hi_next), hi)
        # radius around the best coarse path, interpolated (past the last coarse row:
        # continued with its last slope)
        centre = coarse.double() * f
        slope = float(centre[-1] - centre[-2]) / f if nc > 1 else 0.0
        frac = k.double() / f
        mid = torch.where(
            has_next, centre[i] * (1 - frac) + centre[nxt] * frac, centre[i] + slope * k
        )
        mid = mid.round().long()
        lo = torch.minimum(lo, mid - r)
        hi = torch.maximum(hi, mid + r)
        return self.hull(lo, hi, num_cells)

    def hull(self, lo: Tensor, hi: Tensor, num_cells: int) -> tuple[Tensor, Tensor]:
        """Clamp a band to the level, reach the fixed ends, and drop cells no monotone path
        can use (``lo`` non-decreasing, ``hi`` non-decreasing from the end)."""
        lo, hi = lo.clamp(0, num_cells - 1), hi.clamp(0, num_cells - 1)
        if self.fix_start:
            lo[0] = 0
        if self.fix_end:
            hi[-1] = num_cells - 1
        lo = torch.cummax(lo, 0).values
        hi = torch.cummin(hi.flip(0), 0).values.flip(0)
        return lo, torch.maximum(hi, lo)

    def solve(self, threshold: float | None) -> tuple[Tensor, Tensor]:
        """Path ``(T',)`` and its cost, coarsest level first."""
        scales = self.scales()
        step_lp = (
            np.zeros(self.max_step + 1)
            if self.step_cost is None
            else self.step_cost.double().neg().numpy()
        )
        coarse = keep_lo = keep_hi = None
        for level in range(len(scales) - 1, -1, -1):
            scale = scales[level]
            n = -(-self.num_video // scale)
            m = -(-self.num_ref // scale)
            if coarse is None:
                lo, hi = torch.zeros(n, dtype=torch.long), torch.full((n,), m - 1)
            else:
                lo, hi = self.band(n, m, coarse, keep_lo, keep_hi)
            raw = self.evaluate(scale, torch.arange(n), lo, hi)
            grow = max(self.radius, self.factor)
            for attempt in range(self.max_expand + 1):
                unary, cost, threshold = self.unary(raw, lo, hi, m, threshold)
                path, offsets = self.map(unary, lo)
                # a path on the band's edge may continue better outside: widen there
                bad = raw.gather(-1, offsets[:, None])[:, 0] > threshold
                if not self.expand_bad:
                    bad = torch.zeros_like(bad)
                touch_lo = ((path == lo) | bad) & (lo > 0)
                touch_hi = ((path == hi) | bad) & (hi < m - 1)
                if attempt == self.max_expand or not (touch_lo.any() or touch_hi.any()):
                    break
                reach = grow << (attempt * self.double)
                new_lo = lo - reach * _dilate(touch_lo, reach)
                new_hi = hi + reach * _dilate(touch_hi, reach)
                new_lo, new_hi = self.hull(new_lo, new_hi, m)
                raw = self.extend(scale, raw, lo, hi, new_lo, new_hi)
                lo, hi = new_lo, new_hi
            if level == 0:
                return path, cost.gather(-1, offsets.unsqueeze(-1)).sum()
            marg = _max_marginals(unary[0].numpy(), lo.numpy(), step_lp)
            keep = torch.from_numpy(
                marg >= marg.max() - self.margin * (1.0 if self.robust else threshold)
            )
            cols = torch.arange(keep.shape[1])
            keep_lo = lo + torch.where(keep, cols, keep.shape[1]).amin(-1)
            keep_hi = lo + torch.where(keep, cols, -1).amax(-1)
            coarse = path
        raise AssertionError("unreachable")

    def unary(
        self, raw: Tensor, lo: Tensor, hi: Tensor, m: int, threshold: float | None
    ) -> tuple[Tensor, Tensor, float]:
        """``(1, N, W)`` log-potentials of a band (``-inf`` outside it and off fixed ends),
        the shaped costs, and the threshold."""
        _check_cost(raw)
        cost, threshold = self.shape(raw, threshold)
        cols = torch.arange(raw.shape[1])
        unary = torch.where(cols <= (hi - lo)[:, None], -cost, -math.inf).unsqueeze(0)
        if self.fix_start:
            unary[:, 0] = unary[:, 0].masked_fill(lo[0] + cols != 0, -math.inf)
        if self.fix_end:
            unary[:, -1] = unary[:, -1].masked_fill(lo[-1] + cols != m - 1, -math.inf)
        return unary, cost, threshold

    def map(self, unary: Tensor, lo: Tensor) -> tuple[Tensor, Tensor]:
        """The best path in a band (absolute cells) and its window offsets."""
        step = None if self.step_cost is None else -self.step_cost
        banded = BandedMonotoneFactor(self.max_step, lo, step)
        try:
            result = chain_map(unary.clone(), banded, overwrite=True)
        except InfeasibleError as err:
            raise AlignmentError(
                "no monotone path fits the band around the coarse path "
                f"(T'={self.num_video}, T={self.num_ref}, max_step={self.max_step}, "
                f"fix_start={self.fix_start}, fix_end={self.fix_end}); increase radius"
            ) from err
        offsets = result.assignment[0]
        return lo + offsets, offsets


def _dilate(mask: Tensor, width: int) -> Tensor:
    """``mask`` widened by ``width`` entries either side (long 0/1)."""
    x = mask.double()[None, None]
    return (torch.nn.functional.max_pool1d(x, 2 * width + 1, 1, width)[0, 0] > 0).long()
