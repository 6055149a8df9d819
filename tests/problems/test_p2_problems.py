"""The problems at order 2 (--order 2: P2 fields on the cut lifted by Theta_h; docs/math.md §17-§18):
coarse rates in the fast suite, three levels in the slow one."""

import numpy as np
import pytest

import cutfem


def _rates(res, key):
    return np.array(res.rates[key], dtype=float)


def test_poisson_cut_order_two_coarse_rates():
    """On the lifted Omega_h: L2 about h^3, H1 h^2."""
    res = cutfem.run("poisson-cut", levels=[0.4, 0.2], surface="sphere", order=2)
    r = res.records
    assert r[1]["l2_error"] < 1e-3 and r[1]["h1_error"] < 3e-2
    assert _rates(res, "l2_error")[-1] > 2.8 and _rates(res, "h1_error")[-1] > 1.8


def test_poisson_cut_order_one_is_unchanged_by_the_order_parameter():
    a = cutfem.run("poisson-cut", levels=[0.4], surface="sphere").records[0]
    b = cutfem.run("poisson-cut", levels=[0.4], surface="sphere", order=1).records[0]
    assert a["l2_error"] == b["l2_error"] and a["h1_error"] == b["h1_error"]


@pytest.mark.slow
def test_poisson_cut_order_two_rates():
    res = cutfem.run("poisson-cut", levels=[0.2, 0.1, 0.05], surface="sphere", order=2)
    assert np.all(_rates(res, "l2_error") > 2.9) and np.all(_rates(res, "h1_error") > 1.9)


def test_laplace_beltrami_cut_order_two_rates():
    """P2 trace fields on the lifted Theta_h(S_h), normal-gradient stabilization: L2 about h^3, H1 h^2."""
    res = cutfem.run("laplace-beltrami-cut", levels=[0.2, 0.1], surface="sphere", order=2, stabilization="normal")
    l2, h1 = _rates(res, "l2_error")[-1], _rates(res, "h1_error")[-1]
    assert l2 > 2.9 and h1 > 1.9
    assert res.records[1]["l2_error"] < 1e-4


@pytest.mark.slow
def test_interface_poisson_cut_order_two_rates():
    res = cutfem.run("interface-poisson-cut", levels=[0.2, 0.1], order=2)  # the interface term by the pair loop: 0.05 takes minutes
    for key in ("l2_error_inside", "l2_error_outside"):
        assert np.all(_rates(res, key) > 2.9)
    for key in ("h1_error_inside", "h1_error_outside"):
        assert np.all(_rates(res, key) > 1.9)
