"""The graphs registration builds, end to end, each against an independent answer.

* A body-like tree of SE(3) parts with one ``RigidConnection`` offset per joint, replicated
  over 10 frames by ``SpatioTemporalTemplate`` (per-edge parameters tiled) with temporal
  edges per part: a loopy graph. With flat temporal edges it must give what the frames give
  solved one by one; with informative ones it must carry a frame without observations.
* A hybrid graph: a chain of discrete nodes over 250 states (a monotone time warp) coupled to
  continuous nodes (``LookupGaussian``: the state selects a mean), against a fixed-grid
  discretisation of the continuous nodes through the exact tree engine.
"""

from __future__ import annotations

import math

import torch

from pgm import (
    SE3,
    Discrete,
    Euclidean,
    FactorGraph,
    GaussianUnary,
    Geometric,
    LookupGaussian,
    MonotoneFactor,
    ParticleGraph,
    RigidConnection,
    SpatioTemporalTemplate,
    TableFactor,
    TiledFactor,
    particle_bp,
    tree_inference,
)
from pgm.rotations import qexp, qmul, qrotate

F64 = torch.float64
# pelvis 0; spine 1, head 2; thigh 3, shin 4; arm 5 (parent, child), in topological order
TREE = torch.tensor([[0, 1], [1, 2], [0, 3], [3, 4], [0, 5]])
PARTS = 6


def _body_motion(frames: int, seed: int = 0):
    """Per-joint offsets (E, 3) and a smooth motion of poses consistent with them
    (T, P, 7): each child at its parent's joint, rotations drifting a little per frame."""
    g = torch.Generator().manual_seed(seed)
    offsets = 0.15 * torch.randn(len(TREE), 3, generator=g, dtype=F64)
    t = torch.arange(frames, dtype=F64)[:, None]
    truth = torch.zeros(frames, PARTS, 7, dtype=F64)
    truth[:, 0, :3] = torch.cat([0.02 * t, 0.01 * t, 1.0 + 0 * t], 1)  # 2 cm per frame
    truth[:, 0, 3:] = qexp(torch.cat([0.03 * t, 0 * t, 0.3 + 0 * t], 1))
    bends = 0.3 * torch.randn(len(TREE), 3, generator=g, dtype=F64)
    for e, (a, c) in enumerate(TREE.tolist()):
        bend = qexp(bends[e] + 0.02 * t * (e + 1) / len(TREE))
        truth[:, c, 3:] = qmul(truth[:, a, 3:], bend)
        truth[:, c, :3] = truth[:, a, :3] + qrotate(truth[:, a, 3:], offsets[e].expand(frames, 3))
    return offsets, truth


def _connection(offsets):
    return RigidConnection(
        offsets, torch.zeros(3, dtype=F64), 0.01, 0.3, schedule=Geometric(1.0, 0.3, 6)
    )


def _run(graph, init, seed):
    g = torch.Generator().manual_seed(seed)
    return particle_bp(
        graph,
        init,
        iterations=6,
        generator=g,
        kernel_scale=(0.01, 0.05),
        loopy_iterations=15,
        loopy_damping=0.3,
    )


def _initial(truth, k, seed):
    g = torch.Generator().manual_seed(seed)
    return SE3().perturb(truth.unsqueeze(-2).expand(*truth.shape[:-1], k, 7), (0.04, 0.2), g)


def _spacetime(offsets, truth, temporal, observed):
    frames = truth.shape[0]
    tpl = SpatioTemporalTemplate(PARTS, [(TREE, _connection(offsets))], temporal=temporal)
    groups = tpl.build(frames)
    assert isinstance(groups[0][1], TiledFactor)  # per-joint offsets, tiled over frames
    nodes = tpl.node(observed[:, None], torch.arange(PARTS)[None]).reshape(-1)
    return ParticleGraph(
        frames * PARTS,
        [(SE3(), torch.arange(frames * PARTS))],
        groups,
        [(nodes, _pose_observation(truth[observed].reshape(-1, 7)))],
    )


def _pose_observation(means):
    """A Gaussian of 2 cm on each position and 0.02 on each quaternion coordinate (~0.04
    rad) around ``means`` (..., 7): what a part's observation pins down, in one frame."""
    return GaussianUnary(means, 0.02)


def _one_frame_graph(offsets, means):
    """The body of one frame; the frames go as a batch (``means`` (T, P, 7))."""
    return ParticleGraph(
        PARTS,
        [(SE3(), torch.arange(PARTS))],
        [(TREE, _connection(offsets))],
        [(torch.arange(PARTS), _pose_observation(means))],
    )


def test_body_over_frames_with_flat_temporal_edges_equals_frames_solved_one_by_one():
    """The same posterior either way, so the space-time solution is as close to the
    per-frame one as two per-frame runs with different seeds are to each other (the
    particles' own noise, ~2 cm here), and as accurate."""
    frames, k = 10, 80
    offsets, truth = _body_motion(frames)
    flat = RigidConnection(torch.zeros(3, dtype=F64), torch.zeros(3, dtype=F64), 5.0, 3.0)
    st_graph = _spacetime(offsets, truth, flat, torch.arange(frames))
    init = _initial(truth, k, 1)
    spacetime = _run(st_graph, init.reshape(1, frames * PARTS, k, 7), 2)
    assert spacetime.history[-1].message_change is not None  # loopy: inner loopy BP ran
    one_frame = _one_frame_graph(offsets, truth)
    per_frame = [_run(one_frame, init, seed).mean for seed in (2, 3)]
    st = spacetime.mean[0].reshape(frames, PARTS, 7)
    noise = SE3.position_distance(per_frame[0], per_frame[1]).mean()
    gap = SE3.position_distance(st, per_frame[0]).mean()
    assert gap < 1.3 * noise, (gap, noise)
    err_st = SE3.position_distance(st, truth).mean()
    err_pf = SE3.position_distance(per_frame[0], truth).mean()
    assert err_st < 1.2 * err_pf + 0.003 and err_pf < 0.025, (err_st, err_pf)
    # the joints hold in both (3 mm connection spread at the last annealing step)
    for mean in (st, per_frame[0]):
        joint = mean[:, TREE[:, 0], :3] + qrotate(
            mean[:, TREE[:, 0], 3:], offsets.expand(frames, -1, -1)
        )
        assert (joint - mean[:, TREE[:, 1], :3]).norm(dim=-1).mean() < 0.015


def test_temporal_edges_carry_a_frame_without_observations():
    """Frame 5 has no observation at all and starts 17 cm off: solved alone its parts stay
    there; through the temporal edges they follow their neighbours in time."""
    frames, k = 10, 80
    offsets, truth = _body_motion(frames, seed=3)
    smooth = RigidConnection(torch.zeros(3, dtype=F64), torch.zeros(3, dtype=F64), 0.03, 0.1)
    observed = torch.tensor([t for t in range(frames) if t != 5])
    graph = _spacetime(offsets, truth, smooth, observed)
    start = truth.clone()
    start[5, :, :3] += torch.tensor([0.12, -0.1, 0.05], dtype=F64)
    init = _initial(start, k, 4)
    res = _run(graph, init.reshape(1, frames * PARTS, k, 7), 5)
    err = SE3.position_distance(res.mean[0].reshape(frames, PARTS, 7), truth).mean(-1)  # (T,)
    alone = ParticleGraph(PARTS, [(SE3(), torch.arange(PARTS))], [(TREE, _connection(offsets))])
    err_alone = SE3.position_distance(_run(alone, init[5:6], 5).mean[0], truth[5]).mean()
    assert err_alone > 0.12, err_alone
    assert err[5] < 0.05, err  # within a few cm: the neighbours move 2 cm per frame
    assert err[observed].mean() < 0.035, err


def test_monotone_chain_coupled_to_continuous_nodes_matches_a_grid_through_the_exact_engine():
    """c_t in 250 reference frames, 0 <= c_{t+1} - c_t <= 40; x_t | c_t ~ N(ref(c_t), 0.15^2);
    y_t = x_t + N(0, 0.15^2) observed. Particle BP (x: 300 particles; c: all 250 states,
    padded to 300) against x on a 301-point grid, all nodes discrete, exact tree BP."""
    n, s, k = 8, 250, 300
    ref = torch.linspace(0.0, 3.0, s, dtype=F64) + 0.2 * torch.sin(torch.arange(s) / 9.0)
    true_c = torch.tensor([10, 40, 70, 95, 120, 160, 190, 230])
    g = torch.Generator().manual_seed(6)
    y = ref[true_c] + 0.15 * math.sqrt(2) * torch.randn(n, generator=g, dtype=F64)
    chain = torch.stack([torch.arange(n - 1), torch.arange(1, n)], 1)
    couple = torch.stack([torch.arange(n), torch.arange(n, 2 * n)], 1)  # c_t -> x_t
    graph = ParticleGraph(
        2 * n,
        [(Discrete(s), torch.arange(n)), (Euclidean(1), torch.arange(n, 2 * n))],
        [(chain, MonotoneFactor(40)), (couple, LookupGaussian(ref[:, None], 0.15))],
        [(torch.arange(n, 2 * n), GaussianUnary(y[:, None], 0.15))],
    )
    init = 1.5 + torch.randn(1, 2 * n, k, 1, generator=g, dtype=F64)
    res = particle_bp(graph, init, iterations=6, generator=g, kernel_scale=[None, 0.1])

    grid = torch.linspace(-1.0, 4.0, 301, dtype=F64)
    kk = max(s, len(grid))
    unary = torch.full((1, 2 * n, kk), -math.inf, dtype=F64)
    unary[0, :n, :s] = 0.0
    unary[0, n:, : len(grid)] = -0.5 * ((grid[None] - y[:, None]) / 0.15) ** 2
    coupling = torch.full((kk, kk), -math.inf, dtype=F64)
    coupling[:s, : len(grid)] = -0.5 * ((grid[None] - ref[:, None]) / 0.15) ** 2
    exact = tree_inference(
        FactorGraph(unary, [(chain, MonotoneFactor(40)), (couple, TableFactor(coupling))])
    )
    p_exact = exact.log_marginals[0, :n, :s].exp()
    p = res.log_weights[0, :n, :s].exp()
    assert res.log_weights[0, :n, s:].isneginf().all()  # padding carries no mass
    states = torch.arange(s, dtype=F64)
    mean_exact, mean = (p_exact * states).sum(-1), (p * states).sum(-1)
    sd_exact = ((p_exact * (states - mean_exact[:, None]) ** 2).sum(-1)).sqrt()
    assert ((mean - mean_exact).abs() < 0.2 * sd_exact + 0.5).all(), (mean, mean_exact)
    tv = 0.5 * (p - p_exact).abs().sum(-1)  # total variation per node
    assert tv.max() < 0.1, tv
    x_exact = (exact.log_marginals[0, n:, : len(grid)].exp() * grid).sum(-1)
    x = (res.log_weights[0, n:].exp() * res.particles[0, n:, :, 0]).sum(-1)
    torch.testing.assert_close(x, x_exact, atol=0.03, rtol=0)
