"""register_synthetic's ground truth: the true C of another performer is the monotone
alignment of two root-normalised 3-D motions -- against itself it is the warp exactly; the
swing error leaves out the twist about the bone and only that."""

from __future__ import annotations

import math

import torch

from experiments.register_synthetic import (
    _bone_directions,
    _swing_error_deg,
    true_correspondence,
)
from motion.registration import Reference
from motion.synth import time_warp
from tests.motion.body.conftest import WALK


def test_true_correspondence_of_a_motion_with_itself_is_the_warp():
    ref = Reference.from_bvh(WALK)
    shown = time_warp(60, ref.num_frames, 0.3, torch.Generator().manual_seed(4))
    assert torch.equal(true_correspondence(ref, shown, ref), shown)


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
