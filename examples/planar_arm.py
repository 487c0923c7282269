"""Pose a planar 4-link arm from noisy 2-D joint observations with particle BP -- pgm only.

The reuse example for another articulated object: nothing here comes from `motion`. Each
link is a node with state ``(x, y, theta)`` (its base joint in metres, its direction in
radians); a new factor type, :class:`LinkJoint`, ties the end of one link to the base of the
next. It is a small subclass: a log-potential over two particle sets, plus a sampler and its
density so that it can propose particles. Observations are noisy positions of every joint.

Run: ``python examples/planar_arm.py``.
"""

from __future__ import annotations

import math

import torch

from pgm import Capability, MaxSemiring
from pgm.continuous import ContinuousPairwise, UnaryFactor
from pgm.particle_bp import ParticleGraph, particle_bp
from pgm.schedules import Geometric
from pgm.spaces import Euclidean

LENGTHS = torch.tensor([0.30, 0.25, 0.20, 0.15], dtype=torch.float64)
LOG_2PI = math.log(2 * math.pi)


def link_end(x: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """End point of links ``x`` (..., 3) of the given length (broadcastable). -> (..., 2)."""
    direction = torch.stack([torch.cos(x[..., 2]), torch.sin(x[..., 2])], -1)
    return x[..., :2] + length.unsqueeze(-1) * direction


class LinkJoint(ContinuousPairwise):
    """psi(a, b) = N(base_b; end_a, s^2 I) N(theta_b; theta_a, s_theta^2): link b hangs off a.

    Both factors are normalised in either end, so psi is also the density of its samplers.
    ``lengths`` holds the length of the parent (a) link of each edge: shape (E,).
    """

    capabilities = ContinuousPairwise.capabilities | {Capability.SAMPLABLE}

    def __init__(self, lengths, pos_std, angle_std, schedule=None):
        super().__init__(schedule)
        self.lengths = lengths
        self.num_edges = len(lengths)
        self.pos_std, self.angle_std = pos_std, angle_std

    def _stds(self):
        return self.pos_std * self.anneal, self.angle_std * self.anneal

    def log_potential(self, edges, xa, xb, num_states):
        s, st = self._stds()
        length = self.lengths[edges][None, :, None]  # (1, E, 1)
        end_a = link_end(xa, length)  # (B, E, K, 2)
        d2 = torch.cdist(end_a, xb[..., :2]).square()  # (B, E, K, K) [i, j]
        dth = xb[..., 2].unsqueeze(-2) - xa[..., 2].unsqueeze(-1)
        return (
            -0.5 * d2 / s**2
            - 2 * math.log(s)
            - LOG_2PI
            - 0.5 * (dth / st) ** 2
            - math.log(st)
            - 0.5 * LOG_2PI
        )

    def sample_target(self, x_source, edges, forward, generator):
        s, st = self._stds()
        length = self.lengths[edges][None, :, None]
        noise = torch.randn(x_source.shape, generator=generator, dtype=x_source.dtype)
        theta = x_source[..., 2] + st * noise[..., 2]
        if forward:  # base of the child at the end of the parent
            base = link_end(x_source, length)
        else:  # parent's base one parent-length back from the child's base
            parent = torch.cat([x_source[..., :2], theta.unsqueeze(-1)], -1)
            base = 2 * x_source[..., :2] - link_end(parent, length)
        return torch.cat([base + s * noise[..., :2], theta.unsqueeze(-1)], -1)

    def log_target_density(self, x_target, x_source, edges, forward):
        if forward:
            return self.log_potential(edges, x_source, x_target, None).transpose(-1, -2)
        return self.log_potential(edges, x_target, x_source, None)


class JointObservations(UnaryFactor):
    """Noisy 2-D positions of each link's base and end: N(z; joint, r^2 I)."""

    def __init__(self, bases, ends, std):
        self.bases, self.ends, self.std = bases, ends, std  # (B, L, 2) each

    def log_potential(self, x, nodes, estimates):
        length = LENGTHS[nodes][None, :, None]
        d_base = (x[..., :2] - self.bases[:, nodes].unsqueeze(2)).square().sum(-1)
        d_end = (link_end(x, length) - self.ends[:, nodes].unsqueeze(2)).square().sum(-1)
        return -0.5 * (d_base + d_end) / self.std**2


def forward_kinematics(angles: torch.Tensor) -> torch.Tensor:
    """Absolute link directions (B, L) -> link states (B, L, 3), base of link 0 at the origin."""
    b, n = angles.shape
    states = torch.zeros(b, n, 3, dtype=angles.dtype)
    base = torch.zeros(b, 2, dtype=angles.dtype)
    for i in range(n):  # four links: a Python loop over the arm's structure is fine here
        states[:, i, :2], states[:, i, 2] = base, angles[:, i]
        base = link_end(states[:, i], LENGTHS[i])
    return states


def run(num_particles: int = 200, batch: int = 8, seed: int = 0, verbose: bool = True) -> dict:
    """Pose ``batch`` random arms from perturbed starts; returns mean joint errors (metres)."""
    g = torch.Generator().manual_seed(seed)
    n = len(LENGTHS)
    true_angles = torch.cumsum(
        torch.empty(batch, n, dtype=torch.float64).uniform_(-1.0, 1.0, generator=g), 1
    )
    truth = forward_kinematics(true_angles)
    ends = link_end(truth, LENGTHS)
    obs_std = 0.01
    bases_obs = truth[..., :2] + obs_std * torch.randn(
        batch, n, 2, generator=g, dtype=torch.float64
    )
    ends_obs = ends + obs_std * torch.randn(batch, n, 2, generator=g, dtype=torch.float64)

    start_angles = true_angles + math.radians(30) * torch.randn(
        batch, n, generator=g, dtype=torch.float64
    )
    start = forward_kinematics(start_angles)
    space = Euclidean(3)
    initial = space.perturb(
        start.unsqueeze(2).expand(batch, n, num_particles, 3), torch.tensor([0.05, 0.05, 0.3]), g
    )
    edges = torch.stack([torch.arange(n - 1), torch.arange(1, n)], 1)
    joint = LinkJoint(LENGTHS[:-1], pos_std=0.05, angle_std=1.0, schedule=Geometric(1.0, 0.1, 6))
    graph = ParticleGraph(
        n,
        [(space, torch.arange(n))],
        [(edges, joint)],
        [(torch.arange(n), JointObservations(bases_obs, ends_obs, obs_std))],
    )
    result = particle_bp(
        graph,
        initial,
        iterations=6,
        restarts=2,
        generator=g,
        kernel_scale=torch.tensor([0.02, 0.02, 0.1]),
        kernel_schedule=Geometric(1.0, 0.2, 6),
        semiring=MaxSemiring(),
    )

    def joint_error(states):
        pts = torch.cat([states[..., :2], link_end(states, LENGTHS)], 1)
        ref = torch.cat([truth[..., :2], ends], 1)
        return (pts - ref).norm(dim=-1).mean().item()

    errors = {"start": joint_error(start), "final": joint_error(result.best)}
    if verbose:
        print(f"{batch} arms, {num_particles} particles, 2 x 6 annealed iterations")
        print(
            f"mean joint error: start {errors['start'] * 100:.1f} cm -> final {errors['final'] * 100:.2f} cm "
            f"(observation noise {obs_std * 100:.0f} cm)"
        )
    return errors


if __name__ == "__main__":
    run()
