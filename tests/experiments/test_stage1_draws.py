"""stage1_draws runs stages 0-1 exactly as register() does: the same C for the same seed."""

from __future__ import annotations

import torch

from experiments.register_synthetic import registration_settings, synthetic_inputs
from experiments.stage1_draws import Stage1DrawsConfig, stage1_c
from motion.registration import register
from motion.registration.polish import PosturePolishSettings
from motion.registration.refine import RefineSettings


def test_stage1_c_is_the_c_register_starts_from_for_the_same_seed():
    cfg = Stage1DrawsConfig(frames=8, draws=1, size=[160, 120], focal_px=225.0)
    inputs = synthetic_inputs(cfg)
    seed = 3
    cheap = RefineSettings(particles=8, iterations=1, restarts=1, refine_c=False)
    settings = registration_settings(
        cfg, refine=cheap, polish=PosturePolishSettings(steps=0), seed=seed
    )
    result = register(inputs.reference, inputs.video, settings=settings)
    c = stage1_c(inputs.reference, inputs.video, cfg, seed)
    assert torch.equal(c, result.C_stage1)
    other = stage1_c(inputs.reference, inputs.video, cfg, seed + 1)
    assert other.shape == c.shape  # another seed: another draw, the same frames
