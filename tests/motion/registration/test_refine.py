"""Stages 2-3 (motion.registration.refine): geometry helpers against direct computation,
windows, learnt colours against the renderer's, and the engine on a short synthetic video
started from the truth (T and A kept) and from a shifted C (moved toward the truth)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from motion.body.select import render_residual
from motion.draw import PART_COLOURS
from motion.registration.inputs import features_from_sequence
from motion.registration.refine import (
    RefineSettings,
    _fitted_postures,
    _in_view,
    _owner,
    _problem,
    _tempo_c,
    _window_starts,
    colour_image,
    estimate_part_colours,
    part_keypoints,
    place_poses,
    refine,
    rotation_spread_deg,
    smooth_posture,
)
from motion.registration.types import Reference, RegistrationError, scaled_spec
from motion.synth import SynthConfig, synthesize
from tests.motion.body.conftest import WALK

F64 = torch.float64


def _skew(v: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` -> ``(..., 3, 3)`` cross-product matrices."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v.unbind(-1)
    return torch.stack(
        [torch.stack([z, -w, y], -1), torch.stack([w, z, -x], -1), torch.stack([-y, x, z], -1)], -2
    )


def _yaw(angles: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angles), torch.sin(angles)
    r = torch.zeros(len(angles), 3, 3, dtype=F64)
    r[:, 0, 0], r[:, 0, 2], r[:, 1, 1], r[:, 2, 0], r[:, 2, 2] = c, s, 1.0, -s, c
    return r


@pytest.fixture(scope="module")
def student():
    """A 24-frame synthetic student (the walk itself, turned and warped, no articulation),
    its features, and its true C and root transform T."""
    cfg = SynthConfig(fps=25, yaw_deg=30, size=[200, 150], focal_px=280, seed=0)
    seq = synthesize(WALK, cfg)
    ref = Reference.from_bvh(WALK)
    video = features_from_sequence(seq).cut(slice(20, 44))
    c = torch.from_numpy(seq.arrays["C_shown"][20:44]).long()
    rot = _yaw(torch.from_numpy(seq.arrays["T_yaw_rad"][20:44])) @ ref.rotations[c, 0]
    pos = torch.from_numpy(seq.arrays["joints3d"][20:44, 0])
    return seq, ref, video, c, rot, pos


def test_place_poses_moves_every_landmark_rigidly(student):
    _, ref, _, c, rot, pos = student
    body = ref.body_poses(c[:3])
    placed = place_poses(rot[:3], pos[:3], body)
    want = (rot[:3, None, None] @ ref.spec.landmarks(body)[..., None]).squeeze(-1)
    want = want + pos[:3, None, None]
    torch.testing.assert_close(ref.spec.landmarks(placed), want, atol=1e-9, rtol=0)


def test_placed_reference_is_the_student_and_renders_its_silhouette(student):
    """T applied to B at the true C gives the synthetic student's joints exactly (no
    articulation here), the convention of motion.registration.types."""
    seq, ref, _, c, rot, pos = student
    b = ref.body_frames(c)
    joints = (rot[:, None] @ b.positions[..., None]).squeeze(-1) + pos[:, None]
    truth = torch.from_numpy(seq.arrays["joints3d"][20:44])
    torch.testing.assert_close(joints, truth, atol=1e-9, rtol=0)


@pytest.mark.parametrize("frames,window,overlap", [(5, 8, 2), (40, 12, 4), (101, 24, 4)])
def test_windows_cover_every_frame_and_each_frame_has_one_owner_inside_it(frames, window, overlap):
    starts = _window_starts(frames, window, overlap)
    owner = _owner(frames, starts, window, torch.device("cpu"))
    assert starts[0] == 0 and starts[-1] + min(window, frames) == frames
    assert all(b - a <= window - overlap for a, b in itertools.pairwise(starts))
    t = torch.arange(frames)
    s = torch.tensor(starts)[owner]
    assert ((t >= s) & (t < s + window)).all()


def test_learnt_part_colours_are_the_rendered_ones(student):
    """The synthetic frames colour each part flatly (motion.draw's table); learnt at the
    true posture, each part's median colour is its table colour."""
    _, ref, video, c, rot, pos = student
    spec = scaled_spec(ref.spec, 1.0)
    body = ref.body_poses(c).float()
    colours = estimate_part_colours(spec.shapes, video, place_poses(rot, pos, body).float())
    table = torch.from_numpy(PART_COLOURS[: spec.num_parts].astype(np.float32) / 255)
    err = (colours - table).abs().amax(-1)
    assert float(err.median()) < 0.01, err
    assert int((err < 0.05).sum()) >= spec.num_parts - 2, err  # a hidden part may be mixed


def test_part_colours_from_uint8_frames_in_chunks_are_the_same(student):
    """uint8 frames (what a long video keeps) learnt a few frames at a time give exactly
    the colours of float frames all at once: the same pixels, the same medians."""
    seq, ref, video, c, rot, pos = student
    spec = scaled_spec(ref.spec, 1.0)
    poses = place_poses(rot, pos, ref.body_poses(c).float()).float()
    small = features_from_sequence(seq, image_dtype=torch.uint8).cut(slice(20, 44))
    assert small.observation.image.dtype == torch.uint8
    assert torch.equal(colour_image(small.observation.image), video.observation.image)
    want = estimate_part_colours(spec.shapes, video, poses)
    got = estimate_part_colours(spec.shapes, small, poses, chunk=5)
    assert torch.equal(got, want)


def test_part_keypoints_name_the_joints_at_each_part_end(student):
    _, ref, _, _, _, _ = student
    keys = part_keypoints(ref, ref.skeleton.names)
    spec = ref.spec
    names = ref.skeleton.names
    thigh = spec.part_names.index("thigh_l")
    assert names[int(keys[thigh, 0])] == "LeftUpLeg" and names[int(keys[thigh, 1])] == "LeftLeg"
    assert part_keypoints(ref, None) is None
    assert part_keypoints(ref, ["nothing"]) is None


def _angle_deg(a, b):
    trace = (a.transpose(-1, -2) @ b).diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.rad2deg(torch.acos(((trace - 1) / 2).clamp(-1, 1)))


def test_stage2_from_the_truth_keeps_t_and_a_and_is_reproducible(student):
    """From the true C and T, stage 2 keeps T within a few degrees and centimetres and the
    driven joints within ~10 degrees of the reference's (the student is not articulated);
    the same seed gives the same result."""
    _, ref, video, c, rot, pos = student
    video = video.cut(slice(0, 4))
    s = RefineSettings(particles=40, iterations=3, restarts=1, refine_c=False)
    runs = [
        refine(ref, video, c[:4], rot[:4], pos[:4], 1.0, s, torch.Generator().manual_seed(3))
        for _ in range(2)
    ]
    torch.testing.assert_close(runs[0].rotations, runs[1].rotations, atol=0, rtol=0)
    res = runs[0]
    assert float(_angle_deg(rot[:4], res.rotations[:, 0]).mean()) < 8
    assert float((res.translation - pos[:4]).norm(dim=-1).mean()) < 0.06
    driven = sorted(set(ref.spec.frame_joints.tolist()) - {0})
    err = _angle_deg(ref.rotations[c[:4]][:, driven], res.rotations[:, driven])
    assert float(err.mean()) < 12, err.mean(0)


def test_smoothing_keeps_a_steady_offset_and_the_reference_swing(student):
    """A student that differs from the reference by a constant articulation on one joint
    and a constant heading, following the reference's own pelvis swing: smoothing the
    posture in the reference's terms leaves it as it is (to rounding), however fast the
    reference moves (the heading to within 0.01 degrees at the ends, where a turn is cut)."""
    _, ref, _, c, rot, pos = student
    joint = ref.skeleton.index("LeftLeg")
    offset = torch.linalg.matrix_exp(
        torch.tensor([[0.0, -0.3, 0.1], [0.3, 0.0, -0.2], [-0.1, 0.2, 0.0]], dtype=F64)
    )
    local = ref.rotations[c].clone()
    local[:, joint] = local[:, joint] @ offset
    local[:, 0] = rot  # a turning heading (30 degrees over the video) times the root's swing
    line = pos[0] + torch.arange(len(c), dtype=F64)[:, None] * torch.tensor([0.02, 0.0, 0.01])
    got, root = smooth_posture(ref, c, local, line, sigma=2.5)
    free = [j for j in range(ref.skeleton.num_joints) if j not in (0, joint)]
    torch.testing.assert_close(got[:, free], local[:, free], atol=1e-12, rtol=0)
    torch.testing.assert_close(got[:, joint], local[:, joint], atol=1e-12, rtol=0)
    # the heading turns at a constant rate: away from the ends (where the kernel is cut)
    # its chordal mean is itself (a rotation about one axis: the circular mean); at the ends
    # the local linear fit follows the turn (a weighted mean would lag it by ~2 frames' turn)
    r = math.ceil(3 * 2.5)
    torch.testing.assert_close(got[r:-r, 0], local[r:-r, 0], atol=1e-9, rtol=0)
    assert float(_angle_deg(got[:, 0], local[:, 0]).max()) < 0.01
    # a root moving at a steady speed keeps it to the first and last frames
    torch.testing.assert_close(root, line, atol=1e-12, rtol=0)


def test_smoothing_takes_noise_out_of_the_articulation(student):
    """Frame-to-frame noise on A (what finite particles leave) is mostly averaged out."""
    _, ref, _, c, _, pos = student
    g = torch.Generator().manual_seed(2)
    noise = torch.linalg.matrix_exp(_skew(0.1 * torch.randn(len(c), 3, dtype=F64, generator=g)))
    joint = ref.skeleton.index("RightForeArm")
    local = ref.rotations[c].clone()
    local[:, joint] = local[:, joint] @ noise
    got, _ = smooth_posture(ref, c, local, pos, sigma=2.5)
    before = _angle_deg(ref.rotations[c, joint], local[:, joint]).mean()
    after = _angle_deg(ref.rotations[c, joint], got[:, joint]).mean()
    assert float(after) < 0.5 * float(before), (before, after)


def test_smoothed_refinement_returns_the_poses_of_its_skeleton_posture(student):
    """The part poses returned are the (smoothed) skeleton posture's, so the fit score and
    the overlays show what the angles say."""
    _, ref, video, c, rot, pos = student
    s = RefineSettings(particles=16, iterations=1, restarts=1, refine_c=False, window=4, overlap=1)
    res = refine(ref, video.cut(slice(0, 6)), c[:6], rot[:6], pos[:6], 1.0, s, torch.Generator())
    want = place_poses(res.rotations[:, 0], res.translation, ref.posture_poses(res.rotations))
    torch.testing.assert_close(res.poses, want.float(), atol=1e-5, rtol=0)
    with pytest.raises(RegistrationError, match="smooth_s"):
        RefineSettings(smooth_s=-0.1)


def test_the_fitted_translation_is_the_least_squares_one(student):
    """Without smoothing, the skeleton posture's root position is the least-squares
    translation onto the landmarks of BP's parts, given its rotations: the mean gap between
    the two sets of landmarks is zero in every frame."""
    _, ref, video, c, rot, pos = student
    s = RefineSettings(
        particles=16, iterations=1, restarts=1, refine_c=False, window=4, overlap=1, smooth_s=0
    )
    res = refine(ref, video.cut(slice(0, 5)), c[:5], rot[:5], pos[:5], 1.0, s, torch.Generator())
    skeleton = place_poses(res.rotations[:, 0], res.translation, ref.posture_poses(res.rotations))
    torch.testing.assert_close(res.poses, skeleton.float(), atol=1e-5, rtol=0)
    gap = ref.spec.landmarks(res.particle_poses.double()) - ref.spec.landmarks(skeleton)
    assert float(gap.norm(dim=-1).mean()) > 1e-3  # BP's parts are not a rigid skeleton
    torch.testing.assert_close(gap.mean((-3, -2)), torch.zeros(5, 3, dtype=F64), atol=1e-6, rtol=0)


def test_stages23_read_uint8_frames_as_the_float_ones(student):
    """The intensity cue reads each window's uint8 frames converted to [0, 1]: the same
    result, bit for bit, as from float frames."""
    seq, ref, video, c, rot, pos = student
    small = features_from_sequence(seq, image_dtype=torch.uint8).cut(slice(20, 44))
    s = RefineSettings(
        particles=16, iterations=1, restarts=1, band=6, rounds=1, window=4, overlap=1
    )
    runs = [
        refine(ref, v.cut(slice(0, 6)), c[:6], rot[:6], pos[:6], 1.0, s, torch.Generator())
        for v in (video, small)
    ]
    assert torch.equal(runs[0].poses, runs[1].poses) and torch.equal(runs[0].C, runs[1].C)


@pytest.mark.parametrize(
    "prior, most",
    [(dict(articulation_std=0.2, articulation_outlier=0.0), 0.6), ({}, 0.75)],
    ids=["gaussian-prior", "heavy-tailed-prior"],
)
def test_stage3_moves_a_shifted_c_toward_the_truth(student, prior, most):
    """C started 8 reference frames late on 8 frames: the chain coupled to the parts moves
    it back, monotone. Under the Gaussian articulation prior (0.2 rad) to within 0.6 of
    the shift in 4 rounds; under the default heavy-tailed one (a 0.05 rad core) to 0.67
    of it (measured; asserted 0.75): the tight core holds every joint near the reference
    at the round's C, which is what C must move away from, so each round moves it less."""
    _, ref, video, c, rot, pos = student
    n = 8
    shifted = (c[:n] + 8).clamp(max=ref.num_frames - 1)
    s = RefineSettings(particles=40, iterations=3, restarts=1, band=10, rounds=4, **prior)
    res = refine(
        ref,
        video.cut(slice(0, n)),
        shifted,
        rot[:n],
        pos[:n],
        1.0,
        s,
        torch.Generator().manual_seed(0),
    )
    before = float((shifted - c[:n]).abs().float().mean())
    after = float((res.C - c[:n]).abs().float().mean())
    assert after < most * before, (res.C.tolist(), c[:n].tolist())
    assert bool((res.C[1:] >= res.C[:-1]).all())
    assert res.c_changes and res.c_changes[0] > 0


def test_tempo_pass_reads_c_off_part_estimates_at_the_true_posture(student):
    """Part estimates at the student's true posture (the reference at the true C, placed by
    the true T) and a C started 6 frames late and flat for 6 frames: the tempo pass puts C
    back on the truth, within 2 frames everywhere and 0.6 on average (measured: the
    coupling's 4 cm spread tells frames 1 apart by only ~0.1 nat, against the tempo prior);
    fed the late C's own posture it stays late (the flat start smoothed into a tempo) --
    the evidence is the part estimates', not the start's."""
    _, ref, video, c, rot, pos = student
    problem = _problem(ref, video, 1.0, RefineSettings(tempo_band=10))
    truth = place_poses(rot.float(), pos.float(), problem.body[c])
    late = (c + 6).clamp(max=ref.num_frames - 1)
    late[:6] = late[0]
    found = _tempo_c(problem, truth, late, rot.float(), pos.float())
    assert (found - c).abs().max() <= 2 and (found - c).abs().float().mean() <= 0.75
    placed_late = place_poses(rot.float(), pos.float(), problem.body[late])
    kept = _tempo_c(problem, placed_late, late, rot.float(), pos.float())
    assert (kept - c).float().mean() > 2.5  # measured 3.2


def test_a_posture_fitted_to_its_own_moved_copy_lands_on_it(student):
    """Candidate postures moved by a known rigid motion are the estimates: each fitted
    placement is the estimate itself; a part the cameras do not see (weight 0) may be
    anywhere without moving the fit of the others (to 1e-7 m: the spec's part axes are
    float32, 2^-24 of half a metre is 3e-8)."""
    _, ref, video, c, _, _ = student
    problem = _problem(ref, video, 1.0, RefineSettings())
    body = problem.body[c[:4]].double()  # (4, P, 7) in the root's frame
    motion = _yaw(torch.tensor([0.3, -1.2, 2.0, 0.0], dtype=F64))
    shift = torch.tensor([[0.5, 0.1, 3.0]], dtype=F64).expand(4, 3)
    estimates = place_poses(motion, shift, body)
    seen = torch.ones(4, body.shape[-2], dtype=F64)
    fitted = _fitted_postures(problem.spec, body[:, None], estimates, seen)[:, 0]
    torch.testing.assert_close(fitted[..., :3], estimates[..., :3], atol=1e-7, rtol=0)
    same_frame = (fitted[..., 3:] * estimates[..., 3:]).sum(-1).abs()  # q and -q alike
    torch.testing.assert_close(same_frame, torch.ones_like(same_frame), atol=1e-7, rtol=0)
    moved = estimates.clone()
    moved[:, 3, :3] += 0.5  # part 3 misplaced by 50 cm ...
    seen[:, 3] = 0  # ... where no camera sees it
    fitted = _fitted_postures(problem.spec, body[:, None], moved, seen)[:, 0]
    others = [p for p in range(body.shape[-2]) if p != 3]
    torch.testing.assert_close(fitted[:, others, :3], estimates[:, others, :3], atol=1e-7, rtol=0)


def test_the_fitted_tempo_placement_reads_c_through_a_wrong_t(student):
    """Part estimates at the true posture and a C started 6 frames late, as above, but the
    registration's T turned 20 degrees and 15 cm off: placed by that T the reference's
    postures read C 3.6 frames off on average (measured), placed by their fit to the
    estimates 0.6, as from the true T."""
    _, ref, video, c, rot, pos = student
    late = (c + 6).clamp(max=ref.num_frames - 1)
    late[:6] = late[0]
    wrong_rot = (_yaw(torch.full((len(c),), math.radians(20), dtype=F64)) @ rot).float()
    wrong_pos = (pos + torch.tensor([0.15, 0.0, 0.0], dtype=F64)).float()
    errors = {}
    for placement in ("registered", "fitted"):
        problem = _problem(
            ref, video, 1.0, RefineSettings(tempo_band=10, tempo_placement=placement)
        )
        truth = place_poses(rot.float(), pos.float(), problem.body[c])
        found = _tempo_c(problem, truth, late, wrong_rot, wrong_pos)
        errors[placement] = float((found - c).abs().float().mean())
    assert errors["fitted"] <= 0.75 < errors["registered"], errors


def test_parts_in_view_are_those_the_camera_sees(student):
    """The student in the middle of the image: every part in view; moved 20 m sideways, or
    mirrored through the camera's centre (behind it, where the projection may land inside
    the image): none."""
    _, ref, video, c, rot, pos = student
    problem = _problem(ref, video, 1.0, RefineSettings())
    poses = place_poses(rot.float(), pos.float(), problem.body[c])[:3]
    assert torch.equal(_in_view(problem, poses), torch.ones(3, ref.spec.num_parts))
    away = poses.clone()
    away[..., 0] += 20.0
    assert not _in_view(problem, away).any()
    cam = video.cameras
    centre = -(cam.R[0].T @ cam.t[0]).float()
    behind = poses.clone()
    behind[..., :3] = 2 * centre - poses[..., :3]
    assert not _in_view(problem, behind).any()


def test_bad_inputs_are_refused(student):
    _, ref, video, c, rot, pos = student
    with pytest.raises(RegistrationError, match=r"expected C \(24,\)"):
        refine(ref, video, c[:3], rot, pos, 1.0)
    with pytest.raises(RegistrationError, match="band"):
        RefineSettings(particles=10, band=12)
    with pytest.raises(RegistrationError, match="overlap"):
        RefineSettings(window=4, overlap=4)
    with pytest.raises(RegistrationError, match=r"articulation_outlier must be in \[0, 1\)"):
        RefineSettings(articulation_outlier=1.0)
    with pytest.raises(RegistrationError, match="articulation_outlier_std must exceed"):
        RefineSettings(articulation_outlier=0.1, articulation_outlier_std=0.05)
    assert math.isfinite(float(c.float().mean()))


def test_a_nan_start_transform_is_refused_naming_its_frames(student):
    _, ref, video, c, rot, pos = student
    broken = pos.clone()
    broken[[3, 4, 5, 9]] = float("nan")
    with pytest.raises(RegistrationError, match=r"NaN or infinite on video frames 3-5, 9;"):
        refine(ref, video, c, rot, broken, 1.0)


def test_frames_where_bp_finds_no_finite_posture_keep_their_start(student, monkeypatch):
    """Where particle BP hands back NaN (every hypothesis of a part impossible), those
    frames take the start posture and C, the others BP's, and a warning names them."""
    import motion.registration.refine as refine_module

    _, ref, video, c, rot, pos = student
    video, c, rot, pos = video.cut(slice(0, 4)), c[:4], rot[:4], pos[:4]
    run_window = refine_module._run_window

    def losing(problem, frames, *args):
        est, c_win, spread = run_window(problem, frames, *args)
        if frames.start == 0:
            est = est.clone()
            est[2, 5, 0] = float("nan")
        return est, c_win, spread

    monkeypatch.setattr(refine_module, "_run_window", losing)
    s = RefineSettings(particles=20, iterations=2, restarts=1, refine_c=False, smooth_s=0.0)
    res = refine(ref, video, c, rot, pos, 1.0, s, torch.Generator().manual_seed(0))
    problem = _problem(ref, video, 1.0, s)
    start = place_poses(rot[2:3].float(), pos[2:3].float(), problem.body[c[2:3]])[0]
    torch.testing.assert_close(res.particle_poses[2], start.to(res.particle_poses))
    assert torch.isfinite(res.poses).all() and torch.isfinite(res.rotations).all()
    assert len(res.warnings) == 1 and res.warnings[0].startswith("video frames 2 ")
    # the lost part has no marginal to measure; the others do
    assert math.isnan(res.part_spread_deg[2, 5]) and torch.isfinite(res.part_spread_deg[3]).all()


def test_rotation_spread_is_the_weighted_rms_angle_about_the_chosen_pose():
    """Particles turned 0, 10 and 30 degrees about the chosen pose (one of them as -q, the
    same rotation), weights 1/2, 1/4, 1/4: the spread is sqrt((0 + 100 + 900) / 4) degrees
    whatever the positions; a node without a finite weight has none (NaN)."""
    best = torch.tensor([0.3, 1.0, -2.0, 1.0, 0.0, 0.0, 0.0])

    def turned(deg, sign=1.0):
        half = math.radians(deg) / 2
        q = sign * torch.tensor([math.cos(half), 0.0, math.sin(half), 0.0])
        return torch.cat([torch.randn(3), q])

    particles = torch.stack([turned(0), turned(10, -1.0), turned(30)])[None]  # (1, 3, 7)
    log_w = torch.log(torch.tensor([[0.5, 0.25, 0.25]]))
    got = rotation_spread_deg(particles, log_w, best[None])
    assert float(got) == pytest.approx(math.sqrt((100 + 900) / 4), abs=1e-3)
    none = rotation_spread_deg(particles, torch.full((1, 3), -math.inf), best[None])
    assert math.isnan(float(none))
    padded = torch.log(torch.tensor([[1.0, 0.0, 0.0]]))  # -inf padding: only the first
    assert float(rotation_spread_deg(particles, padded, best[None])) == pytest.approx(0, abs=1e-3)


def test_several_searches_keep_per_window_the_search_that_renders_its_frames_best(
    student, monkeypatch
):
    """With ``searches=3`` each window keeps one search for all its frames, the one whose
    rendering (select.render_residual, recomputed here) explains the window best in sum:
    its part poses, its orientation spreads and its C chain's states, not search 0's."""
    import motion.registration.refine as refine_module

    _, ref, video, c, rot, pos = student
    n = 6
    video, c, rot, pos = video.cut(slice(0, n)), c[:n], rot[:n], pos[:n]
    solve, run_window = refine_module.solve_posture, refine_module._run_window
    solutions, windows = [], []

    def spy_solve(graph, start, settings, generator, images=None):
        solutions.append((solve(graph, start, settings, generator, images), images))
        return solutions[-1][0]

    def spy_window(problem, frames, c_win, *args):
        windows.append((c_win, run_window(problem, frames, c_win, *args)))
        return windows[-1][1]

    monkeypatch.setattr(refine_module, "solve_posture", spy_solve)
    monkeypatch.setattr(refine_module, "_run_window", spy_window)
    s = RefineSettings(
        particles=30, iterations=2, restarts=1, searches=3, band=6, rounds=1, tempo_std=0.0
    )
    refine(ref, video, c, rot, pos, 1.0, s, torch.Generator().manual_seed(1))
    assert len(solutions) == 2  # stage 2 and one stage-3 round, one window each
    kept_any = []
    for (solution, images), (c_in, (poses, c_out, spread)) in zip(solutions, windows, strict=True):
        residual = render_residual(
            images.shapes,
            images.rig,
            images.observation,
            solution.searches,
            images.colours,
            s.intensity,
        )
        kept = int(residual.sum(1).argmin())
        kept_any.append(kept)
        assert solution.choice.tolist() == [kept] * n
        assert torch.equal(poses, solution.searches[kept])
        result = solution.result
        v = n * ref.spec.num_parts
        want = rotation_spread_deg(
            result.particles[kept, :v], result.log_weights[kept, :v], result.best[kept, :v]
        )
        torch.testing.assert_close(spread, want.reshape(n, -1), atol=0, rtol=0)
        if result.best.shape[1] > v:  # stage 3: C is the kept search's chain
            offsets = (c_in - s.band).clamp(0, ref.num_frames - (2 * s.band + 1))
            states = result.best[kept, v:, 0].round().long()
            assert torch.equal(c_out, offsets + states)
    assert any(kept_any), "every window kept search 0: the test would not see a wrong index"
