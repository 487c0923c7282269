"""Loopy BP: exact on trees, close to brute force on weakly coupled cycles, reports changes."""

import math

import pytest
import torch

from pgm import FactorGraph, MaxSemiring, TableFactor, loopy_bp, tree_inference, tree_map
from tests.conftest import brute_marginals, enumerate_scores


def test_loopy_on_a_tree_converges_to_the_exact_marginals():
    torch.manual_seed(0)
    unary = torch.randn(2, 8, 4, dtype=torch.float64)
    edges = torch.tensor([[0, 1], [1, 2], [1, 3], [3, 4], [0, 5], [5, 6], [7, 6]])
    graph = FactorGraph(unary, [(edges, TableFactor(torch.randn(7, 4, 4, dtype=torch.float64)))])
    result = loopy_bp(graph, max_iters=100, damping=0.0, tol=1e-12)
    torch.testing.assert_close(result.log_marginals, tree_inference(graph).log_marginals)
    assert result.message_change[-1] < 1e-12
    assert len(result.message_change) < 100
    best = loopy_bp(graph, MaxSemiring(), max_iters=100, damping=0.3, tol=1e-12)
    assert torch.equal(best.assignment, tree_map(graph).assignment)


def test_loopy_on_a_weakly_coupled_grid_is_close_to_brute_force():
    torch.manual_seed(1)
    k = 3
    unary = torch.randn(1, 9, k, dtype=torch.float64)
    edges = []
    for r in range(3):
        for c in range(3):
            i = 3 * r + c
            if c < 2:
                edges.append((i, i + 1))
            if r < 2:
                edges.append((i, i + 3))
    edges = torch.tensor(edges)
    tables = 0.2 * torch.randn(len(edges), k, k, dtype=torch.float64)
    graph = FactorGraph(unary, [(edges, TableFactor(tables))])
    changes = []
    result = loopy_bp(
        graph,
        damping=0.5,
        tol=1e-10,
        max_iters=500,
        callback=lambda it, ch: changes.append((it, ch)),
    )
    configs, scores = enumerate_scores(unary, [(edges, tables[None])])
    exact = brute_marginals(configs, scores, k)
    # weak couplings: BP's marginals are within 0.02 of the truth (Bethe approximation)
    assert (result.log_marginals.exp() - exact).abs().max() < 0.02
    assert changes == list(enumerate(result.message_change))
    assert result.message_change[-1] < 1e-10
    assert result.log_partition is None


def test_loopy_rejects_bad_settings():
    graph = FactorGraph(
        torch.zeros(2, 2), [(torch.tensor([[0, 1]]), TableFactor(torch.zeros(2, 2)))]
    )
    with pytest.raises(ValueError, match=r"damping must be in \[0, 1\)"):
        loopy_bp(graph, damping=1.0)
    with pytest.raises(ValueError, match="max_iters"):
        loopy_bp(graph, max_iters=0)


class _EveryMessageMax(MaxSemiring):
    """Max-product recomputing every message every iteration (the plain flooding schedule)."""

    batch_invariant = False


def _random_loopy_graph(seed: int) -> FactorGraph:
    """A random multigraph with cycles, a tree-like tail that settles early, -inf entries
    in some unaries and tables, and two factor groups (one table stored transposed)."""
    g = torch.Generator().manual_seed(seed)
    v, k = 14, 5
    cycle = torch.randint(0, 6, (10, 2), generator=g)
    cycle = cycle[cycle[:, 0] != cycle[:, 1]]
    tail = torch.stack([torch.arange(5, v - 1), torch.arange(6, v)], 1)  # a chain: settles
    unary = torch.randn(2, v, k, generator=g, dtype=torch.float64) * 2
    unary[torch.rand(2, v, k, generator=g) < 0.15] = -math.inf
    tables = torch.randn(len(cycle), k, k, generator=g, dtype=torch.float64)
    tables[torch.rand(tables.shape, generator=g) < 0.1] = -math.inf
    transposed = torch.randn(2, len(tail), k, k, generator=g, dtype=torch.float64).transpose(-1, -2)
    return FactorGraph(unary, [(cycle, TableFactor(tables)), (tail, TableFactor(transposed))])


@pytest.mark.parametrize("damping", [0.0, 0.3])
def test_max_product_recomputing_only_what_can_change_gives_the_bits_of_recomputing_all(
    monkeypatch, damping
):
    """Under max-product loopy BP skips the messages none of whose inputs changed; the
    marginals, the assignment and every iteration's change are those of recomputing every
    message, bit for bit, and the skipping does happen (some iterations recompute a
    subset without damping; a damped message, a mix of old and new, seldom comes back bit
    for bit, and the two must then agree all the same)."""
    import pgm.loopy as loopy

    subsets = []
    plain = loopy._new_messages

    def spy(graph, wiring, semiring, msgs, base_out, ids):
        subsets.append(ids is not None)
        return plain(graph, wiring, semiring, msgs, base_out, ids)

    monkeypatch.setattr(loopy, "_new_messages", spy)
    for seed in range(12):
        graph = _random_loopy_graph(seed)
        fast = loopy_bp(graph, MaxSemiring(), max_iters=40, damping=damping, tol=0.0)
        every = loopy_bp(graph, _EveryMessageMax(), max_iters=40, damping=damping, tol=0.0)
        assert torch.equal(fast.log_marginals.nan_to_num(7.0), every.log_marginals.nan_to_num(7.0))
        assert torch.equal(fast.assignment, every.assignment)
        assert fast.message_change == every.message_change
    assert any(subsets) or damping > 0
