"""stokes-cut: P1-P1 Stokes in a cut ball with Nitsche, ghost penalties, a Brezzi-Pitkaranta
pressure stabilization and a mean-value multiplier, solved by block-preconditioned MINRES.  Rates
against the manufactured solution (u = curl A, divergence free) and MINRES's iterations under
refinement."""

import numpy as np
import pytest

import cutfem as cf
from cutfem.problems.stokes import PRESSURE, VELOCITY


def test_the_manufactured_velocity_is_divergence_free():
    x = np.random.default_rng(0).uniform(-1, 1, (20, 3))
    np.testing.assert_allclose(VELOCITY.div(x), 0.0, atol=1e-14)
    assert PRESSURE(x).shape == (20,)


def test_rates_and_iterations_on_two_levels():
    result = cf.run("stokes-cut", levels=[0.2, 0.1], solver="minres")
    rates = {k: v[0] for k, v in result.rates.items()}
    # measured: 2.04, 1.13, 2.02
    assert rates["l2_error_velocity"] > 1.7 and rates["h1_error_velocity"] > 0.9 and rates["l2_error_pressure"] > 1.0
    iterations = [r["solver_iterations"] for r in result.records]
    assert all(r["solver"] == "minres" for r in result.records) and max(iterations) <= 60


def test_minres_and_the_factorization_agree():
    direct = cf.run("stokes-cut", levels=[0.2], solver="direct").records[0]
    minres = cf.run("stokes-cut", levels=[0.2], solver="minres").records[0]
    for key in ("l2_error_velocity", "h1_error_velocity", "l2_error_pressure"):
        assert minres[key] == pytest.approx(direct[key], rel=1e-6)


@pytest.mark.slow
def test_iterations_flat_over_three_levels():
    result = cf.run("stokes-cut", levels=[0.2, 0.1, 0.05], solver="minres")
    iterations = [r["solver_iterations"] for r in result.records]
    assert max(iterations) <= 60 and max(iterations) / min(iterations) <= 1.3, iterations
    assert result.rates["l2_error_velocity"][-1] > 1.8 and result.rates["h1_error_velocity"][-1] > 0.95
