import math

import pytest
import torch

from pgm import CountingSemiring, LogSemiring, MaxSemiring, TemperedSemiring
from pgm.semiring import Semiring

SEMIRINGS = [LogSemiring(), MaxSemiring(), TemperedSemiring(0.5), CountingSemiring()]


@pytest.mark.parametrize("semiring", SEMIRINGS, ids=lambda s: s.name)
@pytest.mark.parametrize("width", [1, 2, 5])
def test_window_sum_matches_explicit_loop(semiring, width):
    torch.manual_seed(0)
    x = semiring.from_log(torch.randn(3, 11, dtype=torch.float64))
    out = semiring.window_sum(x, width)
    for i in range(11):
        lo = max(0, i - width + 1)
        expected = semiring.sum(x[:, lo : i + 1], dim=-1)
        torch.testing.assert_close(out[:, i], expected)


@pytest.mark.parametrize("semiring", SEMIRINGS, ids=lambda s: s.name)
def test_cumsum_is_prefix_sum(semiring):
    torch.manual_seed(1)
    x = semiring.from_log(torch.randn(2, 9, dtype=torch.float64))
    out = semiring.cumsum(x, -1)
    for i in range(9):
        torch.testing.assert_close(out[:, i], semiring.sum(x[:, : i + 1], dim=-1))


def test_max_window_fast_path_equals_generic():
    torch.manual_seed(2)
    x = torch.randn(4, 1000)
    x[0, :5] = -math.inf
    fast = MaxSemiring().window_sum(x, 7)
    generic = Semiring.window_sum(MaxSemiring(), x, 7)
    torch.testing.assert_close(fast, generic)


def test_tempered_interpolates_between_log_and_max():
    torch.manual_seed(3)
    x = torch.randn(5, 20, dtype=torch.float64)
    torch.testing.assert_close(TemperedSemiring(1.0).sum(x, -1), LogSemiring().sum(x, -1))
    mx = MaxSemiring().sum(x, -1)
    for tau in [0.1, 0.01, 0.001]:
        gap = TemperedSemiring(tau).sum(x, -1) - mx
        # max <= tau * logsumexp(x / tau) <= max + tau * log(n)
        assert (gap >= -1e-12).all()
        assert (gap <= tau * math.log(20) + 1e-12).all()


def test_max_is_below_logsumexp():
    x = torch.randn(100, 7, dtype=torch.float64)
    assert (MaxSemiring().sum(x, -1) <= LogSemiring().sum(x, -1)).all()


def test_counting_maps_forbidden_to_zero():
    x = torch.tensor([0.0, -math.inf, 3.0])
    assert CountingSemiring().from_log(x).tolist() == [1.0, 0.0, 1.0]


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_tempered_rejects_bad_temperature(bad):
    with pytest.raises(ValueError, match="temperature"):
        TemperedSemiring(bad)
