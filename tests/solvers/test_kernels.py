"""The compiled kernels of the solvers (cutfem.solvers.sparse_kernels, multigrid_kernels): the Galerkin
product, sweeps, products and dot products against scipy and numpy, bitwise the same on any number
of threads and in a forked process.

References: scipy's sparse products and triangular solves, numpy's sums, computed in the test.
"""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve_triangular

from cutfem.solvers import sparse_kernels
from cutfem.solvers.krylov import mg_solve
from cutfem.solvers.multigrid import multigrid_hierarchy
from surface_matrices import face_matrix, mass_matrix


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
