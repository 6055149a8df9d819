"""Conjugate gradients of cutfem.solvers.krylov: CGSolver and cg_solve against the direct solver,
starting guesses, several right-hand sides as independent recurrences, the Galerkin correction on
the constants, and the failures it reports.

References: the direct solver computed in the test; exact identities (1^T B = 0 for the mean
curvature system).
"""

import numpy as np
import pytest

from cutfem.solvers import krylov
from cutfem.solvers.direct import DirectSolver
from cutfem.solvers.krylov import CGSolver, cg_solve, mg_solve
from cutfem.solvers.multigrid import lattice_indices
from cutfem.solvers.solve import solve
from surface_matrices import face_matrix, mass_matrix, stiffness_matrix


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
    from cutfem.geometry.surface_meshes import torus_mesh

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


def test_simultaneous_cg_equals_column_by_column_and_direct(torus_space, monkeypatch):
    """The columns of B run as independent recurrences side by side: each equals its own solve to
    round-off, the block agrees with the direct solution to the tolerance, and a converged column
    is frozen (a zero column costs no product; the products are the sum of the columns' own)."""
    V = torus_space
    K = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    B = np.column_stack([stiffness_matrix(V) @ V.dof_points, np.zeros(V.n_dofs)])  # (n, 4)
    products = []
    matvec = krylov._matvec
    monkeypatch.setattr(krylov, "_matvec", lambda A: (lambda X, out=None, dots=None: (products.append(X.shape[1]), matvec(A)(X, out, dots=dots))[1]))
    X, info = mg_solve(K, B, lattice_indices(V))
    block_products = sum(products)
    its = []
    for j in range(4):
        x, inf_j = mg_solve(K, B[:, j], lattice_indices(V))
        its.append(inf_j.iterations)
        np.testing.assert_array_equal(X[:, j], x)  # bitwise: the block kernels keep each column's order
    assert its[3] == 0 and np.all(X[:, 3] == 0.0)
    assert info.iterations == max(its) and 15 <= info.iterations <= 40
    assert block_products == sum(its) + 4  # + one true-residual product per column at the end
    X_direct = DirectSolver(K).solve(B[:, :3])
    assert np.linalg.norm(X[:, :3] - X_direct) <= 1e-9 * np.linalg.norm(X_direct)


def test_constant_correction_makes_the_residual_sum_vanish(torus_space):
    """CG ends with the Galerkin correction on the constants: 1^T (B - K X) = 0 to round-off at a
    loose tolerance, and the error in the energy norm is no larger than without it."""
    V = torus_space
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    K = (M + 0.1 * J).tocsr()
    B = A @ V.dof_points  # 1^T B = 0: the mean curvature identity int H_h = 0
    X_direct = DirectSolver(K).solve(B)
    X, info = mg_solve(K, B, lattice_indices(V), tol=1e-4)
    assert info.residual <= 1e-4
    area = M.sum()
    ones = np.ones(V.n_dofs)
    integral = ones @ (M @ X)  # 1^T M H = 1^T B - 1^T r - 1^T J H, J 1 = 0
    assert np.max(np.abs(integral)) <= 1e-12 * area
    R = B - K @ X
    assert np.max(np.abs(ones @ R)) <= 1e-12 * np.abs(B).sum()
    E = X - X_direct
    for delta in (-1e-6, 1e-6):  # the corrected error is K-orthogonal to the constants: a shift is worse
        shifted = E + delta
        assert np.all(np.einsum("ic,ic->c", E, K @ E) < np.einsum("ic,ic->c", shifted, K @ shifted))


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
