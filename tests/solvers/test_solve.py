"""The entry of cutfem.solvers.solve: the choice of the method (direct below DIRECT_LIMIT, multigrid above
it where there is a hierarchy), the checks of the input on every path, the null vectors tested before
an iterative solve, and the default tolerance.

References: the direct solver computed in the test, exact identities (1^T B = 0 for the mean
curvature system).
"""

import numpy as np
import pytest
import scipy.sparse as sp

import cutfem as cf

from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.markers import CUT
from cutfem.geometry.box import structured_box
from cutfem.geometry.surface import SurfaceMesh
from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh
from cutfem.fem.forms import assemble
from cutfem.fem.terms import mass
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.solvers import solve as solve_module
from cutfem.solvers.diagnose import SolverError
from cutfem.solvers.direct import DirectSolver
from cutfem.solvers.krylov import DEFAULT_TOL, CGSolver
from cutfem.solvers.multigrid import multigrid_hierarchy
from cutfem.solvers.solve import solve
from surface_matrices import edge_matrix, face_matrix, mass_matrix, stiffness_matrix


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


def test_auto_picks_multigrid_above_the_limit(torus_space, monkeypatch):
    V = torus_space
    K = mass_matrix(V) + 0.1 * face_matrix(V)
    b = np.ones(V.n_dofs)
    monkeypatch.setattr(solve_module, "DIRECT_LIMIT", 1000)
    x, info = solve(K, b, space=V)
    assert info.method == "cg-mg" and info.residual <= DEFAULT_TOL
    x2, info2 = solve(K, b)  # no space: no lattice, direct below DIRECT_LIMIT_NO_MG
    assert info2.method == "direct"
    np.testing.assert_allclose(x, x2, rtol=0, atol=1e-5 * np.abs(x2).max())


def test_unstabilized_system_is_not_hidden(monkeypatch):
    """tau_F = 0: the nodal vector of phi_h is a null vector of the surface forms; solve() with the
    space reports it on the iterative path too (a consistent right-hand side would hide it)."""
    V = CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=24), Sphere(0.7, [0.03, -0.01, 0.02])))
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    B = A @ V.dof_points
    monkeypatch.setattr(solve_module, "DIRECT_LIMIT", 100)
    for K in (M, A + M):
        with pytest.raises(SolverError, match="phi_h") as err:
            solve(K, B, space=V)
        assert err.value.smallest < 1e-10
    H, info = solve(M + 0.1 * J, B, space=V)  # stabilized: fine
    assert info.method == "cg-mg"


def _edge_system(mesh):
    V = SurfaceP1Space(mesh)
    return V, (mass_matrix(V) + 0.1 * edge_matrix(V)).tocsr(), stiffness_matrix(V) @ V.dof_points


@pytest.mark.parametrize("grid", [True, False])
def test_meshed_auto_solve_uses_multigrid_and_agrees_with_direct(grid):
    """Above DIRECT_LIMIT a meshed system is solved by CG with multigrid: along the torus grid, or
    (a mesh without a grid) through the Kuhn lattice; the result agrees with SuperLU to the
    tolerance and the iteration counts stay small."""
    mesh = torus_mesh(160, "perturbed", seed=1)
    if not grid:
        mesh = SurfaceMesh(mesh.points, mesh.triangles)
        assert mesh.grid is None
    V, K, B = _edge_system(mesh)
    assert V.n_dofs > solve_module.DIRECT_LIMIT
    X, info = solve(K, B, space=V, tol=1e-8)
    assert info.method == "cg-mg" and info.residual <= 1e-8
    assert info.iterations <= (30 if grid else 80)
    X_direct = DirectSolver(K).solve(B)
    assert np.linalg.norm(X - X_direct) <= 1e-6 * np.linalg.norm(X_direct)
    assert multigrid_hierarchy(SurfaceP1Space(sphere_mesh(2))) is not None


@pytest.mark.parametrize("surface", ["cut-0.08", "meshed-96"])
def test_default_tolerance_keeps_the_integral_of_H_at_round_off(surface):
    """int_{S_h} H_h = 1^T M H = -1^T r (1^T B = 0, J 1 = 0): with the default tolerance of the
    multigrid path it stays below 1e-10 of the area (spacing 0.08 is the worst measured: 1.5e-11;
    it was 1.4e-9 with the former 1e-6)."""
    from cutfem.problems.mean_curvature import mean_curvature_system

    if surface == "cut-0.08":
        cut = cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.08), Torus())
        V = CutSpace(cut)
        ds = cut.ds()
        K, B = mean_curvature_system(V, ds, tau_f=0.1, faces=cut.dF(cut.interior_facets(CUT)))
    else:
        V = SurfaceP1Space(torus_mesh(96, "perturbed", seed=1))
        ds = V.mesh.ds()
        K, B = mean_curvature_system(V, ds, tau_e=0.1)
    H, info = solve(K, B, method="cg-mg", space=V)
    assert info.method == "cg-mg" and info.residual <= DEFAULT_TOL
    ones_M = np.asarray(assemble(mass(ds), V).sum(axis=0)).ravel()
    assert np.abs(ones_M @ H).max() <= 1e-10 * ones_M.sum()


def test_cg_mg_without_a_hierarchy_names_the_methods_that_work():
    """A matrix with no geometric hierarchy (no space, no lattice): 'cg-mg' is refused naming the
    methods that need none, and 'cg-amg' solves the same system to its tolerance."""
    n = 2000
    A = sp.diags([-np.ones(n - 1), 2.01 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    b = np.ones(n)
    with pytest.raises(ValueError, match="needs a geometric hierarchy.*use 'cg-amg' \\(algebraic multigrid\\), 'direct' or 'auto'"):
        solve_module.solve(A, b, method="cg-mg")
    x, info = solve_module.solve(A, b, method="cg-amg", tol=1e-10)
    assert np.linalg.norm(A @ x - b) <= 1e-10 * np.linalg.norm(b) and info.method == "cg-amg"


def test_amg_of_a_vector_field_takes_each_components_linear_functions_as_candidates():
    """Elasticity on a cut background without a lattice (a plain TetMesh): AMG with the linear
    functions of each component (which span the rigid motions) as near-kernel candidates, from
    space=VectorSpace(V), against AMG without them; and points that fit no component count."""
    from cutfem.geometry.mesh import TetMesh
    from cutfem.solvers.krylov import _amg

    box = cf.structured_box([-1.1] * 3, [1.1] * 3, spacing=0.1)
    cut = cf.cut_mesh(TetMesh(np.array(box.points), np.array(box.tets)), cf.Sphere(1.0))
    V = cf.CutSpace(cut, cf.NEG)
    W = cf.VectorSpace(V)
    dx, ds, dg = cut.dx(cf.NEG), cut.ds(), cut.dF(cut.ghost_facets(cf.NEG))
    N = cf.elasticity_nitsche(ds, 1.0, 2.0, gamma=10.0, g=lambda x: np.sin(x))
    K = cf.assemble(cf.elasticity(dx, 1.0, 2.0) + N + 0.4 * cf.face_jump_penalty(dg, h_power=1), W)
    b = cf.assemble(N.load, W)
    x, info = cf.solve(K, b, method="cg-amg", space=W)
    x0, info0 = cf.solve(K, b, method="cg-amg")
    assert info.iterations <= 12 and info.iterations < 0.7 * info0.iterations  # 9 against 19 here
    assert np.abs(x - x0).max() <= 1e-6 * np.abs(x0).max()
    with pytest.raises(ValueError, match="do not fit a matrix"):
        _amg(K, V.dof_points[:-1])
