"""The surface heat equation (docs/math.md §11) at its edges: the steps it takes, the inputs it
refuses, and the rates of the schemes in time at a fixed mesh.

Fast: spacing 0.4 and 0.2 (208 and 676 unknowns)."""

import numpy as np
import pytest

import cutfem
from cutfem.runs.registry import ProblemError


def _run(**kw):
    kw.setdefault("levels", [0.4])
    return cutfem.run("heat-surface-cut", **kw).records[0]


@pytest.mark.parametrize("levels, radius", [([1.5], 1.0), ([0.4], 0.05)])
def test_a_spacing_that_does_not_resolve_the_sphere_is_refused(levels, radius):
    """A background cell as large as the sphere gives a surface of the wrong topology (or, for a
    sphere inside one cell, no cut at all): refused with the fix, not a NaN load."""
    with pytest.raises(ValueError, match=r"too coarse to resolve the surface .*use a smaller spacing|larger than a cell \(refine the mesh\)"):
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
    from cutfem.solvers.diagnose import SolverError

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


def _sphere_matrices(spacing=0.4, tau_n=1.0):
    """M_h, A_h, the load G of the problem's source profile and the space, as the problem builds them."""
    from cutfem.geometry.cut import cut_mesh
    from cutfem.fem.forms import assemble
    from cutfem.fem.terms import load, mass, normal_gradient_penalty, tangential_stiffness
    from cutfem.geometry.shapes import Sphere
    from cutfem.geometry.markers import CUT
    from cutfem.geometry.box import structured_box
    from cutfem.problems.heat_surface import HeatSolution
    from cutfem.fem.spaces import CutSpace

    cut = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), Sphere(1.0))
    V, ds = CutSpace(cut, CUT), cut.ds()
    M = assemble(mass(ds) + tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=1), V)
    A = assemble(tangential_stiffness(ds) + tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=-1), V)
    return M, A, assemble(load(HeatSolution(1.0).source_profile, ds), V), V


@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_the_integral_follows_the_source_and_the_energy_decays(theta):
    """Testing with v = 1 (A 1 = 0 on the closed S_h, s(., 1) = 0): 1^T M u^n - 1^T M u^{n-1} =
    dt (theta a(t_n) + (1 - theta) a(t_{n-1})) 1^T G exactly; with G = 0 the integral is
    conserved and u^T M u does not grow, step by step."""
    from cutfem.problems.heat_surface import theta_steps
    from cutfem.solvers.direct import DirectSolver

    M, A, G, V = _sphere_matrices()
    T, N = 0.5, 10
    dt = T / N
    factor = DirectSolver((M + theta * dt * A).tocsr())
    step = lambda b, history: (factor.solve(b), 0)  # noqa: E731
    u0 = np.exp(V.dof_points @ np.array([0.6, 0.3, -0.4]))
    one = np.ones(V.n_dofs)
    u, _ = theta_steps(M, A, u0, G, lambda t: np.exp(-t), T, N, theta, step)
    t = T * np.arange(N + 1) / N
    law = one @ M @ u0 + dt * (theta * np.exp(-t[1:]) + (1 - theta) * np.exp(-t[:-1])).sum() * (one @ G)
    assert abs(one @ M @ u - law) <= 1e-12 * abs(law)
    masses, energies, u = [one @ M @ u0], [u0 @ M @ u0], u0
    for _ in range(N):  # one step at a time, no source
        u, _ = theta_steps(M, A, u, 0 * G, lambda t: 0.0, dt, 1, theta, step)
        masses.append(one @ M @ u)
        energies.append(u @ M @ u)
    assert np.ptp(masses) <= 1e-12 * abs(masses[0])
    assert np.all(np.diff(energies) < 0)


@pytest.mark.parametrize("theta, steps, rate", [(1.0, [8, 16, 32, 64], 1.0), (0.5, [16, 32, 64, 128], 2.0)])
def test_the_schemes_converge_at_their_order_in_time(theta, steps, rate):
    """At a fixed mesh (spacing 0.2) the nodal differences on S_h at T = 0.5 between N and 2N steps
    fall like dt (backward Euler, measured rates 0.98, 0.99) and dt^2 (Crank-Nicolson, 2.02, 2.00): the
    order of the scheme in time."""
    h = 0.2 if theta == 1.0 else 0.2**0.5  # dt_max = c h^2 or c h: c = dt_max / h^p

    def surface_u(n):
        rec = _run(levels=[0.2], theta=theta, dt_scale=0.5 / n / h**2, solver="direct")
        assert rec["time_steps"] == n
        return np.asarray(rec["fields"]["surface"].point_data["u_h"])

    u = [surface_u(n) for n in steps]
    diffs = np.array([np.abs(a - b).max() for a, b in zip(u, u[1:])])
    rates = np.log2(diffs[:-1] / diffs[1:])
    assert np.all(np.abs(rates - rate) <= 0.1), rates


def test_the_json_says_when_and_where_the_error_is_measured():
    """The record of a level gives the steps, the step and the final time the error is at; the
    JSON defines that error (it was 'not defined by the problem')."""
    res = cutfem.run("heat-surface-cut", levels=[0.4], final_time=0.3)
    data = res.to_json()
    rec = data["records"][0]
    assert (rec["time_steps"], rec["dt"], rec["final_time"]) == (2, 0.15, 0.3) == (2, 0.15, data["parameters"]["final_time"])
    assert data["definitions"]["l2_error"].startswith("||u_h(T) - u(T)^e||_L2(S_h) at the final time T")


def test_a_final_time_that_rounding_drowns_is_refused():
    """Backward Euler far past the decay ends at the constant of the initial integral: error
    3.8306423 at spacing 0.4 (T = 1e4).  Every step keeps the constants (seen by M_h alone) to eps dt k
    (k = 58 here) and the steps add these up: T = 1e12 gave 3.8231 in 7 steps.  Refused; at the
    longest T advised the constant comes back to 1e-6."""
    import re

    with pytest.raises(ProblemError, match=r"shorten --final-time to at most ([0-9.e+-]+)") as err:
        _run(final_time=1e12, dt_scale=1e12)
    longest = float(re.search(r"at most ([0-9.e+-]+)", str(err.value)).group(1))
    rec = _run(final_time=longest, dt_scale=longest)
    assert abs(rec["l2_error"] - 3.8306423) <= 1e-6 * 3.8306423
    assert abs(_run(final_time=1e4, dt_scale=1e4)["l2_error"] - 3.8306423) <= 1e-8 * 3.8306423


@pytest.mark.parametrize("spacing", [0.4, 0.1])
def test_the_fastest_time_scale_is_about_9_over_h_squared(spacing):
    """k = max row sum |A_h| / max (M_h 1), the scale check_final_time compares T with, is about
    9 h^-2 on the unit sphere (h the spacing), as its docstring says (it said 60 h^-2)."""
    from cutfem.geometry.cut import CUT, cut_mesh
    from cutfem.fem.forms import assemble
    from cutfem.fem.terms import mass, normal_gradient_penalty, tangential_stiffness
    from cutfem.geometry.shapes import Sphere
    from cutfem.geometry.box import structured_box
    from cutfem.fem.spaces import CutSpace

    cut = cut_mesh(structured_box([-1.1] * 3, [1.1] * 3, spacing=spacing), Sphere(1.0))
    V, ds = CutSpace(cut, CUT), cut.ds()
    M = assemble(mass(ds) + normal_gradient_penalty(cut.dx(CUT), h_power=1), V)
    A = assemble(tangential_stiffness(ds) + normal_gradient_penalty(cut.dx(CUT), h_power=-1), V)
    k = abs(A).sum(axis=1).max() / (M @ np.ones(V.n_dofs)).max()
    assert 7.5 < k * spacing**2 < 10.5


@pytest.mark.parametrize("kw, words", [
    (dict(final_time=0.0), "--final-time 0: the final time must be positive (default 0.5)"),
    (dict(dt_scale=0.0), "--dt-scale 0: the step dt_max = c h^2 or c h must be positive (default 1)"),
])
def test_a_zero_final_time_or_step_is_refused_by_name(kw, words):
    with pytest.raises(ProblemError) as err:
        _run(**kw)
    assert str(err.value) == words
