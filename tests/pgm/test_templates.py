"""Spatiotemporal templates: wiring, tiled parameters, and particle BP on a space-time graph."""

import pytest
import torch

from pgm import FactorGraph, TableFactor, tree_inference
from pgm.continuous import GaussianUnary, LinearGaussian
from pgm.particle_bp import ParticleGraph, particle_bp
from pgm.spaces import Euclidean
from pgm.templates import SpatioTemporalTemplate, TiledFactor
from tests.pgm.test_particle_bp import weighted_moments

F64 = torch.float64


def test_build_wires_frames_and_time_as_tensors():
    tpl = SpatioTemporalTemplate(
        3, [(torch.tensor([[0, 1], [1, 2]]), LinearGaussian(1))], temporal=LinearGaussian(1)
    )
    groups = tpl.build(4)
    assert len(groups) == 2  # one group per template group, not one per frame
    frame_edges, temporal_edges = groups[0][0], groups[1][0]
    assert frame_edges.tolist()[:4] == [[0, 1], [1, 2], [3, 4], [4, 5]]
    assert frame_edges.shape == (8, 2)
    assert temporal_edges.tolist() == [
        [0, 3],
        [1, 4],
        [2, 5],
        [3, 6],
        [4, 7],
        [5, 8],
        [6, 9],
        [7, 10],
        [8, 11],
    ]
    t, p = tpl.frame_and_part(torch.tensor([0, 5, 11]))
    assert t.tolist() == [0, 1, 3] and p.tolist() == [0, 2, 2]
    assert tpl.node(t, p).tolist() == [0, 5, 11]


def test_tiled_factor_equals_explicitly_repeated_parameters():
    torch.manual_seed(0)
    tables = torch.randn(2, 3, 3, dtype=F64)  # per-edge parameters of a 2-edge frame graph
    tpl = SpatioTemporalTemplate(3, [(torch.tensor([[0, 1], [1, 2]]), TableFactor(tables))])
    groups = tpl.build(3)
    assert isinstance(groups[0][1], TiledFactor)
    unary = torch.randn(1, 9, 3, dtype=F64)
    tiled = tree_inference(FactorGraph(unary, groups))
    explicit = tree_inference(
        FactorGraph(unary, [(groups[0][0], TableFactor(tables.repeat(3, 1, 1)))])
    )
    torch.testing.assert_close(tiled.log_partition, explicit.log_partition)
    torch.testing.assert_close(tiled.log_marginals, explicit.log_marginals)


def test_particle_bp_on_a_space_time_gaussian_graph():
    """3 parts x 4 frames, chain per frame plus temporal links (a loopy graph): particle BP
    with inner loopy BP recovers the exact Gaussian means."""
    p, t = 3, 4
    tpl = SpatioTemporalTemplate(
        p,
        [(torch.tensor([[0, 1], [1, 2]]), LinearGaussian(1, 1.0, 0.0, 0.8))],
        temporal=LinearGaussian(1, 1.0, 0.0, 0.5),
    )
    groups = tpl.build(t)
    v = p * t
    obs = torch.linspace(-1.5, 2.0, v, dtype=F64)
    graph = ParticleGraph(
        v,
        [(Euclidean(1), torch.arange(v))],
        groups,
        [(torch.arange(v), GaussianUnary(obs[:, None], 1.0))],
    )
    runs = []
    for seed in (1, 2, 3):  # particle noise is correlated along the graph: several runs
        g = torch.Generator().manual_seed(seed)
        runs.append(
            particle_bp(
                graph,
                2.0 * torch.randn(1, v, 300, 1, generator=g, dtype=F64),
                iterations=8,
                generator=g,
                kernel_scale=0.3,
            )
        )
    all_edges = torch.cat([e for e, _ in groups])
    # per-edge spreads differ (0.8 in frame, 0.5 in time): exact answer by information form
    j = torch.zeros(v, v, dtype=F64)
    for i in range(v):
        j[i, i] += 1.0
    for k, (a, b) in enumerate(all_edges.tolist()):
        w = 1 / 0.8**2 if k < len(groups[0][0]) else 1 / 0.5**2
        j[a, a] += w
        j[b, b] += w
        j[a, b] -= w
        j[b, a] -= w
    cov = torch.linalg.inv(j)
    mu, sd = cov @ obs, cov.diag().sqrt()
    worst = torch.stack([((weighted_moments(r)[0][0] - mu).abs() / sd).max() for r in runs])
    # each run within 0.35 posterior sd of the exact means, on average within 0.2
    assert worst.max() < 0.35 and worst.mean() < 0.2, worst


def test_template_errors():
    with pytest.raises(ValueError, match=r"parts outside \[0, 2\)"):
        SpatioTemporalTemplate(2, [(torch.tensor([[0, 2]]), LinearGaussian(1))])
    with pytest.raises(ValueError, match="parameters for 3 edges but the frame group has 2"):
        SpatioTemporalTemplate(
            3, [(torch.tensor([[0, 1], [1, 2]]), TableFactor(torch.zeros(3, 2, 2)))]
        ).build(2)
    with pytest.raises(ValueError, match="num_edges set"):
        TiledFactor(LinearGaussian(1), 2)
