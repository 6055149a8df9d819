"""Tests for cutfem.solvers.solve (direct and iterative solvers, singularity reports, condition numbers)
and for cutfem.fem.norms (error functionals and rates).

References: scipy's spsolve and dense numpy eigenvalues computed in the test, exact areas summed
from the triangles, exact rates of synthetic data, the known O(h^2) interpolation error.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import discrete_error, fitted_rate, h1_error, l2_error, l2_h1_errors, rates, surface_integral
from cutfem.geometry.levelset import Sphere, Torus
from cutfem.geometry.markers import NEG
from cutfem.geometry.mesh import structured_box
from cutfem.solvers.solve import CGSolver, DirectSolver, SolverError, cg_solve, condition_number, solve
from cutfem.fem.spaces import CutP1Space, SurfaceP1Space
from cutfem.geometry.surface import sphere_mesh
from surface_matrices import face_matrix, mass_matrix, stiffness_matrix


@pytest.fixture(scope="module")
def cut_torus():
    return CutP1Space(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1), Torus()))


@pytest.fixture(scope="module")
def systems(cut_torus):
    """SPD systems: meshed Laplace-Beltrami A + M, stabilized cut mass and cut Laplace-Beltrami."""
    S = SurfaceP1Space(sphere_mesh(4))
    V = cut_torus
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    return {
        "meshed-lb": stiffness_matrix(S) + mass_matrix(S),
        "cut-mass": M + 0.1 * J,
        "cut-lb": A + M + 0.1 * J,
    }


@pytest.fixture(scope="module")
def small_cut_sphere():
    return CutP1Space(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02])))


# ----------------------------------------------------------------------------------------------
# direct solver
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["meshed-lb", "cut-mass", "cut-lb"])
def test_direct_solver_reuse_matches_spsolve(systems, name):
    A = systems[name]
    rng = np.random.default_rng(0)
    B = rng.normal(size=(A.shape[0], 3))
    solver = DirectSolver(A)
    X = solver.solve(B)
    assert X.shape == B.shape
    for c in range(3):
        ref = spla.spsolve(sp.csc_matrix(A), B[:, c])
        np.testing.assert_allclose(X[:, c], ref, rtol=0, atol=1e-9 * np.abs(ref).max())
        np.testing.assert_allclose(solver.solve(B[:, c]), ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    assert 0 < solver.smallest_pivot <= 1.0 + 1e-12  # pivots of the unit-diagonal scaled matrix
    X2, info = solve(A, B, method="direct")
    assert info.method == "direct" and info.residual < 1e-12
    np.testing.assert_allclose(X2, X, rtol=0, atol=1e-12 * np.abs(X).max())


def test_zero_diagonal_is_reported_singular(small_cut_sphere):
    """An unknown without support on S_h has a zero row: SolverError with smallest 0."""
    V = small_cut_sphere
    S = (mass_matrix(V) + 0.1 * face_matrix(V)).tolil()
    S[5, :] = 0.0
    S[:, 5] = 0.0
    S = S.tocsr()
    with pytest.raises(SolverError, match="zero") as err:
        DirectSolver(S)
    assert err.value.smallest == 0.0
    with pytest.raises(SolverError):
        solve(S, np.ones(V.n_dofs), method="direct")
    assert condition_number(S) == np.inf


def test_unstabilized_cut_mass_is_reported_singular(small_cut_sphere):
    V = small_cut_sphere
    M = mass_matrix(V)
    with pytest.raises(SolverError, match="numerically singular") as err:
        DirectSolver(M)
    # relative to a largest pivot of order one: a round-off zero, of either sign (the element matrices are
    # positive semidefinite only up to rounding); a negative one below -1e-10 would be called indefinite
    assert abs(err.value.smallest) < 1e-12 and err.value.cause == "singular"
    DirectSolver(M + 0.1 * face_matrix(V))  # stabilized: no error


def test_plane_on_a_node_layer_is_reported_singular():
    """phi = z cut along a layer of nodes (the zero rule puts S_h in tet faces): the nodes below
    the layer carry basis functions that vanish on S_h, the unstabilized system is singular."""
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=8)
    V = CutP1Space(cut_mesh(box, lambda x: x[..., 2], check_boundary=False))
    below = V.dof_points[:, 2] < 0
    assert below.any()
    M = mass_matrix(V)
    assert np.abs(M.diagonal()[below]).max() < 1e-25 * M.diagonal().max()
    with pytest.raises(SolverError) as err:
        DirectSolver(M)
    assert err.value.smallest < 1e-12


# ----------------------------------------------------------------------------------------------
# iterative solvers
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preconditioner", ["jacobi", "amg"])
@pytest.mark.parametrize("name", ["meshed-lb", "cut-mass", "cut-lb"])
def test_cg_agrees_with_direct(systems, name, preconditioner):
    A = systems[name]
    rng = np.random.default_rng(1)
    B = rng.normal(size=(A.shape[0], 2))
    X_direct = DirectSolver(A).solve(B)
    X, info = cg_solve(A, B, preconditioner=preconditioner, tol=1e-10)
    assert info.method == f"cg-{preconditioner}" and info.iterations > 0
    # CG stops on its recursive residual; the true one agrees up to round-off
    assert info.residual <= 1.5e-10
    for c in range(2):
        assert np.linalg.norm(A @ X[:, c] - B[:, c]) <= 1.5e-10 * np.linalg.norm(B[:, c])
    # error <= cond * residual; the scaled condition numbers here are below 1e4
    assert np.linalg.norm(X - X_direct) <= 1e-6 * np.linalg.norm(X_direct)


@pytest.mark.parametrize("preconditioner", ["jacobi", "amg"])
def test_cg_solver_reuses_its_preconditioner_and_starts_from_a_guess(systems, preconditioner):
    """One CGSolver for several right-hand sides: the setup is counted once; from the exact solution
    as guess no iteration is needed; from a guess the result meets the same tolerance, with fewer
    iterations the closer the guess."""
    A = systems["cut-lb"]
    rng = np.random.default_rng(2)
    B = rng.normal(size=(A.shape[0], 2))
    X_direct = DirectSolver(A).solve(B)
    cg = CGSolver(A, preconditioner, tol=1e-10)
    assert cg.setup > 0 and cg.method == f"cg-{preconditioner}"
    X0, first = cg.solve(B)
    assert first.setup == cg.setup and first.seconds >= first.setup
    X1, again = cg.solve(B[:, 0])
    assert again.setup == 0.0 and X1.shape == (A.shape[0],)
    np.testing.assert_array_equal(X1, X0[:, 0])  # the columns are independent recurrences
    _, exact = cg.solve(B, X_direct)
    assert exact.iterations == 0 and exact.residual <= 1e-10
    near = X_direct + 1e-6 * rng.normal(size=B.shape)
    X, close = cg.solve(B, near)
    assert 0 < close.iterations < first.iterations
    for c in range(2):
        assert np.linalg.norm(A @ X[:, c] - B[:, c]) <= 1.5e-10 * np.linalg.norm(B[:, c])
    with pytest.raises(ValueError, match="x0 must be"):
        cg.solve(B, near[:, 0])
    with pytest.raises(ValueError, match="x0 must be"):
        cg.solve(B, np.full(B.shape, np.nan))
    with pytest.raises(ValueError, match="right-hand side must have shape"):
        cg.solve(np.ones(A.shape[0] + 1))
    with pytest.raises(ValueError, match="tol must be"):
        CGSolver(A, "jacobi", tol=0.0)


def test_a_guess_worse_than_zero_is_not_used(systems):
    """A column of x0 whose residual exceeds |b| starts from zero: bitwise the solve from zero, in
    as many iterations; the other column keeps its (good) guess."""
    A = systems["cut-lb"]
    rng = np.random.default_rng(3)
    B = rng.normal(size=(A.shape[0], 2))
    X_direct = DirectSolver(A).solve(B)
    cg = CGSolver(A, "jacobi", tol=1e-10)
    X_zero, zero = cg.solve(B[:, 0])
    bad = 1e3 * rng.normal(size=A.shape[0])
    assert np.linalg.norm(B[:, 0] - A @ bad) > np.linalg.norm(B[:, 0])
    X_bad, from_bad = cg.solve(B[:, 0], bad)
    np.testing.assert_array_equal(X_bad, X_zero)
    assert from_bad.iterations == zero.iterations
    X, both = cg.solve(B, np.column_stack([bad, X_direct[:, 1] + 1e-6 * rng.normal(size=A.shape[0])]))
    np.testing.assert_array_equal(X[:, 0], X_zero)  # the columns are independent recurrences
    assert np.linalg.norm(A @ X[:, 1] - B[:, 1]) <= 1.5e-10 * np.linalg.norm(B[:, 1])


def test_lumped_guess_of_the_meshed_mean_curvature():
    """H_0 = M_L^{-1} A x: on the structured torus grid close (fewer multigrid iterations, the
    same solution to the tolerance), on the flipped family worse than zero (the solve from zero,
    bitwise); None when a node has no mass."""
    from cutfem.fem.forms import assemble
    from cutfem.fem.terms import basis_integrals
    from cutfem.problems.mean_curvature import SOLVER_TOL, lumped_guess, mean_curvature_system
    from cutfem.fem.spaces import SurfaceP1Space
    from cutfem.geometry.surface import torus_mesh

    for family, fewer in (("structured", True), ("flipped", False)):
        mesh = torus_mesh(128, family=family, seed=0)
        V = SurfaceP1Space(mesh)
        K, B = mean_curvature_system(V, mesh.ds(), tau_e=0.1)
        guess = lumped_guess(B, assemble(basis_integrals(mesh.ds()), V))
        r0 = np.linalg.norm(B - K @ guess, axis=0) / np.linalg.norm(B, axis=0)
        H0, plain = solve(K, B, space=V, method="cg-mg", tol=SOLVER_TOL)
        H, guessed = solve(K, B, space=V, method="cg-mg", tol=SOLVER_TOL, x0=guess)
        if fewer:
            assert r0.max() < 0.05 and guessed.iterations < plain.iterations
            assert np.abs(H - H0).max() < 1e-4 * np.abs(H0).max()
        else:
            assert r0.min() > 1 and guessed.iterations == plain.iterations
            np.testing.assert_array_equal(H, H0)
    assert lumped_guess(np.ones((3, 3)), np.array([1.0, 0.0, 2.0])) is None


@pytest.mark.parametrize("path", ["direct", "solve-auto", "solve-cg", "cg-solver"])
def test_bad_systems_are_refused_with_what_is_wrong(systems, path):
    """A NaN or inf in the matrix or the right-hand side is named with its row on every path, never
    returned as zeros or NaN, nor read as a singular system by the null-vector checks; so are a
    right-hand side of the wrong shape, a complex one (whose imaginary part would be dropped) and a
    matrix that is not square."""
    A = systems["cut-mass"].tocsr()
    b = np.ones(A.shape[0])
    run = {
        "direct": lambda A, b: DirectSolver(A).solve(b),
        "solve-auto": lambda A, b: solve(A, b),
        "solve-cg": lambda A, b: solve(A, b, method="cg-jacobi"),
        "cg-solver": lambda A, b: CGSolver(A, "jacobi").solve(b),
    }[path]
    bad = A.copy()
    row = 7
    bad.data[bad.indptr[row] + 1] = np.nan
    with pytest.raises(ValueError, match=rf"matrix has 1 non-finite entries \(NaN or inf\) among {A.nnz}, the first in row {row}"):
        run(bad, b)
    b_bad = b.copy()
    b_bad[[11, 40]] = [np.inf, np.nan]
    with pytest.raises(ValueError, match=r"right-hand side has 2 non-finite entries \(NaN or inf\) .* the first in row 11"):
        run(A, b_bad)
    n = A.shape[0]
    for wrong in (b[:-1], np.ones((n, 2, 2))):
        with pytest.raises(ValueError, match=rf"right-hand side must have shape \({n},\) or \({n}, c\)"):
            run(A, wrong)
    with pytest.raises(ValueError, match="right-hand side is complex"):
        run(A, b + 1j)
    with pytest.raises(ValueError, match=rf"matrix must be square, got shape \({n}, {n - 1}\)"):
        run(A[:, :-1], b)


def test_cg_failure_and_bad_arguments(systems):
    A = systems["cut-mass"]
    b = np.ones(A.shape[0])
    with pytest.raises(RuntimeError, match="did not converge"):
        cg_solve(A, b, preconditioner="none", maxiter=2)
    with pytest.raises(ValueError, match="unknown preconditioner"):
        cg_solve(A, b, preconditioner="ilu")
    with pytest.raises(ValueError, match="unknown method"):
        solve(A, b, method="gmres")
    x, info = solve(A, b)  # auto: direct for a small system
    assert info.method == "direct"
    np.testing.assert_allclose(A @ x, b, rtol=0, atol=1e-10)


# ----------------------------------------------------------------------------------------------
# condition numbers
# ----------------------------------------------------------------------------------------------


def scaled_condition(A):
    d = A.diagonal()
    S = A.toarray() / np.sqrt(np.outer(d, d))
    ev = np.linalg.eigvalsh(S)
    return ev[-1] / ev[0]


def test_condition_number_matches_dense_reference(small_cut_sphere):
    V = small_cut_sphere  # fewer than 400 unknowns: dense path
    assert V.n_dofs <= 400
    A = mass_matrix(V) + 0.1 * face_matrix(V)
    assert condition_number(A) == pytest.approx(scaled_condition(A), rel=1e-8)
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=11)
    coarse = CutP1Space(cut_mesh(box, Sphere(0.7, [0.03, -0.01, 0.02])))
    assert coarse.n_dofs > 400  # Lanczos path
    B = mass_matrix(coarse) + 0.1 * face_matrix(coarse)
    assert condition_number(B) == pytest.approx(scaled_condition(B), rel=1e-5)


def test_condition_number_of_singular_matrix_lanczos_path(cut_torus):
    M = mass_matrix(cut_torus)  # singular: M phi_h = 0
    assert cut_torus.n_dofs > 400
    assert condition_number(M) > 1e12


def test_conditioning_over_random_shifts():
    """30 seeded spheres (radius 0.6..0.8, centre shifted within a cell) on a coarse grid.

    Unstabilized: the scaled mass matrix is singular for every cut (its kernel holds the nodal
    vector of phi_h), so its condition number is at round-off level (> 1e12) or reported inf,
    whatever the sizes of the pieces.  Stabilized with tau_F = 0.1: bounded by 2000 for every
    shift, including those with pieces 1e-6 times smaller than the largest (measured: 430..550).
    """
    rng = np.random.default_rng(2024)
    box = structured_box([-1, -1, -1], [1, 1, 1], spacing=0.25)
    unstabilized, stabilized, smallest_piece = [], [], []
    for _ in range(30):
        cut = cut_mesh(box, Sphere(rng.uniform(0.6, 0.8), rng.uniform(-0.125, 0.125, size=3)))
        V = CutP1Space(cut)
        M = mass_matrix(V)
        unstabilized.append(condition_number(M))
        stabilized.append(condition_number(M + 0.1 * face_matrix(V)))
        smallest_piece.append(cut.piece_areas.min() / cut.piece_areas.max())
    assert min(smallest_piece) < 1e-4  # the sample does contain tiny pieces
    assert min(unstabilized) > 1e12  # every one blows up (inf counts)
    assert max(unstabilized) > 1e6
    assert max(stabilized) < 2000.0
    assert min(stabilized) > 1.0


# ----------------------------------------------------------------------------------------------
# errors and rates
# ----------------------------------------------------------------------------------------------


def smooth(x):
    return np.sin(2 * x[..., 0]) * x[..., 1] + np.exp(x[..., 2])


def smooth_gradient(x):
    g = np.zeros(x.shape)
    g[..., 0] = 2 * np.cos(2 * x[..., 0]) * x[..., 1]
    g[..., 1] = np.sin(2 * x[..., 0])
    g[..., 2] = np.exp(x[..., 2])
    return g


def test_interpolation_error_rates_meshed_sphere():
    h, e0, e1 = [], [], []
    for level in (2, 3, 4):
        V = SurfaceP1Space(sphere_mesh(level))
        u = V.interpolate(smooth)
        h.append(V.h)
        e0.append(l2_error(V, u, smooth))
        e1.append(h1_error(V, u, smooth_gradient))
    assert V.h == pytest.approx((10 * 4**4 + 2) ** -0.5)
    assert np.all((rates(h, e0) > 1.85) & (rates(h, e0) < 2.15))
    assert np.all((rates(h, e1) > 0.9) & (rates(h, e1) < 1.15))
    assert fitted_rate(h, e0) == pytest.approx(2.0, abs=0.1)


def test_interpolation_error_rate_cut_sphere():
    h, e = [], []
    for cells in (8, 16, 32):
        V = CutP1Space(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=cells), Sphere(0.7, [0.03, -0.01, 0.02])))
        h.append(V.h)
        e.append(l2_error(V, V.interpolate(smooth), smooth))
    assert h[0] == pytest.approx(9**-1.0)
    assert np.all((rates(h, e) > 1.8) & (rates(h, e) < 2.3))


def test_linear_functions_have_zero_error(small_cut_sphere):
    V = small_cut_sphere
    g = np.array([0.5, -1.0, 2.0])
    u = V.interpolate(lambda x: x @ g + 1.0)
    assert l2_error(V, u, lambda x: x @ g + 1.0) < 1e-13
    assert h1_error(V, u, lambda x: np.broadcast_to(g, x.shape)) < 1e-12
    X = V.interpolate(lambda x: x)
    assert l2_error(V, X, lambda x: x) < 1e-13  # vector valued
    assert l2_error(V, u, lambda x: x @ g) == pytest.approx(np.sqrt(V.cut.area), rel=1e-12)  # off by 1
    with pytest.raises(ValueError, match="degree >= 4"):
        l2_error(V, u, lambda x: x @ g, degree=2)


def test_one_pass_errors_equal_the_separate_ones():
    """l2_h1_errors against l2_error and h1_error: on a bulk field over the cut volume of a side
    (whole and cut tets, several blocks), and on a trace over S_h; zero for a linear function."""
    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=10), Sphere(0.7, [0.03, -0.01, 0.02]))
    V = CutP1Space(cut, NEG)
    dx = cut.dx(NEG)
    u = V.interpolate(lambda x: np.cos(x[..., 0]) * x[..., 2])
    pair = l2_h1_errors(V, u, lambda x: (smooth(x), smooth_gradient(x)), dx, chunk=500)
    assert pair[0] == pytest.approx(l2_error(V, u, smooth, dx), rel=1e-13)
    assert pair[1] == pytest.approx(h1_error(V, u, smooth_gradient, dx), rel=1e-13)
    assert pair[0] > 0.1 and pair[1] > 0.1
    T = CutP1Space(cut)
    w = T.interpolate(smooth)
    l2, h1 = l2_h1_errors(T, w, lambda x: (smooth(x), smooth_gradient(x)))
    assert l2 == pytest.approx(l2_error(T, w, smooth), rel=1e-12)
    assert h1 == pytest.approx(h1_error(T, w, smooth_gradient), rel=1e-13)
    g = np.array([0.5, -1.0, 2.0])
    lin = V.interpolate(lambda x: x @ g + 1.0)
    zero = l2_h1_errors(V, lin, lambda x: (x @ g + 1.0, np.broadcast_to(g, x.shape)), dx)
    assert zero[0] < 1e-13 and zero[1] < 1e-12
    with pytest.raises(ValueError, match="scalar field"):
        l2_h1_errors(V, np.stack([u, u], axis=1), lambda x: (np.stack([smooth(x)] * 2, axis=-1), smooth_gradient(x)), dx)


@pytest.mark.parametrize("c", [1, 3])
def test_cell_error_kernels_are_the_weighted_sums(c):
    """element_kernels.cell_value_error and cell_gradient_error against the sums written out in numpy:
    per-cell basis values and one shared table, scalar and vector fields, with and without the
    tangential projection."""
    from cutfem.fem.element_kernels import cell_gradient_error, cell_value_error

    rng = np.random.default_rng(c)
    b, q, k = 37, 14, 4
    phi, local, exact, w = rng.random((b, q, k)), rng.normal(size=(b, k, c)), rng.normal(size=(b, q, c)), rng.random((b, q))
    ref = np.sum(w[..., None] * (exact - np.einsum("bqk,bkc->bqc", phi, local)) ** 2)
    assert cell_value_error(phi, local, exact, w) == pytest.approx(ref, rel=1e-13)
    table = phi[:1]
    ref = np.sum(w[..., None] * (exact - np.einsum("qk,bkc->bqc", table[0], local)) ** 2)
    assert cell_value_error(table, local, exact, w) == pytest.approx(ref, rel=1e-13)
    # the gradients read from a table by type (here 5 types), as the Kuhn table of a structured box
    gtable, types = rng.normal(size=(5, k, 3)), rng.integers(0, 5, b)
    grads, u, ge = gtable[types], rng.normal(size=(b, k)), rng.normal(size=(b, q, 3))
    d = ge - np.einsum("bk,bkd->bd", u, grads)[:, None, :]
    assert cell_gradient_error(gtable, types, u, ge, w, np.zeros((0, 3))) == pytest.approx(np.sum(w * np.sum(d * d, axis=2)), rel=1e-13)
    n = rng.normal(size=(b, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dt = d - np.sum(d * n[:, None, :], axis=2, keepdims=True) * n[:, None, :]
    assert cell_gradient_error(gtable, types, u, ge, w, n) == pytest.approx(np.sum(w * np.sum(dt * dt, axis=2)), rel=1e-13)
    # one table row per element (a generic mesh's stored gradients): the same sum as the gathered rows
    assert cell_gradient_error(grads, np.arange(b), u, ge, w, n) == cell_gradient_error(gtable, types, u, ge, w, n)


def test_discrete_error_and_surface_integral():
    V = SurfaceP1Space(sphere_mesh(2))
    P = np.asarray(V.dof_points)[V.element_dofs]
    area = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1).sum()
    M = mass_matrix(V)
    assert discrete_error(V, np.full(V.n_dofs, 3.0)) == pytest.approx(3.0 * np.sqrt(area), rel=1e-12)
    E = np.column_stack([np.ones(V.n_dofs), 2 * np.ones(V.n_dofs), np.zeros(V.n_dofs)])
    assert discrete_error(V, E) == pytest.approx(np.sqrt(5 * area), rel=1e-12)  # components summed
    rng = np.random.default_rng(3)
    e = rng.normal(size=V.n_dofs)
    assert discrete_error(V, e) == pytest.approx(np.sqrt(e @ (M @ e)), rel=1e-13)  # the mass matrix's quadratic form
    # a cut space: the traces at the vertices of S_h give the cut mass matrix's form
    W = CutP1Space(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02])))
    Mw = mass_matrix(W)
    Ew = rng.normal(size=(W.n_dofs, 2))
    assert discrete_error(W, Ew) == pytest.approx(np.sqrt(np.sum(Ew * (Mw @ Ew))), rel=1e-12)
    with pytest.raises(ValueError):
        discrete_error(CutP1Space(W.cut, NEG), np.ones(CutP1Space(W.cut, NEG).n_dofs))  # a bulk field has no S_h
    assert surface_integral(V, np.full(V.n_dofs, 2.0)) == pytest.approx(2 * area, rel=1e-12)
    np.testing.assert_allclose(surface_integral(V, E), [area, 2 * area, 0.0], rtol=1e-12, atol=1e-14)


def test_rates_on_synthetic_data():
    h = np.array([0.4, 0.2, 0.1, 0.025])
    np.testing.assert_allclose(rates(h, 3.0 * h**2), [2.0, 2.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(rates(h, 0.5 * h**1.3), [1.3, 1.3, 1.3], rtol=1e-12)
    e = np.array([1.0, 0.5, 0.125, 0.1])
    np.testing.assert_allclose(rates(h, e), [1.0, 2.0, np.log(1.25) / np.log(4.0)], rtol=1e-12)
    assert fitted_rate(h, 7.0 * h**1.5) == pytest.approx(1.5, rel=1e-12)
    assert len(rates([1.0], [1.0])) == 0


# ----------------------------------------------------------------------------------------------
# the two factorizations of DirectSolver
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["meshed-lb", "cut-mass", "cut-lb"])
def test_banded_cholesky_agrees_with_superlu(systems, name):
    A = systems[name]
    B = np.random.default_rng(2).normal(size=(A.shape[0], 3))
    banded = DirectSolver(A, method="banded")
    lu = DirectSolver(A, method="superlu")
    assert (banded.kind, lu.kind) == ("banded", "superlu")
    assert DirectSolver(A).kind == "banded"  # these small systems have a narrow band after RCM
    Xb, Xl = banded.solve(B), lu.solve(B)
    np.testing.assert_allclose(Xb, Xl, rtol=0, atol=1e-9 * np.abs(Xl).max())
    np.testing.assert_allclose(banded.solve(B[:, 1]), Xb[:, 1], rtol=0, atol=1e-14 * np.abs(Xb).max())
    assert np.linalg.norm(A @ Xb - B) <= 1e-10 * np.linalg.norm(B)
    # the pivots of L D L^T depend on the ordering, but both lie in (0, 1] for the unit-diagonal S
    assert 0 < banded.smallest_pivot <= 1.0 + 1e-12


def test_banded_cholesky_leaves_blas_threads_as_they_were(systems):
    from threadpoolctl import threadpool_info

    before = [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
    DirectSolver(systems["cut-lb"], method="banded").solve(np.ones(systems["cut-lb"].shape[0]))
    assert [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"] == before


def test_nonsymmetric_matrix_is_refused_unless_spd_false():
    """The banded Cholesky reads one triangle only: a non-symmetric matrix declared SPD is refused;
    with spd=False SuperLU (partial pivoting) solves it."""
    n = 40
    A = sp.diags([-1.0, 4.0, -2.0], [-1, 0, 1], shape=(n, n), format="csr")
    b = np.arange(n, dtype=float)
    with pytest.raises(ValueError, match="not symmetric.*spd=False"):
        DirectSolver(A, method="banded")
    solver = DirectSolver(A, spd=False)
    assert solver.kind == "superlu"
    np.testing.assert_allclose(A @ solver.solve(b), b, atol=1e-12 * np.abs(b).max())


def test_small_indefinite_matrix_is_refused_unless_spd_false():
    """A symmetric indefinite (non-singular) matrix: the Cholesky breaks down and the signs of
    L D L^T name it indefinite; with spd=False the LU solves it."""
    A = sp.csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]]))  # eigenvalues -1, 3, 3
    for method in ("banded", "superlu"):
        with pytest.raises(SolverError, match="indefinite") as err:
            DirectSolver(A, method=method)
        assert err.value.cause == "indefinite" and err.value.smallest < 0
    solver = DirectSolver(A, spd=False)
    b = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(A @ solver.solve(b), b, atol=1e-12)


def test_unknown_factorization_is_refused(systems):
    with pytest.raises(ValueError, match="banded"):
        DirectSolver(systems["cut-lb"], method="cholmod")
