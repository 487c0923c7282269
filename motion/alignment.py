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
) -> Alignment:
    """Monotone alignment of long sequences without the full T' x T cost matrix.

    Both sequences are subsampled by ``factor`` (which keeps the step bound S in coarse
    units) until the problem has at most ``max_cells`` cells; that level is solved exactly by
    :func:`chain_align`; each finer level is solved exactly inside a band of ``radius``
    reference frames around the upsampled coarser path (a chain whose states are sliding
    windows, :class:`pgm.BandedMonotoneFactor`). Cost: O(T' (2 radius + 1) S) per level.
    On smooth warps the result equals the full solution (tested).

    Args:
        cost_fn: ``cost_fn(rows (R,), cols (R, W)) -> (R, W)`` costs of video frames ``rows``
            against reference frames ``cols`` (e.g. :func:`sequence_cost_fn`).
        num_video, num_ref: T' and T.
        max_step: S >= 1.
        factor: subsampling factor per level (>= 2).
        radius: band half-width in reference frames at each level (default ``factor * S``).
        max_cells: solve directly once ``T' * T`` is at most this.
        fix_start, fix_end: force C(0) = 0 / C(T'-1) = T-1.
        step_cost: optional ``(S + 1,)`` cost of each step size 0..S (a slope prior, e.g.
            :func:`slope_step_cost`), at every level: subsampling both sequences by the same
            factor keeps step sizes and the slope. With ``robust``, in units of the threshold.
        robust: ``"truncate"`` or ``"saturate"`` (see :func:`robust_cost`) at every level,
            then divided by the threshold so costs lie in [0, 1].
        robust_scale, threshold: the threshold tau; by default ``robust_scale`` times the
            median over t' of each row's minimum at the coarsest level (the only full
            matrix; its row minima, over subsampled references, are slightly above the full
            ones).

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
    if step_cost is not None:
        step_cost = _step_factor(max_step, step_cost).step_log_potential.neg()  # validated
    levels = _Levels(
        max_step, factor, radius, max_cells, fix_start, fix_end, robust, robust_scale, step_cost
    )
    path, total, _ = levels.solve(cost_fn, num_video, num_ref, threshold)
    return Alignment(path.unsqueeze(0), total.reshape(1))


@dataclass
class _Levels:
    """The settings :func:`coarse_to_fine_align` recurses with."""

    max_step: int
    factor: int
    radius: int
    max_cells: int
    fix_start: bool
    fix_end: bool
    robust: str | None
    robust_scale: float
    step_cost: Tensor | None

    def shape(self, cost: Tensor, threshold: float | None) -> tuple[Tensor, float | None]:
        """Robust, normalised costs; the threshold is fixed by the first (coarsest) call."""
        if self.robust is None:
            return cost, None
        if threshold is None:
            row_min = cost.amin(-1)
            threshold = self.robust_scale * float(row_min[torch.isfinite(row_min)].median())
            threshold = max(threshold, torch.finfo(torch.float64).tiny)
        return robust_cost(cost, threshold, self.robust) / threshold, threshold

    def solve(
        self, cost_fn: CostFn, num_video: int, num_ref: int, threshold: float | None
    ) -> tuple[Tensor, Tensor, float | None]:
        """Path ``(T',)``, its cost, and the threshold used."""
        f = self.factor
        if num_video * num_ref <= self.max_cells or num_video < 2 * f or num_ref < 2 * f:
            rows = torch.arange(num_video)
            cols = torch.arange(num_ref).expand(num_video, num_ref)
            cost, threshold = self.shape(_evaluate(cost_fn, rows, cols), threshold)
            direct = chain_align(
                cost,
                self.max_step,
                fix_start=self.fix_start,
                fix_end=self.fix_end,
                step_cost=self.step_cost,
            )
            return direct.path[0], direct.cost[0], threshold

        vid_idx = torch.arange(0, num_video, f)
        ref_idx = torch.arange(0, num_ref, f)

        def coarse_fn(rows: Tensor, cols: Tensor) -> Tensor:
            return cost_fn(vid_idx[rows], ref_idx[cols])

        coarse_path, _, threshold = self.solve(coarse_fn, len(vid_idx), len(ref_idx), threshold)
        centre = np.interp(
            np.arange(num_video), vid_idx.numpy(), ref_idx[coarse_path].double().numpy()
        )
        # Past the last coarse sample, follow the coarse slope.
        tail = np.arange(num_video) > int(vid_idx[-1])
        if tail.any() and len(vid_idx) > 1:
            slope = (centre[int(vid_idx[-1])] - centre[int(vid_idx[-2])]) / f
            centre[tail] = centre[int(vid_idx[-1])] + slope * (
                np.arange(num_video)[tail] - int(vid_idx[-1])
            )
        width = min(2 * self.radius + 1, num_ref)
        lo = torch.from_numpy(np.round(centre)).long() - self.radius
        lo = torch.cummax(lo.clamp(0, num_ref - width), 0).values
        cols = lo[:, None] + torch.arange(width)
        cost, threshold = self.shape(_evaluate(cost_fn, torch.arange(num_video), cols), threshold)
        _check_cost(cost)
        unary = -cost.unsqueeze(0)
        if self.fix_start:
            unary[:, 0] = unary[:, 0].masked_fill(cols[0] != 0, -math.inf)
        if self.fix_end:
            unary[:, -1] = unary[:, -1].masked_fill(cols[-1] != num_ref - 1, -math.inf)
        step_lp = None if self.step_cost is None else -self.step_cost
        banded = BandedMonotoneFactor(self.max_step, lo, step_lp)
        try:
            result = chain_map(unary, banded)
        except InfeasibleError as err:
            raise AlignmentError(
                "no monotone path fits the band around the coarse path; increase radius"
            ) from err
        offsets = result.assignment[0]
        return lo + offsets, cost.gather(-1, offsets.unsqueeze(-1)).sum(), threshold
