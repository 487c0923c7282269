"""Stage 1, approximate registration: rigid pair fits, C by coarse-to-fine alignment, G.

Synthetic inputs from :mod:`motion.synth` (the bundled CMU walk, 160 x 120, 25 fps) and
capsules rendered with :mod:`motion.render` at a known ``T``. Numbers measured on 2 shared
cores, one torch thread (see the module fixture): the whole file runs in ~30 s.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from motion.body.observation import Observation
from motion.cameras import CameraRig
from motion.features import distance_to_edges
from motion.registration.approximate import (
    PairFit,
    Stage1Result,
    Stage1Settings,
    approximate_registration,
    estimate_body_scale,
    fit_rigid_pairs,
    pair_costs,
)
from motion.registration.approximate import scene as scene_module
from motion.registration.approximate.pairs import _heading_penalty
from motion.registration.approximate.registration import fitted_tempo
from motion.registration.approximate.scene import _build_scene
from motion.registration.types import Reference, RegistrationError, VideoFeatures
from motion.render import label_map, project_parts
from motion.synth import SynthConfig, synthesize

BVH = "motion/data/cmu_02_01_walk.bvh"
F64 = torch.float64
Tensor = torch.Tensor


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Batched problems of a few hundred points on 2 shared cores: torch's intra-op threads
    slow them several times over when other jobs run (as tests/conftest.py notes)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# -- inputs ----------------------------------------------------------------------------------
def _video(seq, cameras: list[int] | None = None, keypoints: bool = False) -> VideoFeatures:
    """A :class:`VideoFeatures` from a synthetic sequence: silhouettes, distance to its
    edges, and optionally its noisy 2-D joints as keypoints (confidence 1), of the chosen
    cameras (default all)."""
    a = seq.arrays
    cams = list(range(a["K"].shape[0])) if cameras is None else cameras
    sil = torch.from_numpy(a["silhouettes"][cams]).float()  # (C, T', H, W)
    c, t, h, w = sil.shape
    edge = torch.from_numpy(a["edges"][cams]).reshape(-1, 1, h, w)
    dist = torch.nan_to_num(distance_to_edges(edge), posinf=1e4).reshape(c, t, h, w)
    kp, names = None, None
    if keypoints:
        uv = torch.from_numpy(a["joints2d_noisy"][cams]).float()  # (C, T', J, 2)
        kp = torch.cat([uv, torch.ones_like(uv[..., :1])], -1).transpose(0, 1)[None]
        names = list(seq.meta["joint_names"])
    obs = Observation(
        silhouette=sil.transpose(0, 1)[None],
        edge_distance=dist.transpose(0, 1)[None],
        keypoints=kp,
    )
    rig = CameraRig(
        torch.from_numpy(a["K"][cams]),
        torch.from_numpy(a["R"][cams]),
        torch.from_numpy(a["t"][cams]),
        torch.zeros(c, 5, dtype=F64),
        torch.tensor([[w, h]] * c, dtype=F64),
        [seq.meta["cameras"][i] for i in cams],
    )
    return VideoFeatures(obs, rig, frame_rate=seq.meta["video_rate_hz"], keypoint_joints=names)


def _true_transforms(reference: Reference, seq) -> tuple[Tensor, Tensor]:
    """The synthetic student's root transform per video frame: rotation ``R_yaw(t') R_root(
    C(t'))`` (synth's yaw about +Y) and the root joint's position, ``(T', 3, 3)``,
    ``(T', 3)``."""
    a = seq.arrays
    yaw = torch.from_numpy(a["T_yaw_rad"])
    r_yaw = axis_angle_to_rotation_matrix(torch.stack([0 * yaw, yaw, 0 * yaw], -1))
    shown = torch.from_numpy(a["C_shown"])
    return r_yaw @ reference.rotations[shown, 0], torch.from_numpy(a["joints3d"][:, 0])


def _angle_deg(a: Tensor, b: Tensor) -> Tensor:
    trace = (a.double() * b.double()).sum((-1, -2))
    return torch.rad2deg(torch.acos(((trace - 1) / 2).clamp(-1, 1)))


@pytest.fixture(scope="module")
def reference() -> Reference:
    return Reference.from_bvh(BVH)


@pytest.fixture(scope="module")
def walk():
    """One camera, a warped walk towards it (72 video frames, 343 reference frames)."""
    return synthesize(BVH, SynthConfig(fps=25, warp=0.3, cameras=1, size=[160, 120], seed=0))


@pytest.fixture(scope="module")
def walk_two_cameras():
    """Two cameras (front and back), body 1.1 times the reference."""
    return synthesize(
        BVH,
        SynthConfig(fps=25, warp=0.3, cameras=2, size=[160, 120], seed=0, body_scale=1.1),
    )


def _look(eye, forward) -> tuple[Tensor, Tensor]:
    """World-to-camera ``R``, ``t`` of a camera at ``eye`` looking along ``forward``, level."""
    fwd = torch.nn.functional.normalize(torch.tensor(forward, dtype=F64), dim=0)
    right = torch.nn.functional.normalize(
        torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0], dtype=F64)), dim=0
    )
    r = torch.stack([right, torch.linalg.cross(fwd, right), fwd])
    return r, -r @ torch.tensor(eye, dtype=F64)


def _rig(orthographic: bool) -> CameraRig:
    """Perspective: one camera 4 m in front (f = 200 px). Orthographic: front and side, 40
    px per metre. 160 x 120 images."""
    views = [_look([0.0, 1.0, 4.0], [0, 0, -1])]
    if orthographic:
        views.append(_look([4.0, 1.0, 0.0], [-1, 0, 0]))
    c = len(views)
    f = 40.0 if orthographic else 200.0
    k = torch.tensor([[f, 0, 80], [0, f, 60], [0, 0, 1]], dtype=F64).expand(c, 3, 3).clone()
    return CameraRig(
        k,
        torch.stack([v[0] for v in views]),
        torch.stack([v[1] for v in views]),
        torch.zeros(c, 5, dtype=F64),
        torch.tensor([[160.0, 120.0]] * c, dtype=F64),
        [f"cam{i}" for i in range(c)],
        orthographic=orthographic,
    )


def _render(reference: Reference, frame: int, rot: Tensor, p: Tensor, rig: CameraRig):
    """Silhouettes of ``B_t`` (the spec's capsules) at root transform ``rot``, ``p``."""
    segments = reference.spec.landmarks(reference.body_poses(torch.tensor([frame])))[0]
    parts = project_parts(rig, segments @ rot.T + p, reference.spec.shapes.radii)
    labels, _ = label_map(parts, 120, 160)  # (C, H, W)
    return VideoFeatures(Observation((labels >= 0).float()[None, None]), rig, 25.0)


# -- (a) a pair whose T is known ---------------------------------------------------------------
@pytest.mark.parametrize(
    "orthographic, dtype",
    [(False, torch.float32), (False, torch.float64), (True, torch.float32)],
    ids=["perspective", "perspective-f64", "orthographic-2cams"],
)
def test_known_pair_is_recovered_and_is_the_minimum(reference, orthographic, dtype):
    """``B_t`` rendered at a known T (30 degrees yaw, 4 degrees tilt): the fit recovers R to
    2 degrees and p to 3 cm (measured: ~1 degree, <1 cm), and the cost at the truth is ~0
    (2e-7 to 1.3e-6: pixel discretisation) and far below that of transforms 8-10 degrees or 5 cm away
    (measured >= 40 times)."""
    frame = 100
    rot = axis_angle_to_rotation_matrix(torch.tensor([[0.0, math.radians(30), 0.0]], dtype=F64))
    rot = (
        rot[0]
        @ axis_angle_to_rotation_matrix(torch.tensor([[math.radians(4), 0.0, 0.0]], dtype=F64))[0]
    )
    p = torch.tensor([0.1, 0.95, 0.0], dtype=F64)
    video = _render(reference, frame, rot, p, _rig(orthographic))
    settings = Stage1Settings(dtype=dtype)
    rows, cols = torch.tensor([0]), torch.tensor([[frame]])
    fit = fit_rigid_pairs(
        reference, video, rows, cols, 1.0, settings, torch.Generator().manual_seed(0)
    )
    assert isinstance(fit, PairFit)
    assert fit.cost.shape == (1, 1) and fit.rotation.shape == (1, 1, 3, 3)
    assert fit.translation.shape == (1, 1, 3) and fit.cost.dtype == dtype
    assert float(_angle_deg(fit.rotation[0, 0], rot)) < 2.0
    assert float((fit.translation[0, 0].double() - p).norm()) < 0.03
    # the truth against transforms around it
    turn = axis_angle_to_rotation_matrix(
        torch.tensor(
            [[0, 0.17, 0], [0, -0.17, 0], [0.14, 0, 0], [0, 0, 0.14], [0, 0, 0], [0, 0, 0]],
            dtype=F64,
        )
    )
    shift = torch.tensor(
        [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], dtype=F64
    )
    rots = torch.cat([rot[None], turn @ rot])[None]  # (1, 7, 3, 3)
    ps = torch.cat([p[None], p + shift])[None]
    costs = pair_costs(
        reference,
        video,
        rows,
        torch.full((1, 7), frame),
        rots,
        ps,
        1.0,
        settings,
        torch.Generator().manual_seed(0),
    )[0]
    assert float(costs[0]) < 5e-6
    assert bool((costs[1:] > 10 * costs[0]).all() & (costs[1:] > 2e-6).all()), costs


def test_pair_partly_out_of_view_is_recovered(reference):
    """``B_t`` 3 m from the camera, its feet below the image's bottom edge (~7 px of the
    body's 113 out of view), silhouette only: points outside the image are not observed, so
    the cost at the truth stays ~0 (measured 1.2e-8; 5.5e-7 when they read the image's
    border row), and the starts hang the body from the silhouette's top at several depths
    (the clipped height alone puts it too far): R within 5 degrees and p within 10 cm
    (measured 3.8 degrees, 7.8 cm; before, 7.6 degrees and 11.5 cm; the same body in full
    view, 3 degrees and 5.5 cm: one silhouette without edges pins a pair only so far)."""
    frame = 100
    rot = axis_angle_to_rotation_matrix(torch.tensor([[0.0, math.radians(30), 0.0]], dtype=F64))
    p = torch.tensor([0.1, 0.95, 1.0], dtype=F64)
    video = _render(reference, frame, rot[0], p, _rig(False))
    sil = video.observation.silhouette[0, 0, 0]
    assert bool(sil[-1].any()) and not bool(sil[0].any())  # the feet leave the image
    rows, cols = torch.tensor([0]), torch.tensor([[frame]])
    g = torch.Generator()
    fit = fit_rigid_pairs(reference, video, rows, cols, 1.0, None, g.manual_seed(0))
    assert float(_angle_deg(fit.rotation[0, 0], rot[0])) < 5.0
    assert float((fit.translation[0, 0].double() - p).norm()) < 0.1
    at_truth = pair_costs(reference, video, rows, cols, rot, p[None], 1.0, None, g.manual_seed(0))
    assert float(at_truth) < 1e-7


def test_pair_cut_by_a_side_edge_is_recovered(reference):
    """``B_t`` 1.65 m to the side of a camera 4 m away (frames 100 and 160, yaws 30 and 120
    degrees): only the body's 8-15 leftmost pixel columns are in the image, the rest beyond
    its right edge; silhouette only. The silhouette's centroid then lies short of the
    body's; starts with the centroid moved toward the cut edge (``clipped_shifts``) recover
    R within 10 degrees and p within 30 cm in all four (measured 3.2-7.1 degrees, 7-26 cm:
    depth is what a sliver pins worst); without them (the same settings, ``clipped_shifts
    =(0.0,)``) the worst of the four was 102 degrees and 1.8 m off."""
    p = torch.tensor([1.65, 0.95, 0.0], dtype=F64)
    rows, cols = torch.tensor([0]), torch.tensor([[0]])
    shifted, unshifted = [], []
    for frame in (100, 160):
        for yaw_deg in (30, 120):
            yaw = torch.tensor([[0.0, math.radians(yaw_deg), 0.0]], dtype=F64)
            rot = axis_angle_to_rotation_matrix(yaw)[0]
            video = _render(reference, frame, rot, p, _rig(False))
            sil = video.observation.silhouette[0, 0, 0]
            assert bool(sil[:, -1].any()) and not bool(sil[:, 0].any())  # cut on the right
            for settings, errors in (
                (Stage1Settings(), shifted),
                (Stage1Settings(clipped_shifts=(0.0,)), unshifted),
            ):
                fit = fit_rigid_pairs(
                    reference,
                    video,
                    rows,
                    cols + frame,
                    1.0,
                    settings,
                    torch.Generator().manual_seed(0),
                )
                errors.append(
                    (
                        float(_angle_deg(fit.rotation[0, 0], rot)),
                        float((fit.translation[0, 0].double() - p).norm()),
                    )
                )
    assert all(angle < 10.0 and shift < 0.3 for angle, shift in shifted), shifted
    assert max(angle for angle, _ in unshifted) > 30.0, unshifted


def test_heading_prior_tells_front_from_back_not_the_exact_heading(reference, walk):
    """On the walk (towards the camera, ~1.2 m/s), the true ``T`` and the true ``T`` turned
    40 degrees about the vertical pay nothing (within ``heading_tolerance_deg`` = 60), turned
    180 degrees they pay ``heading_weight`` (the gate is open at walking speed); with no
    tolerance, 40 degrees pays ``(1 - cos 40) / 2`` of it, as the prior did before."""
    video = _video(walk)
    rot, _ = _true_transforms(reference, walk)
    c_true = torch.from_numpy(walk.arrays["C_true"])
    rows = torch.arange(10, 60, 10)
    turn = axis_angle_to_rotation_matrix(
        torch.tensor([[0.0, math.radians(a), 0.0] for a in (0, 40, 180)], dtype=F64)
    )
    cands = (turn[None] @ rot[rows][:, None]).float()  # (R, 3, 3, 3)
    for tolerance, expected in ((60.0, (0, 0, 1)), (0.0, (0, (1 - math.cos(0.698)) / 2, 1))):
        settings = Stage1Settings(heading_tolerance_deg=tolerance)
        scene = _build_scene(reference, video, 1.0, settings, torch.Generator().manual_seed(0))
        paid = (
            _heading_penalty(
                scene, rows[:, None].expand(-1, 3), c_true[rows][:, None].expand(-1, 3), cands
            )
            / settings.heading_weight
        )
        want = torch.tensor(expected, dtype=paid.dtype).expand_as(paid)
        assert torch.allclose(paid, want, atol=0.03), (tolerance, paid)


def test_a_keypoint_start_that_is_no_pose_is_no_candidate(reference, walk, monkeypatch):
    """In frames where the detector finds no one (every confidence 0) the 2-D joints' pose
    solve may give NaN. Such a start is no candidate: each pair keeps a finite pose and cost
    from its other starts -- where a NaN start's pixels, cast to an index, made stage 1 fail
    with "index out of range" (the CMU kick 10_03 rendered and registered against itself),
    and its NaN cost would have won every argmin."""
    import motion.registration.approximate.starts as starts

    video = _video(walk, keypoints=True)
    rows = torch.arange(0, 72, 12)
    cols = torch.from_numpy(walk.arrays["C_true"])[rows][:, None]
    settings = Stage1Settings(iterations=5, dtype=F64)
    solve = starts.solve_pose_views

    def no_pose(*args, **kwargs):
        res = solve(*args, **kwargs)
        return dataclasses.replace(res, R=torch.full_like(res.R, math.nan), t=res.t * math.nan)

    monkeypatch.setattr(starts, "solve_pose_views", no_pose)
    fit = fit_rigid_pairs(reference, video, rows, cols, 1.0, settings)
    assert torch.isfinite(fit.cost).all()
    assert torch.isfinite(fit.rotation).all() and torch.isfinite(fit.translation).all()
    # the whole stage: the final transforms' smoothness between neighbouring frames'
    # candidates read every candidate's pose ("log_table must be finite": a run against a
    # walk without calibration, and three cameras at 640 x 480)
    result = approximate_registration(
        reference, video, 1.0, Stage1Settings(), torch.Generator().manual_seed(0)
    )
    assert torch.isfinite(result.rotation).all() and torch.isfinite(result.translation).all()
    assert bool((result.C[1:] >= result.C[:-1]).all())


# -- (b) the 2-D joint path against OpenCV ---------------------------------------------------------
def test_keypoint_path_matches_opencv_solvepnp(reference, walk):
    """With keypoints only (silhouette and edge weights 0) and a Cauchy scale far above the
    residuals (``keypoint_sigma`` = 20 body heights: the loss is least squares), the joint
    path solves the problem ``cv2.solvePnP(SOLVEPNP_ITERATIVE)`` solves: the same optimum
    wherever OpenCV converges (0.05 degrees, 1 mm: LM tolerance, measured <= 0.025 degrees),
    and never a worse reprojection error (OpenCV's iterative LM falls into a wrong basin on
    some frames, DESIGN section 7). The noisy joints have 1 px noise."""
    video = _video(walk, keypoints=True)
    c_true = torch.from_numpy(walk.arrays["C_true"])
    rows = torch.arange(0, 72, 6)
    settings = Stage1Settings(
        outside_weight=0.0,
        uncovered_weight=0.0,
        edge_weight=0.0,
        heading_weight=0.0,
        keypoint_sigma=20.0,
        iterations=30,
        dtype=F64,
    )
    fit = fit_rigid_pairs(reference, video, rows, c_true[rows][:, None], 1.0, settings)
    k, r_cam, t_cam = (walk.arrays[n][0] for n in ("K", "R", "t"))
    x3 = reference.body_frames(c_true[rows]).positions.numpy()  # (R, J, 3)
    x2 = walk.arrays["joints2d_noisy"][0][rows.numpy()]  # (R, J, 2)

    def rms(rot: np.ndarray, pos: np.ndarray, i: int) -> float:  # world pose -> px RMS
        cam = (x3[i] @ rot.T + pos) @ r_cam.T + t_cam
        uv = cam[:, :2] / cam[:, 2:] * k[[0, 1], [0, 1]] + k[[0, 1], [2, 2]]
        return float(np.sqrt(((uv - x2[i]) ** 2).sum(-1).mean()))

    agree = 0
    for i in range(len(rows)):
        _, rvec, tvec = cv2.solvePnP(x3[i], x2[i], k, None, flags=cv2.SOLVEPNP_ITERATIVE)
        r_cv = r_cam.T @ cv2.Rodrigues(rvec)[0]
        p_cv = r_cam.T @ (tvec[:, 0] - t_cam)
        ours_r, ours_p = fit.rotation[i, 0].numpy(), fit.translation[i, 0].numpy()
        e_ours, e_cv = rms(ours_r, ours_p, i), rms(r_cv, p_cv, i)
        assert e_ours <= e_cv + 1e-6
        if e_cv <= e_ours + 1e-6:  # OpenCV converged: the same optimum
            agree += 1
            assert float(_angle_deg(torch.from_numpy(ours_r), torch.from_numpy(r_cv))) < 0.05
            assert float(np.linalg.norm(ours_p - p_cv)) < 1e-3
    assert agree >= len(rows) - 2


# -- (c) the whole stage on a synthetic warp ---------------------------------------------------
def test_approximate_registration_recovers_a_warped_walk(reference, walk):
    """72 video frames (25 fps) against 343 reference frames (120 Hz), warp 0.3, one camera
    facing the walker. Measured: mean |C - C_true| 3.7 reference frames (max 19), T within
    2.6 degrees / 6.5 cm (medians), 18.5 % of the T' x T pairs fitted, ~2.5 s."""
    video = _video(walk)
    messages = []
    result = approximate_registration(
        reference, video, 1.0, Stage1Settings(), torch.Generator().manual_seed(0), messages.append
    )
    assert isinstance(result, Stage1Result)
    c_true = torch.from_numpy(walk.arrays["C_true"])
    tv, tr = len(c_true), reference.num_frames
    assert result.C.shape == (tv,) and result.C.dtype == torch.long
    assert bool((result.C[1:] >= result.C[:-1]).all())  # monotone
    assert int(result.C.min()) >= 0 and int(result.C.max()) < tr
    assert float((result.C - c_true).abs().float().mean()) <= 6.0
    assert result.pair_evaluations <= 0.25 * tv * tr  # never all pairs
    assert result.rotation.shape == (tv, 3, 3) and result.translation.shape == (tv, 3)
    assert result.cost.shape == (tv,) and bool(torch.isfinite(result.cost).all())
    rot_true, p_true = _true_transforms(reference, walk)
    assert float(_angle_deg(result.rotation, rot_true).median()) < 10.0
    assert float((result.translation.double() - p_true).norm(dim=-1).median()) < 0.15
    assert result.seconds > 0 and messages and all("\n" not in m for m in messages)


def test_fitted_tempo_is_the_advance_per_moving_frame_whatever_stalls_and_held_ends():
    """5 reference frames per video frame while C moves: held ends and a mid-video stall (the
    cycle drop a second pass should undo) leave the tempo read at 5, where C's mean slope
    reads 50 / 21 = 2.4; a C that never moves has none."""
    moving = [5 * k for k in range(5)]  # 0 .. 20
    c = torch.tensor([0, 0, 0] + moving + [20] * 6 + [25 + 5 * k for k in range(6)] + [50, 50])
    assert fitted_tempo(c) == pytest.approx(5.0)
    assert fitted_tempo(torch.arange(10) * 3) == pytest.approx(3.0)
    assert fitted_tempo(torch.full((8,), 4)) is None


def test_a_second_pass_at_the_fitted_tempo_keeps_a_warped_walk(reference, walk):
    """The same walk as above with the tempo pass on: C within the same bound."""
    video = _video(walk)
    settings = Stage1Settings(tempo_weight=0.1)
    result = approximate_registration(
        reference, video, 1.0, settings, torch.Generator().manual_seed(0)
    )
    c_true = torch.from_numpy(walk.arrays["C_true"])
    assert bool((result.C[1:] >= result.C[:-1]).all())
    assert float((result.C - c_true).abs().float().mean()) <= 6.0


# -- (d) body size -------------------------------------------------------------------------------
def test_body_scale_from_two_cameras_and_not_from_one(reference, walk_two_cameras):
    """G = 1.1 from two calibrated cameras within 3 % (measured 1.083-1.096 over seeds);
    one perspective camera confounds size and depth: G = 1 and a note saying so."""
    two = estimate_body_scale(
        reference, _video(walk_two_cameras), Stage1Settings(), torch.Generator().manual_seed(0)
    )
    assert abs(two.value / 1.1 - 1) < 0.03, two.note
    assert two.measured and "2 calibrated cameras" in two.note
    one = estimate_body_scale(reference, _video(walk_two_cameras, cameras=[0]))
    assert one.value == 1.0 and not one.measured and "one perspective camera" in one.note


# -- reproducibility ---------------------------------------------------------------------------
def test_same_generator_same_fit(reference, walk):
    video = _video(walk)
    rows = torch.tensor([3, 40])
    cols = torch.tensor([[10, 12, 14, 16, 18, 20], [180, 182, 184, 186, 188, 190]])
    a, b = (
        fit_rigid_pairs(reference, video, rows, cols, 1.0, None, torch.Generator().manual_seed(7))
        for _ in range(2)
    )
    assert torch.equal(a.cost, b.cost) and torch.equal(a.rotation, b.rotation)
    assert torch.equal(a.translation, b.translation)
    warm = fit_rigid_pairs(
        reference,
        video,
        rows,
        cols,
        1.0,
        None,
        torch.Generator().manual_seed(7),
        init=(a.rotation[:, 0], a.translation[:, 0]),  # one warm start per row
    )
    assert bool((warm.cost <= a.cost * 1.05 + 1e-7).all())


@pytest.mark.parametrize("fixture", ["walk", "walk_two_cameras"])
def test_scene_built_in_chunks_of_frames_is_the_same(reference, fixture, request, monkeypatch):
    """The scene's per-frame maps and silhouette draws, built a few frames at a time (as a
    long video is, to bound memory), are the same entries as built all at once, and the
    generator is left in the same state (it goes on to stages 2-3)."""
    video = _video(request.getfixturevalue(fixture))
    scenes, states = [], []
    for chunk in (1000, 5):  # all 72 frames at once; then 15 chunks, the last one short
        monkeypatch.setattr(scene_module, "FRAME_CHUNK", chunk)
        g = torch.Generator().manual_seed(4)
        scenes.append(_build_scene(reference, video, 1.0, Stage1Settings(), g))
        states.append(g.get_state())
    whole, chunked = scenes
    names = "dout edist obs obs_w height cam_w centroid top_v clipped side_clipped".split()
    for name in names:
        a, b = getattr(whole, name), getattr(chunked, name)
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), name
    assert torch.equal(states[0], states[1])


# -- (e) bad input ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def short(walk):
    """The first 3 frames of the walk (fast to set up)."""
    video = _video(walk)
    obs = video.observation
    cut = Observation(obs.silhouette[:, :3], obs.edge_distance[:, :3])
    return VideoFeatures(cut, video.cameras, video.frame_rate)


def _one_line(err) -> str:
    text = str(err.value)
    assert "\n" not in text and text
    return text


@pytest.mark.parametrize(
    "rows, cols, expected",
    [
        (torch.tensor([[0]]), torch.tensor([[5]]), "expected rows (R,) and cols (R, W)"),
        (torch.tensor([0]), torch.tensor([5]), "expected rows (R,) and cols (R, W)"),
        (torch.tensor([0, 1]), torch.tensor([[5]]), "expected rows (R,) and cols (R, W)"),
        (torch.tensor([0]), torch.zeros(1, 0, dtype=torch.long), "expected at least one pair"),
        (torch.tensor([3]), torch.tensor([[5]]), "rows must be video frames in [0, 3)"),
        (torch.tensor([0]), torch.tensor([[343]]), "cols must be reference frames in [0, 343)"),
        (torch.tensor([0.0]), torch.tensor([[5]]), "must be integer frame indices"),
    ],
)
def test_bad_pairs_are_refused(reference, short, rows, cols, expected):
    with pytest.raises(RegistrationError) as err:
        fit_rigid_pairs(reference, short, rows, cols)
    assert expected in _one_line(err)


def test_bad_inputs_are_refused(reference, short, walk):
    rows, cols = torch.tensor([0]), torch.tensor([[5]])
    with pytest.raises(RegistrationError) as err:
        fit_rigid_pairs(reference, short, rows, cols, init=(torch.eye(3), torch.zeros(3)))
    assert "init must be rotation (1, 1, 3, 3)" in _one_line(err)
    for scale in (0.0, -1.0, math.nan):
        with pytest.raises(RegistrationError) as err:
            fit_rigid_pairs(reference, short, rows, cols, scale)
        assert "scale (G) must be a finite number > 0" in _one_line(err)
    obs = short.observation
    empty = obs.silhouette.clone()
    empty[:, 1] = 0  # frame 1 shows nobody
    blank = VideoFeatures(Observation(empty), short.cameras, 25.0)
    with pytest.raises(RegistrationError) as err:
        approximate_registration(reference, blank)
    assert "expected a silhouette in at least one camera of every frame" in _one_line(err)
    none = VideoFeatures(Observation(obs.silhouette[:, :0]), short.cameras, 25.0)
    with pytest.raises(RegistrationError) as err:
        approximate_registration(reference, none)
    assert "expected at least one video frame; got 0" in _one_line(err)
    with pytest.raises(RegistrationError) as err:
        estimate_body_scale(reference, short, frames=0)
    assert "frames must be an int >= 1" in _one_line(err)
    kp = torch.zeros(1, 3, 1, 6, 3)
    named = VideoFeatures(
        Observation(obs.silhouette, keypoints=kp),
        short.cameras,
        25.0,
        ["Hips", "Nose"] + ["Head"] * 4,
    )
    with pytest.raises(RegistrationError) as err:
        fit_rigid_pairs(reference, named, rows, cols)
    assert "keypoint joints ['Nose'] are not joints" in _one_line(err)
    with pytest.raises(RegistrationError) as err:
        fit_rigid_pairs(reference, short, rows, cols, settings="fast")
    assert "settings must be Stage1Settings" in _one_line(err)


@pytest.mark.parametrize(
    "kwargs, expected",
    [
        (dict(yaw_starts=0), "yaw_starts must be >= 1; got 0"),
        (dict(iterations=2.5), "iterations must be an integer >= 1; got 2.5"),
        (dict(refine_starts=9), "refine_starts must be <= yaw_starts (8); got 9"),
        (dict(robust="median"), "robust must be one of 'truncate', 'saturate'; got 'median'"),
        (dict(truncate=0.0), "truncate must be > 0; got 0.0"),
        (dict(edge_weight=math.inf), "edge_weight must be a finite number; got inf"),
        (dict(edge_weight=-0.1), "edge_weight must be >= 0; got -0.1"),
        (dict(reference_up=(0.0, 0.0, 0.0)), "reference_up must be a non-zero 3-vector"),
        (dict(reference_up=(0.0, 1.0)), "reference_up must be a list of 3 numbers; got"),
        (dict(factor=1), "factor must be >= 2; got 1"),
        (dict(radius=0), "radius must be >= 1; got 0"),
        (dict(clipped_depths=(1.0, 0.0)), "clipped_depths[1] must be in (0, 1]; got 0.0"),
        (dict(clipped_depths=()), "clipped_depths must be a non-empty list of numbers in (0, 1]"),
        (dict(clipped_shifts=(0.0, 1.0)), "clipped_shifts[1] must be in [0, 1); got 1.0"),
        (dict(clipped_shifts=0.1), "clipped_shifts must be a non-empty list of numbers in [0, 1)"),
        (dict(heading_tolerance_deg=180.0), "heading_tolerance_deg must be in [0, 180); got"),
        (dict(fix_start=1), "fix_start must be true or false; got 1"),
        (dict(dtype=torch.float16), "dtype must be one of torch.float32, torch.float64; got"),
    ],
)
def test_bad_settings_are_refused(kwargs, expected):
    with pytest.raises(RegistrationError) as err:
        Stage1Settings(**kwargs)
    assert _one_line(err).startswith(f"Stage1Settings: {expected}")


def test_settings_are_normalised_and_stay_hashable():
    """Lists become tuples and ints floats, as declared; a frozen, hashable value."""
    settings = Stage1Settings(clipped_shifts=[0.0, 0.1], lm_damping=1, reference_up=[0, 0, 1])
    assert settings.clipped_shifts == (0.0, 0.1) and type(settings.lm_damping) is float
    assert settings.reference_up == (0.0, 0.0, 1.0)
    same = Stage1Settings(clipped_shifts=(0.0, 0.1), lm_damping=1.0, reference_up=(0, 0, 1))
    assert settings == same and hash(settings) == hash(same)
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.yaw_starts = 2  # type: ignore[misc]
