"""Time alignment against brute force, tslearn and dtaidistance, plus robustness and scale."""

import itertools
import math
import re

import numpy as np
import pytest
import torch

from motion.alignment import (
    AlignmentError,
    TempoPrior,
    band_mask,
    chain_align,
    coarse_to_fine_align,
    dtw,
    robust_cost,
    sequence_cost_fn,
    slope_step_cost,
    soft_align,
    tempo_align,
)


def _monotone_paths(n, k, s):
    for path in itertools.product(range(k), repeat=n):
        steps = np.diff(path)
        if ((steps >= 0) & (steps <= s)).all():
            yield path


def _monotone_paths_by_steps(n, k, s):
    """Every monotone path (steps 0..s) of n nodes over k states, built step by step."""
    for start in range(k):
        for steps in itertools.product(range(s + 1), repeat=n - 1):
            path = start + np.concatenate([[0], np.cumsum(steps)])
            if path[-1] < k:
                yield tuple(int(c) for c in path)


def _brute_dtw(cost):
    n, m = cost.shape
    acc = np.full((n, m), np.inf)
    for i in range(n):
        for j in range(m):
            prev = (
                0.0
                if i == j == 0
                else min(
                    acc[i - 1, j - 1] if i and j else np.inf,
                    acc[i - 1, j] if i else np.inf,
                    acc[i, j - 1] if j else np.inf,
                )
            )
            acc[i, j] = cost[i, j] + prev
    return acc[-1, -1]


def _warped_features(seed, num_video=100, slope=4.0, corrupt=False, noise=0.02):
    """Smooth 8-D reference features, a non-linearly warped copy as the 'video'.

    With ``corrupt``, video frames 40-50 are replaced by frames 50-60 (the proposal's Fig. 12
    experiment). Returns cost (T', T) float64, the true C (T',), T.
    """
    g = torch.Generator().manual_seed(seed)
    num_ref = int(num_video * slope) + 20
    t = torch.arange(num_ref, dtype=torch.float64)
    freqs = torch.rand(8, generator=g, dtype=torch.float64) * 0.05 + 0.01
    phase = torch.rand(8, generator=g, dtype=torch.float64) * 2 * math.pi
    ref = torch.sin(t[:, None] * freqs + phase)
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    bend = 1 + float(torch.rand(1, generator=g))
    warp = (u + 0.05 * torch.sin(2 * math.pi * u * bend)) * (num_ref - 1)
    true = torch.cummax(warp.round().long().clamp(0, num_ref - 1), 0).values
    video = ref[true].clone()
    if corrupt:
        video[40:51] = video[50:61].clone()
    video += noise * torch.randn(video.shape, generator=g, dtype=torch.float64)
    cost = (video[:, None] - ref[None]).square().mean(-1)
    return cost, true, num_ref


# -- chain alignment ---------------------------------------------------------------------------
@pytest.mark.parametrize(("n", "k", "s"), [(4, 5, 1), (5, 4, 2), (3, 6, 5)])
def test_chain_align_is_the_best_monotone_path(n, k, s):
    torch.manual_seed(n * 10 + k)
    cost = torch.rand(2, n, k, dtype=torch.float64)
    result = chain_align(cost, s)
    for b in range(2):
        best = min(
            sum(cost[b, i, c].item() for i, c in enumerate(p)) for p in _monotone_paths(n, k, s)
        )
        assert result.cost[b].item() == pytest.approx(best, abs=1e-12)
    steps = result.path.diff(dim=-1)
    assert ((steps >= 0) & (steps <= s)).all()


def test_chain_align_fixed_ends_and_band():
    torch.manual_seed(0)
    n, k, s = 4, 6, 2
    cost = torch.rand(n, k, dtype=torch.float64)
    band = band_mask(n, k, 1)
    result = chain_align(cost, s, fix_start=True, fix_end=True, band=band)
    allowed = [
        p
        for p in _monotone_paths(n, k, s)
        if p[0] == 0 and p[-1] == k - 1 and all(band[i, c] for i, c in enumerate(p))
    ]
    best = min(sum(cost[i, c].item() for i, c in enumerate(p)) for p in allowed)
    assert result.cost.item() == pytest.approx(best, abs=1e-12)
    assert result.path[0, 0] == 0 and result.path[0, -1] == k - 1


def test_chain_align_with_step_cost_matches_brute_force():
    torch.manual_seed(1)
    n, k, s = 5, 6, 3
    cost = torch.rand(n, k, dtype=torch.float64)
    step_cost = slope_step_cost(s, 1.2, 0.7).double()
    result = chain_align(cost, s, step_cost=step_cost)

    def energy(p):
        return sum(cost[i, c].item() for i, c in enumerate(p)) + sum(
            step_cost[b - a].item() for a, b in itertools.pairwise(p)
        )

    best = min(_monotone_paths(n, k, s), key=energy)
    assert tuple(result.path[0].tolist()) == best


@pytest.mark.parametrize(("seed", "m"), [(0, 1), (1, 1), (2, 2), (3, 3)])
def test_tempo_align_is_the_best_phase_path(seed, m):
    """Every monotone phase path on the grid of 1/m frame through random windows, scored by
    hand (each phase costing its rounded frame, the slope prior on each step's tempo, the
    change of tempo): tempo_align's C is the best one's phase rounded (its cost excludes
    the prior)."""
    g = torch.Generator().manual_seed(seed)
    n, w, s = 4, 3, 2
    offsets = torch.cummax(torch.randint(0, 3, (n,), generator=g).cumsum(0) - 1, 0).values
    offsets = (offsets - offsets[0]).clamp(min=0)
    cost = torch.rand(n, w, generator=g, dtype=torch.float64)
    cost[2, 1] = math.inf  # a forbidden frame
    prior = TempoPrior(1.3, 0.4, 0.3, subdivisions=m)

    def at(t, phase):  # the cost at a phase (grid units): its rounded frame's
        return cost[t, (phase + m // 2) // m - int(offsets[t])].item()

    def energy(path):
        tempo = [(b - a) / m for a, b in itertools.pairwise(path)]
        return (
            sum(at(t, p) for t, p in enumerate(path))
            + sum(prior.slope_weight * ((v - 1.3) / 1.3) ** 2 for v in tempo)
            + sum(((b - a) / 1.3) ** 2 / (2 * 0.3**2) for a, b in itertools.pairwise(tempo))
        )

    grids = [range(int(o) * m, (int(o) + w - 1) * m + 1) for o in offsets]
    paths = [
        p
        for p in itertools.product(*grids)
        if all(0 <= b - a <= s * m for a, b in itertools.pairwise(p))
    ]
    best = min(paths, key=energy)
    result = tempo_align(cost, offsets, s, prior)
    expected = [(p + m // 2) // m for p in best]
    assert result.path[0].tolist() == expected
    on_path = sum(cost[t, c - offsets[t]].item() for t, c in enumerate(expected))
    assert result.cost.item() == pytest.approx(on_path, abs=1e-12)


def test_tempo_align_without_a_prior_is_the_chain_on_the_band():
    """No prior: the first-order chain, i.e. chain_align with the band's mask."""
    g = torch.Generator().manual_seed(4)
    n, k, w, s = 30, 60, 9, 3
    offsets = (torch.arange(n) * 1.7).long().clamp(max=k - w)
    cost = torch.rand(n, w, generator=g, dtype=torch.float64)
    full = torch.full((n, k), math.inf, dtype=torch.float64)
    full.scatter_(1, offsets[:, None] + torch.arange(w), cost)
    chained = chain_align(full, s)
    banded = tempo_align(cost, offsets, s)
    assert torch.equal(banded.path, chained.path)
    torch.testing.assert_close(banded.cost, chained.cost)


def test_tempo_prior_holds_the_tempo_where_the_evidence_is_flat():
    """A warp at 2.5 frames per step (steps of 2 and 3 interleaved) whose first and last 8
    rows say nothing: the first-order chain under the slope prior (around 2) drifts there;
    the tempo carries the observed rate through them, and follows the interleaved steps
    exactly (rounding the phase costs them nothing)."""
    n, k, s = 40, 140, 6
    true = (10 + 2.5 * torch.arange(n)).floor().long()
    cost = (torch.arange(k)[None, :] - true[:, None]).abs().double().clamp(max=5) / 5
    cost[:8] = 0.0
    cost[-8:] = 0.0
    offsets = torch.zeros(n, dtype=torch.long)
    first = chain_align(cost, s, step_cost=slope_step_cost(s, 2.0, 1.0).double()).path[0]
    second = tempo_align(cost, offsets, s, TempoPrior(2.0, 1.0, 0.1)).path[0]
    assert (first - true).abs()[:8].float().mean() > 2  # the chain's ends drift
    assert torch.equal(second, true)


def test_tempo_align_input_errors():
    cost = torch.zeros(4, 3)
    offsets = torch.arange(4)
    with pytest.raises(AlignmentError, match=r"one \(T', W\) table"):
        tempo_align(torch.zeros(1, 4, 3), offsets, 2)
    with pytest.raises(AlignmentError, match="non-decreasing"):
        tempo_align(cost, torch.tensor([0, 2, 1, 3]), 2)
    with pytest.raises(AlignmentError, match="subdivisions must be an int >= 1"):
        TempoPrior(1.0, 1.0, 0.1, subdivisions=0)
    with pytest.raises(AlignmentError, match="no monotone path"):
        tempo_align(cost, torch.tensor([0, 0, 9, 9]), 2)
    with pytest.raises(AlignmentError, match="change_std must be"):
        TempoPrior(1.0, 1.0, 0.0)


def test_soft_alignment_matches_brute_force_posterior():
    torch.manual_seed(2)
    n, k, s, tau = 4, 5, 2, 0.3
    cost = torch.rand(n, k, dtype=torch.float64)
    soft = soft_align(cost, s, temperature=tau)
    paths = list(_monotone_paths(n, k, s))
    energies = torch.tensor(
        [sum(cost[i, c].item() for i, c in enumerate(p)) for p in paths], dtype=torch.float64
    )
    w = torch.softmax(-energies / tau, 0)
    post = torch.zeros(n, k, dtype=torch.float64)
    for p, wp in zip(paths, w, strict=True):
        for i, c in enumerate(p):
            post[i, c] += wp
    torch.testing.assert_close(soft.posterior[0], post)
    torch.testing.assert_close(soft.expected[0], (post * torch.arange(k)).sum(-1))
    torch.testing.assert_close(soft.log_partition[0], tau * torch.logsumexp(-energies / tau, 0))


def test_soft_alignment_concentrates_on_the_hard_path():
    cost, _, _ = _warped_features(3, num_video=40, slope=3.0)
    hard = chain_align(cost, 8).path[0]
    soft = soft_align(cost, 8, temperature=1e-5)
    assert torch.equal(soft.posterior[0].argmax(-1), hard)
    assert (soft.expected[0] - hard).abs().max() < 0.5
    assert soft.std.mean() < 0.05


# -- classic DTW -------------------------------------------------------------------------------
@pytest.mark.parametrize(("n", "m"), [(1, 1), (1, 7), (6, 1), (30, 50), (80, 40)])
def test_dtw_matches_tslearn_and_brute_force(n, m):
    tslearn = pytest.importorskip("tslearn.metrics")
    rng = np.random.default_rng(n * 100 + m)
    cost = rng.random((n, m))
    ours = dtw(torch.from_numpy(cost))
    path, total = tslearn.dtw_path_from_metric(cost, metric="precomputed")
    assert ours.cost == pytest.approx(total, rel=1e-12)
    assert ours.cost == pytest.approx(_brute_dtw(cost), rel=1e-12)
    assert [tuple(p) for p in ours.path.tolist()] == [tuple(p) for p in path]


@pytest.mark.parametrize("seed", range(3))
def test_dtw_matches_dtaidistance(seed):
    dtai = pytest.importorskip("dtaidistance.dtw")
    rng = np.random.default_rng(seed)
    x, y = rng.random(60), rng.random(90)
    cost = torch.from_numpy((x[:, None] - y[None]) ** 2)
    ours = dtw(cost)
    dist, paths = dtai.warping_paths_fast(x, y)
    assert ours.cost == pytest.approx(dist**2, rel=1e-9)
    assert [tuple(p) for p in ours.path.tolist()] == [tuple(p) for p in dtai.best_path(paths)]


def test_dtw_choice_is_the_most_similar_frame_on_the_path():
    rng = np.random.default_rng(5)
    cost = torch.from_numpy(rng.random((20, 45)))
    result = dtw(cost)
    for i in range(20):
        cols = result.path[result.path[:, 0] == i, 1]
        assert result.choice[i] == cols[cost[i, cols].argmin()]


# -- robustness --------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_robust_chain_confines_the_error_to_the_replaced_segment(seed):
    cost, true, num_ref = _warped_features(seed, corrupt=True)
    outside = torch.ones(100, dtype=torch.bool)
    outside[40:51] = False
    s = 12
    slope = (num_ref - 1) / 99
    # tau = 4 x the median best-match cost; slope prior weight 5 % of tau per unit deviation
    robust = robust_cost(cost, threshold=4.0 * float(cost.amin(-1).median()))
    prior = slope_step_cost(s, slope, 0.05 * float(robust.max())).double()
    path = chain_align(robust, s, fix_start=True, fix_end=True, step_cost=prior).path[0]
    err = (path - true).abs().double()
    assert err[outside].mean() < 0.75
    assert err[~outside].mean() < 8.0
    dtw_err = (dtw(cost).choice - true).abs().double()
    assert dtw_err[~outside].mean() > 20.0  # the proposal's DTW is dragged along the copy


def test_robust_cost_modes():
    cost = torch.tensor([[0.0, 1.0, 10.0]])
    torch.testing.assert_close(robust_cost(cost, 2.0), torch.tensor([[0.0, 1.0, 2.0]]))
    sat = robust_cost(cost, 2.0, mode="saturate")
    assert (
        sat[0, 0] == 0 and sat[0, 2] < 2.0 and sat[0, 1] == pytest.approx(2 * (1 - math.exp(-0.5)))
    )
    with pytest.raises(AlignmentError, match="mode must be"):
        robust_cost(cost, 2.0, mode="clip")


# -- long sequences ----------------------------------------------------------------------------
def _smooth_warp_problem(seed, num_ref=2400, num_video=500):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(num_ref, dtype=torch.float64)
    ref = torch.sin(
        t[:, None] * (torch.rand(6, generator=g, dtype=torch.float64) * 0.02 + 0.005)
        + torch.rand(6, generator=g, dtype=torch.float64) * 6
    )
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    true = ((u + 0.06 * torch.sin(2 * math.pi * u)) * (num_ref - 1)).round().long()
    video = ref[true] + 0.01 * torch.randn(num_video, 6, generator=g, dtype=torch.float64)
    return video, ref, true, g


@pytest.mark.parametrize("seed", range(3))
def test_coarse_to_fine_equals_full_solution_on_smooth_warps(seed):
    video, ref, _, _ = _smooth_warp_problem(seed)
    num_video, num_ref = len(video), len(ref)
    fn = sequence_cost_fn(video, ref)
    full = chain_align(fn(torch.arange(num_video), torch.arange(num_ref).expand(num_video, -1)), 10)
    c2f = coarse_to_fine_align(fn, num_video, num_ref, 10, max_cells=50_000)
    assert torch.equal(c2f.path, full.path)
    torch.testing.assert_close(c2f.cost, full.cost)


@pytest.mark.parametrize("mode", ["truncate", "saturate"])
def test_coarse_to_fine_robust_with_slope_prior_equals_the_full_robust_chain(mode):
    """A corrupted stretch (video frames 200-259 replaced by noise): with the full solution's
    threshold, coarse-to-fine with the robust cost and a slope prior finds exactly the full
    robust chain's path; with its own threshold (from the coarsest level) it stays on the
    true warp outside the corrupted stretch."""
    video, ref, true, g = _smooth_warp_problem(7)
    video[200:260] = torch.randn(60, 6, generator=g, dtype=torch.float64)
    num_video, num_ref = len(video), len(ref)
    fn = sequence_cost_fn(video, ref)
    cost = fn(torch.arange(num_video), torch.arange(num_ref).expand(num_video, -1))
    tau = 2.0 * float(cost.amin(-1).median())
    prior = slope_step_cost(10, (num_ref - 1) / (num_video - 1), 0.5).double()
    full = chain_align(robust_cost(cost, tau, mode) / tau, 10, step_cost=prior)
    kwargs = {"max_cells": 50_000, "step_cost": prior, "robust": mode}
    c2f = coarse_to_fine_align(fn, num_video, num_ref, 10, threshold=tau, **kwargs)
    assert torch.equal(c2f.path, full.path)
    torch.testing.assert_close(c2f.cost, full.cost)
    own = coarse_to_fine_align(fn, num_video, num_ref, 10, **kwargs)
    outside = torch.ones(num_video, dtype=torch.bool)
    outside[200:260] = False
    assert (own.path[0][outside] - true[outside]).abs().double().mean() < 1.0
    plain = coarse_to_fine_align(fn, num_video, num_ref, 10, max_cells=50_000)
    err = (plain.path[0] - true).abs().double()
    assert err[~outside].mean() > (own.path[0] - true).abs().double()[~outside].mean()
    with pytest.raises(AlignmentError, match="robust must be"):
        coarse_to_fine_align(fn, num_video, num_ref, 10, robust="clip")


def _counting(cost_fn):
    """``cost_fn`` and a list whose sum is the number of (t', t) pairs it was asked for."""
    calls = []

    def counted(rows, cols):
        calls.append(cols.numel())
        return cost_fn(rows, cols)

    return counted, calls


def _gait_problem(seed, drift, num_video=600, period=60.0):
    """A long periodic motion: reference features = phase sine/cosine and second harmonic of a
    60-frame cycle (a gait loop; 50 cycles), plus ``drift`` times a slow feature over the whole
    reference (0: every cycle identical, like a reference that repeats one loop); the video
    is the reference through a smooth monotone warp whose speed varies by +-50 % (2.3 to 6.8
    reference frames per video frame), plus noise. Returns features, the true C, the period.
    """
    g = torch.Generator().manual_seed(seed)
    num_ref = 5 * num_video
    t = torch.arange(num_ref, dtype=torch.float64)
    phase = 2 * math.pi * t / period
    slow = drift * torch.sin(2 * math.pi * t / num_ref + 1.0)
    ref = torch.stack([phase.sin(), phase.cos(), 0.5 * (2 * phase).sin(), slow], 1)
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    warp = (u + 0.08 * torch.sin(2 * math.pi * u)) * 0.9 * (num_ref - 1)
    true = torch.cummax(warp.round().long().clamp(0, num_ref - 1), 0).values
    video = ref[true] + 0.05 * torch.randn(num_video, 4, generator=g, dtype=torch.float64)
    return video, ref, true, period


def _as_stage1(cost_fn, num_video, num_ref, s, prior, tau, **kwargs):
    """Coarse-to-fine alignment as stage 1 calls it: factor 4, radius S + 4, max_cells 2000,
    a slope prior, truncated costs at threshold ``tau``."""
    return coarse_to_fine_align(
        cost_fn,
        num_video,
        num_ref,
        s,
        radius=s + 4,
        max_cells=2000,
        step_cost=prior,
        robust="truncate",
        threshold=tau,
        **kwargs,
    )


def _gait_alignments(seed, drift, **kwargs):
    """The robust chain with a slope prior, on the full matrix and coarse-to-fine as stage 1
    calls it (factor 4, radius S + 4, max_cells 2000 -> 4 levels, coarsest cells of 64
    reference frames, longer than the 60-frame cycle). Returns full, c2f, evaluated pairs,
    T' T, true C, period."""
    video, ref, true, period = _gait_problem(seed, drift)
    num_video, num_ref, s = len(video), len(ref), 10
    fn = sequence_cost_fn(video, ref)
    cost = fn(torch.arange(num_video), torch.arange(num_ref).expand(num_video, -1))
    tau = 2.0 * float(cost.amin(-1).median())
    prior = slope_step_cost(s, 0.9 * (num_ref - 1) / (num_video - 1), 0.02).double()
    full = chain_align(robust_cost(cost, tau) / tau, s, step_cost=prior)
    counted, calls = _counting(fn)
    c2f = _as_stage1(counted, num_video, num_ref, s, prior, tau, **kwargs)
    return full, c2f, sum(calls), num_video * num_ref, true, period


def _in_phase(path, true, period):
    """Fraction of frames within 5 reference frames of the truth modulo the cycle."""
    err = (path - true).double().remainder(period)
    return float((torch.minimum(err, period - err) <= 5).double().mean())


@pytest.mark.parametrize("seed", range(3))
def test_coarse_to_fine_on_a_loop_reaches_the_full_chains_optimum(seed):
    """Every cycle of the reference identical (a reference that repeats one loop): paths a
    whole number of cycles apart tie, so the full chain's path is one of many optima; the
    coarse-to-fine path must be another one: in phase everywhere and at the full chain's
    cost, up to 1 (one truncated pair; the ties are broken by noise on a few frames).
    Classic subsampling (one sample per coarse cell, no tracking) aliases the cycle."""
    full, c2f, evaluated, cells, true, period = _gait_alignments(seed, 0.0)
    assert _in_phase(full.path[0], true, period) == 1.0
    assert _in_phase(c2f.path[0], true, period) == 1.0
    assert float(c2f.cost) <= float(full.cost) + 1.0
    assert evaluated < 0.12 * cells  # here ~8 %; a 7,500 x 40,000 walk: 0.6 %
    _, old, old_evaluated, _, _, _ = _gait_alignments(seed, 0.0, pool_stride=10**6, beam=0)
    assert _in_phase(old.path[0], true, period) < 0.8  # 0.72, 0.69, 0.75
    assert float(old.cost) > float(full.cost) + 50.0
    assert old_evaluated < evaluated


def _valley_problem(seed, num_video=1500, period=130.5, ratio=4.8):
    """Costs of a repeating reference as stage 1's pair fits give them: 0 at the true phase,
    rising quadratically to the cap 1 eight frames off (modulo the cycle), plus uniform
    noise up to 0.3; the true warp spans the whole reference (``ratio`` frames per video
    frame on average) with its speed varying by +-30 %. Returns the cost function, the
    reference length and the true C."""
    g = torch.Generator().manual_seed(seed)
    num_ref = int(ratio * (num_video - 1)) + 1
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    speed = 1 + 0.3 * torch.sin(2 * math.pi * 2.5 * u + seed)
    warp = torch.cumsum(speed, 0) - speed[0]
    true = (warp / warp[-1] * (num_ref - 1)).round().long()
    noise = 0.3 * torch.rand(num_video, 64, generator=g, dtype=torch.float64)

    def cost_fn(rows, cols):
        d = (cols - true[rows, None]).double().remainder(period)
        valley = (torch.minimum(d, period - d) / 8).square().clamp(max=1.0)
        return valley + noise[rows[:, None], cols % 64]

    return cost_fn, num_ref, true


def test_coarse_levels_weigh_the_slope_prior_by_the_frames_a_row_stands_for():
    """Cells of a cycle or more all match a repeating reference, so the coarse levels' start
    and slope are the slope prior's to decide. Counted once per coarse row it was too weak
    against the pooled costs' noise: coarse paths started whole cycles off and ran at the
    wrong mean slope, and the finer bands dropped cycles to follow them (seeds 0-5: 0.77 to
    0.99 of the frames in phase, mean 0.90). Counted ``F`` times at cells of ``F`` frames
    (the least the ``F`` finest steps it stands for cost) the path stays in phase, and on
    seed 0 reaches the full chain's optimum."""
    s, period, in_phase = 10, 130.5, []
    for seed in range(6):
        cost_fn, num_ref, true = _valley_problem(seed)
        num_video = len(true)
        prior = slope_step_cost(s, (num_ref - 1) / (num_video - 1), 0.02).double()
        c2f = _as_stage1(cost_fn, num_video, num_ref, s, prior, 1.0)
        in_phase.append(_in_phase(c2f.path[0], true, period))
        if seed == 0:
            cost = cost_fn(torch.arange(num_video), torch.arange(num_ref).expand(num_video, -1))
            full = chain_align(robust_cost(cost, 1.0), s, step_cost=prior)
            torch.testing.assert_close(c2f.cost, full.cost)
    assert min(in_phase) >= 0.95, in_phase  # 1, 1, 1, 0.951, 1, 0.973
    assert sum(in_phase) / len(in_phase) >= 0.98, in_phase


@pytest.mark.parametrize("seed", range(3))
def test_coarse_to_fine_on_distinct_cycles_equals_the_full_chain(seed):
    """Cycles told apart only by a slow feature (the full chain finds the true warp): with
    margin 1 the band keeps every coarse alternative within one truncated pair of the best,
    and coarse-to-fine finds exactly the full chain's path. Classic subsampling is lost by
    whole cycles, and off phase on much of the video."""
    full, c2f, evaluated, cells, true, period = _gait_alignments(seed, 0.3, margin=1.0)
    assert (full.path[0] - true).abs().max() <= 2
    assert torch.equal(c2f.path, full.path)
    torch.testing.assert_close(c2f.cost, full.cost)
    assert evaluated < 0.2 * cells  # here ~14 %
    _, old, _, _, _, _ = _gait_alignments(seed, 0.3, pool_stride=10**6, beam=0)
    assert (old.path[0] - full.path[0]).abs().max() > period
    assert _in_phase(old.path[0], true, period) < 0.8


@pytest.mark.parametrize("seed", range(4))
def test_coarse_to_fine_with_a_wide_margin_is_the_brute_force_optimum(seed):
    """Random costs on a small grid, two levels (factor 2): with a margin that keeps every
    coarse cell the band is everything monotone paths can reach, so coarse-to-fine (pooling,
    band, tracking, fixed ends, slope prior) must find the brute-force best path."""
    torch.manual_seed(seed)
    n, k, s = 8, 12, 2
    cost = torch.rand(n, k, dtype=torch.float64)
    step_cost = slope_step_cost(s, 1.5, 0.3).double()

    def fn(rows, cols):
        return cost[rows[:, None], cols]

    paths = torch.tensor(list(_monotone_paths_by_steps(n, k, s)))  # (P, n)
    energy = cost[torch.arange(n), paths].sum(-1) + step_cost[paths.diff(dim=-1)].sum(-1)
    for fix in (False, True):
        got = coarse_to_fine_align(
            fn,
            n,
            k,
            s,
            factor=2,
            radius=1,
            max_cells=1,
            margin=1e9,
            fix_start=fix,
            fix_end=fix,
            step_cost=step_cost,
        )
        allowed = (
            (paths[:, 0] == 0) & (paths[:, -1] == k - 1) if fix else torch.ones_like(energy) > 0
        )
        best = paths[torch.where(allowed, energy, math.inf).argmin()]
        assert torch.equal(got.path[0], best)
        assert got.cost.item() == pytest.approx(cost[torch.arange(n), best].sum().item())


def test_coarse_to_fine_max_marginals_match_brute_force():
    """The band's max-marginals (forward + backward max-product on sliding windows) against
    enumeration of every monotone path, with a slope prior and forbidden pairs."""
    from motion.alignment import _max_marginals

    torch.manual_seed(5)
    n, w, s = 5, 4, 2
    offsets = np.array([0, 1, 1, 3, 4])
    unary = -np.random.default_rng(0).random((n, w))
    unary[2, 1] = -np.inf
    step_lp = -np.array([0.3, 0.0, 0.2])
    best = np.full((n, w), -np.inf)
    positions = [range(o, o + w) for o in offsets]
    for p in itertools.product(*positions):
        steps = np.diff(p)
        if not ((steps >= 0) & (steps <= s)).all():
            continue
        score = sum(unary[i, c - offsets[i]] for i, c in enumerate(p)) + step_lp[steps].sum()
        for i, c in enumerate(p):
            best[i, c - offsets[i]] = max(best[i, c - offsets[i]], score)
    np.testing.assert_allclose(_max_marginals(unary, offsets, step_lp), best)


# -- bad input ---------------------------------------------------------------------------------
def test_alignment_input_errors():
    with pytest.raises(
        AlignmentError, match=r"cost must have shape \(T', T\) or \(B, T', T\); got \(5,\)"
    ):
        chain_align(torch.zeros(5), 2)
    with pytest.raises(
        AlignmentError, match=r"cost contains NaN \(1 entries; first at batch 0, t'=1, t=2\)"
    ):
        bad = torch.zeros(3, 4)
        bad[1, 2] = math.nan
        chain_align(bad, 2)
    with pytest.raises(AlignmentError, match=r"max_step \(S\) must be >= 1; got 0"):
        chain_align(torch.zeros(3, 4), 0)
    with pytest.raises(AlignmentError, match="must be non-empty"):
        chain_align(torch.zeros(0, 4), 1)
    with pytest.raises(AlignmentError, match="must be non-empty"):
        dtw(torch.zeros(3, 0))
    with pytest.raises(AlignmentError, match="floating-point"):
        dtw(torch.zeros(3, 3, dtype=torch.long))
    with pytest.raises(AlignmentError, match="no monotone path with max_step=1"):
        chain_align(torch.zeros(3, 10), 1, fix_start=True, fix_end=True)
    with pytest.raises(AlignmentError, match=r"step_cost must have shape \(3,\)"):
        chain_align(torch.zeros(3, 4), 2, step_cost=torch.zeros(4))
    with pytest.raises(AlignmentError, match="same F"):
        sequence_cost_fn(torch.zeros(3, 2), torch.zeros(4, 3))
    fn = sequence_cost_fn(torch.zeros(30, 2), torch.zeros(40, 2))
    for kwargs, message in [
        ({"pool_stride": 0}, "pool_stride must be None or an int >= 1; got 0"),
        ({"margin": -1.0}, "margin must be a finite number >= 0; got -1.0"),
        ({"beam": -2}, "beam must be None or an int >= 0; got -2"),
    ]:
        with pytest.raises(AlignmentError, match=re.escape(message)):
            coarse_to_fine_align(fn, 30, 40, 2, **kwargs)


def test_tracking_follows_a_path_off_the_coarse_band_at_a_bounded_cost_per_row():
    """The finest level's tracking, given a coarse band around reference frame 3 t' while
    the costs' valley runs along 3.5 t' (the coarse level lost the motion's rate): the band
    must follow the valley to its end (200 frames off the coarse band), and each row must
    cost only the coarse band plus the beams (``runs`` of ``2 beam + 1`` cells, cost
    calls padded by at most 1/8), not every cell between the valley and the coarse band."""
    from motion.alignment import _Levels

    n, m, s, beam = 400, 1500, 6, 10
    asked = torch.zeros(n, dtype=torch.long)

    def fn(rows, cols):
        asked.index_add_(0, rows, torch.full_like(rows, cols.shape[1]))
        return ((cols - 3.5 * rows[:, None]).abs() / 5).clamp(max=2.0)

    levels = _Levels(fn, n, m, s, 4, 10, 1, False, False, "truncate", 2.0, None, 1, 0.0, beam, 1.0)
    v = torch.arange(n)
    lo, hi = (3 * v - 10).clamp(min=0), 3 * v + 10
    raw = levels.evaluate(1, v, lo, hi)
    coarse = asked.clone()
    new_lo, new_hi, table, known = levels.track(1, raw, lo, hi, m, 1.0)
    at = (3.5 * v).round().long()
    assert bool(((new_lo <= at) & (at <= new_hi)).all())
    assert bool(known.gather(1, (at - new_lo)[:, None]).all())
    assert float(table.gather(1, (at - new_lo)[:, None]).max()) < 0.2  # half a frame / 5
    extra = asked - coarse
    assert int(extra.max()) <= math.ceil(levels.runs * (2 * beam + 1) * 9 / 8)
    assert int((new_hi - new_lo).max()) > 200  # the band spans both; only the beams cost
