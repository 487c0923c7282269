import itertools
import math

import pytest

from pgm.schedules import Constant, Geometric, Linear, Stepwise


def test_geometric_has_a_constant_ratio_and_holds_its_end():
    s = Geometric(1.0, 0.01, 5)
    values = [s(n) for n in range(7)]
    ratios = [b / a for a, b in itertools.pairwise(values[:5])]
    assert values[0] == 1.0 and values[4] == pytest.approx(0.01) and values[6] == 0.01
    assert all(r == pytest.approx(0.01**0.25) for r in ratios)


def test_linear_and_stepwise_and_constant():
    assert [Linear(2.0, 1.0, 3)(n) for n in range(4)] == [2.0, 1.5, 1.0, 1.0]
    assert [Stepwise([3, 2, 1])(n) for n in range(5)] == [3.0, 2.0, 1.0, 1.0, 1.0]
    assert Constant()(10) == 1.0
    assert Geometric(1.0, 0.5, 1)(0) == 0.5


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_schedules_reject_non_positive_values(bad):
    with pytest.raises(ValueError, match="finite number > 0"):
        Geometric(bad, 1.0, 3)
    with pytest.raises(ValueError, match="finite number > 0"):
        Stepwise([1.0, bad])
    with pytest.raises(ValueError, match="steps must be an int >= 1"):
        Linear(1.0, 2.0, 0)
