"""Diagnostics of cutfem.solvers.diagnose: indefinite, singular and over-stabilized systems are told apart on
every solver path, with advice that applies; condition_number's value and verdict.

References: dense numpy eigenvalues computed in the test (the number of negative eigenvalues, the
scaled condition numbers), exact null vectors (constants of a Neumann Laplacian), the face
penalty's exact null space (linear functions).
"""

import numpy as np
import pytest
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.box import structured_box
from cutfem.geometry.surface_meshes import sphere_mesh
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.solvers.diagnose import ConditionNumber, SolverError, condition_number, diagnose
from cutfem.solvers.direct import DirectSolver
from cutfem.solvers.krylov import cg_solve, mg_solve
from cutfem.solvers.multigrid import lattice_indices
from cutfem.solvers.solve import solve
from surface_matrices import face_matrix, mass_matrix, stiffness_matrix


@pytest.fixture(scope="module")
def sphere16():
    V = CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=16), Sphere(0.7, [0.03, -0.01, 0.02])))
    return V, mass_matrix(V), stiffness_matrix(V), face_matrix(V)


@pytest.fixture(scope="module")
def indefinite(sphere16):
    """-Lap_S u + u - 6 u (stabilized): the Laplace-Beltrami eigenvalues l (l + 1) / 0.7^2 = 0, 4.1,
    12.2, ... give 1 + 3 = 4 negative eigenvalues, well away from zero."""
    V, M, A, J = sphere16
    K = (A + M + 0.1 * J - 6.0 * M).tocsr()
    with threadpool_limits(1):  # threaded LAPACK on a busy 2-core machine: 30 times slower
        n_negative = int((np.linalg.eigvalsh(K.toarray()) < 0).sum())
    return V, K, A @ V.dof_points, n_negative


def test_indefinite_matrix_is_reported_by_every_path(indefinite):
    V, K, B, n_negative = indefinite
    assert n_negative == 4
    for method in ("banded", "superlu"):
        with pytest.raises(SolverError, match=f"indefinite \\({n_negative} negative pivots") as err:
            DirectSolver(K, method=method)
        assert err.value.cause == "indefinite" and err.value.smallest < -1e-3
    for pre in ("none", "jacobi", "amg"):
        with pytest.raises(SolverError, match="negative curvature") as err:
            cg_solve(K, B, preconditioner=pre, tol=1e-8)
        assert err.value.cause == "indefinite" and err.value.smallest < -1e-10
    for coarse_size in (1500, 100):  # the coarsest level is indefinite too (Galerkin: P^T K P)
        with pytest.raises(SolverError, match="indefinite") as err:
            mg_solve(K, B, lattice_indices(V), coarse_size=coarse_size)
        assert err.value.cause == "indefinite" and "coarsest multigrid level" in str(err.value)
    kappa = condition_number(K)
    assert isinstance(kappa, ConditionNumber) and kappa.cause == "indefinite" and kappa.smallest < 0
    assert np.isfinite(kappa)


def test_indefinite_advice_is_the_callers_hint(indefinite):
    """The generic advice names several possible causes; a caller's hint replaces it; the advice
    to raise a stabilization, wrong here, never appears."""
    V, K, B, _ = indefinite
    for method in ("direct", "cg-jacobi"):
        with pytest.raises(SolverError) as err:
            solve(K, B, method=method, indefinite_hint="raise the Nitsche penalty gamma")
        assert err.value.cause == "indefinite"
        assert str(err.value).endswith("raise the Nitsche penalty gamma") and "stabiliz" not in str(err.value)
    with pytest.raises(SolverError, match="Nitsche penalty gamma below its stability bound"):
        solve(K, B)


def test_negative_or_isolated_zero_diagonal_is_indefinite():
    A = sp.csr_matrix(np.array([[2.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))  # minor [[2,1],[1,0]]: det -1
    for run in (lambda: DirectSolver(A), lambda: cg_solve(A, np.ones(3), preconditioner="jacobi")):
        with pytest.raises(SolverError, match="zero diagonal entry but a nonzero row") as err:
            run()
        assert err.value.cause == "indefinite"
    with pytest.raises(SolverError, match="negative diagonal") as err:
        DirectSolver(sp.diags([1.0, -2.0, 3.0]).tocsr())
    assert err.value.cause == "indefinite" and err.value.smallest == -2.0
    kappa = condition_number(sp.diags([1.0, -2.0, 3.0]).tocsr())
    # scaled by |D| the matrix is diag(1, -1, 1): condition number 1, and indefinite
    assert kappa.cause == "indefinite" and kappa == pytest.approx(1.0) and kappa.smallest < 0


def test_neumann_laplacian_is_singular_with_the_constants():
    """-Lap_S on a closed surface without the zero-order term: the constants span its kernel; every
    path says so and advises to fix the constant, not to stabilize."""
    V = SurfaceP1Space(sphere_mesh(3))
    L = stiffness_matrix(V)
    f = V.interpolate(lambda x: x[..., 2])  # consistent: CG alone would converge without noticing
    assert abs(mass_matrix(V).sum(axis=0) @ f) < 1e-12 * V.n_dofs
    for method in ("direct", "cg-jacobi", "cg-amg"):
        with pytest.raises(SolverError, match="constant functions are a null vector") as err:
            solve(L, mass_matrix(V) @ f, method=method)
        assert (err.value.cause, err.value.kernel) == ("singular", "constants") and err.value.smallest < 1e-14
        assert "Fix the constant" in str(err.value) and "Raise the stabilization" not in str(err.value)
    for method in ("banded", "superlu"):
        with pytest.raises(SolverError, match="constant functions") as err:
            DirectSolver(L, method=method)
        assert err.value.kernel == "constants"
    kappa = condition_number(L)
    assert kappa.cause == "singular" and kappa.error.kernel == "constants" and kappa > 1e14
    # a zero-order term makes it definite
    assert condition_number(L + mass_matrix(V)).cause is None


def test_user_kernel_and_phi_h_are_named(sphere16, monkeypatch):
    V, M, A, J = sphere16
    with pytest.raises(SolverError, match="phi_h") as err:
        solve(A + M, A @ V.dof_points, space=V, method="cg-jacobi")
    assert err.value.kernel == "phi_h" and "tau_F > 0" in str(err.value)
    with pytest.raises(SolverError, match="'level set'") as err:
        DirectSolver(M, kernels={"level set": V.cut.values})
    assert err.value.kernel == "level set"
    # the stabilization passed vanishes on a linear phi_h too: raising it does not help
    W = CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), lambda x: x[..., 2] - 0.123,
                            check_boundary=False))
    Mw, Jw = mass_matrix(W), face_matrix(W)
    with pytest.raises(SolverError, match="vanishes on it too") as err:
        DirectSolver(Mw + 0.1 * Jw, kernels={"phi_h": W.cut.values}, stabilization=0.1 * Jw)
    assert err.value.cause == "singular"


def test_over_and_under_stabilization_are_told_apart(sphere16):
    """K = M + tau J_F.  tau = 1e10: the linear functions (null space of J_F), the constants among
    them, are seen by M only relative to a diagonal 1e10 times larger: over-stabilized, lower tau.
    tau = 0 (J_F passed as the zero matrix): phi_h is null for M: raise tau.  Without the
    stabilization matrix the message names both possibilities."""
    V, M, A, J = sphere16
    tau = 1e10
    with pytest.raises(SolverError, match="over-stabilized") as err:
        DirectSolver(M + tau * J, stabilization=tau * J)
    assert err.value.cause == "over-stabilized" and "Lower the stabilization" in str(err.value)
    assert "Raise" not in str(err.value) and err.value.smallest < 1e-10
    with pytest.raises(SolverError) as err:
        solve(M + tau * J, A @ V.dof_points, method="cg-jacobi", stabilization=tau * J)
    assert err.value.cause == "over-stabilized"
    kappa = condition_number(M + tau * J, stabilization=tau * J)
    assert kappa.cause == "over-stabilized" and kappa > 1e10
    with pytest.raises(SolverError) as err:
        DirectSolver(M + tau * J)
    assert err.value.cause == "singular" and "lower it" in str(err.value)
    with pytest.raises(SolverError, match="Raise the stabilization") as err:
        DirectSolver(M, stabilization=0.0 * J)
    assert err.value.cause == "singular" and "Lower" not in str(err.value)
    # the stabilized system with the paper's tau passes, and its condition number has no cause
    DirectSolver(M + 0.1 * J, stabilization=0.1 * J)
    assert condition_number(M + 0.1 * J).cause is None


def test_diagnose_without_evidence_uses_lanczos():
    """No pivots, no vectors: a Lanczos Ritz value (an upper bound of lambda_min) decides."""
    n = 3000
    L = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n), format="csr")  # eigenvalues 2 - 2 cos(k pi / (n + 1))
    err = diagnose(L - 1.0 * sp.identity(n, format="csr"))
    assert err.cause == "indefinite" and err.smallest < -0.99
    with pytest.raises(ValueError, match="unknown cause"):
        SolverError("x", "tired")


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
    coarse = CutSpace(cut_mesh(box, Sphere(0.7, [0.03, -0.01, 0.02])))
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
        V = CutSpace(cut)
        M = mass_matrix(V)
        unstabilized.append(condition_number(M))
        stabilized.append(condition_number(M + 0.1 * face_matrix(V)))
        smallest_piece.append(cut.piece_areas.min() / cut.piece_areas.max())
    assert min(smallest_piece) < 1e-4  # the sample does contain tiny pieces
    assert min(unstabilized) > 1e12  # every one blows up (inf counts)
    assert max(unstabilized) > 1e6
    assert max(stabilized) < 2000.0
    assert min(stabilized) > 1.0
