"""The geometric multigrid path of cutfem.solvers.solve against the direct solver and exact linear functions.

References: the direct solver (SuperLU) computed in the test, exact linear functions.
"""


import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve_triangular

from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.levelset import Sphere, Torus
from cutfem.geometry.markers import CUT
from cutfem.fem.forms import assemble
from cutfem.fem.terms import mass
from cutfem.geometry.mesh import structured_box
from cutfem.solvers.solve import (
    DirectSolver,
    GeometricMultigrid,
    SolverError,
    grid_prolongation,
    kuhn_prolongation,
    lattice_indices,
    mg_solve,
    multigrid_hierarchy,
    solve,
    surface_lattice_prolongation,
)
from cutfem.fem.spaces import CutP1Space, SurfaceP1Space
from cutfem.geometry.surface import SurfaceMesh, sphere_mesh, torus_mesh
from surface_matrices import edge_matrix, face_matrix, mass_matrix, stiffness_matrix
from cutfem.solvers import sparse_kernels

from cutfem.solvers import solve as solve_module


@pytest.fixture(scope="module")
def torus_space():
    return CutP1Space(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.05), Torus()))


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


@pytest.mark.parametrize("room", [12, 1])
@pytest.mark.parametrize("rows_per_chunk", [4096, 7])
def test_galerkin_product_against_scipy(torus_space, monkeypatch, rows_per_chunk, room):
    """The compiled Galerkin product P^T A P: equal to scipy's two products up to round-off, exactly
    symmetric with sorted indices, also when coarse functions see no fine row (an empty column
    of P, so no diagonal entry), when the coarse rows are denser than the room first given to
    them (a dense coarse block; a room of 1 entry a row makes nearly every chunk start again,
    several times), and bitwise the same whether the rows go in one chunk or many, and whether or
    not chunks were done again."""
    from cutfem.solvers import multigrid_kernels
    from cutfem.solvers.multigrid_kernels import galerkin

    monkeypatch.setattr(multigrid_kernels, "GALERKIN_ROWS", rows_per_chunk)
    monkeypatch.setattr(multigrid_kernels, "GALERKIN_ROOM", room)
    V = torus_space
    K = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    P = next(multigrid_hierarchy(V)).tocsr()
    rng = np.random.default_rng(3)
    Q = sp.random(300, 40, density=0.05, random_state=4, format="csr")
    Q = sp.hstack([Q, sp.csr_matrix((300, 5))]).tocsr()  # five coarse functions with no fine rows
    B = sp.random(300, 300, density=0.03, random_state=5)
    S = (B + B.T + sp.diags(rng.random(300) + 1.0)).tocsr()
    D = sp.csr_matrix(rng.random((300, 60)))  # every coarse row full: 30 entries a row right of the diagonal
    for A, P in ((K, P), (S, Q), (S, D)):
        G = galerkin(A, P)
        monkeypatch.setattr(multigrid_kernels, "GALERKIN_ROWS", 10**9)
        one = galerkin(A, P)  # one chunk
        monkeypatch.setattr(multigrid_kernels, "GALERKIN_ROWS", rows_per_chunk)
        monkeypatch.setattr(multigrid_kernels, "GALERKIN_ROOM", 10**3)
        roomy = galerkin(A, P)  # no chunk short of room
        monkeypatch.setattr(multigrid_kernels, "GALERKIN_ROOM", room)
        for other in (one, roomy):
            for a, b in ((G.indptr, other.indptr), (G.indices, other.indices), (G.data, other.data)):
                np.testing.assert_array_equal(a, b)
        ref = (P.T @ A @ P).toarray()
        inner = np.ones(max(G.nnz - 1, 0), dtype=bool)  # consecutive entries of one row
        inner[G.indptr[1:-1][(G.indptr[1:-1] > 0) & (G.indptr[1:-1] < G.nnz)] - 1] = False
        assert np.all(np.diff(G.indices)[inner] > 0)  # sorted, no duplicates
        assert (G != G.T).nnz == 0
        np.testing.assert_allclose(G.toarray(), ref, rtol=0, atol=1e-13 * np.abs(ref).max())


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("c", [1, 2, 3, 5])
def test_presmooth_is_a_forward_sweep_from_zero_and_its_residual(torus_space, dtype, c):
    """presmooth gives, bitwise, the forward Gauss-Seidel sweep from X = 0 of the block kernels and
    the residual as the product -U X with scipy's strict upper triangle (the columns of a row in
    the order they are summed there); in exact terms X = (L + D)^{-1} B and R = B - A X."""
    from cutfem.solvers.sparse_kernels import gauss_seidel, matmul, presmooth

    V = torus_space
    A = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr().astype(dtype)
    A.sort_indices()
    n = A.shape[0]
    B = np.random.default_rng(c).standard_normal((n, c)).astype(dtype)
    X, R = np.full((n, c), np.nan, dtype), np.full((n, c), np.nan, dtype)  # X is written, not read
    presmooth(A, X, B, R)
    X0 = gauss_seidel(A, np.zeros((n, c), dtype), B, forward=True)
    np.testing.assert_array_equal(X, X0)
    np.testing.assert_array_equal(R, matmul(sp.triu(A, 1, format="csr"), X0, alpha=-1.0))
    Xd = spsolve_triangular(sp.tril(A, format="csr").astype(float), B.astype(float), lower=True)
    scale = np.abs(Xd).max()
    assert np.abs(X - Xd).max() <= (1e-4 if dtype == np.float32 else 1e-12) * scale
    Rd = B.astype(float) - A.astype(float) @ X.astype(float)
    assert np.abs(R - Rd).max() <= (1e-4 if dtype == np.float32 else 1e-12) * np.abs(B).max()
    U = A.copy()
    U.has_sorted_indices = False
    U.indices[A.indptr[0]:A.indptr[1]] = U.indices[A.indptr[0]:A.indptr[1]][::-1]
    with pytest.raises(ValueError, match="sorted indices"):
        presmooth(U, X, B, R)



def _chunk_order(bounds):
    """The rows in the order of the chunked sweeps: the even chunks, then the odd ones."""
    k = len(bounds) - 1
    return np.concatenate([np.arange(bounds[ch], bounds[ch + 1]) for ch in [*range(0, k, 2), *range(1, k, 2)]])


def test_sweep_chunks_split_lattice_rows_and_refuse_scattered_ones(torus_space):
    """On a lattice-ordered matrix the chunks are 8 or 4 with about equal nonzeros, and no row
    couples two chunks of one parity or two chunks besides its own; rows in random order get one
    chunk (the natural sweep); a wrong chunking is refused."""
    from cutfem.solvers.sparse_kernels import gauss_seidel, sweep_chunks

    V = torus_space
    A = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    A.sort_indices()
    n = A.shape[0]
    b = sweep_chunks(A)
    k = len(b) - 1
    assert k in (4, 8) and b[0] == 0 and b[-1] == n
    nnz = np.diff(A.indptr[b])
    assert nnz.max() <= 1.1 * nnz.min()
    owner = np.repeat(np.arange(k), np.diff(b))
    C = sp.coo_matrix(A)
    oi, oj = owner[C.row], owner[C.col]
    other = oi != oj
    assert np.all((oi[other] - oj[other]) % 2 == 1)  # never a chunk of the same parity
    pairs = np.unique(np.column_stack([C.row[other], oj[other]]), axis=0)
    assert np.all(np.bincount(pairs[:, 0], minlength=n) <= 1)  # at most one other chunk a row
    perm = np.random.default_rng(0).permutation(n)
    np.testing.assert_array_equal(sweep_chunks(A[perm][:, perm].tocsr()), [0, n])
    X, B = np.zeros((n, 1)), np.ones((n, 1))
    for bad in ([0, n // 3, 2 * n // 3, n], [0, 5, 3, n], [1, n]):
        with pytest.raises(ValueError, match="chunks must be"):
            gauss_seidel(A, X, B, chunks=bad)


@pytest.mark.parametrize("c", [1, 3])
def test_chunked_sweeps_are_gauss_seidel_in_the_chunk_order(torus_space, c):
    """The chunked forward and backward sweeps are the Gauss-Seidel sweeps of the rows taken in the
    chunk order (checked against the natural sweeps of the permuted matrix, to round-off), and
    presmooth with chunks gives, bitwise, the chunked forward sweep from zero, and R = B - A X."""
    from cutfem.solvers.sparse_kernels import gauss_seidel, presmooth, sweep_chunks

    V = torus_space
    A = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    A.sort_indices()
    n = A.shape[0]
    b = sweep_chunks(A)
    assert len(b) > 2
    order = _chunk_order(b)
    Ap = A[order][:, order].tocsr()
    Ap.sort_indices()
    rng = np.random.default_rng(c)
    B, X0 = rng.standard_normal((n, c)), rng.standard_normal((n, c))
    for forward in (True, False):
        X = gauss_seidel(A, X0.copy(), B, forward=forward, chunks=b)
        Xp = gauss_seidel(Ap, X0[order].copy(), B[order], forward=forward)
        np.testing.assert_allclose(X[order], Xp, rtol=0, atol=1e-12 * np.abs(Xp).max())
        assert np.abs(X - gauss_seidel(A, X0.copy(), B, forward=forward)).max() > 1e-6  # another order indeed
    X, R = np.full((n, c), np.nan), np.full((n, c), np.nan)
    presmooth(A, X, B, R, chunks=b)
    np.testing.assert_array_equal(X, gauss_seidel(A, np.zeros((n, c)), B, forward=True, chunks=b))
    np.testing.assert_allclose(R, B - A @ X, rtol=0, atol=1e-12 * np.abs(B).max())


def test_kernels_give_the_same_bits_on_any_number_of_threads(torus_space):
    """Products with dots, column dots, CG updates, chunked sweeps and a whole multigrid solve give
    bitwise the same on one thread as on all of them (rows are split between threads, sums are
    taken in blocks of rows and added in row order)."""
    import numba


    V = torus_space
    A = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    A.sort_indices()
    n = A.shape[0]
    b = sparse_kernels.sweep_chunks(A)
    rng = np.random.default_rng(1)
    B, P, Q = (rng.standard_normal((n, 3)) for _ in range(3))
    A32 = A.astype(np.float32)

    def run():
        out = {}
        dots = np.empty(3)
        out["product"] = sparse_kernels.matmul(A, P, dots=dots)
        out["dots"] = dots.copy()
        out["column_dots"] = np.concatenate(sparse_kernels.column_dots(B, P, Q))
        x, r = P.copy(), B.copy()
        out["cg"] = sparse_kernels.cg_step(x, r, Q[:, :2], P[:, 1:], np.array([0.3, -0.2]), np.array([0, 2]))
        out["x"], out["r"] = x, r
        out["direction"] = sparse_kernels.cg_direction(P.copy(), B.astype(np.float32), np.array([0.5, 2.0, -1.0]))
        X, R = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        sparse_kernels.presmooth(A32, X, B.astype(np.float32), R, chunks=b)
        out["presmooth"], out["residual"] = X, R
        out["backward"] = sparse_kernels.gauss_seidel(A32, X.copy(), B.astype(np.float32), forward=False, chunks=b)
        out["solve"] = mg_solve(A, B, prolongations=multigrid_hierarchy(V), tol=1e-8)[0]
        return out

    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = run()
    finally:
        numba.set_num_threads(threads)
    every = run()
    for key in one:
        np.testing.assert_array_equal(one[key], every[key], err_msg=key)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("c", [1, 2, 3, 5])
def test_product_with_dots_is_the_product_and_its_column_dots(torus_space, dtype, c):
    """matmul with dots= gives, bitwise, the same product and column_dots(X, A X) (in double
    precision), and agrees with numpy's X^T A X to round-off; wrong dots are refused."""
    from cutfem.solvers.sparse_kernels import column_dots, matmul

    V = torus_space
    A = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr().astype(dtype)
    n = A.shape[0]
    X = np.random.default_rng(c).standard_normal((n, c)).astype(dtype)
    dots = np.full(c, np.nan)
    Y = matmul(A, X, dots=dots)
    np.testing.assert_array_equal(Y, matmul(A, X))
    np.testing.assert_array_equal(dots, column_dots(X.astype(float), Y.astype(float)))
    ref = np.einsum("ij,ij->j", X.astype(float), A.astype(float) @ X.astype(float))
    np.testing.assert_allclose(dots, ref, rtol=1e-5 if dtype == np.float32 else 1e-12)
    with pytest.raises(ValueError, match="dots must be"):
        matmul(A, X, dots=np.zeros(c + 1))
    with pytest.raises(ValueError, match="dots must be"):
        matmul(A[:, : n - 1], X[: n - 1], dots=np.zeros(c))

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

    from cutfem.solvers.solve import CGSolver

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


def test_auto_picks_multigrid_above_the_limit(torus_space, monkeypatch):
    V = torus_space
    K = mass_matrix(V) + 0.1 * face_matrix(V)
    b = np.ones(V.n_dofs)
    monkeypatch.setattr(solve_module, "DIRECT_LIMIT", 1000)
    x, info = solve(K, b, space=V)
    assert info.method == "cg-mg" and info.residual <= solve_module.DEFAULT_TOL
    x2, info2 = solve(K, b)  # no space: no lattice, direct below DIRECT_LIMIT_NO_MG
    assert info2.method == "direct"
    np.testing.assert_allclose(x, x2, rtol=0, atol=1e-5 * np.abs(x2).max())


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


def test_unstabilized_system_is_not_hidden(monkeypatch):
    """tau_F = 0: the nodal vector of phi_h is a null vector of the surface forms; solve() with the
    space reports it on the iterative path too (a consistent right-hand side would hide it)."""
    V = CutP1Space(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=24), Sphere(0.7, [0.03, -0.01, 0.02])))
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    B = A @ V.dof_points
    monkeypatch.setattr(solve_module, "DIRECT_LIMIT", 100)
    for K in (M, A + M):
        with pytest.raises(SolverError, match="phi_h") as err:
            solve(K, B, space=V)
        assert err.value.smallest < 1e-10
    H, info = solve(M + 0.1 * J, B, space=V)  # stabilized: fine
    assert info.method == "cg-mg"


# ---------------------------------------------------------------------------------------------
# meshed surfaces: the periodic grid hierarchy and the surface-to-lattice hierarchy
# ---------------------------------------------------------------------------------------------


def _edge_system(mesh):
    V = SurfaceP1Space(mesh)
    return V, (mass_matrix(V) + 0.1 * edge_matrix(V)).tocsr(), stiffness_matrix(V) @ V.dof_points


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


# ---------------------------------------------------------------------------------------------
# several right-hand sides: simultaneous CG with per-column freezing; the default tolerance
# ---------------------------------------------------------------------------------------------


def test_simultaneous_cg_equals_column_by_column_and_direct(torus_space, monkeypatch):
    """The columns of B run as independent recurrences side by side: each equals its own solve to
    round-off, the block agrees with the direct solution to the tolerance, and a converged column
    is frozen (a zero column costs no product; the products are the sum of the columns' own)."""
    V = torus_space
    K = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    B = np.column_stack([stiffness_matrix(V) @ V.dof_points, np.zeros(V.n_dofs)])  # (n, 4)
    products = []
    matvec = solve_module._matvec
    monkeypatch.setattr(solve_module, "_matvec", lambda A: (lambda X, out=None, dots=None: (products.append(X.shape[1]), matvec(A)(X, out, dots=dots))[1]))
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


@pytest.mark.parametrize("surface", ["cut-0.08", "meshed-96"])
def test_default_tolerance_keeps_the_integral_of_H_at_round_off(surface):
    """int_{S_h} H_h = 1^T M H = -1^T r (1^T B = 0, J 1 = 0): with the default tolerance of the
    multigrid path it stays below 1e-10 of the area (spacing 0.08 is the worst measured: 1.5e-11;
    it was 1.4e-9 with the former 1e-6)."""
    from cutfem.problems.mean_curvature import mean_curvature_system

    if surface == "cut-0.08":
        cut = cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.08), Torus())
        V = CutP1Space(cut)
        ds = cut.ds()
        K, B = mean_curvature_system(V, ds, tau_f=0.1, faces=cut.dF(cut.interior_facets(CUT)))
    else:
        V = SurfaceP1Space(torus_mesh(96, "perturbed", seed=1))
        ds = V.mesh.ds()
        K, B = mean_curvature_system(V, ds, tau_e=0.1)
    H, info = solve(K, B, method="cg-mg", space=V)
    assert info.method == "cg-mg" and info.residual <= solve_module.DEFAULT_TOL
    ones_M = np.asarray(assemble(mass(ds), V).sum(axis=0)).ravel()
    assert np.abs(ones_M @ H).max() <= 1e-10 * ones_M.sum()


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


def test_augmented_hierarchy_doubles_the_coarse_spaces(torus_space):
    """[P_0, diag(w) P_0], then diag(P_l, P_l): level 2 holds P_0 P_1 v and w P_0 P_1 v'."""
    V = torus_space
    ijk = lattice_indices(V)
    w = V.cut.values
    P0, c1 = kuhn_prolongation(ijk)
    P1, _ = kuhn_prolongation(c1)
    hierarchy = solve_module.augmented_hierarchy(solve_module.lattice_hierarchy(ijk), w)
    Q = [next(hierarchy), next(hierarchy)]
    assert Q[0].shape == (V.n_dofs, 2 * P0.shape[1]) and Q[1].shape == (2 * P1.shape[0], 2 * P1.shape[1])
    rng = np.random.default_rng(1)
    v, v2 = rng.normal(size=P1.shape[1]), rng.normal(size=P1.shape[1])
    np.testing.assert_allclose(Q[0] @ (Q[1] @ np.concatenate([v, v2])), P0 @ (P1 @ v) + w * (P0 @ (P1 @ v2)), atol=1e-12)
    with pytest.raises(ValueError, match="augment must be .* shape"):
        GeometricMultigrid(sp.eye(V.n_dofs, format="csr"), ijk, augment=w[:-1])


@pytest.mark.parametrize("c", [1, 3])
def test_column_dots_of_three_blocks_and_mixed_precision(c):
    """column_dots(a, b, c) is, bitwise, (column_dots(a, b), column_dots(b, c)); a float32 block is
    read as the float64 block of the same values (no copy needed for the same result); the sums
    agree with numpy's to round-off and do not depend on the columns beside a column."""
    from cutfem.jit import SUM_BLOCK
    from cutfem.solvers.sparse_kernels import column_dots

    rng = np.random.default_rng(7)
    n = 3 * SUM_BLOCK + 17
    a, b, q = (rng.standard_normal((n, c)) for _ in range(3))
    b32 = b.astype(np.float32)
    ab, bq = column_dots(a, b32, q)
    np.testing.assert_array_equal(ab, column_dots(a, b32.astype(float)))
    np.testing.assert_array_equal(bq, column_dots(b32.astype(float), q))
    np.testing.assert_allclose(ab, np.einsum("ij,ij->j", a, b32.astype(float)), rtol=1e-12)
    np.testing.assert_array_equal(column_dots(a[:, :1], b32[:, :1], q[:, :1])[1], bq[:1])


def test_csr_diagonal_is_scipys():
    """The compiled diagonal equals scipy's A.diagonal() bitwise: duplicates on the diagonal summed,
    a missing diagonal entry zero, unsorted rows, rectangular matrices, float32 kept."""
    from cutfem.solvers.sparse_kernels import csr_diagonal

    rng = np.random.default_rng(11)
    n, per_row = 300, 12
    indices = rng.integers(0, n, (n, per_row))  # unsorted rows, with repeated columns
    indices[::3, :2] = np.arange(0, n, 3)[:, None]  # every third row: its diagonal twice
    indices[1::3] = np.where(indices[1::3] == np.arange(1, n, 3)[:, None], 0, indices[1::3])  # these rows: none
    A = sp.csr_matrix((rng.standard_normal(n * per_row), indices.reshape(-1), np.arange(0, n * per_row + 1, per_row)),
                      shape=(n, n))
    assert not A.has_canonical_format
    d = csr_diagonal(A)
    np.testing.assert_array_equal(d, A.diagonal())
    assert np.all(d[1::3] == 0) and np.all(d[::3] != 0)
    C = A.copy()
    C.sum_duplicates()  # canonical: the binary search
    assert C.has_canonical_format
    for B in (C, A[:200], A[:, :120], A.astype(np.float32), C[:, :120]):
        B = sp.csr_matrix(B)
        d = csr_diagonal(B)
        assert d.dtype == B.dtype
        np.testing.assert_array_equal(d, B.diagonal())


def test_single_precision_application_is_the_cycle_output(torus_space):
    """GeometricMultigrid.apply(R, single=True) (what mg_solve's CG uses) returns the float32
    values whose float64 copy apply(R) returns."""
    from cutfem.solvers.solve import GeometricMultigrid, lattice_indices

    V = torus_space
    A = (mass_matrix(V) + 0.1 * face_matrix(V)).tocsr()
    mg = GeometricMultigrid(A, lattice_indices(V), coarse_size=50)
    R = np.random.default_rng(3).standard_normal((A.shape[0], 3))
    Z = mg.apply(R)
    Z32 = mg.apply(R, single=True)
    assert Z32.dtype == np.float32 and Z.dtype == np.float64
    np.testing.assert_array_equal(Z32.astype(float), Z)


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="fork exists on POSIX systems only")
def test_kernels_in_a_process_forked_after_the_threads_started(tmp_path):
    """A process forked after its parent ran the threaded kernels (multiprocessing's default on
    Linux) gets the same bits from the kernels, compiled there for one thread, with one warning
    naming the fix; on GNU OpenMP the threaded kernels would end it with SIGTERM."""
    import json
    import subprocess
    import sys

    code = """
import json, os, warnings
import numpy as np, scipy.sparse as sp
from cutfem.solvers import sparse_kernels
n = 5000
rng = np.random.default_rng(0)
offsets = [-40, -3, -1, 0, 1, 3, 40]  # a band, as lattice rows: sweep_chunks finds chunks
A = sp.diags([rng.random(n - abs(k)) + (10.0 if k == 0 else 0.0) for k in offsets], offsets, format="csr")
A = (A + A.T).tocsr()
A.sort_indices()
chunks = sparse_kernels.sweep_chunks(A)
assert len(chunks) == 9
X = rng.standard_normal((n, 3))
def run():
    dots = np.empty(3)
    Y = sparse_kernels.matmul(A, X, dots=dots)
    Z = sparse_kernels.gauss_seidel(A, X.copy(), Y, forward=False, chunks=chunks)
    return [Y.tobytes().hex(), dots.tobytes().hex(), Z.tobytes().hex()]
parent = run()
read, write = os.pipe()
pid = os.fork()
if pid == 0:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        child = run()
    os.write(write, json.dumps({"same": child == parent, "warnings": [str(w.message) for w in caught]}).encode())
    os._exit(0)
os.close(write)
data = b""
while chunk := os.read(read, 1 << 16):
    data += chunk
_, status = os.waitpid(pid, 0)
import numba
print(json.dumps({"status": status, "layer": numba.threading_layer(), **json.loads(data or b"{}")}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["status"] == 0 and res["same"] is True
    if res["layer"] == "omp" and sys.platform.startswith("linux"):  # GNU OpenMP: the child compiled its kernels for one thread, and said so once
        assert len(res["warnings"]) == 1 and "'spawn' or 'forkserver'" in res["warnings"][0]
    else:
        assert res["warnings"] == []


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
