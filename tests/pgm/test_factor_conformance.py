"""Conformance: every factor pgm exports, plain and wrapped, against its own dense table.

A registry (:data:`CASES`) lists each exported factor in its variants; every case also runs
through a plain :class:`~pgm.factors.FactorWrapper` and, where it has per-edge parameters,
a :class:`~pgm.TiledFactor`. Checked for each, where it applies:

* messages equal the generic dense-table message in every semiring (log, max, tempered,
  counting), both directions, on all edges and on a subset;
* ``backtrack`` picks the argmax and ``source_given_target`` is the table's row or column;
* samplers draw from their densities (importance ratio) and those densities are normalised
  (against a broad reference whose density is known);
* mixture densities equal the log-sum-exp of the components;
* bounds bound the table at every annealing step; ``log_potential_into`` writes what
  ``log_potential`` returns; annealing returns values and leaves the factor as it was;
* declared capabilities are implemented, undeclared ones refuse, wrappers declare what they
  forward; fused Viterbi equals the generic path;
* inside graphs: discrete factors in a hybrid ``ParticleGraph`` against enumeration, and
  tiled continuous factors in particle BP's mixture proposal equal the same factor with its
  parameters repeated.

A new factor joins by one :class:`Case` line.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import pytest
import torch

import pgm
from pgm import (
    SE3,
    AnnealingStep,
    BandedMonotoneFactor,
    BandedTempoFactor,
    Capability,
    CountingSemiring,
    Discrete,
    Euclidean,
    EulerBox,
    FactorWrapper,
    GaussianUnary,
    Geometric,
    LimitedConnection,
    LinearGaussian,
    LogSemiring,
    LookupGaussian,
    LookupPose,
    MaxSemiring,
    MissingCapabilityError,
    MonotoneFactor,
    PairwiseFactor,
    ParticleGraph,
    RigidConnection,
    TableFactor,
    TemperedSemiring,
    TiledFactor,
    UnaryFactor,
    chain_map,
    particle_bp,
)
from pgm.kernels import so3_log_kernel
from pgm.rotations import qangle, qexp

F64 = torch.float64
B = 2  # batch of every check
SEMIRINGS = [LogSemiring(), MaxSemiring(), TemperedSemiring(0.5), CountingSemiring()]


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@dataclass(frozen=True)
class Case:
    """One exported factor in one configuration.

    Attributes:
        name: test id.
        make: builds the factor (float64 parameters) with its per-edge parameters repeated
            ``repeat`` times (the reference a tiled factor must equal).
        kind: what its ends hold: ``"discrete"`` (state indices), ``"euclid1"``,
            ``"euclid2"``, ``"se3"`` (particles), ``"lookup"`` (a discrete a, an R^2 b),
            ``"lookup-se3"`` (a discrete a, an SE3 b).
        states: K of the checks.
        edges: E of the checks (the factor's own count when it has per-edge parameters).
    """

    name: str
    make: Callable[[int], PairwiseFactor]
    kind: str
    states: int
    edges: int = 3


def _rand(*shape, seed=0, scale=1.0):
    return scale * torch.randn(*shape, generator=_gen(seed), dtype=F64)


def _se3(shape, seed):
    centre = torch.tensor([0.1, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)
    return SE3().perturb(centre.expand(*shape, 7), (0.06, 0.4), _gen(seed))


def _table_with_holes(e, k, seed):
    t = _rand(e, k, k, seed=seed)
    t[0, 1, :] = -math.inf  # a forbidden row, a forbidden column and a forbidden pair
    t[1, :, 2] = -math.inf
    t[-1, 0, 0] = -math.inf
    return t


def _steps(s, seed):
    return _rand(s + 1, seed=seed, scale=0.7)


def _emissions():
    """Two tempo levels, each emitting two of the three steps (the rest forbidden)."""
    table = _rand(2, 3, seed=9, scale=0.5)
    table[0, 2] = table[1, 0] = -math.inf
    return table


def _rigid(
    repeat,
    rotation="bingham",
    rot_std=0.3,
    per_edge=True,
    rel=True,
    rot_schedule=None,
    outlier=0.0,
    outlier_rot_std=None,
):
    schedule = Geometric(1.0, 0.3, 4)
    if not per_edge:
        return RigidConnection(
            torch.zeros(3, dtype=F64), torch.zeros(3, dtype=F64), 0.05, rot_std, None, schedule
        )
    off_a = _rand(3, 3, seed=11, scale=0.05).repeat(repeat, 1)
    off_b = _rand(3, 3, seed=12, scale=0.05).repeat(repeat, 1)
    rel_rot = qexp(_rand(3, 3, seed=13, scale=0.2)).repeat(repeat, 1) if rel else None
    return RigidConnection(
        off_a,
        off_b,
        0.05,
        rot_std,
        rel_rot,
        schedule,
        rotation,
        rot_schedule,
        outlier=outlier,
        outlier_rot_std=outlier_rot_std,
    )


def _limited(repeat, rotation="bingham", per_edge=True):
    """A connection with Euler-box limits around its mean relative rotation: per-edge boxes
    in three orders (one with a free channel, one that excludes the mean), or one shared
    box; spreads such that the acceptance rate is ~0.3-0.9."""
    rigid = _rigid(repeat, rotation, rot_std=0.4)
    inf = math.inf
    if per_edge:
        lower = torch.tensor([[-0.45, -0.35, -0.6], [-inf, -0.25, -0.05], [0.1, -0.5, -0.4]])
        upper = torch.tensor([[0.35, 0.5, 0.55], [inf, 0.45, 0.7], [0.6, 0.05, 0.2]])
        box = EulerBox(
            lower.repeat(repeat, 1), upper.repeat(repeat, 1), ["ZYX", "XZY", "YXZ"] * repeat, 0.1
        )
    else:
        box = EulerBox([-0.35, -0.4, -0.2], [0.4, 0.3, 0.5], "ZXY", 0.15)
    return LimitedConnection(
        rigid.offset_a,
        rigid.offset_b,
        rigid.pos_std,
        rigid.rot_std,
        rigid.rel_rot,
        rigid.schedule,
        rotation,
        limits=box,
    )


def _float64(build):
    """Factors take the default dtype for their parameters: build them in float64."""

    def make(repeat):
        old = torch.get_default_dtype()
        torch.set_default_dtype(F64)
        try:
            return build(repeat)
        finally:
            torch.set_default_dtype(old)

    return make


BANDED_OFFSETS = torch.tensor([0, 1, 3, 4])  # 4 nodes, 3 edges, shifts 1, 2, 1
CASES = [
    Case("table-shared", lambda r: TableFactor(_rand(5, 5, seed=1)), "discrete", 5),
    Case(
        "table-per-edge",
        lambda r: TableFactor(_table_with_holes(3, 5, 2).repeat(r, 1, 1)),
        "discrete",
        5,
    ),
    Case(
        "table-batched",
        lambda r: TableFactor(_rand(B, 3, 4, 4, seed=3).repeat(1, r, 1, 1)),
        "discrete",
        4,
    ),
    Case(
        "table-matmul",
        lambda r: TableFactor(_table_with_holes(3, 40, 4).repeat(r, 1, 1)),
        "discrete",
        40,
    ),
    Case(
        "table-bounded",
        lambda r: TableFactor(_rand(3, 40, 40, seed=5).repeat(r, 1, 1), upper_bound=4.5),
        "discrete",
        40,
    ),
    Case("monotone-window", lambda r: MonotoneFactor(2), "discrete", 7),
    Case("monotone-prefix", lambda r: MonotoneFactor(None), "discrete", 7),
    Case("monotone-steps", lambda r: MonotoneFactor(3, _steps(3, 6)), "discrete", 7),
    Case(
        "banded",
        lambda r: BandedMonotoneFactor(2, _tile_offsets(r)),
        "discrete",
        6,
    ),
    Case(
        "banded-steps",
        lambda r: BandedMonotoneFactor(2, _tile_offsets(r), _steps(2, 7)),
        "discrete",
        6,
    ),
    Case(
        "banded-tempo",
        lambda r: BandedTempoFactor(
            2, _tile_offsets(r), _rand(3, 3, seed=10, scale=0.7), _rand(3, 3, seed=11, scale=0.7)
        ),
        "discrete",
        6,  # W = 2 positions x L = 3 tempo levels
    ),
    Case(
        "banded-tempo-forbidden",
        lambda r: BandedTempoFactor(2, _tile_offsets(r), _emissions(), _rand(2, 2, seed=12)),
        "discrete",
        8,  # W = 4 positions x L = 2 levels
    ),
    Case(
        "linear-gaussian",
        _float64(
            lambda r: LinearGaussian(
                2, 0.8, torch.tensor([0.3, -0.2]), torch.tensor([0.5, 0.7]), Geometric(1, 0.2, 4)
            )
        ),
        "euclid2",
        12,
    ),
    Case(
        "linear-gaussian-per-edge",
        _float64(lambda r: LinearGaussian(1, -1.3, _rand(3, 1, seed=8).repeat(r, 1), 0.6)),
        "euclid1",
        12,
    ),
    Case("rigid-bingham", _float64(_rigid), "se3", 12),
    Case("rigid-gaussian", _float64(lambda r: _rigid(r, "gaussian")), "se3", 12),
    Case("rigid-no-rotation", _float64(lambda r: _rigid(r, rot_std=None)), "se3", 12),
    Case("rigid-at-origin", _float64(lambda r: _rigid(r, per_edge=False)), "se3", 12),
    Case("rigid-no-relative", _float64(lambda r: _rigid(r, rel=False)), "se3", 12),
    Case(
        "rigid-own-rotation-schedule",
        _float64(lambda r: _rigid(r, rot_std=0.8, rot_schedule=Geometric(1.0, 0.8, 3))),
        "se3",
        12,
    ),
    Case(
        "rigid-outlier-bingham",
        _float64(lambda r: _rigid(r, rot_std=0.15, outlier=0.2, outlier_rot_std=0.35)),
        "se3",
        12,
    ),
    Case(
        "rigid-outlier-gaussian",
        _float64(lambda r: _rigid(r, "gaussian", rot_std=0.15, outlier=0.2, outlier_rot_std=0.35)),
        "se3",
        12,
    ),
    Case("limited-bingham", _float64(_limited), "se3", 12),
    Case("limited-gaussian", _float64(lambda r: _limited(r, "gaussian")), "se3", 12),
    Case("limited-shared-box", _float64(lambda r: _limited(r, per_edge=False)), "se3", 12),
    Case(
        "lookup-gaussian",
        lambda r: LookupGaussian(_rand(6, 2, seed=9), torch.tensor([0.4, 0.6], dtype=F64)),
        "lookup",
        12,
    ),
    Case(
        "lookup-per-edge",
        lambda r: LookupGaussian(
            _rand(3, 6, 2, seed=10).repeat(r, 1, 1), 0.5, schedule=Geometric(1, 0.5, 3)
        ),
        "lookup",
        12,
    ),
    Case("lookup-pose", lambda r: LookupPose(_se3((6,), 30), 0.05, 0.2), "lookup-se3", 12),
    Case(
        "lookup-pose-gaussian-per-edge",
        lambda r: LookupPose(
            _se3((3, 6), 31).repeat(r, 1, 1), 0.04, 0.25, Geometric(1, 0.5, 3), "gaussian"
        ),
        "lookup-se3",
        12,
    ),
    Case(
        "lookup-pose-rotation-only",
        lambda r: LookupPose(_se3((3, 6), 32).repeat(r, 1, 1), None, 0.3),
        "lookup-se3",
        12,
    ),
    Case(
        "lookup-pose-position-only",
        lambda r: LookupPose(_se3((6,), 33), 0.05, None, rotation="gaussian"),
        "lookup-se3",
        12,
    ),
]


def _tile_offsets(repeat):
    """Banded offsets of ``repeat`` chains laid end to end: edge shifts repeat with them."""
    shifts = BANDED_OFFSETS.diff().repeat(repeat)
    return torch.cat([BANDED_OFFSETS[:1], BANDED_OFFSETS[0] + shifts.cumsum(0)])


class Relabel(FactorWrapper):
    """The plainest wrapper: every edge is itself. Any forwarding gap shows against the base."""

    def rewrap(self, base):
        return Relabel(base)


@dataclass(frozen=True)
class Variant:
    """A case as it is exercised: the factor, its edge count, and how its edges map to the
    base's (for the per-edge reference)."""

    factor: PairwiseFactor
    base: PairwiseFactor
    num_edges: int
    tiles: int


def _variant(case: Case, how: str) -> Variant:
    base = case.make(1)
    e = base.num_edges or case.edges
    if how == "plain":
        return Variant(base, base, e, 1)
    if how == "wrapped":
        return Variant(Relabel(base), base, e, 1)
    return Variant(TiledFactor(base, 2), base, 2 * e, 2)


def _variants():
    out = []
    for case in CASES:
        hows = ["plain", "wrapped"] + (["tiled"] if case.make(1).num_edges is not None else [])
        out += [pytest.param(case, how, id=f"{case.name}-{how}") for how in hows]
    return out


VARIANTS = _variants()


def _edge_choices(num_edges: int) -> dict[str, torch.Tensor | slice]:
    return {"all": slice(None), "subset": torch.tensor([num_edges - 1, 0])}


def _count(edges, num_edges):
    return num_edges if isinstance(edges, slice) else len(edges)


def _supports(case: Case, e: int, seed: int = 0):
    """Values of both ends, ``(B, E, K, D)`` each, or ``None`` for discrete supports."""
    k = case.states
    if case.kind == "discrete":
        return None, None
    if case.kind == "lookup":
        a = torch.randint(0, 6, (B, e, k, 1), generator=_gen(seed)).to(F64)
        return a, _rand(B, e, k, 2, seed=seed + 1)
    if case.kind == "lookup-se3":
        a = torch.randint(0, 6, (B, e, k, 1), generator=_gen(seed)).to(F64)
        return a, _se3((B, e, k), seed + 1)
    if case.kind == "se3":
        return _se3((B, e, k), seed), _se3((B, e, k), seed + 1)
    d = int(case.kind[-1])
    return _rand(B, e, k, d, seed=seed), _rand(B, e, k, d, seed=seed + 1)


def _messages_in(semiring, shape, seed):
    """Incoming beliefs in the semiring's domain, with a forbidden state."""
    if semiring.log_space:
        h = _rand(*shape, seed=seed)
        h[0, 0, 1] = -math.inf
        return h
    h = torch.rand(*shape, generator=_gen(seed), dtype=F64)
    h[0, 0, 1] = 0.0
    return h


def _dense_message(table, h, forward, semiring):
    t = semiring.from_log(table).expand(*h.shape[:2], h.shape[-1], h.shape[-1])
    if forward:
        return semiring.sum(semiring.mul(t, h.unsqueeze(-1)), dim=-2)
    return semiring.sum(semiring.mul(t, h.unsqueeze(-2)), dim=-1)


def _assert_close_inf(a, b, **kw):
    assert a.shape == b.shape, (a.shape, b.shape)
    assert torch.equal(torch.isneginf(a), torch.isneginf(b))
    finite = torch.isfinite(a)
    torch.testing.assert_close(a[finite], b[finite], **kw)


# -- messages and decoding -----------------------------------------------------------------
@pytest.mark.parametrize("semiring", SEMIRINGS, ids=lambda s: s.name)
@pytest.mark.parametrize("forward", [True, False], ids=["forward", "backward"])
@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_messages_equal_the_dense_table(case, how, forward, semiring):
    var = _variant(case, how)
    for name, edges in _edge_choices(var.num_edges).items():
        e = _count(edges, var.num_edges)
        xa, xb = _supports(case, e)
        h = _messages_in(semiring, (B, e, case.states), seed=3)
        table = var.factor.log_potential(edges, xa, xb, case.states)
        got = var.factor.message(h, edges, forward, semiring, xa, xb)
        want = _dense_message(table, h, forward, semiring)
        if semiring.log_space:
            _assert_close_inf(got, want, rtol=1e-9, atol=1e-9)
        else:
            torch.testing.assert_close(got, want, rtol=1e-12, atol=0, msg=name)


@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_tiled_and_wrapped_tables_are_the_base_on_mapped_edges(case, how):
    var = _variant(case, how)
    edges = torch.arange(var.num_edges).flip(0)
    mapped = edges % (var.base.num_edges or var.num_edges)
    xa, xb = _supports(case, var.num_edges)
    _assert_close_inf(
        var.factor.log_potential(edges, xa, xb, case.states),
        var.base.log_potential(mapped, xa, xb, case.states),
        rtol=0,
        atol=0,
    )


@pytest.mark.parametrize("forward", [True, False], ids=["forward", "backward"])
@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_backtrack_is_the_argmax_of_the_table(case, how, forward):
    var = _variant(case, how)
    k, e = case.states, var.num_edges
    xa, xb = _supports(case, e)
    table = var.factor.log_potential(slice(None), xa, xb, k).expand(B, e, k, k)
    target = torch.randint(0, k, (B, e), generator=_gen(4))
    column = (
        table.gather(-1, target[..., None, None].expand(B, e, k, 1)).squeeze(-1)
        if forward
        else table.gather(-2, target[..., None, None].expand(B, e, 1, k)).squeeze(-2)
    )
    cond = var.factor.source_given_target(target, slice(None), forward, k, xa, xb)
    _assert_close_inf(cond, column, rtol=1e-12, atol=1e-12)
    h = _rand(B, e, k, seed=5)
    chosen = var.factor.backtrack(h, target, slice(None), forward, xa, xb)
    score = (h + column).gather(-1, chosen[..., None]).squeeze(-1)
    best = (h + column).amax(-1)
    _assert_close_inf(score, best, rtol=0, atol=1e-12)


# -- samplers and densities ----------------------------------------------------------------
def _samplable_directions(case: Case):
    if case.kind == "discrete":
        return []
    return [True] if case.kind.startswith("lookup") else [True, False]


SAMPLERS = [
    pytest.param(case, how, forward, id=f"{case.name}-{how}-{'fwd' if forward else 'bwd'}")
    for case, how in (p.values for p in VARIANTS)
    if Capability.SAMPLABLE in case.make(1).capabilities
    for forward in _samplable_directions(case)
]


def _sources(case: Case, forward: bool, e: int, seed: int):
    """Two nearby source particles per edge, ``(1, E, 2, D_s)``."""
    xa, xb = _supports(case, e, seed)
    src = (xa if forward else xb)[:1, :, :2].clone()
    if case.kind == "se3":
        src[..., 1, :3] = src[..., 0, :3] + 0.01
        src[..., 1, 3:] = pgm.rotations.qmul(
            qexp(torch.tensor([0.05, -0.03, 0.0], dtype=F64)), src[..., 0, 3:]
        )
    elif case.kind.startswith("lookup"):
        src[..., 1, :] = (src[..., 0, :] + 1) % 6
    else:
        src[..., 1, :] = src[..., 0, :] + 0.1
    return src


def _log_reference(case: Case, draws: torch.Tensor):
    """A broad density around the draws (twice their spread) and samples from it, to check
    a conditional density against: it must integrate to 1 and give the draws' moments.
    Shapes: draws (1, E, n, D) -> samples (1, E, n, D), their log density (1, E, n)."""
    g = _gen(21)
    se3 = case.kind in ("se3", "lookup-se3")
    pos = draws[..., :3] if se3 else draws
    mean, std = pos.mean(-2, keepdim=True), 2 * pos.std(-2, keepdim=True)
    y = mean + std * torch.randn(pos.shape, generator=g, dtype=F64)
    log_r = torch.distributions.Normal(mean, std).log_prob(y).sum(-1)
    if not se3:
        return y, log_r
    # rotations: the rotation-vector Gaussian around the draws' mean rotation, twice as
    # wide as their spread (its density is pgm.kernels.so3_log_kernel)
    uniform = torch.zeros(draws.shape[:-1], dtype=F64)
    centre = SE3().weighted_mean(draws, uniform)[..., None, 3:].expand(*draws.shape[:-1], 4)
    spread = qangle(draws[..., 3:], centre).square().mean(-1, keepdim=True).sqrt() / math.sqrt(3)
    width = 2 * spread.clamp_min(1e-3)
    if float(width.max()) > 0.5:
        # too wide for a Gaussian of rotation vectors (it would wrap past pi): uniform
        # rotations, density 1 / (8 pi^2) in the same measure (the volume of SO(3))
        q = torch.nn.functional.normalize(
            torch.randn(*draws.shape[:-1], 4, generator=g, dtype=F64), dim=-1
        )
        return torch.cat([y, q], -1), log_r - math.log(8 * math.pi**2)
    noise = qexp(width.unsqueeze(-1) * torch.randn(*draws.shape[:-1], 3, generator=g, dtype=F64))
    q = pgm.rotations.qmul(noise, centre)
    log_r = log_r + so3_log_kernel(qangle(q, centre), width)
    return torch.cat([y, q], -1), log_r


@pytest.mark.parametrize(("case", "how", "forward"), SAMPLERS)
def test_samplers_draw_from_their_normalised_densities(case, how, forward):
    """Against a broad reference r with a known density: E_r[psi(x0, y) / r(y)] = 1 (the
    density is normalised) and the psi / r-weighted mean of r's samples is the mean of the
    sampler's draws (they follow the density). With continuous sources also the direct
    importance ratio E_{y ~ psi(x0, .)}[psi(x1, y) / psi(x0, y)] = 1 for a nearby x1."""
    var = _variant(case, how)
    factor = var.factor.annealed(AnnealingStep(iteration=1))
    e, n = var.num_edges, 40_000
    src = _sources(case, forward, e, seed=6)
    draws = factor.sample_target(
        src[..., :1, :].expand(1, e, n, src.shape[-1]), slice(None), forward, _gen(7)
    )
    dens = factor.log_target_density(draws, src, slice(None), forward)  # (1, E, n, 2)
    assert dens.shape == (1, e, n, 2)
    if not case.kind.startswith("lookup"):  # nearby states of a lookup table have unrelated means
        ratio = (dens[..., 1] - dens[..., 0]).exp().mean(-1)
        torch.testing.assert_close(ratio, torch.ones_like(ratio), atol=0.05, rtol=0)
    y, log_r = _log_reference(case, draws)
    log_iw = factor.log_target_density(y, src[..., :1, :], slice(None), forward)[..., 0] - log_r
    z = log_iw.exp().mean(-1)
    torch.testing.assert_close(z, torch.ones_like(z), atol=0.05, rtol=0)
    w = torch.softmax(log_iw, -1).unsqueeze(-1)
    d = 3 if case.kind in ("se3", "lookup-se3") else draws.shape[-1]
    weighted = (w * y[..., :d]).sum(-2)
    drawn = draws[..., :d].mean(-2)
    tol = 0.1 * draws[..., :d].std(-2)
    assert ((weighted - drawn).abs() <= tol).all(), (weighted - drawn).abs() / tol


@pytest.mark.parametrize(("case", "how", "forward"), SAMPLERS)
def test_mixture_density_is_the_log_sum_exp_of_its_components(case, how, forward):
    var = _variant(case, how)
    e = var.num_edges
    xa, xb = _supports(case, e, seed=8)
    sources = (xa if forward else xb)[:, :, :9]
    targets = var.factor.sample_target(sources[:, :, :5], slice(None), forward, _gen(9))
    log_w = torch.log_softmax(_rand(B, e, 9, seed=10), -1)
    got = var.factor.log_target_mixture(targets, sources, log_w, slice(None), forward)
    dens = var.factor.log_target_density(targets, sources, slice(None), forward)
    torch.testing.assert_close(got, torch.logsumexp(dens + log_w.unsqueeze(-2), -1))


# -- bounds, buffers, annealing, declarations ------------------------------------------------
@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_bounds_bound_the_table_at_every_step(case, how):
    var = _variant(case, how)
    if Capability.BOUNDED not in var.factor.capabilities:
        assert var.factor.log_potential_bound() is None
        return
    for it in range(5):
        f = var.factor.annealed(AnnealingStep(iteration=it))
        xa, xb = _supports(case, var.num_edges, seed=it)
        if xb is not None:
            xb[..., 0, :] = xa[..., 0, :]  # a pair at (nearly) the mode too
        table = f.log_potential(slice(None), xa, xb, case.states)
        assert float(table.max()) <= f.log_potential_bound() + 1e-9


@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_buffered_table_is_the_table(case, how):
    var = _variant(case, how)
    xa, xb = _supports(case, var.num_edges)
    k = case.states
    want = var.factor.log_potential(slice(None), xa, xb, k).expand(B, var.num_edges, k, k)
    out = torch.full((want.numel(),), math.nan, dtype=F64)
    got = var.factor.log_potential_into(slice(None), xa, xb, k, out)
    _assert_close_inf(got.expand_as(want), want, rtol=0, atol=1e-12)
    if Capability.BUFFERED in var.factor.capabilities:
        assert got.data_ptr() == out.data_ptr(), "a buffered factor writes into the buffer"


@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_annealing_returns_a_value_and_leaves_the_factor_alone(case, how):
    var = _variant(case, how)
    xa, xb = _supports(case, var.num_edges)
    k = case.states
    before = var.factor.log_potential(slice(None), xa, xb, k)
    later = var.factor.annealed(AnnealingStep(iteration=3, restart=1))
    _assert_close_inf(var.factor.log_potential(slice(None), xa, xb, k), before, rtol=0, atol=0)
    if Capability.ANNEALED not in var.factor.capabilities:
        assert later is var.factor
        return
    again = var.factor.annealed(AnnealingStep(iteration=3)).log_potential(slice(None), xa, xb, k)
    _assert_close_inf(later.log_potential(slice(None), xa, xb, k), again, rtol=0, atol=0)
    assert (
        var.factor.annealed(AnnealingStep(iteration=0))
        .log_potential(slice(None), xa, xb, k)
        .equal(before)
    )
    assert type(later) is type(var.factor) and later.capabilities == var.factor.capabilities


@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_declared_capabilities_are_implemented_and_forwarded(case, how):
    var = _variant(case, how)
    caps = var.factor.capabilities
    expected = frozenset(var.base.capabilities)
    if var.tiles > 1:
        expected -= {Capability.FUSED_VITERBI}
    assert caps == expected
    if Capability.SAMPLABLE not in caps:
        x = torch.zeros(1, 1, 1, 7, dtype=F64)
        with pytest.raises(MissingCapabilityError, match="samplable"):
            var.factor.sample_target(x, slice(0, 1), True, None)
    if Capability.BOUNDED in caps:
        assert isinstance(var.factor.log_potential_bound(), float)


def _chain_length(case, var):
    return var.num_edges + 1 if var.factor.num_edges is not None else 6


@pytest.mark.parametrize(("case", "how"), VARIANTS)
def test_fused_viterbi_equals_the_generic_path(case, how):
    var = _variant(case, how)
    if case.kind != "discrete":
        assert var.factor.viterbi(torch.zeros(1, 3, case.states, dtype=F64)) is None
        return
    n = _chain_length(case, var)
    unary = _rand(B, n, case.states, seed=11)
    fused = var.factor.viterbi(unary.clone())
    if Capability.FUSED_VITERBI not in var.factor.capabilities:
        assert fused is None
        return
    assert fused is not None
    generic = chain_map(unary, var.factor, use_fused=False)
    torch.testing.assert_close(fused[0], generic.log_partition)
    assert torch.equal(fused[1], generic.assignment)


# -- inside graphs ---------------------------------------------------------------------------
DISCRETE = [
    p for p in VARIANTS if p.values[0].kind == "discrete" and p.values[0].name != "table-batched"
]


@pytest.mark.parametrize(("case", "how"), DISCRETE)
def test_discrete_factor_in_a_hybrid_particle_graph_matches_enumeration(case, how):
    """A chain of discrete nodes joined by the factor, the last one choosing the mean of a
    continuous node that is observed: particle BP (discrete nodes padded to K particles)
    against enumerating every discrete configuration, with x integrated out in closed form
    (N(y; mu_c, s^2 + r^2))."""
    var = _variant(case, how)
    s = case.states
    n = var.num_edges + 1 if var.factor.num_edges is not None else 3
    mu = torch.linspace(-2, 2, s, dtype=F64)[:, None]
    sd, r, y = 0.4, 0.5, 0.7
    chain = torch.stack([torch.arange(n - 1), torch.arange(1, n)], 1)
    graph = ParticleGraph(
        n + 1,
        [(Discrete(s), torch.arange(n)), (Euclidean(1), torch.tensor([n]))],
        [(chain, var.factor), (torch.tensor([[n - 1, n]]), LookupGaussian(mu, sd))],
        [(torch.tensor([n]), GaussianUnary(torch.tensor([[y]], dtype=F64), r))],
    )
    k = 1000  # the x-message's Monte Carlo error on p(c) is then ~0.01
    init = 2 * torch.randn(1, n + 1, k, 1, generator=_gen(12), dtype=F64)
    res = particle_bp(graph, init, iterations=5, generator=_gen(13), kernel_scale=[None, 0.3])
    table = var.factor.log_potential(slice(None), None, None, s).expand(1, n - 1, s, s)[0]
    lik = torch.distributions.Normal(mu[:, 0], math.sqrt(sd**2 + r**2)).log_prob(
        torch.tensor(y, dtype=F64)
    )
    for node, exact in enumerate(_chain_marginals(table, lik)):
        got = res.log_weights[0, node, :s].exp()
        torch.testing.assert_close(got, exact, atol=0.03, rtol=0)
        assert res.log_weights[0, node, s:].isneginf().all()


def _chain_marginals(table, last_unary):
    """Marginals of a chain with pairwise log-tables ``(N - 1, S, S)`` and a unary on its
    last node: by enumeration where that is small, else by the exact tree engine on the
    dense tables (itself checked against enumeration in test_tree.py)."""
    n, s = table.shape[0] + 1, table.shape[-1]
    if s**n > 50_000:
        unary = torch.zeros(1, n, s, dtype=F64)
        unary[0, -1] = last_unary
        chain = torch.stack([torch.arange(n - 1), torch.arange(1, n)], 1)
        exact = pgm.tree_inference(pgm.FactorGraph(unary, [(chain, TableFactor(table))]))
        return exact.log_marginals[0].exp()
    configs = torch.tensor(list(itertools.product(range(s), repeat=n)))
    score = last_unary[configs[:, -1]].clone()
    for t in range(n - 1):
        score += table[t, configs[:, t], configs[:, t + 1]]
    p = torch.softmax(score, 0)
    return [torch.zeros(s, dtype=F64).index_add_(0, configs[:, i], p) for i in range(n)]


CONTINUOUS_TILED = [
    p
    for p in VARIANTS
    if p.values[1] == "tiled"
    and p.values[0].kind in ("euclid1", "euclid2", "se3")
    and Capability.SAMPLABLE in p.values[0].make(1).capabilities
]


@pytest.mark.parametrize(("case", "how"), CONTINUOUS_TILED)
def test_tiled_factor_in_the_mixture_proposal_equals_repeated_parameters(case, how):
    """Two chains of E + 1 nodes share one tiled factor: particle BP (mixture proposal,
    fast paths) gives exactly what the factor with its parameters written out twice gives."""
    var = _variant(case, how)
    e = var.base.num_edges
    chain = torch.stack([torch.arange(e), torch.arange(1, e + 1)], 1)
    edges = torch.cat([chain, chain + e + 1])
    v = 2 * (e + 1)
    space = SE3() if case.kind == "se3" else Euclidean(int(case.kind[-1]))
    scale = (0.02, 0.1) if case.kind == "se3" else 0.2
    if case.kind == "se3":
        init = _se3((1, v, 40), 14)
        mean = init[0, :, 0, :3]
    else:
        init = _rand(1, v, 40, space.dim, seed=14)
        mean = torch.zeros(v, space.dim, dtype=F64)
    unary = [(torch.arange(v), GaussianUnary(mean, 0.3))]
    results = []
    for factor in (var.factor, case.make(2)):
        graph = ParticleGraph(v, [(space, torch.arange(v))], [(edges, factor)], unary)
        results.append(
            particle_bp(graph, init, iterations=3, generator=_gen(15), kernel_scale=scale)
        )
    torch.testing.assert_close(results[0].particles, results[1].particles)
    torch.testing.assert_close(results[0].log_weights, results[1].log_weights)


# -- the registry is complete ----------------------------------------------------------------
def _exported(cls):
    return {
        getattr(pgm, name)
        for name in pgm.__all__
        if isinstance(getattr(pgm, name), type) and issubclass(getattr(pgm, name), cls)
    }


def test_every_exported_factor_is_in_the_registry():
    abstract = {PairwiseFactor, pgm.ContinuousPairwise, FactorWrapper}
    wrappers = {c for c in _exported(PairwiseFactor) if issubclass(c, FactorWrapper)}
    covered = {type(case.make(1)) for case in CASES}
    assert _exported(PairwiseFactor) - abstract - wrappers == covered
    assert wrappers - {FactorWrapper} == {TiledFactor}  # exercised as the "tiled" variant
    assert _exported(UnaryFactor) - {UnaryFactor} == {GaussianUnary}


def test_unary_factors_score_every_particle_and_anneal_as_values():
    factor = GaussianUnary(_rand(3, 2, seed=16), 0.5)
    x = _rand(B, 3, 7, 2, seed=17)
    out = factor.log_potential(x, torch.arange(3), _rand(B, 3, 2, seed=18))
    assert out.shape == (B, 3, 7) and torch.isfinite(out).all()
    assert factor.annealed(AnnealingStep(iteration=2)) is factor


def test_declaring_a_capability_without_its_methods_fails_at_class_definition():
    with pytest.raises(TypeError, match="declares the capability 'samplable' but does not"):

        class Broken(pgm.ContinuousPairwise):
            capabilities = pgm.ContinuousPairwise.capabilities | {Capability.SAMPLABLE}

            def log_potential(self, edges, xa, xb, num_states):
                return torch.zeros(1, 1, num_states, num_states)
