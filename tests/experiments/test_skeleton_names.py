"""The held-back evaluation set names the CMU skeleton as cgspeed's 3ds Max-friendly
conversion does (LeftHip, LeftKnee, Chest2, lowerneck, LeftWrist, lhand, ...); the bundled
files use its MotionBuilder names. Only the names differ, so a registration of another
performer must not move by a bit between the two."""

from __future__ import annotations

import dataclasses

import torch

from experiments.register_synthetic import (
    SyntheticStudentConfig,
    registration_settings,
    synthetic_inputs,
    true_differences,
)
from motion.bvh import read_bvh, write_bvh
from motion.registration import register
from motion.registration.polish import PosturePolishSettings
from motion.registration.refine import RefineSettings
from tests.motion.test_bad_input import MB_TO_MAX

WALKS = ("motion/data/cmu_02_01_walk.bvh", "motion/data/cmu_07_01_walk.bvh")


def _renamed(path: str, folder) -> str:
    bvh = read_bvh(path)
    out = folder / path.rsplit("/", 1)[-1]
    write_bvh(dataclasses.replace(bvh, names=[MB_TO_MAX.get(n, n) for n in bvh.names]), out)
    return str(out)


def test_another_performer_registers_bit_for_bit_alike_under_3ds_max_names(tmp_path):
    """Subject 7's walk against subject 2's, 6 frames, cheap settings (stage 3's C on, the
    polish on): C, T, the local rotations and the fit equal those of the bundled names, and
    so do the true clinical-angle differences the findings are scored against."""
    results, truths = [], []
    for reference, student in (WALKS, tuple(_renamed(p, tmp_path) for p in WALKS)):
        cfg = SyntheticStudentConfig(
            reference=reference, student=student, frames=6, size=[96, 72], focal_px=135.0
        )
        inputs = synthetic_inputs(cfg)
        settings = registration_settings(
            cfg,
            refine=RefineSettings(particles=25, iterations=1, restarts=1),
            polish=PosturePolishSettings(steps=5),
        )
        results.append(register(inputs.reference, inputs.video, settings=settings))
        truths.append(true_differences(inputs.reference, inputs.student, inputs.truth))
    mb, mx = results
    assert torch.equal(mb.C, mx.C) and torch.equal(mb.C_stage1, mx.C_stage1)
    for field in ("T_rotation", "T_translation", "rotations", "fit"):
        assert torch.equal(getattr(mb, field), getattr(mx, field)), field
    torch.testing.assert_close(truths[0], truths[1], rtol=0, atol=0)
