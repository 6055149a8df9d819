"""DirectSolver (cutfem.solvers.direct): its two factorizations agree with scipy's and with each other,
and singular, indefinite and non-symmetric matrices are refused unless declared so.

References: scipy's spsolve computed in the test, exact null vectors of the unstabilized cut mass matrix.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.box import structured_box
from cutfem.fem.spaces import CutSpace
from cutfem.solvers.diagnose import SolverError, condition_number
from cutfem.solvers.direct import DirectSolver
from cutfem.solvers.solve import solve
from surface_matrices import face_matrix, mass_matrix


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
    V = CutSpace(cut_mesh(box, lambda x: x[..., 2], check_boundary=False))
    below = V.dof_points[:, 2] < 0
    assert below.any()
    M = mass_matrix(V)
    assert np.abs(M.diagonal()[below]).max() < 1e-25 * M.diagonal().max()
    with pytest.raises(SolverError) as err:
        DirectSolver(M)
    assert err.value.smallest < 1e-12


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
