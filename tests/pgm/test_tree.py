"""Exact tree inference against brute-force enumeration, identities and pgmpy."""

import math
import warnings

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pgm import (
    CountingSemiring,
    FactorGraph,
    LogSemiring,
    MaxSemiring,
    MonotoneFactor,
    NotATreeError,
    TableFactor,
    TemperedSemiring,
    chain_inference,
    tree_inference,
    tree_map,
)
from tests.conftest import brute_marginals, enumerate_scores


@st.composite
def random_forest(draw, max_nodes=6, max_states=3):
    """A random forest: node i > 0 attaches to an earlier node or starts a new tree."""
    v = draw(st.integers(1, max_nodes))
    k = draw(st.integers(1, max_states))
    b = draw(st.integers(1, 3))
    seed = draw(st.integers(0, 2**31 - 1))
    edges = []
    for i in range(1, v):
        parent = draw(st.integers(-1, i - 1))
        if parent >= 0:
            # random orientation so that both message directions are exercised
            edges.append((parent, i) if draw(st.booleans()) else (i, parent))
    g = torch.Generator().manual_seed(seed)
    unary = torch.randn(b, v, k, generator=g, dtype=torch.float64)
    edges_t = torch.tensor(edges, dtype=torch.long).reshape(-1, 2)
    tables = torch.randn(b, len(edges), k, k, generator=g, dtype=torch.float64)
    if draw(st.booleans()) and k > 1:  # some forbidden pairs
        tables = tables.masked_fill(torch.rand(tables.shape, generator=g) < 0.2, -math.inf)
        tables[..., 0, 0] = 0.0  # keep at least one allowed configuration
    return unary, edges_t, tables


def _graph(unary, edges, tables):
    groups = [(edges, TableFactor(tables))] if len(edges) else []
    return FactorGraph(unary, groups)


@settings(max_examples=40, deadline=None)
@given(random_forest())
def test_log_partition_and_marginals_match_brute_force(problem):
    unary, edges, tables = problem
    configs, scores = enumerate_scores(unary, [(edges, tables)])
    result = tree_inference(_graph(unary, edges, tables), LogSemiring())
    torch.testing.assert_close(result.log_partition, torch.logsumexp(scores, -1))
    expected = brute_marginals(configs, scores, unary.shape[-1])
    torch.testing.assert_close(result.log_marginals.exp(), expected, atol=1e-10, rtol=1e-8)


@settings(max_examples=40, deadline=None)
@given(random_forest())
def test_map_matches_brute_force(problem):
    unary, edges, tables = problem
    configs, scores = enumerate_scores(unary, [(edges, tables)])
    result = tree_map(_graph(unary, edges, tables))
    best = scores.max(-1).values
    torch.testing.assert_close(result.log_partition, best)
    # the score of the decoded assignment equals the max (robust to ties)
    idx = (configs[None] == result.assignment[:, None]).all(-1).float().argmax(-1)
    torch.testing.assert_close(scores.gather(-1, idx[:, None]).squeeze(-1), best)
    # max-marginals: max over configurations with x_v = k
    for v in range(unary.shape[1]):
        for k in range(unary.shape[2]):
            sel = scores[:, configs[:, v] == k].max(-1).values - best
            torch.testing.assert_close(result.log_marginals[:, v, k], sel)


@settings(max_examples=25, deadline=None)
@given(random_forest(), st.floats(0.05, 3.0))
def test_tempered_semiring_matches_brute_force(problem, tau):
    unary, edges, tables = problem
    configs, scores = enumerate_scores(unary, [(edges, tables)])
    result = tree_inference(_graph(unary, edges, tables), TemperedSemiring(tau))
    torch.testing.assert_close(result.log_partition, tau * torch.logsumexp(scores / tau, -1))
    expected = brute_marginals(configs, scores / tau, unary.shape[-1])
    torch.testing.assert_close(result.log_marginals.exp(), expected, atol=1e-10, rtol=1e-8)


@settings(max_examples=25, deadline=None)
@given(random_forest())
def test_counting_semiring_counts_allowed_configurations(problem):
    unary, edges, tables = problem
    _, scores = enumerate_scores(unary, [(edges, tables)])
    result = tree_inference(_graph(unary, edges, tables), CountingSemiring())
    torch.testing.assert_close(result.log_partition, torch.isfinite(scores).sum(-1).double())


@pytest.mark.parametrize(("v", "k"), [(1, 5), (4, 3), (7, 2)])
def test_counting_without_constraints_gives_k_to_the_n(v, k):
    edges = torch.stack([torch.arange(v - 1), torch.arange(1, v)], 1)
    graph = FactorGraph(
        torch.zeros(1, v, k, dtype=torch.float64),
        [(edges, TableFactor(torch.zeros(k, k, dtype=torch.float64)))],
    )
    assert tree_inference(graph, CountingSemiring()).log_partition.item() == k**v


def test_max_is_at_most_logsumexp_and_marginals_normalised():
    torch.manual_seed(0)
    unary = torch.randn(4, 9, 5, dtype=torch.float64)
    edges = torch.tensor([[0, 1], [1, 2], [1, 3], [3, 4], [0, 5], [5, 6], [6, 7], [2, 8]])
    graph = FactorGraph(unary, [(edges, TableFactor(torch.randn(8, 5, 5, dtype=torch.float64)))])
    log_z = tree_inference(graph).log_partition
    assert (tree_map(graph).log_partition <= log_z).all()
    torch.testing.assert_close(
        tree_inference(graph).log_marginals.exp().sum(-1), torch.ones(4, 9, dtype=torch.float64)
    )


@pytest.mark.parametrize(
    "semiring", [LogSemiring(), MaxSemiring(), CountingSemiring()], ids=lambda s: s.name
)
def test_chain_as_generic_tree_gives_same_answer(semiring):
    torch.manual_seed(1)
    n, k = 12, 6
    unary = torch.randn(2, n, k, dtype=torch.float64)
    edges = torch.stack([torch.arange(n - 1), torch.arange(1, n)], 1)
    for factor in [TableFactor(torch.randn(n - 1, k, k, dtype=torch.float64)), MonotoneFactor(2)]:
        tree = tree_inference(FactorGraph(unary, [(edges, factor)]), semiring)
        chain = chain_inference(unary, factor, semiring)
        torch.testing.assert_close(tree.log_partition, chain.log_partition)
        torch.testing.assert_close(tree.log_marginals, chain.log_marginals)


def test_batched_equals_looped():
    torch.manual_seed(2)
    unary = torch.randn(5, 7, 4, dtype=torch.float64)
    edges = torch.tensor([[0, 1], [2, 1], [1, 3], [3, 4], [5, 3], [6, 5]])
    tables = torch.randn(5, 6, 4, 4, dtype=torch.float64)
    batched = tree_map(FactorGraph(unary, [(edges, TableFactor(tables))]))
    batched_log = tree_inference(FactorGraph(unary, [(edges, TableFactor(tables))]))
    for i in range(5):
        one = FactorGraph(unary[i : i + 1], [(edges, TableFactor(tables[i : i + 1]))])
        assert torch.equal(tree_map(one).assignment, batched.assignment[i : i + 1])
        torch.testing.assert_close(
            tree_inference(one).log_marginals, batched_log.log_marginals[i : i + 1]
        )


def test_several_factor_groups_and_support_measure():
    """Two factor types on one tree, and a non-uniform log-measure, against brute force."""
    torch.manual_seed(3)
    unary = torch.randn(2, 5, 4, dtype=torch.float64)
    measure = torch.randn(2, 5, 4, dtype=torch.float64)
    g1 = torch.tensor([[0, 1], [1, 2]])
    g2 = torch.tensor([[3, 1], [2, 4]])
    t1 = torch.randn(2, 4, 4, dtype=torch.float64)
    mono = MonotoneFactor(1)
    t2 = mono.log_potential(None, None, None, 4).double()
    graph = FactorGraph(unary, [(g1, TableFactor(t1)), (g2, mono)], log_measure=measure)
    configs, scores = enumerate_scores(unary + measure, [(g1, t1[None]), (g2, t2)])
    result = tree_inference(graph)
    torch.testing.assert_close(result.log_partition, torch.logsumexp(scores, -1))
    torch.testing.assert_close(result.log_marginals.exp(), brute_marginals(configs, scores, 4))


def test_cycle_is_rejected():
    edges = torch.tensor([[0, 1], [1, 2], [2, 0]])
    graph = FactorGraph(torch.zeros(3, 2), [(edges, TableFactor(torch.zeros(2, 2)))])
    with pytest.raises(NotATreeError, match=r"edge \(2, 0\) closes a cycle"):
        tree_inference(graph)


def test_against_pgmpy_belief_propagation():
    pytest.importorskip("pgmpy")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from pgmpy.factors.discrete import DiscreteFactor
        from pgmpy.inference import BeliefPropagation
        from pgmpy.models import DiscreteMarkovNetwork

    gen = torch.Generator().manual_seed(4)
    for trial in range(5):
        v, k = 7, 3
        parents = [int(torch.randint(0, i, (1,), generator=gen)) for i in range(1, v)]
        edges = torch.tensor([[p, i + 1] for i, p in enumerate(parents)])
        unary = torch.randn(1, v, k, generator=gen, dtype=torch.float64)
        tables = torch.randn(1, v - 1, k, k, generator=gen, dtype=torch.float64)
        ours = tree_inference(FactorGraph(unary, [(edges, TableFactor(tables))]))
        ours_map = tree_map(FactorGraph(unary, [(edges, TableFactor(tables))]))

        names = [f"x{i}" for i in range(v)]
        model = DiscreteMarkovNetwork([(names[a], names[b]) for a, b in edges.tolist()])
        factors = [DiscreteFactor([names[i]], [k], unary[0, i].exp().numpy()) for i in range(v)]
        factors += [
            DiscreteFactor([names[a], names[b]], [k, k], tables[0, e].exp().numpy().ravel())
            for e, (a, b) in enumerate(edges.tolist())
        ]
        model.add_factors(*factors)
        bp = BeliefPropagation(model)
        bp.calibrate()
        for i in range(v):
            q = bp.query([names[i]], show_progress=False)
            torch.testing.assert_close(
                ours.log_marginals[0, i].exp(),
                torch.as_tensor(q.values),
                atol=1e-9,
                rtol=1e-7,
                msg=f"trial {trial} node {i}",
            )
        pg_map = bp.map_query(names, show_progress=False)
        assert [pg_map[n] for n in names] == ours_map.assignment[0].tolist()


@pytest.mark.parametrize("semiring", [LogSemiring(), MaxSemiring(), CountingSemiring()])
@pytest.mark.parametrize("dim", [0, 1, 2])
def test_exclusive_products_equal_the_product_of_the_others(semiring, dim):
    """prefix x suffix along any axis equals multiplying every other entry directly."""
    from pgm.tree import exclusive_products

    x = torch.rand(3, 4, 5, dtype=torch.float64) * 2 - 1
    if isinstance(semiring, CountingSemiring):
        x = x.abs() + 0.5
    out = exclusive_products(x, dim, semiring)
    for i in range(x.shape[dim]):
        others = torch.cat([x.narrow(dim, 0, i), x.narrow(dim, i + 1, x.shape[dim] - i - 1)], dim)
        torch.testing.assert_close(out.select(dim, i), semiring.prod(others, dim=dim))
