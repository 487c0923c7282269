"""Exact inference on chains with one pairwise factor between consecutive nodes.

A chain is a tree, and :func:`pgm.tree.tree_inference` handles it; this module is the lean
path for long chains (a time-correspondence chain of 7,500 video frames over 36,000 reference
frames): one factor call per step, messages rescaled every step so that a chain of any length
neither underflows nor loses float32 precision, and O(S) backtracking per step for
:class:`~pgm.factors.MonotoneFactor`.

Shapes: ``B`` batch, ``N`` chain length, ``K`` states. The pairwise factor sits on edges
``(t, t + 1)``; a per-step factor (e.g. a :class:`~pgm.factors.TableFactor` with ``N - 1``
tables) is indexed by ``slice(t, t + 1)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from pgm.factors import Capability, PairwiseFactor
from pgm.graph import GraphError
from pgm.semiring import LogSemiring, MaxSemiring, Semiring
from pgm.tree import InferenceResult

__all__ = ["InfeasibleError", "chain_inference", "chain_map"]


class InfeasibleError(ValueError):
    """Every configuration of the chain has zero potential (e.g. no monotone path fits)."""


def _check_chain(unary: Tensor, factor: PairwiseFactor) -> Tensor:
    if not isinstance(unary, Tensor):
        raise GraphError(f"unary must be a torch.Tensor, got {type(unary).__name__}")
    if unary.dim() == 2:
        unary = unary.unsqueeze(0)
    if unary.dim() != 3:
        raise GraphError(
            f"chain unary must have shape (B, N, K) or (N, K); got {tuple(unary.shape)}"
        )
    if unary.shape[1] == 0 or unary.shape[2] == 0:
        raise GraphError(
            f"chain must have N >= 1 nodes and K >= 1 states; got {tuple(unary.shape)}"
        )
    total = unary.sum()  # one pass: NaN or +inf anywhere makes the sum NaN or +inf
    if (torch.isnan(total) or torch.isposinf(total)) and (
        torch.isnan(unary).any() or torch.isposinf(unary).any()
    ):
        raise GraphError("chain unary contains NaN or +inf (log-potentials must be finite or -inf)")
    if not isinstance(factor, PairwiseFactor):
        raise GraphError(f"factor must be a PairwiseFactor; got {type(factor).__name__}")
    if Capability.READS_VALUES in factor.capabilities:
        raise GraphError(
            f"factor {type(factor).__name__} reads support values (capability "
            f"'{Capability.READS_VALUES.value}'); a chain's states are indices, so it needs a "
            "factor over states (use pgm.particle_bp for particles)"
        )
    if factor.num_edges is not None and factor.num_edges != unary.shape[1] - 1:
        raise GraphError(
            f"factor {type(factor).__name__} has parameters for {factor.num_edges} edges; a chain "
            f"of {unary.shape[1]} nodes has {unary.shape[1] - 1}"
        )
    return unary


def _rescale(x: Tensor, semiring: Semiring) -> tuple[Tensor, Tensor]:
    """Shift a log-space message to semiring-sum 0; returns it and the shift (B,) in float64."""
    if not semiring.log_space:
        return x, torch.zeros(x.shape[0], dtype=torch.float64, device=x.device)
    c = semiring.sum(x, dim=-1)  # (B, 1)
    c = torch.where(torch.isfinite(c), c, torch.zeros_like(c))
    return x - c.unsqueeze(-1), c.squeeze(-1).double()


def _forward(unary: Tensor, factor: PairwiseFactor, semiring: Semiring) -> tuple[Tensor, Tensor]:
    """Rescaled forward messages ``alpha`` (B, N, K) and the accumulated log-scale (B,)."""
    _b, n, _k = unary.shape
    base = semiring.from_log(unary)
    alpha = torch.empty_like(base)
    a, log_scale = _rescale(base[:, 0:1], semiring)
    alpha[:, 0:1] = a
    for t in range(1, n):
        m = factor.message(a, slice(t - 1, t), True, semiring)
        a, c = _rescale(semiring.mul(base[:, t : t + 1], m), semiring)
        alpha[:, t : t + 1] = a
        log_scale = log_scale + c
    return alpha, log_scale


def _total(alpha_last: Tensor, log_scale: Tensor, semiring: Semiring) -> Tensor:
    z = semiring.sum(alpha_last, dim=-1)  # (B,)
    if semiring.log_space:
        return (z.double() + log_scale).to(alpha_last.dtype)
    return z


def chain_inference(
    unary: Tensor, factor: PairwiseFactor, semiring: Semiring | None = None
) -> InferenceResult:
    """Forward-backward on a chain.

    Args:
        unary: ``(B, N, K)`` log-potentials (or ``(N, K)``).
        factor: the pairwise factor on every edge ``(t, t + 1)``.
        semiring: default :class:`LogSemiring`.

    Returns:
        :class:`InferenceResult` with ``log_partition`` (B,) and ``log_marginals`` (B, N, K).
    """
    semiring = semiring or LogSemiring()
    unary = _check_chain(unary, factor)
    b, n, k = unary.shape
    alpha, log_scale = _forward(unary, factor, semiring)
    base = semiring.from_log(unary)
    beta = torch.empty_like(alpha)
    r = torch.full((b, 1, k), semiring.one, dtype=alpha.dtype, device=alpha.device)
    beta[:, n - 1 : n] = r
    for t in range(n - 2, -1, -1):
        h = semiring.mul(base[:, t + 1 : t + 2], r)
        r, _ = _rescale(factor.message(h, slice(t, t + 1), False, semiring), semiring)
        beta[:, t : t + 1] = r
    belief = semiring.mul(alpha, beta)
    return InferenceResult(
        _total(alpha[:, -1], log_scale, semiring), semiring.normalize(belief, -1)
    )


def _check_feasible(score: Tensor) -> None:
    if not torch.isfinite(score).all():
        bad = (~torch.isfinite(score)).nonzero().flatten().tolist()
        raise InfeasibleError(
            f"no configuration of the chain has a finite score (batch items {bad})"
        )


def chain_map(
    unary: Tensor, factor: PairwiseFactor, use_fused: bool = True, overwrite: bool = False
) -> InferenceResult:
    """Viterbi: the MAP assignment of a chain by max-product and backtracking.

    Args:
        unary: ``(B, N, K)`` log-potentials (or ``(N, K)``).
        factor: the pairwise factor on every edge ``(t, t + 1)``.
        use_fused: let a factor that offers a fused ``viterbi(unary)`` kernel run the whole
            sweep (the ``fused_viterbi`` capability, e.g. :meth:`pgm.MonotoneFactor.viterbi`);
            ``False`` forces the generic path.
        overwrite: allow a fused kernel to use ``unary`` as its work buffer (saves a copy
            of a possibly very large tensor; ``unary`` is garbage afterwards).

    Returns:
        :class:`InferenceResult` with ``log_partition`` = MAP score (B,) and ``assignment``
        (B, N) long; ``log_marginals`` is ``None``.

    Raises:
        InfeasibleError: if no configuration has a finite score.
    """
    semiring = MaxSemiring()
    unary = _check_chain(unary, factor)
    b, n, _k = unary.shape
    fused_result = factor.viterbi(unary, overwrite=overwrite) if use_fused else None
    if fused_result is not None:
        score, states = fused_result
        _check_feasible(score)
        return InferenceResult(score, None, states)
    alpha, log_scale = _forward(unary, factor, semiring)
    score = _total(alpha[:, -1], log_scale, semiring)
    _check_feasible(score)
    states = torch.empty(b, n, dtype=torch.long, device=unary.device)
    s = alpha[:, -1].argmax(-1, keepdim=True)  # (B, 1)
    states[:, -1:] = s
    for t in range(n - 2, -1, -1):
        s = factor.backtrack(alpha[:, t : t + 1], s, slice(t, t + 1), True)
        states[:, t : t + 1] = s
    return InferenceResult(score, None, states)
