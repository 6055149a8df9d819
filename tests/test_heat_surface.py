"""The surface heat equation (docs/math.md §11) at its edges: the steps it takes, the inputs it
refuses, and the rates of the schemes in time at a fixed mesh.

Fast: spacing 0.4 and 0.2 (208 and 676 unknowns)."""

import numpy as np
import pytest

import cutfem
from cutfem.registry import ProblemError


def _run(**kw):
    kw.setdefault("levels", [0.4])
    return cutfem.run("heat-surface-cut", **kw).records[0]


@pytest.mark.parametrize("levels, radius", [([1.5], 1.0), ([0.4], 0.05)])
def test_a_spacing_that_does_not_resolve_the_sphere_is_refused(levels, radius):
    """A background cell as large as the sphere gives a surface of the wrong topology (and a node
    at the centre, where the closest point is undefined): refused with the fix, not a NaN load."""
    with pytest.raises(ProblemError, match=r"too coarse to resolve the surface .*use a smaller spacing"):
        _run(levels=levels, radius=radius)


def test_the_steps_end_exactly_at_the_final_time():
    """dt = T / ceil(T / dt_max): 0.5 / ceil(0.5 / 0.16) = 0.125 in 4 steps; a dt_max beyond T is one
    step of T; 0.3 / ceil(0.3 / 0.16) = 0.15.  The record's final time is the one the error is at."""
    rec = _run()
    assert (rec["time_steps"], rec["dt"], rec["final_time"]) == (4, 0.125, 0.5)
    rec = _run(dt_scale=100.0)
    assert (rec["time_steps"], rec["dt"], rec["final_time"]) == (1, 0.5, 0.5)
    rec = _run(final_time=0.3)
    assert (rec["time_steps"], rec["dt"], rec["final_time"]) == (2, 0.15, 0.3)


@pytest.mark.parametrize(
    "kw",
    [
        dict(dt_scale=5e-324),  # dt_max = 0 in floating point
        dict(dt_scale=1e-320),  # T / dt_max = inf
        dict(final_time=1e300, dt_scale=1e-300),
        dict(dt_scale=1e-9),  # 3.1e9 steps: finite, but days
        dict(levels=[0.2], theta=0.5, dt_scale=1e-7),  # 2.5e7 steps
    ],
)
def test_a_step_count_that_cannot_finish_is_refused_with_the_fix(kw):
    with pytest.raises(ProblemError, match=r"time steps .* raise --dt-scale to at least [0-9.e+-]+ or shorten --final-time") as err:
        _run(**kw)
    print(err.value)


def test_the_advice_of_a_refused_step_count_is_the_largest_step_that_runs():
    """3.1e9 steps of 1.6e-10 at spacing 0.4 are refused: dt_scale >= 0.5 / (1e6 * 0.4^2) = 3.125e-6
    (rounded up) takes at most the 1e6 steps a level runs, and not many fewer.  At spacing 0.05
    (11 824 unknowns) the bound is the 1e10 unknowns x steps: 845 737 steps."""
    import math
    import re

    with pytest.raises(ProblemError, match=r"more than the 1000000 a level takes") as err:
        _run(dt_scale=1e-9)
    need = float(re.search(r"at least ([0-9.e+-]+)", str(err.value)).group(1))
    assert 0.999e6 < math.ceil(0.5 / (need * 0.16)) <= 1_000_000
    with pytest.raises(ProblemError, match=r"9e\+05 time steps .* on 11824 unknowns, more than the 845737 a level takes"):
        _run(levels=[0.05], dt_scale=0.5 / 9e5 / 0.05**2)


@pytest.mark.parametrize("solver", ["direct", "cg-mg"])
def test_no_stabilization_is_refused_naming_the_null_vector(solver):
    """tau_N = 0 leaves M_h and A_h the common null vector phi_h (the P1 level set, zero on S_h):
    the factorization and the multigrid say so and name the term that removes it."""
    from cutfem.solve import SolverError

    with pytest.raises(SolverError, match=r"the nodal vector of phi_h \(zero on S_h\) is a null vector.*"
                                          r"Add a stabilization that acts on it \(.*the normal-gradient term") as err:
        _run(levels=[0.2], tau_n=0.0, solver=solver)
    assert err.value.cause == "singular"


def test_jacobi_cg_without_stabilization_gives_the_surface_solution():
    """Jacobi-CG on the consistent singular steps never meets the null vector phi_h; it is zero on
    S_h, so the error there is that of a vanishing stabilization (measured 2e-8 relative)."""
    bare = _run(levels=[0.2], tau_n=0.0, solver="cg-jacobi")
    tiny = _run(levels=[0.2], tau_n=1e-8, solver="direct")
    assert abs(bare["l2_error"] - tiny["l2_error"]) <= 1e-6 * tiny["l2_error"]
