"""Chains: long-chain numerics, structured monotone kernels, fused Viterbi."""

import itertools
import math

import pytest
import torch

from pgm import (
    BandedMonotoneFactor,
    BandedTempoFactor,
    CountingSemiring,
    FactorGraph,
    GraphError,
    InfeasibleError,
    LogSemiring,
    MaxSemiring,
    MonotoneFactor,
    PairwiseFactor,
    TableFactor,
    TemperedSemiring,
    chain_inference,
    chain_map,
    tree_map,
)
from tests.conftest import brute_marginals, enumerate_scores


def _chain_edges(n):
    return torch.stack([torch.arange(n - 1), torch.arange(1, n)], 1)


def _count_monotone(n, k, s):
    """Number of sequences x_0..x_{n-1} in [0, k) with steps in [0, s], by plain DP."""
    ways = [1] * k
    for _ in range(n - 1):
        ways = [sum(ways[max(0, j - s) : j + 1]) for j in range(k)]
    return sum(ways)


@pytest.mark.parametrize(("n", "k", "s"), [(2, 5, 1), (6, 5, 2), (10, 8, 3), (4, 6, 10)])
def test_monotone_counting_matches_combinatorics(n, k, s):
    unary = torch.zeros(1, n, k, dtype=torch.float64)
    count = chain_inference(unary, MonotoneFactor(s), CountingSemiring()).log_partition.item()
    assert count == _count_monotone(n, k, s)


@pytest.mark.parametrize(("n", "k"), [(3, 4), (8, 6)])
def test_unbounded_monotone_counts_multisets(n, k):
    # non-decreasing sequences of length n over k values: C(n + k - 1, n)
    unary = torch.zeros(1, n, k, dtype=torch.float64)
    count = chain_inference(unary, MonotoneFactor(None), CountingSemiring()).log_partition.item()
    assert count == math.comb(n + k - 1, n)


@pytest.mark.parametrize(
    "factor",
    [
        MonotoneFactor(2),
        MonotoneFactor(None),
        MonotoneFactor(3, torch.tensor([0.0, -0.5, 0.3, -2.0])),
    ],
    ids=["window", "prefix", "weighted"],
)
@pytest.mark.parametrize(
    "semiring", [LogSemiring(), MaxSemiring(), CountingSemiring()], ids=lambda s: s.name
)
def test_structured_kernel_equals_its_dense_table(factor, semiring):
    torch.manual_seed(0)
    n, k = 9, 7
    unary = torch.randn(3, n, k, dtype=torch.float64)
    dense = TableFactor(factor.log_potential(None, None, None, k).double())
    a = chain_inference(unary, factor, semiring)
    b = chain_inference(unary, dense, semiring)
    torch.testing.assert_close(a.log_partition, b.log_partition)
    torch.testing.assert_close(a.log_marginals, b.log_marginals)


def test_monotone_chain_against_brute_force():
    torch.manual_seed(1)
    n, k = 5, 4
    unary = torch.randn(2, n, k, dtype=torch.float64)
    factor = MonotoneFactor(1)
    configs, scores = enumerate_scores(
        unary, [(_chain_edges(n), factor.log_potential(None, None, None, k).double())]
    )
    res = chain_inference(unary, factor)
    torch.testing.assert_close(res.log_partition, torch.logsumexp(scores, -1))
    torch.testing.assert_close(res.log_marginals.exp(), brute_marginals(configs, scores, k))
    best = chain_map(unary, factor)
    torch.testing.assert_close(best.log_partition, scores.max(-1).values)
    assert torch.equal(best.assignment, configs[scores.argmax(-1)])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_thousand_step_chain_does_not_underflow(dtype):
    """Potentials of e^-50 per node: the linear-space product would underflow at step ~15."""
    torch.manual_seed(2)
    n, k = 1000, 5
    unary = (-50.0 + torch.rand(1, n, k, dtype=torch.float64)).to(dtype)
    table = torch.rand(k, k, dtype=torch.float64).to(dtype)
    ref = chain_inference(unary.double(), TableFactor(table.double()))
    for semiring in [LogSemiring(), MaxSemiring()]:
        res = chain_inference(unary, TableFactor(table), semiring)
        assert torch.isfinite(res.log_partition).all()
        assert torch.isfinite(res.log_marginals).all()
    res = chain_inference(unary, TableFactor(table))
    tol = 1e-9 if dtype == torch.float64 else 1e-5
    assert abs(res.log_partition.double().item() - ref.log_partition.item()) / 5e4 < tol
    torch.testing.assert_close(
        res.log_marginals.exp().double(), ref.log_marginals.exp(), atol=tol * 100, rtol=0
    )
    # Closed form with uniform potentials: log Z = n log k exactly.
    flat = chain_inference(
        torch.zeros(1, n, k, dtype=dtype), TableFactor(torch.zeros(k, k, dtype=dtype))
    )
    assert flat.log_partition.item() == pytest.approx(n * math.log(k), rel=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_viterbi_equals_generic_path(dtype):
    torch.manual_seed(3)
    unary = torch.rand(3, 300, 400, dtype=dtype).neg()
    unary[1, :, :50] = -math.inf  # forbidden region
    factor = MonotoneFactor(5)
    fused = chain_map(unary, factor)
    generic = chain_map(unary, factor, use_fused=False)
    assert torch.equal(fused.assignment, generic.assignment)
    torch.testing.assert_close(fused.log_partition, generic.log_partition)
    steps = fused.assignment.diff(dim=-1)
    assert ((steps >= 0) & (steps <= 5)).all()
    # score of the argmax equals the max
    score = unary.gather(-1, fused.assignment[..., None]).squeeze(-1).sum(-1)
    torch.testing.assert_close(score, fused.log_partition)


def test_banded_factor_equals_dense_table():
    torch.manual_seed(4)
    n, w = 25, 6
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.randint(0, 4, (n - 1,)).cumsum(0)])
    factor = BandedMonotoneFactor(3, offsets)
    dense = TableFactor(factor.log_potential(slice(0, n - 1), None, None, w).double())
    unary = torch.randn(2, n, w, dtype=torch.float64)
    for semiring in [LogSemiring(), MaxSemiring(), CountingSemiring()]:
        a = chain_inference(unary, factor, semiring)
        b = chain_inference(unary, dense, semiring)
        torch.testing.assert_close(a.log_partition, b.log_partition)
    a = chain_map(unary, factor)
    assert torch.equal(a.assignment, chain_map(unary, dense).assignment)
    assert torch.equal(
        a.assignment, tree_map(FactorGraph(unary, [(_chain_edges(n), factor)])).assignment
    )


def test_banded_factor_with_step_potentials_equals_dense_table_and_monotone_factor():
    """A slope prior on the band: the dense table of the same factor (every semiring,
    counting included: a step potential counts once, it is no weight), the fused kernel, and
    -- with windows covering the whole axis -- MonotoneFactor with the same step potentials
    on the full problem, all agree."""
    torch.manual_seed(6)
    n, w, s = 20, 7, 3
    steps = torch.tensor([-0.5, 0.0, -0.3, -2.0], dtype=torch.float64)
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.randint(0, 3, (n - 1,)).cumsum(0)])
    factor = BandedMonotoneFactor(s, offsets, steps)
    dense = TableFactor(factor.log_potential(slice(0, n - 1), None, None, w).double())
    unary = torch.randn(2, n, w, dtype=torch.float64)
    for semiring in [LogSemiring(), MaxSemiring(), TemperedSemiring(0.3), CountingSemiring()]:
        a = chain_inference(unary, factor, semiring)
        b = chain_inference(unary, dense, semiring)
        torch.testing.assert_close(a.log_partition, b.log_partition)
        torch.testing.assert_close(a.log_marginals, b.log_marginals)
    count = chain_inference(unary, factor, CountingSemiring()).log_partition
    assert (count == count.round()).all() and (count > 0).all()  # a count of paths
    fused, generic = chain_map(unary, factor), chain_map(unary, factor, use_fused=False)
    assert torch.equal(fused.assignment, chain_map(unary, dense).assignment)
    assert torch.equal(fused.assignment, generic.assignment)
    torch.testing.assert_close(fused.log_partition, generic.log_partition)
    # windows = the whole axis
    full = torch.randn(2, n, 12, dtype=torch.float64)
    banded = chain_map(full, BandedMonotoneFactor(s, torch.zeros(n, dtype=torch.long), steps))
    plain = chain_map(full, MonotoneFactor(s, steps))
    assert torch.equal(banded.assignment, plain.assignment)
    torch.testing.assert_close(banded.log_partition, plain.log_partition)
    with pytest.raises(ValueError, match=r"step_log_potential must have shape \(4,\)"):
        BandedMonotoneFactor(s, offsets, torch.zeros(3))


def test_tempo_factor_with_one_level_per_step_is_a_second_order_chain():
    """L = S + 1 levels, level l emitting step l only: the lifted chain's log-partition and
    MAP are those of the second-order chain on positions (steps' and changes' potentials),
    summed / maximised over every monotone position path by brute force -- the first
    node's level is free, so the brute force sums (or maximises) over it too."""
    torch.manual_seed(8)
    n, w, s = 5, 3, 2
    offsets = torch.tensor([0, 1, 1, 3, 4])
    step_lp = torch.randn(s + 1, dtype=torch.float64)
    change = torch.randn(s + 1, s + 1, dtype=torch.float64)
    emission = torch.full((s + 1, s + 1), -math.inf, dtype=torch.float64)
    emission.diagonal().copy_(step_lp)
    factor = BandedTempoFactor(s, offsets, emission, change)
    unary = torch.randn(n, w, dtype=torch.float64)
    lifted = unary.repeat_interleave(s + 1, -1)[None]
    scores, paths = [], []
    for idx in itertools.product(range(w), repeat=n):
        pos = [int(offsets[t]) + i for t, i in enumerate(idx)]
        steps = [b - a for a, b in itertools.pairwise(pos)]
        if not all(0 <= x <= s for x in steps):
            continue
        base = sum(unary[t, i].item() for t, i in enumerate(idx))
        base += sum(step_lp[x].item() for x in steps)
        base += sum(change[b, a].item() for a, b in itertools.pairwise(steps))
        free = torch.logsumexp(change[steps[0]], 0).item()  # the first node's level
        scores.append((base + free, base + change[steps[0]].max().item()))
        paths.append(idx)
    total = torch.logsumexp(torch.tensor([a for a, _ in scores], dtype=torch.float64), 0)
    torch.testing.assert_close(
        chain_inference(lifted, factor, LogSemiring()).log_partition[0], total
    )
    best = max(range(len(paths)), key=lambda i: scores[i][1])
    result = chain_map(lifted, factor)
    assert (result.assignment[0] // (s + 1)).tolist() == list(paths[best])
    assert result.log_partition[0].item() == pytest.approx(scores[best][1], abs=1e-10)
    padded = factor.log_potential(slice(0, 1), None, None, w * (s + 1) + 2)
    assert padded[..., -2:, :].isneginf().all() and padded[..., -2:].isneginf().all()


def test_infeasible_chain_raises():
    unary = torch.zeros(1, 3, 10)
    unary[:, 0, 1:] = -math.inf
    unary[:, 2, :9] = -math.inf  # need +9 in two steps of at most 2
    with pytest.raises(InfeasibleError, match="no configuration"):
        chain_map(unary, MonotoneFactor(2))


def test_infeasible_band_raises_on_the_fused_and_generic_paths():
    """Windows too far apart for the step bound (a shift of 9 with W = 3, S = 2)."""
    factor = BandedMonotoneFactor(2, torch.tensor([0, 0, 9, 9]))
    for fused in (True, False):
        with pytest.raises(InfeasibleError, match="no configuration"):
            chain_map(torch.zeros(1, 4, 3), factor, use_fused=fused)


def test_chain_input_errors():
    with pytest.raises(GraphError, match=r"shape \(B, N, K\) or \(N, K\); got \(4,\)"):
        chain_map(torch.zeros(4), MonotoneFactor(1))
    with pytest.raises(GraphError, match="NaN"):
        chain_map(torch.tensor([[0.0, math.nan]]), MonotoneFactor(1))
    with pytest.raises(GraphError, match="N >= 1"):
        chain_map(torch.zeros(1, 0, 3), MonotoneFactor(1))
    with pytest.raises(GraphError, match="parameters for 2 edges; a chain of 5 nodes has 4"):
        chain_map(torch.zeros(5, 3), TableFactor(torch.zeros(2, 3, 3)))
    with pytest.raises(ValueError, match="max_step"):
        MonotoneFactor(0)
    with pytest.raises(ValueError, match=r"step_log_potential must have shape \(3,\)"):
        MonotoneFactor(2, torch.zeros(2))


@pytest.mark.parametrize(("s", "k"), [(1, 9), (2, 9), (3, 9), (8, 9), (9, 9), (12, 5)])
def test_fused_viterbi_breaks_ties_like_the_generic_path(s, k):
    """All-equal potentials: every path ties, so both paths must apply the same rule."""
    unary = torch.zeros(2, 7, k)
    unary[1, :, 0] = -1.0
    fused = chain_map(unary, MonotoneFactor(s))
    generic = chain_map(unary, MonotoneFactor(s), use_fused=False)
    assert torch.equal(fused.assignment, generic.assignment)
    torch.testing.assert_close(fused.log_partition, generic.log_partition)


def test_fused_viterbi_overwrite_uses_the_buffer():
    unary = -torch.rand(1, 50, 30)
    keep = unary.clone()
    a = chain_map(unary, MonotoneFactor(3))
    assert torch.equal(unary, keep)
    b = chain_map(unary, MonotoneFactor(3), overwrite=True)
    assert torch.equal(a.assignment, b.assignment)


def test_banded_fused_viterbi_breaks_ties_like_the_generic_path():
    offsets = torch.tensor([0, 0, 2, 3, 3, 7, 9])
    unary = torch.zeros(2, 7, 5)
    unary[1, :, 1] = -1.0
    factor = BandedMonotoneFactor(3, offsets)
    fused = chain_map(unary, factor)
    generic = chain_map(unary, factor, use_fused=False)
    assert torch.equal(fused.assignment, generic.assignment)
    torch.testing.assert_close(fused.log_partition, generic.log_partition)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_table_matmul_messages_equal_log_sum_exp(dtype):
    """Large tables take the exp-matmul path; it must agree with log-sum-exp, including
    forbidden pairs and a dynamic range that underflows exp() (recomputed exactly)."""
    torch.manual_seed(5)
    k = 64
    table = torch.randn(2, 3, k, k, dtype=dtype) * 5
    table[0, 0, :, 3] = -math.inf  # a column with no mass
    table[1, 2, 7] = -math.inf
    table[1, 1, :10, 20] = -400.0  # far below the column's peak -> exp underflows
    table[1, 1, 10:, 20] = -math.inf
    h = torch.randn(2, 3, k, dtype=dtype) * 3
    h[1, 1, 10:] = -math.inf
    h[1, 1, :10] = 50.0
    factor = TableFactor(table)
    for forward in (True, False):
        fast = factor.message(h, slice(None), forward, LogSemiring())
        slow = PairwiseFactor.message(factor, h, slice(None), forward, LogSemiring())
        torch.testing.assert_close(
            fast, slow, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=1e-4
        )
    assert torch.isfinite(factor.message(h, slice(None), True, LogSemiring())[1, 1, 20])


@pytest.mark.parametrize("bound", [0.0, 40.0, 60.0, -20.0, 70.0, 120.0])
def test_table_messages_with_an_upper_bound_equal_log_sum_exp(bound):
    """One exp(T - bound) table for both directions: exact wherever the floor could matter --
    columns and rows whose entries all lie 100-400 nats below the bound, single surviving
    entries, forbidden pairs -- against the generic log-sum-exp message, float32. Bounds in
    [0, 60] take exp(T) unshifted; the others shift first."""
    torch.manual_seed(7)
    k = 64
    table = -torch.rand(2, 3, k, k) * 30 - 1.0  # below the bound 0
    table[0, 1, :, 5] -= 300.0  # a column far below the bound
    table[1, 0, 9, :] -= 150.0  # a row far below it
    table[1, 2, :, 7] = -400.0
    table[1, 2, 3, 7] = -80.0  # one entry just above the floor
    table[0, 0, 2, :4] = -math.inf
    h = torch.randn(2, 3, k) * 3
    table = table + bound
    bounded = TableFactor(table, upper_bound=bound)
    plain = TableFactor(table)
    for forward in (True, False):
        fast = bounded.message(h, slice(None), forward, LogSemiring())
        slow = PairwiseFactor.message(plain, h, slice(None), forward, LogSemiring())
        torch.testing.assert_close(fast, slow, rtol=1e-5, atol=1e-4)
