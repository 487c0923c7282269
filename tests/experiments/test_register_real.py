"""register_real's comparison of clinical angles with another model's (OpenSim's .mot):
the RMSE, the RMSE once the constant offset is taken out, and the leg means, against
closed-form values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from experiments.register_real import LEG_FLEXION, RegisterRealConfig, _overrides, rmse_against
from motion.angles import ClinicalAngles
from motion.registration.config import load_config
from motion.settings import ConfigError


def test_rmse_against_another_model_splits_off_a_constant_offset():
    frames = 200
    t = np.arange(frames) * (4 * np.pi / frames)  # whole periods of every wave
    names = ["knee_angle_r", "hip_flexion_r", "arm_flex_r"]
    other = np.stack([40 * np.sin(t), 20 * np.cos(t), 10 * np.sin(2 * t)], -1)
    wiggle = 3 * np.sin(7 * t)  # RMS 3 / sqrt(2) over whole periods
    ours = other.copy()
    ours[:, 0] += 8.0 + wiggle  # a neutral 8 degrees apart, and a shape error
    ours[:, 1] += 2.0  # the neutral only
    angles = ClinicalAngles(names, torch.from_numpy(ours), torch.zeros(frames, 3, 3, 3))
    # the other model names its columns in another order, has one more, and 10 more frames
    columns = ["time", "arm_flex_r", "hip_flexion_r", "knee_angle_r"]
    rows = np.concatenate([t[:, None], other[:, ::-1]], 1)
    rows = np.concatenate([rows, np.zeros((10, 4))])
    out = rmse_against(angles, columns, rows, "x")
    shape = 3 / math.sqrt(2)
    assert out["x_knee_angle_r"] == pytest.approx(math.sqrt(8.0**2 + shape**2), rel=1e-3)
    assert out["x_centred_knee_angle_r"] == pytest.approx(shape, rel=1e-3)
    assert out["x_hip_flexion_r"] == pytest.approx(2.0)
    assert out["x_centred_hip_flexion_r"] == pytest.approx(0.0, abs=1e-9)
    assert out["x_arm_flex_r"] == pytest.approx(0.0, abs=1e-9)
    # the leg mean is over the leg flexion coordinates both give: the knee's and the hip's
    assert {"knee_angle_r", "hip_flexion_r"} <= set(LEG_FLEXION) and "arm_flex_r" not in LEG_FLEXION
    legs = (out["x_knee_angle_r"] + out["x_hip_flexion_r"]) / 2
    assert out["x_leg_flexion_mean"] == pytest.approx(legs)
    assert out["x_centred_leg_flexion_mean"] == pytest.approx(shape / 2, rel=1e-3)
    assert "x_time" not in out and "x_centred_time" not in out


def test_any_register_setting_reaches_the_command_line_after_the_fields():
    """``registration:`` adds ``motion register`` settings by their dotted keys, after the
    experiment's own (so they win); the command's parser reads them as a user's."""
    cfg = RegisterRealConfig(
        polish_steps=50, registration={"polish.steps": "7", "refine.articulation_std": "0.2"}
    )
    overrides = _overrides(cfg, 240)
    assert overrides[-2:] == ("polish.steps=7", "refine.articulation_std=0.2")
    settings = load_config(None, list(overrides)).registration
    assert settings.polish.steps == 7 and settings.refine.articulation_std == 0.2
    with pytest.raises(ConfigError, match="articulation_sd"):
        load_config(
            None,
            list(_overrides(RegisterRealConfig(registration={"refine.articulation_sd": "1"}), 240)),
        )
