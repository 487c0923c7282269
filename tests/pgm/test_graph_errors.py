"""Bad input to graph construction raises GraphError naming what was expected and given."""

import math

import pytest
import torch

from pgm import FactorGraph, GraphError, TableFactor


def test_unary_shape():
    with pytest.raises(
        GraphError, match=r"unary must have shape \(B, V, K\) or \(V, K\); got \(3,\)"
    ):
        FactorGraph(torch.zeros(3))


def test_unary_values():
    with pytest.raises(GraphError, match="unary contains NaN"):
        FactorGraph(torch.tensor([[0.0, math.nan]]))
    with pytest.raises(GraphError, match=r"unary contains \+inf"):
        FactorGraph(torch.tensor([[0.0, math.inf]]))


def test_empty_graph():
    with pytest.raises(GraphError, match="V >= 1 nodes and K >= 1 states"):
        FactorGraph(torch.zeros(1, 0, 3))


def test_edges_shape_and_range():
    unary = torch.zeros(3, 2)
    table = TableFactor(torch.zeros(2, 2))
    with pytest.raises(
        GraphError, match=r"edges must be an integer tensor of shape \(E, 2\); got \(3,\)"
    ):
        FactorGraph(unary, [(torch.tensor([0, 1, 2]), table)])
    with pytest.raises(GraphError, match=r"nodes outside \[0, 3\)"):
        FactorGraph(unary, [(torch.tensor([[0, 3]]), table)])
    with pytest.raises(GraphError, match="self-loop"):
        FactorGraph(unary, [(torch.tensor([[1, 1]]), table)])


def test_factor_edge_count():
    with pytest.raises(GraphError, match="parameters for 3 edges but 2 edges were given"):
        FactorGraph(
            torch.zeros(3, 2), [(torch.tensor([[0, 1], [1, 2]]), TableFactor(torch.zeros(3, 2, 2)))]
        )


def test_table_validation():
    with pytest.raises(ValueError, match=r"log_table must have shape \(K, K\)"):
        TableFactor(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="NaN or \\+inf"):
        TableFactor(torch.tensor([[0.0, math.nan], [0.0, 0.0]]))


def test_log_measure_shape():
    with pytest.raises(
        GraphError, match=r"log_measure must have shape \(1, 3, 2\); got \(1, 3, 4\)"
    ):
        FactorGraph(torch.zeros(3, 2), log_measure=torch.zeros(1, 3, 4))


def test_table_states_must_match_graph():
    """Checked when the graph is built, not when inference first reads the table."""
    with pytest.raises(GraphError, match="TableFactor has 2 states per node but the graph has 3"):
        FactorGraph(torch.zeros(2, 3), [(torch.tensor([[0, 1]]), TableFactor(torch.zeros(2, 2)))])
