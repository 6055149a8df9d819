"""heat-moving-cut: the heat equation in a translating ball (Eulerian BDF, ghost-penalty strip).
Rates of the error at the final time against the manufactured solution: BDF2 with dt = h / 2 and
BDF1 with dt = 2 h^2 reach 2 in L2 and 1 in H1."""

import numpy as np
import pytest

import cutfem as cf
from cutfem.runs.registry import ProblemError


def rates(result, key):
    return [r for r in result.rates[key] if r is not None]


def test_bdf2_converges_at_rate_two():
    result = cf.run("heat-moving-cut", levels=[0.1, 0.05])
    (l2,), (h1,) = rates(result, "l2_error"), rates(result, "h1_error")
    assert l2 > 1.8 and h1 > 0.9  # 2.09 and 1.11 here
    first, last = result.records
    assert last["steps"] == 2 * first["steps"] and np.isclose(last["dt"], 0.025)
    assert last["strip_facets"] > 0 and last["solver_iterations"] >= 0


@pytest.mark.slow
def test_bdf1_and_bdf2_over_three_levels():
    bdf2 = cf.run("heat-moving-cut", levels=[0.2, 0.1, 0.05], order=2)
    assert rates(bdf2, "l2_error")[-1] > 1.8
    bdf1 = cf.run("heat-moving-cut", levels=[0.1, 0.05], order=1, dt_factor=2.0)
    assert rates(bdf1, "l2_error")[-1] > 1.8  # 2.00 here


def test_a_ball_that_leaves_the_box_is_refused():
    with pytest.raises(ProblemError, match="leave the box"):
        cf.run("heat-moving-cut", levels=[0.2], final_time=3.0)
