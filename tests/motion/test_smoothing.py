"""Smoothing along time against independent answers: a dense weight matrix written out
from the Gaussian's formula, NumPy's weighted least-squares line (``np.polyfit``) for the
local linear fit, the circular mean of angles about one axis, and invariants (constants,
straight lines, rotations stay rotations)."""

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


def _line_weights(n: int, sigma: float) -> np.ndarray:
    """Row t: the weights the local linear fit gives each frame, from the normal equations
    of the weighted least-squares line through the frames the kernel reaches (its value at
    t: ``e0^T (X^T W X)^-1 X^T W``, ``X = [1, s - t]``)."""
    rows = []
    for t in range(n):
        d = np.arange(n) - t
        w = np.exp(-0.5 * (d / sigma) ** 2) * (np.abs(d) <= math.ceil(TRUNCATE_SIGMAS * sigma))
        x = np.stack([np.ones(n), d], 1)
        rows.append(np.linalg.solve(x.T @ (w[:, None] * x), x.T * w)[0])
    return np.stack(rows)


@pytest.mark.parametrize("n,sigma", [(1, 2.0), (7, 0.6), (40, 2.5), (25, 9.0)])
def test_values_are_the_dense_weighted_means(n, sigma):
    values = torch.randn(n, 3, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
    want = np.einsum("ts,sij->tij", _dense_weights(n, sigma), values.numpy())
    got = smooth_values(values, sigma, fit="constant")
    assert got.shape == values.shape and got.dtype == values.dtype
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("n,sigma", [(2, 2.0), (3, 0.6), (7, 0.6), (40, 2.5), (25, 9.0)])
def test_the_linear_fit_is_numpys_weighted_least_squares_line(n, sigma):
    """Each frame: np.polyfit's degree-1 fit to the frames the kernel reaches, weighted by
    the Gaussian (polyfit weighs residuals, so by its square root), evaluated at the frame."""
    values = torch.randn(n, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
    reach = math.ceil(TRUNCATE_SIGMAS * sigma)
    want = np.empty((n, 2))
    for t in range(n):
        s = np.arange(max(0, t - reach), min(n, t + reach + 1))
        w = np.exp(-0.5 * ((s - t) / sigma) ** 2)
        for k in range(2):
            want[t, k] = np.polyval(np.polyfit(s, values[s, k].numpy(), 1, w=np.sqrt(w)), t)
    got = smooth_values(values, sigma)
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-10)


def test_the_linear_fit_keeps_a_trend_to_the_ends_and_is_the_mean_inside():
    """A steady movement keeps its rate to the last frame (the weighted mean lags there by
    well over a frame's worth); where the kernel is whole the two fits are the same numbers;
    one frame, or a kernel far narrower than a frame, returns the values."""
    line = torch.arange(30, dtype=torch.float64)[:, None] * torch.tensor([0.5, -2.0]) + 3.0
    sigma = 2.5
    r = math.ceil(TRUNCATE_SIGMAS * sigma)
    torch.testing.assert_close(smooth_values(line, sigma), line, rtol=0, atol=1e-12)
    lag = (smooth_values(line, sigma, fit="constant") - line)[-1, 0] / 0.5  # frames
    assert -0.8 * sigma - 0.2 < lag < -0.6 * sigma  # E|d| of a half Gaussian, 0.8 sigma
    noisy = torch.randn(30, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    inside = slice(r, 30 - r)
    assert torch.equal(
        smooth_values(noisy, sigma)[inside], smooth_values(noisy, sigma, fit="constant")[inside]
    )
    assert torch.equal(smooth_values(noisy[:1], sigma), noisy[:1])
    torch.testing.assert_close(smooth_values(noisy, 0.05), noisy, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="fit must be one of"):
        smooth_values(noisy, sigma, fit="quadratic")


def test_constants_stay_and_lines_stay_away_from_the_ends():
    line = torch.arange(30, dtype=torch.float64)[:, None] * torch.tensor([0.5, -2.0]) + 3.0
    sigma = 2.0
    r = math.ceil(TRUNCATE_SIGMAS * sigma)
    got = smooth_values(line, sigma, fit="constant")
    torch.testing.assert_close(got[r:-r], line[r:-r], rtol=0, atol=1e-12)
    const = torch.full((9, 4), 1.7, dtype=torch.float64)
    for fit in ("constant", "linear"):
        torch.testing.assert_close(smooth_values(const, 3.0, fit), const, rtol=0, atol=1e-14)
    assert torch.equal(smooth_values(line, 0), line)


@pytest.mark.parametrize("fit", ["constant", "linear"])
def test_rotations_about_one_axis_take_the_circular_mean_of_the_angles(fit):
    """Weighted by the fit's own weights (the linear fit's are negative at the ends: it
    extrapolates the turn)."""
    n, sigma = 24, 2.0
    g = torch.Generator().manual_seed(0)
    angles = torch.linspace(-0.6, 0.9, n, dtype=torch.float64) + 0.2 * torch.randn(
        n, dtype=torch.float64, generator=g
    )
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -1.0, 0.5], dtype=torch.float64), dim=0)
    rot = axis_angle_to_rotation_matrix(angles[:, None] * axis)  # (T, 3, 3)
    w = _dense_weights(n, sigma) if fit == "constant" else _line_weights(n, sigma)
    mean = np.arctan2(w @ np.sin(angles.numpy()), w @ np.cos(angles.numpy()))
    want = axis_angle_to_rotation_matrix(torch.from_numpy(mean)[:, None] * axis)
    got = smooth_rotations(rot[:, None], sigma, fit)[:, 0]  # a joint axis in between
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
