"""The posture solver (motion.body.solve) on the bundled robot arm seen by two views: one
search is the plain sequence (perturb the start, particle max-product) bit for bit; several
keep per frame the search select.py's render residual prefers; the polish is
motion.body.polish's; what the graph adds past the parts starts at zero with no kernel; bad
settings and inputs are refused naming expected and actual."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from motion.body.graph import Connections, body_graph
from motion.body.observation import BodyObservation, Edges, Observation, Silhouette
from motion.body.polish import polish
from motion.body.select import best_per_frame, render_residual
from motion.body.solve import Images, PostureSettings, anneal_schedule, solve_posture
from motion.features import distance_to_edges, edges
from motion.render import label_map, project_parts, render_intensity, silhouette
from motion.settings import SettingError
from pgm import SE3, Discrete, Geometric, MaxSemiring, ParticleGraph, particle_bp
from tests.motion.body.test_new_object import H, W, _poses, _rig  # the arm's views

FRAMES = [3, 9]
K = 24  # particles: a few seconds a solve, enough to move the arm toward the truth


@pytest.fixture(scope="module")
def problem(arm):
    """The arm at two frames (truth), a start with +-25 degrees on every joint's rotation
    channels, what two views see of the truth (silhouette, edges, part colours), its body
    graph."""
    bvh, _, _, motion, spec = arm
    g = torch.Generator().manual_seed(0)
    rows = motion[FRAMES].clone()
    channels = [(j, c) for j, cs in enumerate(bvh.channels) for c in cs]
    rotations = [i for i, (j, c) in enumerate(channels) if j > 0 and c.endswith("rotation")]
    rows[:, rotations] += 25 * (2 * torch.rand(len(FRAMES), len(rotations), generator=g) - 1)
    truth, start = _poses(arm, motion[FRAMES]).float(), _poses(arm, rows).float()
    centre = spec.landmarks(truth).reshape(len(FRAMES), -1, 3).mean(1)
    truth[..., :3] -= centre[:, None]
    start[..., :3] -= centre[:, None]
    rig, p = _rig(), spec.num_parts
    colours = torch.rand(p, 3, generator=g)
    parts = project_parts(rig, spec.landmarks(truth), spec.shapes.radii.float())
    sil = silhouette(parts, H, W).float()
    dist = distance_to_edges(edges(sil.reshape(-1, 1, H, W))).reshape(sil.shape)
    dist = torch.where(torch.isfinite(dist), dist, torch.full_like(dist, 1e3))
    image = render_intensity(label_map(parts, H, W)[0], colours, 0.5)
    obs = Observation(sil[None], dist[None], image[None])
    images = Images(spec, rig, obs, colours, colour_weight=0.05)
    unary = BodyObservation(images.shapes, rig, obs, cues=[Silhouette(1.0, 1.0), Edges(0.2)])
    connections = Connections(pos_std=0.02, rot_std=0.5, schedule=Geometric(1.0, 0.25, 3))
    graph = body_graph(spec, len(FRAMES), [(torch.arange(len(FRAMES) * p), unary)], connections)
    return spec, truth, start, images, graph


SETTINGS = PostureSettings(particles=K, iterations=3, restarts=1, kernel_end=0.1)


def _plain(graph, start, searches: int, seed: int):
    """Today's sequence written out: perturb the start (2 cm, 0.1 rad) in every search, then
    particle max-product with annealed kernels and 30 proposal centres at most."""
    g = torch.Generator().manual_seed(seed)
    v = start.shape[0] * start.shape[1]
    centres = start.reshape(1, v, 1, 7).expand(searches, v, K, 7)
    initial = SE3().perturb(centres, (0.02, 0.1), g)
    return particle_bp(
        graph,
        initial,
        iterations=3,
        restarts=1,
        generator=g,
        semiring=MaxSemiring(),
        kernel_scale=(0.02, 0.5),
        kernel_schedule=Geometric(1.0, 0.1, 3),
        proposal_centres=min(30, K),
    )


def _error(spec, poses, truth) -> torch.Tensor:
    """``(T,)`` mean landmark distance, metres."""
    return (spec.landmarks(poses) - spec.landmarks(truth)).norm(dim=-1).mean((-1, -2))


def test_one_search_is_the_plain_sequence_bit_for_bit(problem):
    spec, truth, start, _, graph = problem
    got = solve_posture(graph, start, SETTINGS, torch.Generator().manual_seed(3))
    want = _plain(graph, start, 1, 3)
    assert torch.equal(got.poses, want.best[0].reshape(start.shape))
    assert torch.equal(got.result.particles, want.particles)
    assert torch.equal(got.result.log_weights, want.log_weights)
    assert got.choice.tolist() == [0, 0] and got.residual is None
    # the known optimum is the truth: the solve moves toward it from the start
    assert (_error(spec, got.poses, truth) < _error(spec, start, truth)).all()


def test_several_searches_keep_per_frame_the_smallest_render_residual(problem):
    _, _, start, images, graph = problem
    settings = PostureSettings(particles=K, iterations=3, restarts=1, kernel_end=0.1, searches=3)
    got = solve_posture(graph, start, settings, torch.Generator().manual_seed(4), images)
    searches = _plain(graph, start, 3, 4).best.reshape(3, *start.shape)
    assert torch.equal(got.searches, searches)
    assert not torch.equal(searches[0], searches[1])  # different draws, different postures
    residual = render_residual(
        images.shapes, images.rig, images.observation, searches, images.colours, 0.05
    )
    want, choice = best_per_frame(searches, residual)
    assert torch.equal(got.residual, residual)
    assert torch.equal(got.choice, choice) and torch.equal(got.poses, want)
    assert torch.equal(got.choice, residual.argmin(0))
    frames = torch.arange(len(FRAMES))
    assert (residual[got.choice, frames] <= residual.amin(0)).all()


def test_choosing_for_all_frames_keeps_one_search_the_smallest_residual_in_sum(problem):
    _, _, start, images, graph = problem
    settings = PostureSettings(
        particles=K, iterations=3, restarts=1, kernel_end=0.1, searches=3, choose="all"
    )
    got = solve_posture(graph, start, settings, torch.Generator().manual_seed(4), images)
    per_frame = solve_posture(
        graph, start, replace(settings, choose="frame"), torch.Generator().manual_seed(4), images
    )
    assert torch.equal(got.searches, per_frame.searches)  # the same draws
    best = int(got.residual.sum(1).argmin())
    assert got.choice.tolist() == [best] * len(FRAMES)
    assert torch.equal(got.poses, got.searches[best])
    # the frames' own best searches differ (seed 4: [2, 0]), so one frame keeps a worse one
    assert len(set(per_frame.choice.tolist())) > 1
    assert not torch.equal(got.poses, per_frame.poses)


def test_polish_is_motion_body_polish_of_the_chosen_poses(problem):
    spec, _, start, images, graph = problem
    plain = solve_posture(graph, start, SETTINGS, torch.Generator().manual_seed(5))
    settings = PostureSettings(particles=K, iterations=3, restarts=1, kernel_end=0.1, polish=True)
    got = solve_posture(graph, start, settings, torch.Generator().manual_seed(5), images)
    want = polish(spec, images.rig, images.observation, plain.poses, images.colours)
    assert torch.equal(got.poses, want) and not torch.equal(got.poses, plain.poses)


def test_nodes_past_the_parts_start_at_zero_with_no_kernel(problem, monkeypatch):
    """A graph with a discrete node after the parts (registration's C chain): its initial
    values are zero, its kernel scale None; the parts' draws are those of the parts alone."""
    import motion.body.solve as solve

    _, _, start, _, graph = problem
    v = graph.num_nodes
    chained = ParticleGraph(
        v + 1, [(SE3(), torch.arange(v)), (Discrete(3), torch.tensor([v]))], graph.pairwise
    )
    calls = []

    def recording(graph, initial, **kwargs):
        calls.append((initial, kwargs))
        return particle_bp(graph, initial, **kwargs)

    monkeypatch.setattr(solve, "particle_bp", recording)
    solve_posture(graph, start, SETTINGS, torch.Generator().manual_seed(6))
    solve_posture(chained, start, SETTINGS, torch.Generator().manual_seed(6))
    (alone, alone_kw), (initial, kwargs) = calls
    assert initial.shape == (1, v + 1, K, 7) and initial.dtype == torch.float32
    assert torch.equal(initial[:, :v], alone) and (initial[:, v:] == 0).all()
    assert alone_kw["kernel_scale"] == [(0.02, 0.5)]
    assert kwargs["kernel_scale"] == [(0.02, 0.5), None]


def test_anneal_schedule_shrinks_geometrically_or_holds_the_geometric_mean():
    on, off = anneal_schedule(0.04, 5), anneal_schedule(0.04, 5, annealing=False)
    assert [on(i) for i in (0, 2, 4)] == pytest.approx([1.0, 0.2, 0.04])
    assert [off(i) for i in (0, 4)] == pytest.approx([0.2, 0.2])


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"searches": 0}, "PostureSettings: searches must be >= 1; got 0"),
        ({"start_spread": (-0.01, 0.1)}, r"start_spread\[0\] must be >= 0; got -0.01"),
        ({"kernel_scale": (0.02,)}, r"kernel_scale must be a list of 2 numbers > 0; got \[0.02\]"),
        ({"proposal": "best"}, "proposal must be one of 'mixture', 'own'; got 'best'"),
        ({"proposal_centres": 0}, "proposal_centres must be >= 1; got 0"),
        ({"particles": 1}, "particles must be >= 2; got 1"),
        ({"choose": "window"}, "choose must be one of 'frame', 'all'; got 'window'"),
    ],
)
def test_bad_settings_state_expected_and_actual(fields, message):
    with pytest.raises(SettingError, match=message):
        PostureSettings(**fields)


def test_bad_inputs_state_expected_and_actual(problem):
    _, _, start, _, graph = problem
    g = torch.Generator()
    three = PostureSettings(particles=K, searches=3)
    with pytest.raises(ValueError, match="searches = 3 needs images to choose among them by"):
        solve_posture(graph, start, three, g)
    with pytest.raises(ValueError, match="polish needs images to polish against; got none"):
        solve_posture(graph, start, PostureSettings(particles=K, polish=True), g)
    with pytest.raises(ValueError, match=r"start must have shape \(T, P, 7\); got \(10, 7\)"):
        solve_posture(graph, start.reshape(-1, 7), SETTINGS, g)
    with pytest.raises(ValueError, match=r"at least T \* P = 15 nodes .*; got 10"):
        solve_posture(graph, torch.cat([start, start[:1]]), SETTINGS, g)
    discrete = ParticleGraph(10, [(Discrete(3), torch.arange(10))])
    with pytest.raises(ValueError, match="first 10 nodes must be SE3; got Discrete"):
        solve_posture(discrete, start, SETTINGS, g)
