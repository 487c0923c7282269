"""Factors over continuous supports: samplers for proposals, annealing, observation factors.

Pairwise factors for particle BP read particle values and usually declare the *samplable*
capability (:class:`pgm.factors.Capability`): given particles of one end, draw the other end
from ``psi(x_source, .)`` normalised as a density, and evaluate that density (the proposal
density ``q`` needs it). Annealed factors scale their spread by a
:class:`~pgm.schedules.Schedule`; the engine asks each for its value at an iteration with
``annealed(step)``, never modifying the factor it was given.

Observation (unary) factors see a node group's particles *and the current estimates of every
node*, so an occlusion-aware factor can render a part together with the rest of the body.

Shapes: ``B`` batch, ``E`` edges, ``N`` nodes of a unary group, ``V`` all nodes, ``K`` / ``M``
particles, ``D`` state width.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import Tensor

from pgm.factors import (
    AnnealingStep,
    Capability,
    EdgeIndex,
    MissingCapabilityError,
    PairwiseFactor,
)
from pgm.kernels import (
    ROTATION_KERNELS,
    rotation_log_kernel_from_dot,
    rotation_noise,
    se3_kernel_mixture,
    se3_kernel_table,
)
from pgm.rotations import qconj, qmul, qnormalize, qrotate
from pgm.schedules import Constant, Schedule

__all__ = [
    "ContinuousPairwise",
    "GaussianUnary",
    "LinearGaussian",
    "LookupGaussian",
    "LookupPose",
    "RigidConnection",
    "UnaryFactor",
]

_LOG_2PI = math.log(2 * math.pi)


class ContinuousPairwise(PairwiseFactor):
    """A pairwise factor over particle values, annealed by a schedule.

    Subclasses implement :meth:`log_potential` (the table over two particle sets) and, to
    take part in proposals, :meth:`sample_target` and :meth:`log_target_density`, declaring
    ``capabilities = ContinuousPairwise.capabilities | {Capability.SAMPLABLE}``. Spreads read
    :attr:`anneal`, the schedule's multiplier at the step this value was made for by
    :meth:`annealed` (a fresh factor is at iteration 0).
    """

    capabilities = frozenset({Capability.READS_VALUES, Capability.ANNEALED})
    schedule: Schedule = Constant()
    _step: AnnealingStep = AnnealingStep()

    def __init__(self, schedule: Schedule | None = None):
        self.schedule = schedule or Constant()

    def annealed(self, step: AnnealingStep) -> ContinuousPairwise:
        """A shallow copy at ``step`` (``self`` when its spreads would not change)."""
        if self.multipliers(step.iteration) == self.multipliers(self._step.iteration):
            return self
        out = copy.copy(self)
        out._step = step
        return out

    def multipliers(self, iteration: int) -> tuple[float, ...]:
        """Every spread multiplier this factor reads at an iteration (a subclass with more
        than one schedule lists them all)."""
        return (self.schedule(iteration),)

    @property
    def anneal(self) -> float:
        """Spread multiplier of this value: ``schedule(iteration)`` at its annealing step."""
        return self.schedule(self._step.iteration)


_SAMPLABLE = ContinuousPairwise.capabilities | {Capability.SAMPLABLE}


class LinearGaussian(ContinuousPairwise):
    """``psi(x_a, x_b) = N(x_b; gain * x_a + offset, (anneal * std)^2 I)`` on R^dim.

    Args:
        dim: state width of both ends (values beyond it are ignored).
        gain: non-zero scalar (so that both directions can be sampled).
        offset: ``(dim,)`` or per edge ``(E, dim)``.
        std: scalar or ``(dim,)`` standard deviation.
        schedule: annealing multiplier of ``std``.
    """

    capabilities = _SAMPLABLE

    def __init__(self, dim: int, gain: float = 1.0, offset=0.0, std=1.0, schedule=None):
        super().__init__(schedule)
        if not isinstance(dim, int) or dim < 1:
            raise ValueError(f"dim must be an int >= 1; got {dim!r}")
        if not (math.isfinite(gain) and gain != 0):
            raise ValueError(f"gain must be finite and non-zero; got {gain}")
        self.dim, self.gain = dim, float(gain)
        self.offset = torch.as_tensor(offset, dtype=torch.get_default_dtype())
        if self.offset.dim() == 2:
            self.num_edges = self.offset.shape[0]
        std = torch.as_tensor(std, dtype=torch.get_default_dtype())
        self.std = std.expand(dim) if std.dim() == 0 else std
        if self.std.shape != (dim,) or not (self.std > 0).all():
            raise ValueError(f"std must be > 0, a scalar or shape ({dim},); got {tuple(std.shape)}")

    def _offset(self, edges: EdgeIndex, like: Tensor) -> Tensor:
        off = self.offset.to(like)
        if off.dim() == 2:
            return off[edges][None, :, None, :]  # (1, E, 1, dim)
        return off

    def _log_gauss(self, diff: Tensor, std: Tensor) -> Tensor:
        return (-0.5 * (diff / std).square() - torch.log(std) - 0.5 * _LOG_2PI).sum(-1)

    def log_potential(self, edges, xa, xb, num_states):
        xa, xb = xa[..., : self.dim], xb[..., : self.dim]
        std = self.std.to(xa) * self.anneal
        mean_b = self.gain * xa + self._offset(edges, xa)  # (B, E, K, dim)
        return self._log_gauss(xb.unsqueeze(-3) - mean_b.unsqueeze(-2), std)  # [i, j]

    def sample_target(self, x_source, edges, forward, generator):
        x = x_source[..., : self.dim]
        std = self.std.to(x) * self.anneal
        noise = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        if forward:
            return self.gain * x + self._offset(edges, x) + std * noise
        # x_a | x_b ~ N((x_b - offset) / gain, (std / |gain|)^2)
        return (x - self._offset(edges, x)) / self.gain + std / abs(self.gain) * noise

    def log_target_density(self, x_target, x_source, edges, forward):
        xt, xs = x_target[..., : self.dim], x_source[..., : self.dim]
        std = self.std.to(xt) * self.anneal
        if forward:
            mean = self.gain * xs + self._offset(edges, xs)
            return self._log_gauss(xt.unsqueeze(-2) - mean.unsqueeze(-3), std)
        mean = (xs - self._offset(edges, xs)) / self.gain
        return self._log_gauss(xt.unsqueeze(-2) - mean.unsqueeze(-3), std / abs(self.gain))


class RigidConnection(ContinuousPairwise):
    """Connection of two rigid parts (SE3 values) at a shared joint, as in the proposal's
    ``psi_ij = N(T(x_i) - p_j; 0, Lambda^n)``, with an optional relative-rotation prior.

    ``psi(x_a, x_b) = N(p_a + R_a o_a - (p_b + R_b o_b); 0, s_p^2 I) * k(R_a r, R_b; s_r)``:
    the joint seen from part a (point ``o_a`` in a's frame) meets the joint seen from part b
    (``o_b`` in b's frame); ``k`` is the rotation kernel of the kind ``rotation`` (see
    :func:`pgm.kernels.rotation_noise`: an isotropic Bingham density by default, or the
    Gaussian of rotation vectors) around the mean relative rotation ``r``. Both spreads are
    multiplied by the schedule.

    Args:
        offset_a, offset_b: ``(3,)`` or ``(E, 3)`` joint position in each part's frame (metres).
        pos_std: metres. rot_std: radians (``None``: rotation unconstrained -- then this
            factor cannot sample, as the conditional is improper).
        rel_rot: ``(4,)`` or ``(E, 4)`` mean relative rotation ``R_a^T R_b`` (default identity).
        schedule: multiplier of both spreads per iteration (annealing).
        rotation: ``"bingham"`` or ``"gaussian"``, the rotation kernel's family.
        rotation_schedule: multiplier of the rotation spread alone, replacing ``schedule``
            for it (e.g. ``Constant()``: a broad rotation prior that does not tighten while
            the joints' positions anneal, as the proposal's position-only connection).
        outlier, outlier_rot_std: a heavy-tailed rotation kernel, the mixture
            ``(1 - outlier) k(.; rot_std) + outlier k(.; outlier_rot_std)`` (both spreads
            under the same schedule; ``outlier_rot_std > rot_std``): a joint usually stays
            within ``rot_std`` of ``r`` but may turn much further at a small, fixed price --
            a prior under which a few joints far off cost less than every joint a little
            off. 0 (default): the single kernel.
    """

    capabilities = _SAMPLABLE | {Capability.BOUNDED, Capability.BUFFERED}

    def __init__(
        self,
        offset_a,
        offset_b,
        pos_std: float,
        rot_std: float | None = None,
        rel_rot=None,
        schedule=None,
        rotation: str = "bingham",
        rotation_schedule: Schedule | None = None,
        outlier: float = 0.0,
        outlier_rot_std: float | None = None,
    ):
        super().__init__(schedule)
        self.rotation_schedule = rotation_schedule
        if not 0.0 <= outlier < 1.0:
            raise ValueError(f"outlier must be a weight in [0, 1); got {outlier}")
        if outlier > 0 and (
            rot_std is None or outlier_rot_std is None or not outlier_rot_std > rot_std
        ):
            raise ValueError(
                "an outlier kernel needs rot_std and outlier_rot_std > rot_std; got rot_std="
                f"{rot_std}, outlier_rot_std={outlier_rot_std}"
            )
        self.outlier = float(outlier)
        self.outlier_rot_std = None if outlier_rot_std is None else float(outlier_rot_std)
        if rotation not in ROTATION_KERNELS:
            raise ValueError(f"rotation must be one of {ROTATION_KERNELS}; got {rotation!r}")
        self.rotation = rotation
        dt = torch.get_default_dtype()
        self.offset_a = torch.as_tensor(offset_a, dtype=dt)
        self.offset_b = torch.as_tensor(offset_b, dtype=dt)
        identity = torch.tensor([1.0, 0, 0, 0], dtype=dt, device=self.offset_a.device)
        self.rel_rot = identity if rel_rot is None else torch.as_tensor(rel_rot, dtype=dt)
        for name, t, w in (
            ("offset_a", self.offset_a, 3),
            ("offset_b", self.offset_b, 3),
            ("rel_rot", self.rel_rot, 4),
        ):
            if t.shape[-1] != w or t.dim() not in (1, 2):
                raise ValueError(f"{name} must have shape ({w},) or (E, {w}); got {tuple(t.shape)}")
            if t.dim() == 2:
                if self.num_edges not in (None, t.shape[0]):
                    raise ValueError(
                        f"{name} has {t.shape[0]} rows; other parameters have {self.num_edges}"
                    )
                self.num_edges = t.shape[0]
        if not pos_std > 0:
            raise ValueError(f"pos_std must be > 0; got {pos_std}")
        if rot_std is not None and not rot_std > 0:
            raise ValueError(f"rot_std must be > 0 or None; got {rot_std}")
        self.pos_std, self.rot_std = float(pos_std), rot_std
        if rot_std is None:  # an improper conditional in the rotation: nothing to sample
            self.capabilities = type(self).capabilities - {Capability.SAMPLABLE}
        elif rotation != "bingham":  # only the Bingham table is one product into a buffer
            self.capabilities = type(self).capabilities - {Capability.BUFFERED}

    def _param(self, t: Tensor, edges: EdgeIndex, like: Tensor) -> Tensor:
        t = t.to(like)
        return t[edges][None, :, None, :] if t.dim() == 2 else t

    # The common conventions -- a part's frame at its joint, no mean relative rotation --
    # make the joint the position itself and R_a r = R_a: those products are skipped.
    def _at_origin(self, end: str) -> bool:
        return bool((getattr(self, f"offset_{end}") == 0).all())

    def _rel_identity(self) -> bool:
        return bool((self.rel_rot == self.rel_rot.new_tensor([1.0, 0, 0, 0])).all())

    def _joint(self, x: Tensor, end: str, edges: EdgeIndex) -> Tensor:
        """The joint seen from end ``"a"`` or ``"b"``: ``p + R o``. Shapes: (..., 7) -> (..., 3)."""
        if self._at_origin(end):
            return x[..., :3]
        offset = self._param(getattr(self, f"offset_{end}"), edges, x)
        return x[..., :3] + qrotate(x[..., 3:7], offset.expand(*x.shape[:-1], 3))

    def log_potential(self, edges, xa, xb, num_states):
        return self.log_potential_into(edges, xa, xb, num_states, None)

    def log_potential_into(self, edges, xa, xb, num_states, out):
        (ja, qa), (jb, qb) = self._ends(edges, xa, xb)
        s_p, s_r = self._spreads()
        table = se3_kernel_table(ja, qa, jb, qb, s_p, s_r, self.rotation, out)  # [i, j]
        if not self.outlier:
            return table
        # the position Gaussian is common to both components: log-add-exp of two tables
        wide = se3_kernel_table(ja, qa, jb, qb, s_p, self._outlier_spread(), self.rotation)
        keep, leave = self._outlier_log_weights()
        return torch.logaddexp(table.add_(keep), wide.add_(leave), out=table)

    def _outlier_log_weights(self) -> tuple[float, float]:
        return math.log1p(-self.outlier), math.log(self.outlier)

    def _outlier_spread(self) -> float:
        return self.outlier_rot_std * self.multipliers(self._step.iteration)[1]

    def _ends(self, edges, xa, xb) -> tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor]]:
        """What the kernel compares: the joint seen from each part and the rotations
        ``R_a r`` and ``R_b``. Shapes: (B, E, K, 3) and (B, E, K, 4) per end."""
        ja, jb = self._joint(xa, "a", edges), self._joint(xb, "b", edges)
        qa = xa[..., 3:7]
        if self.rot_std is not None and not self._rel_identity():
            qa = qmul(qa, self._param(self.rel_rot, edges, xa).expand(*xa.shape[:-1], 4))
        return (ja, qa), (jb, xb[..., 3:7])

    def log_potential_bound(self) -> float:
        s_p, s_r = self._spreads()
        bound = -3 * math.log(s_p) - 1.5 * _LOG_2PI  # the position Gaussian's peak
        if s_r is not None:  # and the rotation kernel's (at zero angle)
            one = torch.ones((), dtype=torch.float64, device="cpu")
            peak = float(rotation_log_kernel_from_dot(one.clone(), s_r, self.rotation))
            if self.outlier:  # both components peak at zero angle
                wide = float(
                    rotation_log_kernel_from_dot(one, self._outlier_spread(), self.rotation)
                )
                keep, leave = self._outlier_log_weights()
                hi, lo = sorted((peak + keep, wide + leave), reverse=True)
                peak = hi + math.log1p(math.exp(lo - hi))
            bound += peak
        return bound

    def multipliers(self, iteration: int) -> tuple[float, ...]:
        rotation = self.rotation_schedule or self.schedule
        return self.schedule(iteration), rotation(iteration)

    def _spreads(self) -> tuple[float, float | None]:
        m_p, m_r = self.multipliers(self._step.iteration)
        s_r = None if self.rot_std is None else self.rot_std * m_r
        return self.pos_std * m_p, s_r

    def log_target_mixture(self, x_target, x_source, log_w_source, edges, forward):
        # The kernel is symmetric in its ends: the mixture over sources is one call.
        xa, xb = (x_source, x_target) if forward else (x_target, x_source)
        (ja, qa), (jb, qb) = self._ends(edges, xa, xb)
        target, source = ((jb, qb), (ja, qa)) if forward else ((ja, qa), (jb, qb))
        s_p, s_r = self._spreads()
        mix = se3_kernel_mixture(*target, *source, log_w_source, s_p, s_r, self.rotation)
        if not self.outlier:
            return mix
        # sum_m w_m ((1 - e) k + e k_wide) = (1 - e) sum_m w_m k + e sum_m w_m k_wide
        wide = se3_kernel_mixture(
            *target, *source, log_w_source, s_p, self._outlier_spread(), self.rotation
        )
        keep, leave = self._outlier_log_weights()
        return torch.logaddexp(mix + keep, wide + leave)

    def sample_target(self, x_source, edges, forward, generator):
        if Capability.SAMPLABLE not in self.capabilities:
            raise MissingCapabilityError(self, Capability.SAMPLABLE)
        s_p, s_r = self._spreads()
        lead = x_source.shape[:-1]
        rel = self._param(self.rel_rot, edges, x_source).expand(*lead, 4)
        noise = rotation_noise(
            lead, float(s_r), self.rotation, generator, x_source.dtype, x_source.device
        )
        if self.outlier:  # each draw from the wide component with probability `outlier`
            wide = rotation_noise(
                lead,
                self._outlier_spread(),
                self.rotation,
                generator,
                x_source.dtype,
                x_source.device,
            )
            pick = torch.rand(
                lead, generator=generator, dtype=x_source.dtype, device=x_source.device
            )
            noise = torch.where((pick < self.outlier)[..., None], wide, noise)
        ep = torch.randn(
            (*lead, 3), generator=generator, dtype=x_source.dtype, device=x_source.device
        )
        q_s = x_source[..., 3:7]
        if not self._rel_identity():
            q_s = qmul(q_s, rel if forward else qconj(rel))
        # forward, b given a: R_b = exp(e) R_a r, p_b = joint_a - R_b o_b + noise;
        # backward, a given b: R_a = exp(e) R_b r^-1, p_a = joint_b - R_a o_a + noise.
        q_t = qnormalize(qmul(noise, q_s))
        source, target = ("a", "b") if forward else ("b", "a")
        p_t = self._joint(x_source, source, edges) + s_p * ep
        if not self._at_origin(target):
            offset = self._param(getattr(self, f"offset_{target}"), edges, x_source)
            p_t = p_t - qrotate(q_t, offset.expand(*lead, 3))
        return torch.cat([p_t, q_t], -1)

    def log_target_density(self, x_target, x_source, edges, forward):
        # psi is already normalised in the target: position Gaussian given the rotation, and
        # the SO(3) kernel in the rotation.
        if forward:
            return self.log_potential(edges, x_source, x_target, x_source.shape[-2]).transpose(
                -1, -2
            )
        return self.log_potential(edges, x_target, x_source, x_source.shape[-2])


class UnaryFactor:
    """Observation factor ``phi_j(x_j, X_-j, z_j)`` over a group of nodes.

    Subclasses implement :meth:`log_potential`; an observation that anneals (a likelihood
    sharpened over the iterations) also overrides :meth:`annealed`.

    The contract of one iteration: the engine calls :meth:`log_potential` once for the whole
    group and the whole batch, after the proposal has drawn this iteration's particles and
    before any message is computed, with

    * ``x``: the new particles of the group's nodes;
    * ``estimates``: one value per node of the graph (all V, not just the group), fixed for
      the iteration so that every particle of every node is scored against the same rest
      of the model: on the very first iteration the mean of each node's initial particles
      (the starting posture), on every later one -- restarts included -- each node's
      highest-weight particle of the previous iteration (``ParticleResult.best`` so far).
      Discrete nodes' entries are their state index as a float. Row ``j`` of a node in the
      group is its own old estimate: an occlusion-aware factor scores ``x_j`` in its place
      (the ``X_-j`` of Eq. 28).

    It returns finite log-potentials or ``-inf`` (checked), and must not keep state between
    calls that changes its answer: the same inputs give the same scores.
    """

    def log_potential(self, x: Tensor, nodes: Tensor, estimates: Tensor) -> Tensor:
        """Shapes: x (B, N, K, D) particles of ``nodes`` (N,), estimates (B, V, D) -> (B, N, K)."""
        raise NotImplementedError

    def annealed(self, step: AnnealingStep) -> UnaryFactor:
        """This factor at an annealing step, as a value (default: ``self``)."""
        return self


class GaussianUnary(UnaryFactor):
    """``phi(x) = N(x[:dim]; mean, std^2 I)`` per node. mean: ``(N, dim)`` or ``(B, N, dim)``."""

    def __init__(self, mean: Tensor, std):
        self.mean = mean if mean.dim() == 3 else mean.unsqueeze(0)
        self.std = torch.as_tensor(std, dtype=mean.dtype)
        self.dim = self.mean.shape[-1]

    def log_potential(self, x, nodes, estimates):
        z = (x[..., : self.dim] - self.mean.to(x).unsqueeze(-2)) / self.std.to(x)
        return -0.5 * z.square().sum(-1)


def _per_state(table: Tensor, state: Tensor, edges: EdgeIndex) -> Tensor:
    """Rows of ``table`` ``(E or 1, S, D)`` for the states ``(B, E', M)`` (values of a
    discrete end) of ``edges`` -> ``(B, E', M, D)``; padding states beyond ``S`` are clamped
    to ``S - 1`` (they carry no mass)."""
    if table.shape[0] > 1:
        table = table[edges]
    s = state.long().clamp(0, table.shape[1] - 1)
    e = torch.arange(table.shape[0], device=state.device)[None, :, None]
    e = e if table.shape[0] > 1 else torch.zeros_like(e)
    return table[e.expand_as(s), s]


class LookupGaussian(ContinuousPairwise):
    """A discrete node choosing the mean of a continuous one:
    ``psi(c, x) = N(x[:dim]; means[c], (anneal * std)^2 I)``.

    Edges run from the discrete node (a, states ``0..S-1``) to the continuous node (b). This
    couples a correspondence chain (states = reference frames) to the quantities it selects
    (the reference's value at the chosen frame). Only the continuous end is ever sampled (a
    discrete node's support is fixed).

    Args:
        means: ``(S, dim)`` one mean per state, or ``(E, S, dim)`` per edge.
        std: scalar or ``(dim,)`` standard deviation. schedule: annealing multiplier of it.
    """

    capabilities = _SAMPLABLE

    def __init__(self, means: Tensor, std, schedule: Schedule | None = None):
        super().__init__(schedule)
        if not isinstance(means, Tensor) or means.dim() not in (2, 3):
            shape = tuple(means.shape) if isinstance(means, Tensor) else type(means).__name__
            raise ValueError(f"means must have shape (S, dim) or (E, S, dim); got {shape}")
        if not torch.isfinite(means).all():
            raise ValueError("means must be finite")
        self.means = means if means.dim() == 3 else means.unsqueeze(0)  # (E or 1, S, dim)
        if means.dim() == 3:
            self.num_edges = means.shape[0]
        self.dim = means.shape[-1]
        std = torch.as_tensor(std, dtype=means.dtype)
        self.std = std.expand(self.dim) if std.dim() == 0 else std
        if self.std.shape != (self.dim,) or not (self.std > 0).all():
            raise ValueError(
                f"std must be > 0, a scalar or shape ({self.dim},); got {tuple(std.shape)}"
            )

    def _mean(self, state: Tensor, edges: EdgeIndex) -> Tensor:
        """Means of states ``(B, E, M)`` (values of the discrete end) -> (B, E, M, dim)."""
        return _per_state(self.means.to(state.device), state, edges)

    def _log_gauss(self, x: Tensor, mean: Tensor) -> Tensor:
        """x (B, E, K, D), mean (B, E, M, dim) -> (B, E, K, M)."""
        std = self.std.to(x) * self.anneal
        z = (x[..., : self.dim].unsqueeze(-2) - mean.to(x).unsqueeze(-3)) / std
        return (-0.5 * z.square() - torch.log(std) - 0.5 * _LOG_2PI).sum(-1)

    def log_potential(self, edges, xa, xb, num_states):
        return self._log_gauss(xb, self._mean(xa[..., 0], edges)).transpose(-1, -2)  # [c, x]

    def _check_forward(self, forward: bool) -> None:
        if not forward:
            raise ValueError(
                "LookupGaussian samples only its continuous end (b): its discrete end is "
                "never resampled"
            )

    def sample_target(self, x_source, edges, forward, generator):
        self._check_forward(forward)
        mean = self._mean(x_source[..., 0], edges).to(x_source.dtype)
        std = self.std.to(mean) * self.anneal
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
        return mean + std * noise

    def log_target_density(self, x_target, x_source, edges, forward):
        self._check_forward(forward)
        return self._log_gauss(x_target, self._mean(x_source[..., 0], edges))


class LookupPose(ContinuousPairwise):
    """A discrete node choosing the target pose of an SE(3) node:
    ``psi(c, x) = N(p(x); p(t_c), (anneal * pos_std)^2 I_3) * k(q(x); q(t_c), anneal * rot_std)``.

    The SE(3) analogue of :class:`LookupGaussian`: edges run from the discrete node (a,
    states ``0..S-1``) to the SE(3) node (b, values ``(x, y, z, qw, qx, qy, qz)``), and
    state ``c`` pulls the pose toward the target ``t_c`` -- e.g. part p of video frame t'
    toward the reference posture's part p at reference frame ``offsets[t'] + c`` (per-edge
    targets). ``k`` is the rotation kernel of the family ``rotation`` (see
    :func:`pgm.kernels.rotation_noise`: an isotropic Bingham density by default, or the
    Gaussian of rotation vectors), normalised on SO(3) in the measure of
    :class:`pgm.spaces.SE3`'s kernels, so ``psi(c, .)`` is a normalised density of the pose:
    what :meth:`sample_target` draws and :meth:`log_target_density` evaluates (only the
    continuous end is ever sampled: a discrete node's support is fixed). Padding states
    beyond ``S`` (a discrete node padded to K particles) are clamped to ``S - 1``; they carry
    no mass. The schedule multiplies both spreads.

    Either spread may be ``None``: that half of the pose is unconstrained (``pos_std=None``:
    rotation only; ``rot_std=None``: position only). ``psi(c, .)`` is then improper in that
    half and cannot be sampled, so such a factor drops :attr:`Capability.SAMPLABLE` from its
    capabilities when it is built (as :class:`RigidConnection` does without ``rot_std``) and
    its sampler and density raise :class:`~pgm.factors.MissingCapabilityError`; its table is
    still exact, so it serves in a ``ParticleGraph(..., proposal="own")`` (one built for the
    mixture proposal refuses it with a :class:`~pgm.graph.GraphError`).

    Args:
        targets: ``(S, 7)`` one pose per state, or ``(E, S, 7)`` per edge (unit quaternions).
        pos_std: metres, or ``None``. rot_std: radians, or ``None`` (not both ``None``).
        schedule: multiplier of both spreads per iteration (annealing).
        rotation: ``"bingham"`` or ``"gaussian"``, the rotation kernel's family.
    """

    capabilities = _SAMPLABLE

    def __init__(
        self,
        targets: Tensor,
        pos_std: float | None,
        rot_std: float | None,
        schedule: Schedule | None = None,
        rotation: str = "bingham",
    ):
        super().__init__(schedule)
        if not isinstance(targets, Tensor) or targets.dim() not in (2, 3) or targets.shape[-1] != 7:
            shape = tuple(targets.shape) if isinstance(targets, Tensor) else type(targets).__name__
            raise ValueError(f"targets must have shape (S, 7) or (E, S, 7); got {shape}")
        if not torch.isfinite(targets).all():
            raise ValueError("targets must be finite")
        norm = targets[..., 3:].norm(dim=-1)
        if ((norm - 1).abs() > 1e-3).any():
            raise ValueError(
                "targets' quaternions must have unit norm (max |norm - 1| = "
                f"{float((norm - 1).abs().max()):.3g})"
            )
        if rotation not in ROTATION_KERNELS:
            raise ValueError(f"rotation must be one of {ROTATION_KERNELS}; got {rotation!r}")
        if pos_std is None and rot_std is None:
            raise ValueError(
                "pos_std and rot_std cannot both be None: nothing would be constrained"
            )
        for name, std in (("pos_std", pos_std), ("rot_std", rot_std)):
            if std is not None and not (math.isfinite(std) and std > 0):
                raise ValueError(f"{name} must be finite and > 0, or None; got {std}")
        targets = torch.cat([targets[..., :3], qnormalize(targets[..., 3:])], -1)
        self.targets = targets if targets.dim() == 3 else targets.unsqueeze(0)  # (E or 1, S, 7)
        if targets.dim() == 3:
            self.num_edges = targets.shape[0]
        self.pos_std = None if pos_std is None else float(pos_std)
        self.rot_std = None if rot_std is None else float(rot_std)
        self.rotation = rotation
        if pos_std is None or rot_std is None:  # an improper conditional: nothing to sample
            self.capabilities = type(self).capabilities - {Capability.SAMPLABLE}

    def _spreads(self) -> tuple[float | None, float | None]:
        m = self.anneal
        s_p = None if self.pos_std is None else self.pos_std * m
        s_r = None if self.rot_std is None else self.rot_std * m
        return s_p, s_r

    def _target(self, state: Tensor, edges: EdgeIndex, like: Tensor) -> Tensor:
        """Targets of states ``(B, E, M)`` (values of the discrete end) -> (B, E, M, 7)."""
        return _per_state(self.targets.to(device=like.device, dtype=like.dtype), state, edges)

    def _table(self, x: Tensor, target: Tensor) -> Tensor:
        """``log psi`` of poses x (B, E, K, >= 7) against targets (B, E, M, 7) -> (B, E, K, M)."""
        s_p, s_r = self._spreads()
        qx, qt = x[..., 3:7], target[..., 3:7]
        if s_p is None:  # rotation only
            return rotation_log_kernel_from_dot(qx @ qt.transpose(-1, -2), s_r, self.rotation)
        return se3_kernel_table(x[..., :3], qx, target[..., :3], qt, s_p, s_r, self.rotation)

    def log_potential(self, edges, xa, xb, num_states):
        return self._table(xb, self._target(xa[..., 0], edges, xb)).transpose(-1, -2)  # [c, x]

    def _check_sampling(self, forward: bool) -> None:
        if Capability.SAMPLABLE not in self.capabilities:
            raise MissingCapabilityError(self, Capability.SAMPLABLE)
        if not forward:
            raise ValueError(
                "LookupPose samples only its continuous end (b): its discrete end is never "
                "resampled"
            )

    def sample_target(self, x_source, edges, forward, generator):
        self._check_sampling(forward)
        target = self._target(x_source[..., 0], edges, x_source)
        s_p, s_r = self._spreads()
        lead = target.shape[:-1]
        ep = torch.randn((*lead, 3), generator=generator, dtype=target.dtype, device=target.device)
        noise = rotation_noise(lead, s_r, self.rotation, generator, target.dtype, target.device)
        q = qnormalize(qmul(noise, target[..., 3:7]))
        return torch.cat([target[..., :3] + s_p * ep, q], -1)

    def log_target_density(self, x_target, x_source, edges, forward):
        # psi(c, .) is already normalised: a Gaussian in position, the SO(3) kernel in rotation.
        self._check_sampling(forward)
        return self._table(x_target, self._target(x_source[..., 0], edges, x_target))
