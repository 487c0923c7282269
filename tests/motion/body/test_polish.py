"""Gradient polish on the soft renderer: it pulls a posture a pixel or so off back toward
the observed one, and keeps the joints together."""

import numpy as np
import pytest
import torch

from experiments.nbp_single_image import NbpSingleImageConfig, _errors, _observe, _postures, _ring
from motion.body.polish import Polish, polish
from motion.draw import PART_COLOURS
from pgm import SE3
from pgm.rotations import qrotate


@pytest.fixture(scope="module")
def scene():
    cfg = NbpSingleImageConfig(frames=2, noise_deg=0)
    g = torch.Generator().manual_seed(0)
    spec, truth, _ = _postures(cfg, g)
    rig = _ring(cfg)
    return spec, rig, _observe(spec, rig, truth), truth


def test_polish_moves_a_perturbed_posture_toward_the_observation(scene):
    spec, rig, obs, truth = scene
    g = torch.Generator().manual_seed(1)
    start = SE3().perturb(truth, (0.015, 0.05), g)  # ~1 px and 3 degrees per part
    colours = torch.from_numpy(PART_COLOURS[:15].astype(np.float32) / 255)
    out = polish(spec, rig, obs, start, colours, Polish(steps=40))
    e2_start = _errors(spec, rig, truth, start)[0].mean()
    e2_out = _errors(spec, rig, truth, out)[0].mean()
    assert e2_out < 0.6 * e2_start, (e2_start, e2_out)
    assert _joint_gap(spec, out) < _joint_gap(spec, start)


def _joint_gap(spec, poses):
    """Mean distance between each joint seen from the parent and the child's origin."""
    e = spec.edges
    parent = poses[:, e[:, 0]]
    offsets = spec.offsets[e[:, 1]].expand(len(poses), -1, -1).to(poses)
    return (
        (parent[..., :3] + qrotate(parent[..., 3:], offsets) - poses[:, e[:, 1], :3])
        .norm(dim=-1)
        .mean()
    )


def test_polish_checks_its_inputs(scene):
    spec, rig, obs, truth = scene
    with pytest.raises(ValueError, match="poses have 1 frames; the observation 2"):
        polish(spec, rig, obs, truth[:1])
