"""Loopy BP: exact on trees, close to brute force on weakly coupled cycles, reports changes."""

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
