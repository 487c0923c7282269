"""The movement check (motion.registration.movement) on constructed registrations whose
travel and time warp are known: a walker at another tempo matches; a student in place, one
covering 2.5 times the ground, a stop-and-go C, a racing C, a student going back and forth
and a runner against a walker (by the Froude numbers) do not; the verdict does not depend on where the world's origin or axes
are."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from motion.angles import SegmentMap
from motion.body.observation import Observation
from motion.cameras import CameraRig
from motion.kinematics import forward_kinematics
from motion.registration.movement import (
    GRAVITY,
    HIP_HEIGHT_PER_HIP_TO_ANKLE,
    MovementSettings,
    check_movement,
    held_ends,
    leg_length_m,
    path_straightness,
    peak_speed,
)
from motion.registration.types import Reference, VideoFeatures
from motion.registration.video import default_camera
from tests.motion.registration.conftest import REFERENCE

REF_RATE, VIDEO_RATE = 120.0, 25.0
F64 = torch.float64


def _walking_reference(frames: int = 600, speed: float = 1.2) -> torch.Tensor:
    """``(frames, 3)`` a root walking along +z at ``speed`` m/s with a 3 cm side sway."""
    t = torch.arange(frames, dtype=F64) / REF_RATE
    return torch.stack([0.03 * torch.sin(2 * math.pi * t), 0.95 + 0 * t, speed * t], -1)


def _warped_c(n: int = 50, speed: float = 0.9, start: int = 20) -> torch.Tensor:
    """A smooth monotone C at ``speed`` times the reference's pace with +-15 % tempo drift."""
    t = torch.arange(n, dtype=F64)
    pace = speed * REF_RATE / VIDEO_RATE
    return (start + pace * (t + 1.5 * torch.sin(t / 8))).round().long()


def _check(c, translation, root, scale=1.0, legs_m=None, **settings):
    return check_movement(
        c, translation, root, REF_RATE, VIDEO_RATE, scale, MovementSettings(**settings), legs_m
    )


def _straight(n: int, speed: float) -> torch.Tensor:
    """``(n, 3)`` a student's root going along +x at ``speed`` m/s, one row per video frame."""
    x = speed * torch.arange(n, dtype=F64) / VIDEO_RATE
    return torch.stack([x, 0.9 + 0 * x, 1.0 + 0 * x], -1)


def test_another_walker_at_another_tempo_matches():
    root = _walking_reference()
    c = _warped_c()
    result = _check(c, 1.1 * root[c] + torch.tensor([2.0, 0.0, -1.0], dtype=F64), root, 1.05)
    assert result.motions_match and result.reasons == []
    assert result.student_travel_m / result.reference_travel_m == pytest.approx(1.1 / 1.05)
    design = torch.stack([torch.arange(len(c), dtype=F64), torch.ones(len(c), dtype=F64)], 1)
    slope = torch.linalg.lstsq(design, c.double()[:, None]).solution[0, 0]
    assert result.speed_ratio == pytest.approx(float(slope) * VIDEO_RATE / REF_RATE)
    assert result.stalled_fraction == 0.0 and result.fast_fraction == 0.0


def test_a_video_too_short_to_check_says_the_verdict_is_not_known():
    """Eight frames (0.32 s) of another walker: no check can be read (a stride takes about a
    second), so the match is a default and a warning says so; a second and a half of the
    same walker is checked and gets no such warning; a failed check needs none."""
    root = _walking_reference()
    short = _check(_warped_c(8), root[_warped_c(8)], root)
    assert short.motions_match and short.reasons == []
    (warning,) = short.warnings
    assert warning.startswith("the video lasts 0.32 s where it matches the reference")
    assert "need 1 s (about one stride)" in warning
    assert warning.endswith("whether the student performs the reference's movement is not known")
    c = _warped_c(40)
    assert _check(c, root[c], root).warnings == []
    far = _check(_warped_c(8), 8.0 * root[_warped_c(8)], root, travelling_m=0.01)
    assert not far.motions_match and far.warnings == []


def test_the_verdict_does_not_depend_on_the_world_frame():
    root = _walking_reference()
    c = _warped_c()
    angle = torch.tensor(0.7, dtype=F64)
    turn = torch.tensor(
        [[angle.cos(), 0, angle.sin()], [0, 1, 0], [-angle.sin(), 0, angle.cos()]], dtype=F64
    )
    student = 2.6 * root[c]  # a run: 2.6 times the ground
    moved = student @ turn.T + torch.tensor([5.0, -1.0, 3.0], dtype=F64)
    a, b = _check(c, student, root), _check(c, moved, root)
    assert not a.motions_match and a.reasons == b.reasons
    assert a.student_travel_m == pytest.approx(b.student_travel_m)


def test_a_student_in_place_or_covering_far_more_ground_does_not_match():
    root = _walking_reference()
    c = _warped_c()
    in_place = root[c][:1].expand(len(c), 3) + 0.05 * torch.randn(
        len(c), 3, dtype=F64, generator=torch.Generator().manual_seed(0)
    )
    jump = _check(c, in_place, root)
    assert not jump.motions_match and len(jump.reasons) == 1
    assert jump.reasons[0].startswith("the reference travels")
    run = _check(c, 2.5 * root[c], root)
    assert not run.motions_match and "2.50 times as far" in run.reasons[0]


def test_a_difference_under_half_a_metre_says_nothing():
    """A reference that drifts 0.6 m; the student 0.35 m (ratio 0.58, outside 1/1.6 but
    within one step's sway and the depth estimate's error): matches."""
    root = _walking_reference(speed=0.3)
    c = _warped_c(n=50, speed=1.0, start=0)  # 2 s of the reference: 0.6 m
    result = _check(c, 0.58 * root[c], root)
    assert result.reference_travel_m > 0.5 and result.motions_match


def test_a_reference_in_place_against_a_travelling_student_does_not_match():
    root = _walking_reference(speed=0.0)
    c = _warped_c()
    walker = torch.zeros(len(c), 3, dtype=F64)
    walker[:, 2] = torch.linspace(0, 2.5, len(c), dtype=F64)
    result = _check(c, walker, root)
    assert (
        not result.motions_match
        and "over the matched stretch but the student 2.4 m" in result.reasons[0]
    )
    assert _check(c, 0 * walker, root).motions_match


def test_stop_and_go_or_racing_c_does_not_match():
    root = _walking_reference(speed=0.0)
    steps = torch.full((49,), 5)
    steps[1::3] = 0  # a third of the frames stand still (inside C's range, not at its ends)
    c = torch.cat([torch.zeros(1, dtype=torch.long), steps.cumsum(0)])
    still = _check(c, root[c], root)
    assert not still.motions_match and still.stalled_fraction == pytest.approx(16 / 49)
    assert "stands still on 33 %" in still.reasons[0]
    assert still.held_start == still.held_end == 0
    racing = torch.full((49,), 4)
    racing[::2] = 10  # 2.08 x the frame-rate ratio (4.8) on half the frames
    c = torch.cat([torch.zeros(1, dtype=torch.long), racing.cumsum(0)])
    fast = _check(c, root[c], root)
    assert not fast.motions_match and fast.fast_fraction == pytest.approx(25 / 49)
    assert "races ahead" in fast.reasons[0]
    # a video at the reference's own rate moves C by about one frame: stalls are normal
    slow = torch.cat([torch.zeros(1, dtype=torch.long), (torch.arange(49) % 2).cumsum(0)])
    at_rate = check_movement(slow, root[slow], root, REF_RATE, REF_RATE, 1.0)
    assert at_rate.stalled_fraction is None and at_rate.motions_match


def test_a_verdict_read_from_doubtful_evidence_says_so_by_each_reason():
    root = _walking_reference(speed=0.0)
    steps = torch.full((49,), 5)
    steps[1::3] = 0
    c = torch.cat([torch.zeros(1, dtype=torch.long), steps.cumsum(0)])
    still = _check(c, root[c], root)
    caveat = "read from silhouettes that miss parts of the body"
    hedged = still.read_from(caveat)
    assert hedged.reasons == [f"{r} -- {caveat}" for r in still.reasons] and hedged.reasons
    assert dataclasses.replace(hedged, reasons=still.reasons) == still
    agreed = _check(torch.arange(50) * 5, root[torch.arange(50) * 5], root)
    assert agreed.motions_match and agreed.read_from(caveat) == agreed


def test_held_ends_count_the_repeats_of_the_first_and_last_values():
    assert held_ends(torch.tensor([5, 5, 5, 7, 9, 9, 9])) == (2, 2)
    assert held_ends(torch.tensor([5, 6, 9])) == (0, 0)
    assert held_ends(torch.tensor([4, 4, 4])) == (2, 0)  # one run: held at the start


def test_a_short_held_end_is_left_out_without_a_warning():
    """Two frames (0.08 s) holding C's first value: a fraction of a step, left out of the
    checks and the findings, not worth a sentence (held_warning_s 0.25 s)."""
    root = _walking_reference()
    c = torch.cat([torch.full((2,), int(_warped_c()[0])), _warped_c()])
    result = _check(c, root[c], root)
    assert result.motions_match and (result.held_start, result.held_end) == (2, 0)
    assert result.warnings == []


def test_a_walker_who_walks_on_past_the_references_end_matches():
    """Another walker whose last 13 of 63 frames all match the reference's last matched
    frame (he walks on past the stretch of the reference his phase matches, as the true
    alignment of two CMU walks does): not stop-and-go. The held frames are left out of the
    checks (travel compared over the matched stretch), reported in a warning, and marked."""
    root = _walking_reference()
    c = torch.cat([_warped_c(50), torch.full((13,), int(_warped_c(50)[-1]))])
    walker = 1.1 * _walking_reference(2000)[: len(c) * 5 : 5]  # walks on throughout
    walker = walker[: len(c)]
    result = _check(c, walker, root)
    assert result.motions_match, result.reasons
    assert (result.held_start, result.held_end) == (0, 13)
    assert result.stalled_fraction == 0.0
    assert len(result.warnings) == 1 and "the last 13 video frames" in result.warnings[0]
    assert result.held(len(c)).tolist() == [False] * 50 + [True] * 13
    # counted as before, the same C is stop-and-go
    strict = _check(c, walker, root, max_held=0.0)
    assert not strict.motions_match and strict.stalled_fraction == pytest.approx(13 / 62)
    assert strict.held_end == 0 and strict.warnings == []


def test_held_ends_beyond_max_held_count_as_stalls():
    """A C that holds its first value for 20 frames and its last for 20 of 60 is not a
    movement played with a margin at each end: beyond max_held (0.4) the held frames are
    stalls again, and a C that never moves is one stall."""
    root = _walking_reference()
    c = torch.cat([torch.full((20,), 30), _warped_c(20, start=30), torch.full((20,), 200)])
    result = _check(c, root[c], root)
    assert result.held_start == result.held_end == 0
    assert not result.motions_match and "stands still" in " ".join(result.reasons)
    frozen = _check(torch.full((30,), 40), root[:30], root)
    assert frozen.held_start == frozen.held_end == 0


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match=r"^MovementSettings: max_stalled must be in \(0, 1\]"):
        MovementSettings(max_stalled=0.0)
    with pytest.raises(ValueError, match=r"max_travel_ratio must be > 1; got 1\.0"):
        MovementSettings(max_travel_ratio=1.0)
    with pytest.raises(ValueError, match=r"fast_step_factor must be > 1; got 0\.5"):
        MovementSettings(fast_step_factor=0.5)
    with pytest.raises(ValueError, match=r"travelling_m must be >= 0; got -1\.0"):
        MovementSettings(travelling_m=-1.0)
    with pytest.raises(ValueError, match=r"walking_froude must be below running_froude"):
        MovementSettings(walking_froude=0.5, running_froude=0.5)


LEGS = (0.9, 0.95)  # the reference's and the student's hip heights, metres


def _froude(speed, leg):
    return speed**2 / (GRAVITY * leg)


def test_a_runner_against_a_walker_does_not_match_by_the_froude_numbers():
    """The reference walks at 1.2 m/s (Froude 0.16); a student going 2.4 m/s (0.62) over a
    stretch that C plays at 1.5 times the reference's pace (a runner's cadence) covers 1.33
    times the reference's ground per stride, which the travel check allows: the gait check
    alone says no, with both speeds. The same student at 1.5 m/s (0.24) walks briskly and
    matches; at 1.9 m/s (0.39), between a walk and a run, nothing is said."""
    root = _walking_reference(frames=1200)
    c = _warped_c(n=60, speed=1.5, start=0)
    run = _check(c, _straight(60, 2.4), root, legs_m=LEGS)
    assert not run.motions_match and len(run.reasons) == 1
    assert run.reasons[0] == (
        "the student at 2.4 m/s (Froude number 0.62 for a 0.95 m leg: a run) but the "
        "reference at 1.2 m/s (Froude number 0.16 for a 0.90 m leg: a walk): people walk "
        "below 0.3 and run from 0.5"
    )
    assert run.student_froude == pytest.approx(_froude(2.4, LEGS[1]), rel=1e-9)
    # the reference's speed at its own clock: the sway's 3 cm across the stretch aside
    assert run.reference_froude == pytest.approx(_froude(1.2, LEGS[0]), rel=0.01)
    brisk = _check(c, _straight(60, 1.5), root, legs_m=LEGS)
    assert brisk.motions_match and brisk.student_froude == pytest.approx(_froude(1.5, 0.95))
    between = _check(c, _straight(60, 1.9), root, legs_m=LEGS)
    assert between.motions_match and 0.3 < between.student_froude < 0.5


def test_a_walker_against_a_running_reference_does_not_match():
    root = _walking_reference(frames=1200, speed=3.0)  # Froude 1.02
    c = _warped_c(n=60, speed=0.6, start=0)
    walk = _check(c, _straight(60, 1.3), root, legs_m=LEGS)
    assert not walk.motions_match and "a walk) but the reference at 3.0 m/s" in walk.reasons[0]
    # without the legs, or over less than min_compared_s, the gait is not compared
    assert _check(c, _straight(60, 1.3), root).motions_match
    short = _check(c[:20], _straight(20, 1.3), root, legs_m=LEGS)  # 0.8 s at 25 fps
    assert short.motions_match and math.isnan(short.student_froude)
    assert math.isnan(short.reference_froude)
    held = _check(torch.full((60,), 40), _straight(60, 1.3), root, legs_m=LEGS)
    assert math.isnan(held.reference_froude)  # C never moves: no reference speed


def test_the_leg_length_is_the_rest_poses_hip_to_ankle_times_winters_ratio():
    """On the bundled CMU walk against its rest pose computed by forward kinematics; scaling
    the offsets by 1.1 scales it by 1.1."""
    reference = Reference.from_bvh(REFERENCE)
    skeleton = reference.skeleton
    segments = SegmentMap.from_roles(skeleton, reference.model.mapping)
    eye = torch.eye(3, dtype=F64).expand(skeleton.num_joints, 3, 3)
    rest = forward_kinematics(skeleton, eye, torch.zeros(3, dtype=F64)).positions
    sides = []
    for side in (0, 1):
        hip, knee, ankle = (
            rest[skeleton.index(segments.joint(s, side))] for s in ("thigh", "shank", "foot")
        )
        sides.append(float((knee - hip).norm() + (ankle - knee).norm()))
    expected = HIP_HEIGHT_PER_HIP_TO_ANKLE * sum(sides) / 2
    got = leg_length_m(skeleton, skeleton.offsets, segments)
    assert got == pytest.approx(expected, rel=1e-12)
    assert 0.7 < got < 1.0  # an adult's hip height, metres
    assert leg_length_m(skeleton, 1.1 * skeleton.offsets, segments) == pytest.approx(1.1 * got)


def test_a_student_who_holds_a_posture_while_c_crawls_does_not_match():
    """A student standing still for 2 s against a walk whose C crawls through 0.05 s of it
    (2 % of its pace; the travels both under half a metre, no stall counted at a nominal step
    under 2): another movement. The same over 0.8 s (under min_compared_s) says nothing, and
    a student at half the reference's pace matches."""
    root = _walking_reference()
    c = torch.linspace(100, 106, 50).round().long()  # 6 reference frames over 50 video frames
    still = root[100:101].expand(50, 3).clone()
    result = _check(c, still, root)
    assert result.speed_ratio == pytest.approx(6 / 49 * VIDEO_RATE / REF_RATE, rel=0.05)
    assert not result.motions_match and len(result.reasons) == 1
    assert result.reasons[0].startswith("the matching reference moment advances at 3 % of the")
    assert _check(c[:20], still[:20], root).motions_match
    half = _warped_c(speed=0.5)
    assert _check(half, root[half], root).motions_match  # a slow walker: a finding


def _arc(n: int, radius: float, turn: float) -> torch.Tensor:
    """``(n, 3)`` a root walking at uniform speed along a circular arc of ``turn`` radians."""
    theta = turn * torch.arange(n, dtype=F64) / (n - 1)
    return torch.stack([radius * theta.sin(), 0.9 + 0 * theta, radius * (1 - theta.cos())], -1)


@pytest.mark.parametrize("turn, window", [(0.5, 5), (math.pi / 2, 6), (math.pi, 4)])
def test_path_straightness_of_an_arc_is_its_chord_over_its_polygon(turn, window):
    """Window means of equally spaced points on a circle lie on a smaller circle, equally
    spaced ``window * step`` apart: the straightness of ``N`` such segments is the chord over
    the polygon, sin(N phi / 2) / (N sin(phi / 2)), whatever the radius."""
    n = 61
    straightness, net, path = path_straightness(_arc(n, 3.0, turn), window)
    segments = n // window - 1
    phi = window * turn / (n - 1)
    assert straightness == pytest.approx(
        math.sin(segments * phi / 2) / (segments * math.sin(phi / 2)), rel=1e-9
    )
    assert straightness == pytest.approx(net / path)
    assert path_straightness(_straight(n, 1.0), window)[0] == pytest.approx(1.0)
    there_and_back = torch.cat([_straight(30, 1.0), _straight(30, 1.0).flip(0)])
    assert path_straightness(there_and_back, 6)[0] == pytest.approx(0.0, abs=1e-12)
    assert path_straightness(torch.zeros(10, 3, dtype=F64), 2) == (1.0, 0.0, 0.0)


def test_a_student_going_back_and_forth_where_the_reference_travels_does_not_match():
    """A student covering 0.8 of the walk's ground per stride (inside the travel band) while
    the registered root swings 0.4 m to and fro across the way at 1.5 Hz (a depth estimate
    jumping between postures that do not fit): its path is under 0.6 times as straight as
    the reference's. The same travel without the swing, or walking a quarter circle,
    matches."""
    root = _walking_reference()
    c = _warped_c()
    t = torch.arange(len(c), dtype=F64) / VIDEO_RATE
    walker = 0.8 * root[c]
    swinging = walker.clone()
    swinging[:, 0] += 0.4 * torch.sin(2 * math.pi * 1.5 * t)
    result = _check(c, swinging, root)
    assert not result.motions_match and len(result.reasons) == 1
    assert result.reasons[0].startswith("the student goes back and forth: ")
    assert result.student_straightness < 0.6 * result.reference_straightness
    window = round(MovementSettings().path_window_s * VIDEO_RATE)
    assert result.student_straightness == pytest.approx(path_straightness(swinging, window)[0])
    assert _check(c, walker, root).motions_match
    curve = _arc(len(c), 2.0, math.pi / 2)  # 3.1 m along a quarter circle in 2 s
    turning = _check(c, curve, root)
    assert turning.motions_match and 0.85 < turning.student_straightness < 0.95
    short = _check(c[:20], swinging[:20], root)  # 0.8 s, under min_compared_s: not measured
    assert short.motions_match and math.isnan(short.student_straightness)


def _run_up(n: int, fast_s: float, fast: float, slow: float) -> torch.Tensor:
    """``(n, 3)`` a student's root going along +x at ``fast`` m/s for ``fast_s`` seconds, then
    at ``slow`` m/s (a run-up, then the kick's stop), one row per video frame."""
    t = torch.arange(n, dtype=F64) / VIDEO_RATE
    x = torch.where(t <= fast_s, fast * t, fast * fast_s + slow * (t - fast_s))
    return torch.stack([x, 0.9 + 0 * x, 1.0 + 0 * x], -1)


def test_peak_speed_is_the_fastest_windows_net_speed():
    """3 s at 1 m/s, then 1.5 s at 3 m/s: a 1 s window lies wholly in the fast stretch, where
    the net speed is exact; times that never advance give no speed."""
    n = round(4.5 * VIDEO_RATE)
    positions = _run_up(n, 3.0, 1.0, 3.0)
    times = torch.arange(n, dtype=F64) / VIDEO_RATE
    assert peak_speed(positions, times, 25, 3) == pytest.approx(3.0, rel=1e-9)
    assert peak_speed(positions[:60], times[:60], 25, 3) == pytest.approx(1.0, rel=1e-9)
    assert math.isnan(peak_speed(positions, torch.zeros(n, dtype=F64), 25, 3))


def test_a_run_up_and_stop_against_a_walk_does_not_match_by_the_peak_froude():
    """A student running 3 m/s for 1.2 s, then all but stopping (0.3 m/s) for 1.8 s, against
    a walk at 1.2 m/s played at its pace: over the whole stretch a walker's speed and ground
    (the travel and the whole-stretch gait allow it), but its peak Froude number (0.97 at
    3 m/s) is a run's while the reference's peak stays a walk's. A walker at 1.6 m/s, then
    1.2 m/s (a peak of 0.27) matches."""
    root = _walking_reference(frames=1200)
    n = 75
    c = _warped_c(n=n, speed=1.0, start=0)
    student = _run_up(n, 1.2, 3.0, 0.3)
    result = _check(c, student, root, legs_m=LEGS)
    assert not result.motions_match and len(result.reasons) == 1
    assert result.student_froude < 0.3  # the whole stretch: a walk
    assert result.reasons[0].startswith("the student runs for 1 s at 3.0 m/s (Froude number 0.97)")
    assert "the reference never leaves a walk" in result.reasons[0]
    assert result.student_froude_peak == pytest.approx(_froude(3.0, LEGS[1]), rel=1e-9)
    assert result.reference_froude_peak < 0.3
    surge = _check(c, _run_up(n, 1.5, 1.6, 1.2), root, legs_m=LEGS)
    assert surge.motions_match and 0.25 < surge.student_froude_peak < 0.3
    assert _check(c, student, root).motions_match  # without the legs: not compared


def test_a_root_that_swings_after_the_body_leaves_the_view_is_not_read():
    """A walker whose registered root swings 2 m to and fro over the last 0.8 s, where the
    body is cut by the image's edge (a monocular depth placed on half a body): read there,
    the path is refused; read where the whole body is in view, it is the walk's."""
    root = _walking_reference()
    c = _warped_c(n=75, speed=1.0, start=0)
    walker = root[c].clone()
    t = torch.arange(20, dtype=F64) / VIDEO_RATE
    walker[55:, 0] += 2.0 * torch.sin(2 * math.pi * 2.5 * t)
    in_view = torch.arange(75) < 55
    assert not _check(c, walker, root, legs_m=LEGS).motions_match
    seen = check_movement(
        c, walker, root, REF_RATE, VIDEO_RATE, 1.0, MovementSettings(), LEGS, in_view
    )
    assert seen.motions_match and seen.student_straightness > 0.95
    none = torch.zeros(75, dtype=torch.bool)  # never wholly in view: the path is not read
    blind = check_movement(c, walker, root, REF_RATE, VIDEO_RATE, 1.0, None, LEGS, none)
    assert math.isnan(blind.student_straightness) and math.isnan(blind.student_froude_peak)


def test_a_person_is_within_the_sides_where_a_silhouette_is_off_the_left_and_right_edges():
    """Per frame: empty in both cameras; cut by the left edge in one and empty in the other;
    cut by the right edge in one but off both sides in the other; cut only by the bottom
    (feet out of the frame: a framing, still read)."""
    one = default_camera(40, 30)
    rig = CameraRig(
        *(torch.cat([a, a]) for a in (one.K, one.R, one.t, one.dist, one.size)), ["a", "b"]
    )
    sil = torch.zeros(1, 4, 2, 30, 40, dtype=F64)
    sil[0, 1, 0, 10:20, 0:5] = 1  # touches the left edge
    sil[0, 2, 0, 10:20, 35:40] = 1  # touches the right edge ...
    sil[0, 2, 1, 5:25, 10:20] = 1  # ... but off both sides in the other camera
    sil[0, 3, 0, 10:30, 1:39] = 1  # touches the bottom only, a pixel from either side
    video = VideoFeatures(Observation(sil), rig, VIDEO_RATE)
    assert video.within_sides().tolist() == [False, False, True, True]
