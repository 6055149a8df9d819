"""The geometric multigrid of cutfem.solvers.multigrid: its prolongations (Kuhn lattices, surface grids,
surface to lattice, augmented) against exact linear functions, its hierarchy and cycles, and CG
with it against the direct solver.

References: the direct solver (SuperLU) computed in the test, exact linear functions, numpy's
least squares for the minimum-norm weights.
"""

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh
from cutfem.solvers.diagnose import SolverError
from cutfem.solvers.direct import DirectSolver
from cutfem.solvers.krylov import CGSolver, mg_solve
from cutfem.solvers.multigrid import (
    GeometricMultigrid,
    augmented_hierarchy,
    grid_prolongation,
    kuhn_prolongation,
    lattice_hierarchy,
    lattice_indices,
    surface_lattice_prolongation,
)
from cutfem.solvers.solve import solve
from surface_matrices import face_matrix, mass_matrix, stiffness_matrix


def test_kuhn_prolongation_reproduces_linear_functions(torus_space):
    V = torus_space
    ijk = lattice_indices(V)
    assert ijk.shape == (V.n_dofs, 3)
    np.testing.assert_array_equal(V.cut.background.node_coordinates(V.node_ids), V.dof_points)
    P, cijk = kuhn_prolongation(ijk)
    assert P.shape == (V.n_dofs, len(cijk)) and len(cijk) < V.n_dofs / 3
    g = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(P @ (2 * cijk @ g + 1.5), ijk @ g + 1.5, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0)  # partition of unity
    # coarse nodes in lexicographic (z, y, x) order, each used; the CSR arrays written directly are canonical
    rel = cijk - cijk.min(axis=0)
    d = rel.max(axis=0) + 1
    assert np.all(np.diff(rel[:, 0] + d[0] * (rel[:, 1] + d[1] * rel[:, 2])) > 0)
    assert np.all(np.bincount(P.indices, minlength=P.shape[1]) > 0)
    Q = sp.coo_matrix(P).tocsr()
    Q.sum_duplicates()
    np.testing.assert_array_equal(Q.indptr, P.indptr)
    np.testing.assert_array_equal(Q.indices, P.indices)
    np.testing.assert_array_equal(Q.data, P.data)


def test_kuhn_prolongation_refuses_empty_or_misshapen_indices():
    for bad in (np.zeros((0, 3), dtype=np.int64), np.zeros((4, 2), dtype=np.int64)):
        with pytest.raises(ValueError, match=r"shape \(m, 3\)"):
            kuhn_prolongation(bad)


def test_coarse_space_is_nested(torus_space):
    """A coarse Kuhn P1 function is P1 on every fine tet: its prolongation has zero face jumps
    wherever all its coarse values are linear... checked by the stronger statement that the
    prolongated coarse basis functions are piecewise linear on the fine Kuhn tets."""
    V = torus_space
    P, cijk = kuhn_prolongation(lattice_indices(V))
    rng = np.random.default_rng(0)
    uc = rng.normal(size=P.shape[1])
    u = P @ uc
    # on every fine tet, the prolongated function equals the coarse P1 interpolant evaluated at
    # the fine nodes: check at the barycentre against the mean of the four nodal values
    ijk = lattice_indices(V)
    centre = ijk[V.element_dofs].mean(axis=1)  # fine lattice units
    # coarse Kuhn tet containing the centre: sort the fractional parts (Freudenthal)
    y = centre / 2.0
    base = np.floor(y).astype(np.int64)
    frac = y - base
    order = np.argsort(-frac, axis=1)
    verts = [base.copy()]
    cur = base.copy()
    for k in range(3):
        cur = cur.copy()
        cur[np.arange(len(cur)), order[:, k]] += 1
        verts.append(cur)
    lookup = {tuple(c): i for i, c in enumerate(cijk)}
    fs = np.sort(frac, axis=1)[:, ::-1]
    weights = np.stack([1 - fs[:, 0], fs[:, 0] - fs[:, 1], fs[:, 1] - fs[:, 2], fs[:, 2]], axis=1)
    vals = np.array([[uc[lookup[tuple(v[e])]] if tuple(v[e]) in lookup else np.nan for v in verts] for e in range(len(y))])
    interp = np.einsum("ek,ek->e", weights, np.nan_to_num(vals))
    ok = ~np.isnan(vals).any(axis=1) | (weights * np.isnan(vals) == 0).all(axis=1)
    np.testing.assert_allclose(interp[ok], u[V.element_dofs].mean(axis=1)[ok], rtol=0, atol=1e-12)


def test_grid_prolongation_is_exact_for_linear_functions_on_a_planar_grid():
    """On a perturbed planar grid the minimum-norm weights reproduce every linear function exactly
    (also across the periodic seam, where the corners are far away but still in the plane)."""
    n, m = 12, 8
    rng = np.random.default_rng(3)
    i, j = np.divmod(np.arange(n * m), m)
    X = np.column_stack([i + rng.uniform(-0.25, 0.25, n * m), 0.5 * j + rng.uniform(-0.1, 0.1, n * m), np.zeros(n * m)])
    P, Xc, shape = grid_prolongation(X, (n, m), drop=0.0)
    assert P.shape == (n * m, n * m // 4) and shape == (n // 2, m // 2)
    np.testing.assert_array_equal(Xc, X.reshape(n, m, 3)[::2, ::2].reshape(-1, 3))
    g = np.array([0.7, -1.3, 5.0])
    np.testing.assert_allclose(P @ (Xc @ g + 2.0), X @ g + 2.0, rtol=0, atol=1e-10)  # seam cells: round-off
    coarse = (i % 2 == 0) & (j % 2 == 0)
    np.testing.assert_array_equal(P[np.flatnonzero(coarse)].toarray(), np.eye(n * m // 4))
    with pytest.raises(ValueError, match="even"):
        grid_prolongation(X[: 11 * m], (11, m))
    with pytest.raises(ValueError, match="drop must be"):
        grid_prolongation(X, (n, m), drop=0.5)


def test_grid_prolongation_drops_small_weights_off_the_edge_of_a_node():
    """A node on a coarse edge with both weights off that edge below ``drop`` takes the weights of
    its projection on the edge: exact for linear functions on a planar grid whose edge nodes lie on
    their coarse edges (a general quadrilateral grid, edge nodes anywhere along the edge); on the
    structured torus every edge node of the finest level drops them, constants stay exact and the
    linear functions are reproduced as well as by the four weights."""
    n, m = 12, 8
    rng = np.random.default_rng(4)
    i, j = np.divmod(np.arange(n * m), m)
    corner = np.column_stack([i + rng.uniform(-0.3, 0.3, n * m), 0.5 * j + rng.uniform(-0.1, 0.1, n * m), np.zeros(n * m)])
    X = corner.copy()
    base = (i - i % 2) * m + (j - j % 2)  # the corner (2a, 2b) of each node's coarse cell
    for along, step in (((i % 2 == 1) & (j % 2 == 0), 2 * m), ((i % 2 == 0) & (j % 2 == 1), 2)):
        p = np.flatnonzero(along & (i < n - 1) & (j < m - 1))  # edges inside the sheet: no seam
        t = rng.uniform(0.3, 0.7, p.size)[:, None]
        X[p] = (1 - t) * corner[base[p]] + t * corner[base[p] + step]
    P, Xc, _ = grid_prolongation(X, (n, m))
    P0, _, _ = grid_prolongation(X, (n, m), drop=0.0)
    g = np.array([0.7, -1.3, 5.0])
    inner = (i < n - 2) & (j < m - 2)  # cells away from the periodic seam, where the sheet is not closed
    np.testing.assert_allclose((P @ (Xc @ g + 2.0))[inner], (X @ g + 2.0)[inner], rtol=0, atol=1e-12)
    edge_rows = np.flatnonzero(inner & ((i % 2) != (j % 2)))
    two = np.diff(P.indptr)[edge_rows] == 2
    assert two.any() and np.all(np.diff(P0.indptr)[edge_rows] >= np.diff(P.indptr)[edge_rows])
    # the structured torus: all edge nodes of the finest level drop the weights off their edge
    mesh = torus_mesh(192)
    P, Xc, _ = grid_prolongation(mesh.points, mesh.grid)
    P0, _, _ = grid_prolongation(mesh.points, mesh.grid, drop=0.0)
    n, m = mesh.grid
    i, j = np.divmod(np.arange(n * m), m)
    counts = np.diff(P.indptr)
    assert np.all(counts[(i % 2) != (j % 2)] == 2) and np.all(counts[(i % 2 == 1) & (j % 2 == 1)] == 4)
    np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-13)
    g = np.array([0.3, -1.1, 0.8])
    err, err0 = (np.abs(Q @ (Xc @ g) - mesh.points @ g).max() for Q in (P, P0))
    assert err <= 1.5 * err0


def test_grid_prolongation_on_the_torus_is_second_order():
    """On the curved torus constants are exact and linear functions are reproduced up to the
    normal offsets of the coarse corners, O(H^2): the error falls by about 4 per refinement."""
    g = np.array([0.3, -1.1, 0.8])
    errs = []
    for n in (48, 96, 192):
        mesh = torus_mesh(n, "perturbed-flipped", seed=2)
        assert mesh.grid == (n, n // 2)
        P, Xc, _ = grid_prolongation(mesh.points, mesh.grid)
        np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-13)
        errs.append(np.abs(P @ (Xc @ g) - mesh.points @ g).max())
    assert errs[0] < 0.05 and 3.5 < errs[0] / errs[1] < 4.5 and 3.5 < errs[1] / errs[2] < 4.5


def test_grid_prolongation_weights_are_the_minimum_norm_solution():
    """Each fine node's weights against an independent reference: the minimum-norm solution of the
    three constraints C w = (1, 0, 0) by numpy's least squares, on a perturbed torus."""
    mesh = torus_mesh(24, "perturbed-flipped", seed=5)
    n, m = mesh.grid
    X = mesh.points
    P, Xc, _ = grid_prolongation(X, (n, m), drop=0.0)
    nc, mc = n // 2, m // 2
    for p in range(n * m):
        i, j = divmod(p, m)
        if i % 2 == 0 and j % 2 == 0:
            continue
        a, b = i // 2, j // 2
        corners = [a * mc + b, (a + 1) % nc * mc + b, (a + 1) % nc * mc + (b + 1) % mc, a * mc + (b + 1) % mc]
        D = Xc[corners] - X[p]
        C = np.vstack([np.ones(4), D @ (D[2] - D[0]), D @ (D[3] - D[1])])
        w = np.linalg.lstsq(C, np.array([1.0, 0.0, 0.0]), rcond=None)[0]
        np.testing.assert_allclose(P[p, corners].toarray().ravel(), w, rtol=0, atol=1e-12)


def test_surface_lattice_prolongation_is_exact_for_linear_functions():
    mesh = sphere_mesh(4)
    P, ijk = surface_lattice_prolongation(mesh.points, 0.2)
    assert P.shape == (mesh.n_points, len(ijk)) and P.data.min() > 0
    np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-13)
    g = np.array([0.3, -1.1, 0.8])
    # lattice coordinates of the coarse nodes: anchored half a spacing below the smallest point
    Xc = ijk * 0.2 + (mesh.points.min(axis=0) - 0.1)
    np.testing.assert_allclose(P @ (Xc @ g + 1.0), mesh.points @ g + 1.0, rtol=0, atol=1e-12)


def test_augmented_hierarchy_doubles_the_coarse_spaces(torus_space):
    """[P_0, diag(w) P_0], then diag(P_l, P_l): level 2 holds P_0 P_1 v and w P_0 P_1 v'."""
    V = torus_space
    ijk = lattice_indices(V)
    w = V.cut.values
    P0, c1 = kuhn_prolongation(ijk)
    P1, _ = kuhn_prolongation(c1)
    hierarchy = augmented_hierarchy(lattice_hierarchy(ijk), w)
    Q = [next(hierarchy), next(hierarchy)]
    assert Q[0].shape == (V.n_dofs, 2 * P0.shape[1]) and Q[1].shape == (2 * P1.shape[0], 2 * P1.shape[1])
    rng = np.random.default_rng(1)
    v, v2 = rng.normal(size=P1.shape[1]), rng.normal(size=P1.shape[1])
    np.testing.assert_allclose(Q[0] @ (Q[1] @ np.concatenate([v, v2])), P0 @ (P1 @ v) + w * (P0 @ (P1 @ v2)), atol=1e-12)
    with pytest.raises(ValueError, match="augment must be .* shape"):
        GeometricMultigrid(sp.eye(V.n_dofs, format="csr"), ijk, augment=w[:-1])


def test_multigrid_hierarchy_shape(torus_space):
    V = torus_space
    K = mass_matrix(V) + 0.1 * face_matrix(V)
    mg = GeometricMultigrid(K, lattice_indices(V), coarse_size=500)
    assert mg.sizes[0] == V.n_dofs and all(a > 3 * b for a, b in zip(mg.sizes, mg.sizes[1:]))
    assert mg.operator_complexity < 1.5
    R = np.random.default_rng(1).normal(size=(V.n_dofs, 2))
    Z = mg.apply(R)
    # the K-cycle below the finest level: positive, not linear (its coarse steps depend on the input)
    assert R[:, 0] @ Z[:, 0] > 0 and R[:, 1] @ Z[:, 1] > 0
    assert not np.allclose(mg.apply(2.0 * R[:, 0] + R[:, 1]), 2.0 * Z[:, 0] + Z[:, 1], rtol=1e-4, atol=0)
    # the columns are independent: the block gives, bitwise, what each column gives alone
    np.testing.assert_array_equal(Z[:, 1], mg.apply(R[:, 1]))
    # V-cycles: a symmetric positive definite operator, up to the rounding of its single-precision cycle
    v = GeometricMultigrid(K, lattice_indices(V), coarse_size=500, visits=(1,))
    Zv = v.apply(R)
    assert R[:, 0] @ Zv[:, 1] == pytest.approx(R[:, 1] @ Zv[:, 0], rel=1e-5)
    assert R[:, 0] @ Zv[:, 0] > 0
    np.testing.assert_allclose(v.apply(2.0 * R[:, 0] + R[:, 1]), 2.0 * Zv[:, 0] + Zv[:, 1], rtol=0, atol=1e-5 * np.abs(Zv).max())
    with pytest.raises(ValueError, match="visits must be"):
        GeometricMultigrid(K, lattice_indices(V), visits=(1, 3))


def test_single_precision_application_is_the_cycle_output(torus_space):
    """GeometricMultigrid.apply(R, single=True) (what mg_solve's CG uses) returns the float32
    values whose float64 copy apply(R) returns."""
    V = torus_space
    A = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    mg = GeometricMultigrid(A, lattice_indices(V), coarse_size=50)
    R = np.random.default_rng(3).standard_normal((A.shape[0], 3))
    Z = mg.apply(R)
    Z32 = mg.apply(R, single=True)
    assert Z32.dtype == np.float32 and Z.dtype == np.float64
    np.testing.assert_array_equal(Z32.astype(float), Z)


def test_multigrid_reports_zero_diagonal_and_bad_lattice(torus_space):
    V = torus_space
    K = (mass_matrix(V) + 0.1 * face_matrix(V)).tolil()
    K[7, :] = 0.0
    K[:, 7] = 0.0
    with pytest.raises(SolverError, match="zero"):
        mg_solve(K.tocsr(), np.ones(V.n_dofs), lattice_indices(V))
    with pytest.raises(ValueError, match="lattice"):
        GeometricMultigrid(K.tocsr(), np.zeros((3, 3), dtype=int))
    with pytest.raises(ValueError, match="geometric hierarchy"):
        solve(sp.identity(V.n_dofs, format="csr"), np.ones(V.n_dofs), method="cg-mg")


@pytest.mark.parametrize("system", ["mean-curvature", "laplace-beltrami"])
def test_mg_solve_agrees_with_direct(torus_space, system):
    V = torus_space
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    K = M + 0.1 * J if system == "mean-curvature" else A + M + 0.1 * J
    B = A @ V.dof_points
    X_direct = DirectSolver(K).solve(B)
    X, info = mg_solve(K, B, lattice_indices(V), tol=1e-10)
    assert info.method == "cg-mg" and 0 < info.iterations < 60
    assert info.residual <= 1e-10
    for c in range(3):
        assert np.linalg.norm(K @ X[:, c] - B[:, c]) <= 1.5e-10 * np.linalg.norm(B[:, c])
    assert np.linalg.norm(X - X_direct) <= 1e-8 * np.linalg.norm(X_direct)


def test_multigrid_solver_is_reused_and_freed_with_its_last_reference(torus_space):
    """CGSolver with the multigrid: one hierarchy for several solves, a guess near the solution
    needs fewer iterations, and the solver (with its hierarchy) is freed as soon as it is no longer
    referenced, without waiting for the cycle collector (no reference cycle through its closures)."""
    import gc
    import weakref

    V = torus_space
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    K = (M + 0.1 * J).tocsr()
    B = A @ V.dof_points
    cg = CGSolver(K, "mg", tol=1e-10, lattice=lattice_indices(V))
    X, first = cg.solve(B)
    X_direct = DirectSolver(K).solve(B)
    assert np.linalg.norm(X - X_direct) <= 1e-8 * np.linalg.norm(X_direct)
    _, again = cg.solve(B, X_direct * (1 + 1e-6))
    assert first.setup > 0 and again.setup == 0 and 0 < again.iterations < first.iterations
    hierarchy = weakref.ref(cg.multigrid)
    gc.disable()
    try:
        del cg
        assert hierarchy() is None
    finally:
        gc.enable()


def test_cut_laplace_beltrami_multigrid_iterations_stay_flat():
    """A_Gamma + M + 0.1 J_F on the cut unit sphere: with the coarse spaces augmented by phi_h v
    (augmented_hierarchy, passed by the problem) CG needs few iterations that do not grow from
    spacing 0.1 to 0.05.  The plain Kuhn hierarchy needed 17 and 28: each coarser level added a
    cluster of small eigenvalues from the normally linear near-null vectors phi_h g."""
    import cutfem

    res = cutfem.run("laplace-beltrami-cut", levels=[0.1, 0.05], solver="cg-mg")
    its = [r["solver_iterations"] for r in res.records]
    assert all(r["solver"] == "cg-mg" for r in res.records)
    assert max(its) <= 13 and its[1] <= its[0] + 1, its
    # the normal-gradient stabilization gains as much from the same coarse spaces (18, 27 plain)
    res = cutfem.run("laplace-beltrami-cut", levels=[0.1, 0.05], solver="cg-mg", stabilization="normal")
    its = [r["solver_iterations"] for r in res.records]
    assert max(its) <= 15 and its[1] <= its[0] + 1, its
