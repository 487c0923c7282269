"""register_synthetic's ground truth: the true C of another performer is the monotone
alignment of two root-normalised 3-D motions -- against itself it is the warp exactly; the
swing error leaves out the twist about the bone and only that; stated findings are scored
against the true differences over their own frames."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from experiments.config import ConfigError
from experiments.register_synthetic import (
    RegisterSyntheticConfig,
    Truth,
    _bone_direction_error_deg,
    _bone_directions,
    _first,
    _iou_of_alternatives,
    _long_bones,
    _settings,
    _swing_error_deg,
    angle_error_metrics,
    finding_agreement,
    nearest_truth,
    posture_cost,
    posture_excess,
    synthetic_truth,
    true_correspondence,
    true_correspondences,
    true_differences,
)
from motion.registration import Reference
from motion.registration.export import JointAngles
from motion.settings import SettingError
from motion.synth import time_warp
from tests.motion.body.conftest import WALK


def test_true_correspondence_of_a_motion_with_itself_is_the_warp():
    ref = Reference.from_bvh(WALK)
    shown = time_warp(60, ref.num_frames, 0.3, torch.Generator().manual_seed(4))
    assert torch.equal(true_correspondence(ref, shown, ref), shown)


def test_a_repeated_reference_has_two_equally_true_alignments_and_a_plain_one_has_one():
    """A reference that performs the student's clip twice over matches it equally well at
    either repetition (the cycle ambiguity of a walk): both are true, the registration is
    scored against the nearer; a reference without repetition keeps one truth."""
    ref = Reference.from_bvh(WALK)
    clip = slice(20, 140)
    twice = dataclasses.replace(
        ref,
        rotations=torch.cat([ref.rotations[clip], ref.rotations[clip]]),
        root=torch.cat([ref.root[clip], ref.root[clip]]),
    )
    student = dataclasses.replace(ref, rotations=ref.rotations[clip], root=ref.root[clip])
    shown = torch.arange(0, 120, 4)
    alternatives = true_correspondences(student, shown, twice)
    assert {tuple(shown.tolist()), tuple((shown + 120).tolist())} <= {
        tuple(a) for a in alternatives.tolist()
    }
    assert nearest_truth(shown + 118, alternatives) == alternatives.tolist().index(
        (shown + 120).tolist()
    )
    alone = true_correspondences(ref, torch.arange(40, 200, 4), ref)
    assert alone.shape[0] == 1 and torch.equal(alone[0], torch.arange(40, 200, 4))


def test_a_c_off_the_truth_is_scored_by_how_much_farther_its_postures_lie():
    """Against itself, the warp's C has excess 0 and a C 30 frames late an infinite one
    (its postures differ, the truth's do not); by hand on a 2 x 3 cost, C = (1, 2) against the
    truth (0, 2) costs (4 + 1) / (2 + 1) - 1 = 2/3; no cost (the reference's own student)
    gives NaN."""
    ref = Reference.from_bvh(WALK)
    shown = time_warp(40, ref.num_frames - 40, 0.3, torch.Generator().manual_seed(4))
    cost = posture_cost(ref, shown, ref)
    assert posture_excess(cost, shown, shown) == 0.0
    assert posture_excess(cost, shown + 30, shown) == math.inf
    by_hand = torch.tensor([[2.0, 4.0, 9.0], [7.0, 5.0, 1.0]])
    c, best = torch.tensor([1, 2]), torch.tensor([0, 2])
    assert posture_excess(by_hand, c, best) == pytest.approx(2 / 3)
    assert math.isnan(posture_excess(None, c, best))


def test_swing_error_ignores_twist_about_the_bone_and_measures_a_bend():
    ref = Reference.from_bvh(WALK)
    knee = ref.skeleton.index("LeftLeg")
    d = _bone_directions(ref, [knee])  # (1, 3)
    eye = torch.eye(3, dtype=torch.float64)[None, None]

    def turn(axis, angle):
        k = torch.tensor(
            [[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]],
            dtype=torch.float64,
        )
        return torch.linalg.matrix_exp(angle * k)[None, None]

    twist = turn(d[0], math.radians(40))
    assert float(_swing_error_deg(eye, twist, d)) < 1e-5
    side = torch.nn.functional.normalize(
        torch.linalg.cross(d[0], torch.tensor([0.0, 0, 1], dtype=torch.float64)), dim=0
    )
    bend = turn(side, math.radians(25))
    assert abs(float(_swing_error_deg(eye, bend, d)) - 25) < 1e-6


def test_a_stated_finding_agrees_when_its_sign_and_size_match_the_truth_over_its_frames():
    """Findings scored by hand: the truth over each finding's frames (not the whole video)
    decides; a finding not stated is only counted as withheld."""
    time_s = torch.arange(10, dtype=torch.float64) / 10
    truth = torch.zeros(10, 2, dtype=torch.float64)
    truth[2:5, 0] = 12.0  # knee: +12 over 0.2-0.4 s, 0 elsewhere
    truth[:, 1] = -3.0  # elbow: a steady -3
    names = ["knee_angle_l", "elbow_flex_r"]

    def finding(name, start, end, deg, stated=True):
        return {
            "coordinate": name,
            "start_s": start,
            "end_s": end,
            "mean_difference_deg": deg,
            "stated": stated,
        }

    found = [
        finding("knee_angle_l", 0.2, 0.4, 8.0),  # within 5 of 12, same sign: agrees
        finding("knee_angle_l", 0.5, 0.9, 4.0),  # true 0 there: no difference to state
        finding("elbow_flex_r", 0.0, 0.9, -9.0),  # 6 off: too far
        finding("elbow_flex_r", 0.0, 0.9, -1.0, stated=False),
    ]
    score = finding_agreement(found, time_s, truth, names)
    assert score == {
        "findings_stated": 3.0,
        "findings_agree_fraction": 1 / 3,
        "findings_withheld_fraction": 0.25,
    }
    assert math.isnan(finding_agreement([], time_s, truth, names)["findings_agree_fraction"])
    quiet = finding_agreement(found[3:], time_s, truth, names)
    assert quiet["findings_stated"] == 0 and math.isnan(quiet["findings_agree_fraction"])


def test_true_differences_of_the_reference_against_itself_are_zero():
    ref = Reference.from_bvh(WALK)
    shown = torch.arange(0, 40, 2)
    truth = Truth(shown, None, None, ref.rotations[shown], None, 1.7, shown[None])
    assert true_differences(ref, None, truth).abs().max() < 1e-9


def test_angle_error_metrics_measure_the_error_and_how_often_the_uncertainty_covers_it():
    """Errors 1, -3 (twice) and 5 degrees against uncertainties of 1: RMS sqrt(44 / 4), one
    of four within 2u; an untrusted frame with a huge error is left out."""
    diff = torch.tensor([[1.0, -3.0], [-3.0, 5.0], [90.0, 90.0]], dtype=torch.float64)
    angles = JointAngles(
        ["knee_angle_l", "elbow_flex_r"],
        torch.arange(3, dtype=torch.float64),
        torch.zeros(3, 2, dtype=torch.float64),
        diff,
        diff,
        diff.abs(),
        uncertainty_deg=torch.ones(3, 2, dtype=torch.float64),
    )
    trusted = torch.tensor([True, True, False])
    got = angle_error_metrics(angles, torch.zeros(3, 2, dtype=torch.float64), trusted)
    assert got["angle_diff_err_deg_rms"] == pytest.approx(math.sqrt(44 / 4))
    assert got["angle_uncertainty_deg_rms"] == pytest.approx(1.0)
    assert got["angle_err_within_2u"] == pytest.approx(0.25)
    plain = angle_error_metrics(
        dataclasses.replace(angles, uncertainty_deg=None), torch.zeros(3, 2), trusted
    )
    assert math.isnan(plain["angle_err_within_2u"])


def test_bone_direction_error_measures_a_bend_and_ignores_a_twist_and_the_skeletons_rest_pose():
    """From joint positions: a knee bent 25 degrees more reads 25 at the thigh's child (the
    shin), 0 elsewhere; the forearm twisted about its own axis moves no joint and reads 0;
    the long bones are the limbs' (thighs, shins, upper arms, forearms)."""
    ref = Reference.from_bvh(WALK)
    driven = sorted(set(ref.spec.frame_joints.tolist()) - {0})
    long = [driven[i] for i in _long_bones(ref, driven)]
    names = [ref.skeleton.names[j] for j in long]
    assert {"LeftUpLeg", "LeftLeg", "RightArm", "RightForeArm"} <= set(names)
    assert not {"LeftFoot", "Neck1", "LeftFingerBase"} & set(names)
    frames = torch.arange(3)
    rotations = ref.rotations[frames].clone()
    true = ref.body_frames(frames).positions
    knee = ref.skeleton.index("LeftLeg")
    bent = rotations.clone()
    d = _bone_directions(ref, [knee])[0]  # the shin in the knee's frame
    side = torch.nn.functional.normalize(
        torch.linalg.cross(d, torch.tensor([0.0, 0, 1], dtype=torch.float64)), dim=0
    )
    k = torch.tensor(
        [[0, -side[2], side[1]], [side[2], 0, -side[0]], [-side[1], side[0], 0]],
        dtype=torch.float64,
    )
    bent[:, knee] = bent[:, knee] @ torch.linalg.matrix_exp(math.radians(25) * k)
    moved = ref.posture_frames(bent).positions
    err = _bone_direction_error_deg(ref, long, moved, true)
    shin = long.index(knee)
    assert torch.allclose(err[:, shin], torch.full((3,), 25.0, dtype=torch.float64), atol=1e-6)
    others = [i for i in range(len(long)) if i != shin]
    assert float(err[:, others].abs().max()) < 1e-5
    forearm = ref.skeleton.index("LeftForeArm")
    along = _bone_directions(ref, [forearm])[0]
    kk = torch.tensor(
        [[0, -along[2], along[1]], [along[2], 0, -along[0]], [-along[1], along[0], 0]],
        dtype=torch.float64,
    )
    twisted = rotations.clone()
    twisted[:, forearm] = twisted[:, forearm] @ torch.linalg.matrix_exp(math.radians(40) * kk)
    err = _bone_direction_error_deg(ref, long, ref.posture_frames(twisted).positions, true)
    assert float(err.max()) < 1e-5


def test_any_registration_setting_is_set_by_its_dotted_key_and_a_wrong_one_is_refused():
    base = _settings(RegisterSyntheticConfig())
    cfg = RegisterSyntheticConfig(
        registration={
            "refine.articulation_std": 0.15,
            "polish.steps": 7,
            "refine.tempo_placement": "fitted",
        },
        polish_steps=50,
    )
    settings = _settings(cfg)
    assert settings.refine.articulation_std == 0.15 != base.refine.articulation_std
    assert settings.polish.steps == 7  # applied after the experiment's own fields
    assert settings.refine.tempo_placement == "fitted" != base.refine.tempo_placement
    assert settings.refine.particles == base.refine.particles  # the rest untouched
    with pytest.raises(ConfigError, match=r"refine\.articulation_sd.*did you mean"):
        _settings(RegisterSyntheticConfig(registration={"refine.articulation_sd": 0.1}))
    with pytest.raises(ConfigError, match=r"refine\.particles must be an integer"):
        _settings(RegisterSyntheticConfig(registration={"refine.particles": 0.5}))


def test_the_device_reaches_the_registration_and_the_runner_holds_a_gpu_for_it():
    from experiments.runner import _resources

    assert _settings(RegisterSyntheticConfig()).device == "cpu"
    assert _resources(RegisterSyntheticConfig(), 2) == (2, 0)
    gpu = RegisterSyntheticConfig(device="cuda")
    assert _resources(gpu, 2) == (2, 1)
    if torch.cuda.is_available():
        assert _settings(gpu).device == "cuda"
    else:  # checked where the registration is built, on the machine that runs it
        with pytest.raises(SettingError, match="'cuda' asked for"):
            _settings(gpu)


def test_the_true_posture_covers_the_rendered_silhouettes_and_a_wrong_one_less():
    """The student is the walk itself, turned and re-articulated by motion synth: its true
    posture on its own body (G 1) renders the silhouettes the synthesiser drew (IoU ~1);
    the reference's posture at the true C and T (A = identity) misses the bent joints."""
    from motion.registration.inputs import features_from_sequence
    from motion.registration.types import Registration
    from motion.synth import SynthConfig, synthesize

    cfg = SynthConfig(fps=25, size=[160, 120], focal_px=220, seed=0, articulation={"LeftLeg": 40.0})
    seq = synthesize(WALK, cfg)
    reference = Reference.from_bvh(WALK)
    truth = synthetic_truth(seq, reference, None)
    video, truth = _first(features_from_sequence(seq), truth, 6)
    n = video.num_frames
    result = Registration(  # the registration found C and T exactly, and no articulation
        C=truth.C,
        T_rotation=truth.rotation,
        T_translation=truth.position,
        A=torch.eye(3, dtype=torch.float64).expand(n, reference.skeleton.num_joints, 3, 3),
        G=1.0,
        rotations=truth.local,
        fit=torch.ones(n),
        C_stage1=truth.C,
    )
    out = _iou_of_alternatives(reference, video, result, truth)
    assert out["silhouette_iou_truth_mean"] > 0.97  # rasterisation at the rim
    assert out["silhouette_iou_no_change_mean"] < out["silhouette_iou_truth_mean"] - 0.02
