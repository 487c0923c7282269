"""Smoothing along time against independent answers: a dense weight matrix written out
from the Gaussian's formula, the circular mean of angles about one axis, and invariants
(constants, straight lines, rotations stay rotations)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from motion.smoothing import TRUNCATE_SIGMAS, smooth_rotations, smooth_values


def _dense_weights(n: int, sigma: float) -> np.ndarray:
    """Row t: the normalised weights of frames s with |t - s| <= ceil(3 sigma)."""
    t = np.arange(n)
    d = t[:, None] - t[None]
    w = np.exp(-0.5 * (d / sigma) ** 2) * (np.abs(d) <= math.ceil(TRUNCATE_SIGMAS * sigma))
    return w / w.sum(1, keepdims=True)


@pytest.mark.parametrize("n,sigma", [(1, 2.0), (7, 0.6), (40, 2.5), (25, 9.0)])
def test_values_are_the_dense_weighted_means(n, sigma):
    values = torch.randn(n, 3, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
    want = np.einsum("ts,sij->tij", _dense_weights(n, sigma), values.numpy())
    got = smooth_values(values, sigma)
    assert got.shape == values.shape and got.dtype == values.dtype
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)


def test_constants_stay_and_lines_stay_away_from_the_ends():
    line = torch.arange(30, dtype=torch.float64)[:, None] * torch.tensor([0.5, -2.0]) + 3.0
    sigma = 2.0
    r = math.ceil(TRUNCATE_SIGMAS * sigma)
    got = smooth_values(line, sigma)
    torch.testing.assert_close(got[r:-r], line[r:-r], rtol=0, atol=1e-12)
    const = torch.full((9, 4), 1.7, dtype=torch.float64)
    torch.testing.assert_close(smooth_values(const, 3.0), const, rtol=0, atol=1e-14)
    assert torch.equal(smooth_values(line, 0), line)


def test_rotations_about_one_axis_take_the_circular_mean_of_the_angles():
    n, sigma = 24, 2.0
    g = torch.Generator().manual_seed(0)
    angles = torch.linspace(-0.6, 0.9, n, dtype=torch.float64) + 0.2 * torch.randn(
        n, dtype=torch.float64, generator=g
    )
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -1.0, 0.5], dtype=torch.float64), dim=0)
    rot = axis_angle_to_rotation_matrix(angles[:, None] * axis)  # (T, 3, 3)
    w = _dense_weights(n, sigma)
    mean = np.arctan2(w @ np.sin(angles.numpy()), w @ np.cos(angles.numpy()))
    want = axis_angle_to_rotation_matrix(torch.from_numpy(mean)[:, None] * axis)
    got = smooth_rotations(rot[:, None], sigma)[:, 0]  # a joint axis in between
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_smoothed_rotations_are_rotations_and_constant_ones_stay():
    g = torch.Generator().manual_seed(1)
    base = axis_angle_to_rotation_matrix(torch.randn(5, 3, dtype=torch.float64, generator=g))
    noisy = (
        axis_angle_to_rotation_matrix(0.2 * torch.randn(50, 5, 3, dtype=torch.float64, generator=g))
        @ base
    )
    got = smooth_rotations(noisy, 3.0)
    eye = torch.eye(3, dtype=torch.float64).expand_as(got)
    torch.testing.assert_close(got.transpose(-1, -2) @ got, eye, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.det(got), torch.ones(50, 5, dtype=torch.float64))

    # the noise averages out: closer to the base than the noisy ones, on average
    def err(r):
        trace = (base.transpose(-1, -2) @ r).diagonal(dim1=-2, dim2=-1).sum(-1)
        return torch.acos(((trace - 1) / 2).clamp(-1, 1)).mean()

    assert float(err(got)) < 0.5 * float(err(noisy))
    still = base.expand(12, 5, 3, 3)
    torch.testing.assert_close(smooth_rotations(still, 2.0), still, rtol=0, atol=1e-12)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="sigma must be"):
        smooth_values(torch.zeros(4), -1.0)
    with pytest.raises(ValueError, match="sigma must be"):
        smooth_values(torch.zeros(4), math.inf)
    with pytest.raises(ValueError, match=r"\(T, \.\.\., 3, 3\)"):
        smooth_rotations(torch.zeros(4, 3), 1.0)
