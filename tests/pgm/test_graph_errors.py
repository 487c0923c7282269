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


# -- what a factor can do, checked when a graph is built (not during inference) ------------
def _hybrid_spaces():
    from pgm import Discrete, Euclidean

    return [(Discrete(3), torch.tensor([0, 1])), (Euclidean(1), torch.tensor([2]))]


def test_particle_graph_refuses_a_state_table_on_a_continuous_node():
    from pgm import ParticleGraph

    with pytest.raises(
        GraphError,
        match=r"pairwise\[0\]: TableFactor joins continuous node 2 but does not read particle "
        r"values \(capability 'reads_values'\)",
    ):
        ParticleGraph(
            3, _hybrid_spaces(), [(torch.tensor([[1, 2]]), TableFactor(torch.zeros(3, 3)))]
        )


def test_particle_graph_takes_a_state_table_between_discrete_nodes_of_its_size():
    from pgm import ParticleGraph

    ParticleGraph(3, _hybrid_spaces(), [(torch.tensor([[0, 1]]), TableFactor(torch.zeros(3, 3)))])
    with pytest.raises(
        GraphError,
        match=r"pairwise\[0\]: TableFactor has 4 states per node but node 0 is Discrete\(3\)",
    ):
        ParticleGraph(
            3, _hybrid_spaces(), [(torch.tensor([[0, 1]]), TableFactor(torch.zeros(4, 4)))]
        )


def test_mixture_proposal_needs_samplers_into_continuous_nodes():
    from pgm import SE3, Euclidean, ParticleGraph, RigidConnection, particle_bp

    rot_free = RigidConnection(torch.zeros(3), torch.zeros(3), pos_std=0.1)  # cannot sample
    edges = torch.tensor([[0, 1]])
    with pytest.raises(
        GraphError,
        match=r"pairwise\[0\]: RigidConnection lacks the capability 'samplable', but the mixture "
        r"proposal draws continuous node 1 \(end b\) through it",
    ):
        ParticleGraph(2, [(SE3(), torch.arange(2))], [(edges, rot_free)])
    own = ParticleGraph(2, [(SE3(), torch.arange(2))], [(edges, rot_free)], proposal="own")
    x = SE3().perturb(torch.tensor([0, 0, 0, 1.0, 0, 0, 0]).expand(1, 2, 8, 7), (0.1, 0.1))
    particle_bp(own, x, iterations=2, kernel_scale=(0.05, 0.05))  # messages only: fine
    with pytest.raises(GraphError, match="lacks the capability 'samplable'"):
        particle_bp(own, x, iterations=2, kernel_scale=(0.05, 0.05), proposal="mixture")
    with pytest.raises(GraphError, match="proposal must be one of"):
        ParticleGraph(1, [(Euclidean(1), torch.arange(1))], proposal="neighbours")


def test_particle_graph_checks_per_edge_parameter_counts():
    from pgm import LinearGaussian, ParticleGraph
    from pgm.spaces import Euclidean

    link = LinearGaussian(1, offset=torch.zeros(3, 1))  # parameters for 3 edges
    with pytest.raises(
        GraphError, match=r"pairwise\[0\]: factor LinearGaussian has parameters for 3 edges but 2"
    ):
        ParticleGraph(
            3, [(Euclidean(1), torch.arange(3))], [(torch.tensor([[0, 1], [1, 2]]), link)]
        )


def test_value_reading_factors_need_values():
    from pgm import LinearGaussian, chain_inference

    with pytest.raises(
        GraphError,
        match=r"pairwise\[0\]: factor LinearGaussian reads support values \(capability "
        r"'reads_values'\) but the graph has no values",
    ):
        FactorGraph(torch.zeros(2, 3), [(torch.tensor([[0, 1]]), LinearGaussian(1))])
    with pytest.raises(GraphError, match="a chain's states are indices"):
        chain_inference(torch.zeros(4, 3), LinearGaussian(1))


def test_a_wrapper_that_misses_a_method_of_the_interface_is_named():
    from pgm.factors import FactorWrapper, _unforwarded

    assert _unforwarded(FactorWrapper) == []

    class Partial(FactorWrapper):
        pass

    partial_dict = {"log_potential": None}
    fake = type("Fake", (), partial_dict)
    assert "sample_target" in _unforwarded(fake) and "log_potential_bound" in _unforwarded(fake)
    assert Partial(TableFactor(torch.zeros(2, 2))).num_states == 2  # sizes forwarded too
