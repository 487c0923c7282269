"""Particle BP against exact answers: Gaussian information form, grids, mixtures, hybrids."""

import math

import pytest
import torch

from pgm import FactorGraph, LogSemiring, MaxSemiring, TableFactor, tree_inference
from pgm.continuous import ContinuousPairwise, GaussianUnary, LinearGaussian, UnaryFactor
from pgm.factors import Capability
from pgm.particle_bp import ParticleGraph, ParticleResult, particle_bp
from pgm.schedules import Geometric
from pgm.spaces import Discrete, Euclidean

F64 = torch.float64


def gaussian_exact(num_nodes, edges, obs, r_std, gain, q_std):
    """Exact marginals of x with unaries N(x_i; obs_i, r^2) and N(x_b; gain x_a, q^2) links,
    from the information form J x = h (1-D states)."""
    j = torch.zeros(num_nodes, num_nodes, dtype=F64)
    h = torch.zeros(num_nodes, dtype=F64)
    for i in range(num_nodes):
        j[i, i] += 1 / r_std**2
        h[i] += obs[i] / r_std**2
    for a, b in edges.tolist():
        # (x_b - g x_a)^2 / q^2
        j[b, b] += 1 / q_std**2
        j[a, a] += gain**2 / q_std**2
        j[a, b] -= gain / q_std**2
        j[b, a] -= gain / q_std**2
    cov = torch.linalg.inv(j)
    return cov @ h, cov.diag().sqrt()


def weighted_moments(result):
    w = result.log_weights.exp()
    x = result.particles[..., 0]
    m = (w * x).sum(-1)
    return m, ((w * (x - m.unsqueeze(-1)) ** 2).sum(-1)).sqrt()


TREE_EDGES = torch.tensor([[0, 1], [1, 2], [1, 3], [3, 4], [0, 5]])
CHAIN_EDGES = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]])


def _run_gaussian(edges, k, seed, gain=0.9, q_std=0.7, r_std=1.0, iterations=8, device="cpu", **kw):
    """Particle BP on a linear-Gaussian graph (on ``device``) and the exact marginals."""
    v = int(edges.max()) + 1
    obs = torch.linspace(-2, 3, v, dtype=F64)
    graph = ParticleGraph(
        v,
        [(Euclidean(1), torch.arange(v))],
        [(edges, LinearGaussian(1, gain, 0.0, q_std))],
        [(torch.arange(v), GaussianUnary(obs[:, None].to(device), r_std))],
    )
    g = torch.Generator(device=device).manual_seed(seed)
    init = 3.0 * torch.randn(1, v, k, 1, generator=g, dtype=F64, device=device)
    res = particle_bp(graph, init, iterations=iterations, generator=g, kernel_scale=0.3, **kw)
    mu, sd = gaussian_exact(v, edges, obs, r_std, gain, q_std)
    return res, mu, sd


@pytest.mark.parametrize("edges", [CHAIN_EDGES, TREE_EDGES], ids=["chain", "tree"])
def test_linear_gaussian_marginals_match_information_form(edges):
    res, mu, sd = _run_gaussian(edges, k=400, seed=0)
    m, s = weighted_moments(res)
    ratio = s[0] / sd
    # double-counted weights (naive PBP) give ratios around 0.5-0.7: caught here
    assert ((ratio > 0.9) & (ratio < 1.1)).all(), ratio
    assert ((m[0] - mu).abs() / sd).max() < 0.15


def test_mean_error_shrinks_as_particles_grow():
    def err(k):
        total = 0.0
        for seed in range(4):
            res, mu, sd = _run_gaussian(TREE_EDGES, k=k, seed=seed)
            m, _ = weighted_moments(res)
            total += ((m[0] - mu).abs() / sd).mean().item()
        return total / 4

    e_small, e_large = err(50), err(800)
    assert e_large < 0.6 * e_small, (e_small, e_large)


def test_own_proposal_variant_is_also_consistent():
    res, mu, sd = _run_gaussian(CHAIN_EDGES, k=400, seed=1, proposal="own")
    m, s = weighted_moments(res)
    assert ((s[0] / sd > 0.85) & (s[0] / sd < 1.15)).all()
    assert ((m[0] - mu).abs() / sd).max() < 0.2


def test_particle_max_product_finds_the_mode():
    res, mu, sd = _run_gaussian(TREE_EDGES, k=400, seed=2, semiring=MaxSemiring())
    # Gaussian: the MAP is the mean; the best particle lands within a fraction of a std
    assert ((res.best[0, :, 0] - mu).abs() / sd).max() < 0.25


def test_grid_particles_with_uniform_proposal_equal_the_discrete_engine():
    grid = torch.linspace(-3, 3, 41, dtype=F64)
    v = 4
    edges = torch.tensor([[0, 1], [1, 2], [1, 3]])
    obs = torch.tensor([0.5, -1.0, 2.0, 0.0], dtype=F64)
    graph = ParticleGraph(
        v,
        [(Euclidean(1), torch.arange(v))],
        [(edges, LinearGaussian(1, 0.8, 0.1, 0.5))],
        [(torch.arange(v), GaussianUnary(obs[:, None], 0.7))],
    )
    init = grid.expand(1, v, 41).unsqueeze(-1).clone()
    res = particle_bp(graph, init, iterations=1, kernel_scale=0.1)
    # The same problem written as discrete tables by hand.
    table = -0.5 * ((grid[None, :] - (0.8 * grid[:, None] + 0.1)) / 0.5) ** 2
    unary = -0.5 * ((grid[None, :] - obs[:, None]) / 0.7) ** 2
    exact = tree_inference(FactorGraph(unary[None], [(edges, TableFactor(table))]), LogSemiring())
    torch.testing.assert_close(res.log_weights, exact.log_marginals)


class MixtureUnary(UnaryFactor):
    """Two-bump unary on 1-D nodes: 0.5 N(-2, 0.5^2) + 0.5 N(2, 0.5^2) (a user subclass)."""

    def log_potential(self, x, nodes, estimates):
        x = x[..., 0]
        return torch.logaddexp(-0.5 * ((x + 2) / 0.5) ** 2, -0.5 * ((x - 2) / 0.5) ** 2)


def test_bimodal_unary_matches_fine_grid_discretisation():
    v = 3
    edges = torch.tensor([[0, 1], [1, 2]])
    link = LinearGaussian(1, 1.0, 0.0, 0.6)
    graph = ParticleGraph(
        v,
        [(Euclidean(1), torch.arange(v))],
        [(edges, link)],
        [
            (torch.tensor([0]), MixtureUnary()),
            (torch.tensor([2]), GaussianUnary(torch.tensor([[1.0]], dtype=F64), 1.5)),
        ],
    )
    g = torch.Generator().manual_seed(7)
    init = 3.0 * torch.randn(1, v, 600, 1, generator=g, dtype=F64)
    res = particle_bp(graph, init, iterations=10, generator=g, kernel_scale=0.3)
    # Fine grid: 1201 points on [-8, 8], exact tree BP.
    grid = torch.linspace(-8, 8, 1201, dtype=F64)
    table = -0.5 * ((grid[None, :] - grid[:, None]) / 0.6) ** 2
    unary = torch.zeros(3, 1201, dtype=F64)
    unary[0] = MixtureUnary().log_potential(grid[None, None, :, None], None, None)[0, 0]
    unary[2] = -0.5 * ((grid - 1.0) / 1.5) ** 2
    exact = tree_inference(
        FactorGraph(unary[None], [(edges, TableFactor(table))])
    ).log_marginals.exp()[0]
    w = res.log_weights.exp()[0]
    x = res.particles[0, :, :, 0]
    for node in range(3):
        p_pos_exact = exact[node, grid > 0].sum()
        p_pos = w[node, x[node] > 0].sum()
        assert abs(p_pos - p_pos_exact) < 0.06, (node, p_pos, p_pos_exact)
        m_exact = (exact[node] * grid).sum()
        s_exact = ((exact[node] * (grid - m_exact) ** 2).sum()).sqrt()
        m = (w[node] * x[node]).sum()
        s = ((w[node] * (x[node] - m) ** 2).sum()).sqrt()
        assert abs(m - m_exact) < 0.15 * s_exact
        assert abs(s / s_exact - 1) < 0.1


def test_annealing_satisfies_the_connection_constraint():
    """Two 2-D nodes pulled apart by their unaries; a link x_b = x_a + (1, 0) whose spread
    shrinks geometrically from 1 to 0.005: at the end the link holds to 0.03."""
    link = LinearGaussian(
        2, 1.0, torch.tensor([1.0, 0.0], dtype=F64), 1.0, schedule=Geometric(1.0, 0.005, 8)
    )
    obs = torch.tensor([[0.0, 0.0], [2.0, 1.0]], dtype=F64)
    graph = ParticleGraph(
        2,
        [(Euclidean(2), torch.arange(2))],
        [(torch.tensor([[0, 1]]), link)],
        [(torch.arange(2), GaussianUnary(obs, 1.0))],
    )
    g = torch.Generator().manual_seed(8)
    init = torch.randn(1, 2, 300, 2, generator=g, dtype=F64)
    res = particle_bp(
        graph,
        init,
        iterations=8,
        generator=g,
        kernel_scale=0.2,
        kernel_schedule=Geometric(1.0, 0.05, 8),
        semiring=MaxSemiring(),
    )
    gap = res.best[0, 1] - res.best[0, 0] - torch.tensor([1.0, 0.0], dtype=F64)
    assert gap.norm() < 0.03
    # and the pair sits where the unaries balance: midpoint of (obs_a, obs_b - offset)
    torch.testing.assert_close(
        res.best[0, 0], torch.tensor([0.5, 0.5], dtype=F64), atol=0.15, rtol=0
    )


class StateMeans(ContinuousPairwise):
    """psi(c, x) = N(x; mu[c], s^2): a discrete node c (a) choosing the mean of x (b)."""

    capabilities = ContinuousPairwise.capabilities | {Capability.SAMPLABLE}

    def __init__(self, mu, s):
        super().__init__()
        self.mu, self.s = mu, s

    def log_potential(self, edges, xa, xb, num_states):
        c = xa[..., 0].long().clamp(0, len(self.mu) - 1)  # (B, E, K) states (padding clamped)
        mean = self.mu[c]
        return -0.5 * ((xb[..., 0].unsqueeze(-2) - mean.unsqueeze(-1)) / self.s) ** 2 - math.log(
            self.s
        )

    def sample_target(self, x_source, edges, forward, generator):
        if not forward:
            raise NotImplementedError("the discrete end is never resampled")
        c = x_source[..., 0].long()
        noise = torch.randn(c.shape, generator=generator, dtype=self.mu.dtype, device=c.device)
        return (self.mu[c] + self.s * noise).unsqueeze(-1)

    def log_target_density(self, x_target, x_source, edges, forward):
        return self.log_potential(edges, x_source, x_target, None).transpose(
            -1, -2
        ) - 0.5 * math.log(2 * math.pi)


def check_hybrid_toy(device="cpu"):
    """c in {0, 1, 2} uniform; x | c ~ N(mu_c, 0.5^2); y = x + N(0, 0.8^2) observed at 1.6.
    Exact: p(c | y) ~ N(y; mu_c, 0.5^2 + 0.8^2); E[x | y] = sum_c p(c|y) posterior mean."""
    mu = torch.tensor([-2.0, 0.0, 2.0], dtype=F64)
    y, s, r = 1.6, 0.5, 0.8
    graph = ParticleGraph(
        2,
        [(Discrete(3), torch.tensor([0])), (Euclidean(1), torch.tensor([1]))],
        [(torch.tensor([[0, 1]]), StateMeans(mu.to(device), s))],
        [(torch.tensor([1]), GaussianUnary(torch.tensor([[y]], dtype=F64, device=device), r))],
    )
    g = torch.Generator(device=device).manual_seed(9)
    init = 3.0 * torch.randn(1, 2, 500, 1, generator=g, dtype=F64, device=device)
    res = particle_bp(graph, init, iterations=6, generator=g, kernel_scale=[None, 0.3])
    res = ParticleResult(res.particles.cpu(), res.log_weights.cpu(), res.mean, res.best)
    lik = torch.distributions.Normal(mu, math.sqrt(s**2 + r**2)).log_prob(
        torch.tensor(y, dtype=F64)
    )
    p_c = torch.softmax(lik, 0)
    w_c = res.log_weights[0, 0, :3].exp()
    torch.testing.assert_close(w_c, p_c, atol=0.03, rtol=0)
    assert res.log_weights[0, 0, 3:].isneginf().all()  # padding states carry no mass
    post_mean = (mu / s**2 + y / r**2) / (1 / s**2 + 1 / r**2)
    exact_x = (p_c * post_mean).sum()
    w = res.log_weights[0, 1].exp()
    assert abs((w * res.particles[0, 1, :, 0]).sum() - exact_x) < 0.08


def test_hybrid_discrete_continuous_toy():
    check_hybrid_toy()


def test_same_seed_same_result_and_diagnostics():
    stats = []
    a, _, _ = _run_gaussian(TREE_EDGES, k=100, seed=3, iterations=4, callback=stats.append)
    b, _, _ = _run_gaussian(TREE_EDGES, k=100, seed=3, iterations=4)
    c, _, _ = _run_gaussian(TREE_EDGES, k=100, seed=4, iterations=4)
    assert torch.equal(a.particles, b.particles) and torch.equal(a.log_weights, b.log_weights)
    assert not torch.equal(a.particles, c.particles)
    assert [s.iteration for s in stats] == [0, 1, 2, 3]
    assert (
        stats[0].ess.shape == (1, 6) and (stats[-1].ess > 10).all() and (stats[-1].ess <= 100).all()
    )
    assert math.isnan(stats[0].estimate_change) and stats[-1].estimate_change < 1.0
    assert (stats[-1].log_weight_range >= 0).all() and stats[-1].message_change is None


def test_restarts_run_the_schedule_again():
    stats = []
    _run_gaussian(CHAIN_EDGES, k=50, seed=5, iterations=3, restarts=2, callback=stats.append)
    assert [(s.restart, s.iteration) for s in stats] == [
        (0, 0),
        (0, 1),
        (0, 2),
        (1, 0),
        (1, 1),
        (1, 2),
    ]


def test_loopy_gaussian_graph_means_are_exact():
    """On a Gaussian graph with a cycle, BP's fixed-point means are exact (Weiss & Freeman)."""
    edges = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0], [1, 4]])
    res, mu, sd = _run_gaussian(edges, k=400, seed=6, gain=0.5, q_std=1.0)
    m, _ = weighted_moments(res)
    assert ((m[0] - mu).abs() / sd).max() < 0.2
    assert res.history[-1].message_change is not None


class WrongShape(UnaryFactor):
    def log_potential(self, x, nodes, estimates):
        return x[..., 0, 0]


class NaNUnary(UnaryFactor):
    def log_potential(self, x, nodes, estimates):
        return torch.full(x.shape[:3], math.nan, dtype=x.dtype)


def test_bad_input_errors():
    graph = ParticleGraph(
        2,
        [(Euclidean(1), torch.arange(2))],
        [(torch.tensor([[0, 1]]), LinearGaussian(1, 1.0, 0.0, 1.0))],
    )
    good = torch.zeros(1, 2, 10, 1)
    with pytest.raises(
        ValueError, match=r"initial must have shape \(B, 2, K, 1\); got \(1, 2, 10, 3\)"
    ):
        particle_bp(graph, torch.zeros(1, 2, 10, 3), kernel_scale=0.1)
    with pytest.raises(ValueError, match="initial particles contain NaN or inf"):
        particle_bp(graph, torch.full((1, 2, 10, 1), math.nan), kernel_scale=0.1)
    with pytest.raises(ValueError, match="kernel_scale is required"):
        particle_bp(graph, good)
    with pytest.raises(ValueError, match="proposal must be"):
        particle_bp(graph, good, kernel_scale=0.1, proposal="other")
    bad = ParticleGraph(2, [(Euclidean(1), torch.arange(2))], [], [(torch.arange(2), WrongShape())])
    with pytest.raises(
        ValueError, match=r"WrongShape.log_potential returned \(1, 2\); expected \(1, 2, 10\)"
    ):
        particle_bp(bad, good, kernel_scale=0.1)
    nan = ParticleGraph(2, [(Euclidean(1), torch.arange(2))], [], [(torch.arange(2), NaNUnary())])
    with pytest.raises(ValueError, match="returned NaN"):
        particle_bp(nan, good, kernel_scale=0.1)
    with pytest.raises(ValueError, match=r"initial_log_density must have shape \(1, 2, 10\)"):
        particle_bp(graph, good, kernel_scale=0.1, initial_log_density=torch.zeros(2))
    from pgm import GraphError

    with pytest.raises(GraphError, match=r"nodes \[1\] have no state space"):
        ParticleGraph(2, [(Euclidean(1), torch.tensor([0]))])
    with pytest.raises(ValueError, match="fewer than the 5 states"):
        hyb = ParticleGraph(
            2, [(Discrete(5), torch.tensor([0])), (Euclidean(1), torch.tensor([1]))]
        )
        particle_bp(hyb, torch.zeros(1, 2, 4, 1), kernel_scale=[None, 0.1])


class Recorder(UnaryFactor):
    """Records the estimates it is given; pulls node 1 towards node 0's current estimate."""

    def __init__(self):
        self.seen = []

    def log_potential(self, x, nodes, estimates):
        self.seen.append(estimates.clone())
        return -0.5 * ((x[..., 0] - estimates[:, :1, None, 0]) / 0.5) ** 2


def test_observation_factors_see_the_other_nodes_current_estimates():
    """The occlusion-aware interface: a factor on node 1 receives every node's estimate
    from the previous iteration (the best particles), batched (B, V, D)."""

    def run(iterations):
        rec = Recorder()
        graph = ParticleGraph(
            2,
            [(Euclidean(1), torch.arange(2))],
            [],
            [
                (torch.tensor([0]), GaussianUnary(torch.tensor([[3.0]], dtype=F64), 0.3)),
                (torch.tensor([1]), rec),
            ],
        )
        g = torch.Generator().manual_seed(11)
        init = torch.randn(2, 2, 100, 1, generator=g, dtype=F64)
        return particle_bp(graph, init, iterations=iterations, generator=g, kernel_scale=0.8), rec

    one, _ = run(1)
    three, rec = run(8)
    assert rec.seen[1].shape == (2, 2, 1)
    torch.testing.assert_close(rec.seen[1], one.best)  # iteration 1 sees iteration 0's estimates
    # node 1 has no observation of its own but follows node 0 (observed at 3.0)
    assert (three.mean[:, 1, 0] - 3.0).abs().max() < 0.3


def test_non_finite_initial_density_is_rejected():
    graph = ParticleGraph(1, [(Euclidean(1), torch.arange(1))])
    with pytest.raises(ValueError, match="initial_log_density contains NaN"):
        particle_bp(
            graph,
            torch.zeros(1, 1, 5, 1),
            kernel_scale=0.1,
            initial_log_density=torch.full((1, 1, 5), math.nan),
        )
