"""Preconditioned MINRES (cutfem.solvers.minres) on saddle-point systems with known answers: with
the exact block-diagonal preconditioner diag(A^-1, S^-1), S = B A^-1 B^T, the preconditioned matrix
has the three eigenvalues 1 and (1 +- sqrt 5) / 2 (Murphy, Golub and Wathen, SIAM J. Sci. Comput.
21, 2000), so MINRES ends in at most three iterations; against a direct solve otherwise."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cutfem.solvers.minres import BlockDiagonal, minres


def saddle(n=300, m=60, seed=0, stabilization=0.0):
    rng = np.random.default_rng(seed)
    k = int(round(n ** 0.5))
    T = sp.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    A = (sp.kronsum(T, T) + 0.01 * sp.identity(k * k)).tocsr()
    n = k * k
    B = sp.random(m, n, density=0.05, random_state=seed) + sp.eye(m, n)
    C = stabilization * sp.identity(m)
    K = sp.bmat([[A, B.T], [B, -C]]).tocsr()
    return K, A.tocsc(), B.tocsr(), C, n, m, rng


def test_exact_schur_preconditioner_ends_in_three_iterations():
    K, A, B, C, n, m, rng = saddle()
    S = (B @ spla.spsolve(A, B.T.tocsc())).toarray()
    lu = spla.splu(A)
    Sinv = np.linalg.inv(S)
    P = BlockDiagonal(n + m, [(slice(0, n), lu.solve), (slice(n, n + m), lambda r: Sinv @ r)])
    b = rng.standard_normal(n + m)
    x, it, rel = minres(K, b, P, tol=1e-10)
    assert it == 3 and rel <= 1e-10
    np.testing.assert_allclose(x, spla.spsolve(K.tocsc(), b), rtol=1e-8, atol=1e-10)


def test_against_a_direct_solve_with_a_diagonal_schur_approximation_and_stabilization():
    K, A, B, C, n, m, rng = saddle(stabilization=0.1, seed=3)
    lu = spla.splu(A)
    d = 1.0 / (np.asarray((B @ sp.diags(1 / A.diagonal()) @ B.T).diagonal()) + 0.1)
    P = BlockDiagonal(n + m, [(slice(0, n), lu.solve), (np.arange(n, n + m), lambda r: d * r)])
    b = rng.standard_normal(n + m)
    x, it, rel = minres(K, b, P, tol=1e-9)
    assert rel <= 1e-9 and it < 200
    np.testing.assert_allclose(x, spla.spsolve(K.tocsc(), b), rtol=1e-6, atol=1e-8)
    unpreconditioned = minres(K, b, None, tol=1e-9, maxiter=5000)
    assert unpreconditioned[1] > it  # the preconditioner pays


def test_indefinite_preconditioner_and_no_convergence_are_named():
    K, A, B, C, n, m, rng = saddle()
    b = rng.standard_normal(n + m)
    with pytest.raises(ValueError, match="not positive definite"):
        minres(K, b, lambda r: -r)
    with pytest.raises(RuntimeError, match=r"did not converge in 3 iterations"):
        minres(K, b, None, maxiter=3)
    x, it, rel = minres(K, np.zeros(n + m))
    assert it == 0 and not np.any(x)
