"""The problems at order 2 (--order 2: P2 fields on the cut lifted by Theta_h; docs/math.md §17-§18):
coarse rates in the fast suite, three levels in the slow one."""

import numpy as np
import pytest

import cutfem
from cutfem.runs.registry import ProblemError


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
    """P2 trace fields on the lifted Theta_h(S_h), the order-2 default (auto: the normal-gradient term
    tau_N h^-1, tau_N = 1), CG with the multigrid: L2 4.05e-4, 4.53e-5 (rate 3.16), H1 1.31e-2, 3.24e-3
    (rate 2.02), 13 iterations at both spacings."""
    res = cutfem.run("laplace-beltrami-cut", levels=[0.2, 0.1], surface="sphere", order=2, solver="cg-mg")
    l2, h1 = _rates(res, "l2_error")[-1], _rates(res, "h1_error")[-1]
    assert 2.9 < l2 < 3.4 and 1.9 < h1 < 2.2
    assert res.records[1]["l2_error"] < 6e-5
    assert all(r["solver"] == "cg-mg" and r["solver_iterations"] <= 20 for r in res.records), res.records


def test_laplace_beltrami_cut_stabilization_by_order():
    """auto is the face term at order 1 and the normal-gradient term at order 2: a face parameter beside
    it at order 2 is refused (it would be ignored), and at order 1 auto's record equals face's."""
    with pytest.raises(ProblemError, match="pass --stabilization face"):
        cutfem.run("laplace-beltrami-cut", levels=[0.4], order=2, tau_f=1.0)
    auto = cutfem.run("laplace-beltrami-cut", levels=[0.4], solver="direct").records[0]
    face = cutfem.run("laplace-beltrami-cut", levels=[0.4], stabilization="face", solver="direct").records[0]
    assert auto["l2_error"] == face["l2_error"] and auto["h1_error"] == face["h1_error"]


@pytest.mark.slow
def test_interface_poisson_cut_order_two_rates():
    res = cutfem.run("interface-poisson-cut", levels=[0.2, 0.1], order=2)  # the interface term by the pair loop: 0.05 takes minutes
    for key in ("l2_error_inside", "l2_error_outside"):
        assert np.all(_rates(res, key) > 2.9)
    for key in ("h1_error_inside", "h1_error_outside"):
        assert np.all(_rates(res, key) > 1.9)


def test_mean_curvature_cut_order_two_coarse_rate():
    """The paper's torus, P2 on the lifted cut, the order-2 default (face term with a = 1: first and second
    normal-derivative jumps weighted h, h^3 / 4; plus tau_N h J_N, tau_N = 1): L2 2.20e-1, 2.66e-2 at 0.2,
    0.1 (rate 3.04; the P1 cut torus: about 1.3), CG with the multigrid 27 iterations at both, and
    int H_h = 0 to round-off."""
    res = cutfem.run("mean-curvature-cut", levels=[0.2, 0.1], order=2, solver="cg-mg")
    r = res.records
    assert 2.7 < _rates(res, "l2_error")[-1] < 3.4 and r[1]["l2_error"] < 3e-2
    assert all(rec["solver_iterations"] <= 32 for rec in r), r
    assert all(np.abs(rec["integral_H"]).max() < 1e-10 for rec in r)


def test_mean_curvature_cut_stabilization_by_order():
    """auto is the face term, its power a fixed to 1 at order 2: a --face-h-power beside it there is
    refused (it would be ignored); the normal-gradient parameters go with --stabilization normal only."""
    with pytest.raises(ProblemError, match="--stabilization face with --face-h-power"):
        cutfem.run("mean-curvature-cut", levels=[0.2], order=2, face_h_power=2.0)
    with pytest.raises(ProblemError, match="applies only with --stabilization"):
        cutfem.run("mean-curvature-cut", levels=[0.2], tau_n=1.0)


@pytest.mark.slow
def test_mean_curvature_cut_order_two_rates():
    """Three levels on the paper's torus, the order-2 default: L2 2.20e-1, 2.66e-2, 2.60e-3 (rates 3.04, 3.36; ngsxfem with its normal-gradient term: 1.5e-1, 3.5e-2, 6.6e-3)."""
    res = cutfem.run("mean-curvature-cut", levels=[0.2, 0.1, 0.05], order=2)
    assert np.all(_rates(res, "l2_error") > 2.1) and res.records[-1]["l2_error"] < 4e-3


def test_poisson_cut_order_two_default_ghost_penalty_is_the_accurate_one():
    """At order 2 gamma_g defaults to 0.01 (poisson_cut's docstring): its L2 error at spacing 0.2 is
    0.60 times that of the order-1 default 0.1 (5.0e-4 against 8.4e-4), below ngsxfem's 8.5e-4 with the
    same jump penalty and within 10 % of its patch penalty's 4.6e-4."""
    default = cutfem.run("poisson-cut", levels=[0.2], order=2).records[0]
    strong = cutfem.run("poisson-cut", levels=[0.2], order=2, gamma_g=0.1).records[0]
    explicit = cutfem.run("poisson-cut", levels=[0.2], order=2, gamma_g=0.01).records[0]
    assert default["l2_error"] == explicit["l2_error"]
    assert default["l2_error"] < 0.65 * strong["l2_error"] and default["l2_error"] < 5.1e-4
    assert default["h1_error"] < 0.8 * strong["h1_error"]


def test_mean_curvature_cut_refuses_the_edge_penalty_at_order_two():
    """J_E has its P1 form only: --tau-e at --order 2 is refused before the geometry, naming the fix."""
    with pytest.raises(ProblemError, match="--tau-e 0.1 at --order 2.*leave --tau-e out"):
        cutfem.run("mean-curvature-cut", levels=[0.4], order=2, tau_e=0.1)
