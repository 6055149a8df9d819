"""Compiled kernels of the geometric multigrid's setup: the prolongation of a structured box
between Kuhn levels, the prolongation weights of a periodic surface grid, and the Galerkin product
P^T A P row by row with a dense accumulator (its upper triangle, then mirrored: exactly symmetric).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit, prange

from ..geometry.numbering import index_dtype
from ..jit import parallel_kernel

@njit(cache=True, error_model="numpy")
def kuhn_ends_bounds(ijk, bounds):
    """``bounds`` (2, 3) = the smallest and largest indices of the ends (ijk - o) / 2 and
    (ijk + o) / 2, o = ijk mod 2, of the coarse Kuhn edges of the fine nodes ``ijk`` (m, 3)
    (:func:`cutfem.solvers.multigrid.kuhn_prolongation`)."""
    for a in range(3):
        bounds[0, a] = (ijk[0, a] - (ijk[0, a] & 1)) >> 1
        bounds[1, a] = bounds[0, a]
    for i in range(ijk.shape[0]):
        for a in range(3):
            o = ijk[i, a] & 1
            lo = (ijk[i, a] - o) >> 1
            if lo < bounds[0, a]:
                bounds[0, a] = lo
            if lo + o > bounds[1, a]:
                bounds[1, a] = lo + o


@njit(cache=True, error_model="numpy")
def kuhn_ends_codes(ijk, base, dims, codes):
    """``codes`` (2m,): the lexicographic numbers x + dims_0 (y + dims_1 z) relative to ``base`` of
    the lower ends of the coarse Kuhn edges of the fine nodes ``ijk`` (m, 3), then of the upper
    ends (the node itself twice where every index is even)."""
    m = ijk.shape[0]
    for i in range(m):
        lo = 0
        hi = 0
        for a in range(2, -1, -1):
            o = ijk[i, a] & 1
            x = ((ijk[i, a] - o) >> 1) - base[a]
            lo = lo * dims[a] + x
            hi = hi * dims[a] + x + o
        codes[i] = lo
        codes[m + i] = hi


@njit(cache=True, error_model="numpy")
def kuhn_prolongation_csr(ijk, cols, indptr, indices, data):
    """The CSR arrays of the Kuhn prolongation (:func:`cutfem.solvers.multigrid.kuhn_prolongation`): row i is 1
    at column ``cols[i]`` when every index of ``ijk[i]`` is even, else 1/2 at ``cols[i]`` and at
    ``cols[m + i]`` (the two ends of its coarse edge, the lower first); ``indptr`` (m + 1,)."""
    m = ijk.shape[0]
    indptr[0] = 0
    n = 0
    for i in range(m):
        two = ((ijk[i, 0] | ijk[i, 1] | ijk[i, 2]) & 1) != 0
        indices[n] = cols[i]
        if two:
            data[n] = 0.5
            indices[n + 1] = cols[m + i]
            data[n + 1] = 0.5
            n += 2
        else:
            data[n] = 1.0
            n += 1
        indptr[i + 1] = n


@parallel_kernel
def _galerkin_upper(r_ptr, r_idx, r_val, a_ptr, a_idx, a_val, p_ptr, p_idx, p_val, nc, bounds, starts, stops, todo, count,
                    idx, val, strict):
    """The upper triangles of the rows of P^T A P for the chunks ``ch`` of ``bounds`` with
    ``todo[ch]`` (in parallel): the rows of chunk ch one after the other in idx/val[starts[ch]:
    stops[ch]], the length of row I in count[I].  strict[ch] becomes -1 if the chunk's rows
    overflowed their room, else the number of its entries right of the diagonal."""
    nch = bounds.shape[0] - 1
    for ch in prange(nch):
        if not todo[ch]:
            continue
        strict[ch] = 0
        acc = np.zeros(nc)
        mark = np.full(nc, -1, dtype=np.int64)
        cols = np.empty(nc, dtype=np.int64)
        nnz = starts[ch]
        room = stops[ch]
        for I in range(bounds[ch], bounds[ch + 1]):
            ncols = 0
            for ii in range(r_ptr[I], r_ptr[I + 1]):
                i, ri = r_idx[ii], r_val[ii]
                for jj in range(a_ptr[i], a_ptr[i + 1]):
                    j, ra = a_idx[jj], ri * a_val[jj]
                    for kk in range(p_ptr[j], p_ptr[j + 1]):
                        J = p_idx[kk]
                        if J < I:
                            continue
                        if mark[J] != I:
                            mark[J] = I
                            cols[ncols] = J
                            ncols += 1
                            acc[J] = 0.0
                        acc[J] += ra * p_val[kk]
            if nnz + ncols > room:
                strict[ch] = -1
                break
            for x in range(1, ncols):  # insertion sort of the row's columns (a few dozen)
                c = cols[x]
                y = x - 1
                while y >= 0 and cols[y] > c:
                    cols[y + 1] = cols[y]
                    y -= 1
                cols[y + 1] = c
            for x in range(ncols):
                idx[nnz + x] = cols[x]
                val[nnz + x] = acc[cols[x]]
                if cols[x] > I:
                    strict[ch] += 1
            nnz += ncols
            count[I] = ncols


@njit(cache=True, error_model="numpy")
def _mirror_upper(bounds, starts, count, idx, val, indptr, indices, data):
    """The full CSR arrays of the symmetric matrix whose upper triangles :func:`_galerkin_upper`
    wrote (row I of chunk ch after the rows before it, from starts[ch])."""
    n = count.shape[0]
    start = np.empty(n, dtype=np.int64)
    for ch in range(bounds.shape[0] - 1):
        pos = starts[ch]
        for I in range(bounds[ch], bounds[ch + 1]):
            start[I] = pos
            pos += count[I]
    lower = np.zeros(n, dtype=np.int64)
    for I in range(n):
        for x in range(start[I], start[I] + count[I]):
            if idx[x] > I:
                lower[idx[x]] += 1
    indptr[0] = 0
    for I in range(n):
        indptr[I + 1] = indptr[I] + lower[I] + count[I]
    nxt = indptr[:-1].copy()
    for I in range(n):
        pos = indptr[I] + lower[I]
        for x in range(start[I], start[I] + count[I]):
            J = idx[x]
            indices[pos], data[pos] = J, val[x]
            pos += 1
            if J > I:
                indices[nxt[J]], data[nxt[J]] = I, val[x]
                nxt[J] += 1


#: coarse rows of the Galerkin product per parallel chunk (about; at most 64 chunks)
GALERKIN_ROWS = 4096


#: the room first given to each coarse row's upper triangle in the Galerkin product (entries; a
#: chunk whose rows need more is done again with twice its room, the others are kept).  Room that
#: is not written costs address space only: the pages of np.empty are never touched.  The upper
#: triangles need about 9 entries a row on the cut torus, 13 on the perturbed torus grids (25-point
#: coarse stencils) and more than 24 with the augmented hierarchy of the cut Laplace-Beltrami
#: problem; with room for 12, every chunk of those two was computed twice or three times (the
#: coarse operators of the meshed torus 768 x 384, perturbed: 0.19 s against 0.31 s; the Galerkin
#: products of `cutfem run laplace-beltrami-cut --levels 0.025 0.0125`: 0.21-0.24 s against
#: 0.49-0.74 s, 11 passes against 25).
GALERKIN_ROOM = 32


def galerkin(A, P, R=None):
    """The Galerkin product P^T A P of a symmetric CSR matrix A (n, n) and a CSR prolongation P
    (n, m), as a CSR matrix with sorted indices, exactly symmetric: each coarse row I sums only its
    columns J >= I (sum over i, j of R[I, i] A[i, j] P[j, J], R = P^T, with a dense accumulator
    and a marker per coarse column), and the lower triangle is their mirror.  ``R``: P^T in CSR,
    when the caller has it.  One pass over the products, where scipy's two sparse products build
    A P first (and their result still needs symmetrizing).  The coarse rows go in chunks on the
    available cores, each into room for :data:`GALERKIN_ROOM` entries a row; a chunk that needs
    more is done again, alone, with twice its room (the chunks that fitted are kept: on the cut
    torus at spacing 0.00625, 2 chunks of 64 overflowed, and redoing all of them doubled the
    product's time).  The values depend neither on the number of threads nor on the retries."""
    R = sp.csr_matrix(P.T) if R is None else R
    R, A, P = (sp.csr_matrix(M) for M in (R, A, P))
    m = P.shape[1]
    args = []
    for M in (R, A, P):
        args += [M.indptr, M.indices, M.data.astype(float, copy=False)]
    nch = int(min(64, max(1, m // GALERKIN_ROWS)))
    bounds = (np.arange(nch + 1, dtype=np.int64) * m) // nch
    count = np.zeros(m, dtype=np.int64)
    rooms = GALERKIN_ROOM * np.diff(bounds)
    starts = np.concatenate([[0], np.cumsum(rooms)[:-1]]).astype(np.int64)
    strict, todo = np.zeros(nch, dtype=np.int64), np.ones(nch, dtype=np.bool_)
    idx, val = np.empty(int(rooms.sum()), dtype=index_dtype(m)), np.empty(int(rooms.sum()))
    while True:
        _galerkin_upper(*args, np.int64(m), bounds, starts, starts + rooms, todo, count, idx, val, strict)
        todo = strict < 0
        if not todo.any():
            break
        # the chunks that overflowed get twice their room in new arrays, into which the others'
        # rows are copied (only what they wrote: the pages of unused room are never touched)
        csum = np.concatenate([[0], np.cumsum(count)])
        used = csum[bounds[1:]] - csum[bounds[:-1]]
        rooms = np.where(todo, 2 * rooms, rooms)
        fresh = np.concatenate([[0], np.cumsum(rooms)[:-1]]).astype(np.int64)
        new_idx, new_val = np.empty(int(rooms.sum()), dtype=idx.dtype), np.empty(int(rooms.sum()))
        for ch in np.flatnonzero(~todo):  # chunks (at most 64), not rows
            a, b, k = starts[ch], fresh[ch], used[ch]
            new_idx[b : b + k] = idx[a : a + k]
            new_val[b : b + k] = val[a : a + k]
        idx, val, starts = new_idx, new_val, fresh
    nnz = int(count.sum() + strict.sum())
    index = index_dtype(nnz)  # int32 written here: scipy checks int64 contents min/max to narrow them
    indptr, indices, data = np.empty(m + 1, dtype=index), np.empty(nnz, dtype=index), np.empty(nnz)
    _mirror_upper(bounds, starts, count, idx, val, indptr, indices, data)
    out = sp.csr_matrix((data, indices, indptr), shape=(m, m))
    out.has_canonical_format = True  # sorted rows without duplicates, by construction (saves scipy's scans)
    return out


@njit(cache=True, error_model="numpy")
def grid_weights(X, n, m, drop):
    """The four coarse corners and weights of each node of a doubly periodic (n, m) surface grid,
    for :func:`cutfem.solvers.multigrid.grid_prolongation` (which states the weights): node (i, j), index
    i m + j, in the coarse cell (2a, 2b) + {0, 2}^2, corners (a, b), (a + 1, b), (a + 1, b + 1),
    (a, b + 1) modulo (n/2, m/2).  Returns (cols (n m, 4), weights (n m, 4)); a coarse node gets
    the weights (1, 0, 0, 0).  A node on a coarse edge (one index odd) whose two weights off that
    edge are both below ``drop`` in magnitude takes the weights (1 - s, s) of its projection
    X_0 + s (X_1 - X_0) on the edge instead.  One pass over the nodes, where numpy made (n m, 4, 3)
    blocks."""
    nc, mc = n // 2, m // 2
    N = n * m
    cols = np.empty((N, 4), np.int64)
    w = np.empty((N, 4))
    D = np.empty((4, 3))
    u = np.empty(4)
    v = np.empty(4)
    for p in range(N):
        i, j = p // m, p % m
        a, b = i // 2, j // 2
        a1, b1 = (a + 1) % nc, (b + 1) % mc
        cols[p, 0], cols[p, 1], cols[p, 2], cols[p, 3] = a * mc + b, a1 * mc + b, a1 * mc + b1, a * mc + b1
        if i % 2 == 0 and j % 2 == 0:
            w[p, 0], w[p, 1], w[p, 2], w[p, 3] = 1.0, 0.0, 0.0, 0.0
            continue
        for k in range(4):
            q = 2 * (cols[p, k] // mc) * m + 2 * (cols[p, k] % mc)
            for c in range(3):
                D[k, c] = X[q, c] - X[p, c]
        su = sv = suu = svv = suv = 0.0
        for k in range(4):
            u[k] = D[k, 0] * (D[2, 0] - D[0, 0]) + D[k, 1] * (D[2, 1] - D[0, 1]) + D[k, 2] * (D[2, 2] - D[0, 2])
            v[k] = D[k, 0] * (D[3, 0] - D[1, 0]) + D[k, 1] * (D[3, 1] - D[1, 1]) + D[k, 2] * (D[3, 2] - D[1, 2])
            su += u[k]
            sv += v[k]
            suu += u[k] * u[k]
            svv += v[k] * v[k]
            suv += u[k] * v[k]
        c0 = suu * svv - suv * suv
        c1 = suv * sv - su * svv
        c2 = su * suv - suu * sv
        det = 4.0 * c0 + su * c1 + sv * c2
        for k in range(4):
            w[p, k] = (c0 + c1 * u[k] + c2 * v[k]) / det
        if i % 2 == 1 and j % 2 == 1:
            continue
        e = 1 if j % 2 == 0 else 3  # the other end of the node's coarse edge, from corner 0
        f, g = (2, 3) if e == 1 else (1, 2)  # the corners off it
        if abs(w[p, f]) < drop and abs(w[p, g]) < drop:
            se = sx = 0.0  # X_p - X_0 = -D_0, X_1 - X_0 = D_e - D_0
            for c in range(3):
                se += (D[e, c] - D[0, c]) * (D[e, c] - D[0, c])
                sx += -D[0, c] * (D[e, c] - D[0, c])
            s = sx / se
            w[p, 0], w[p, e], w[p, f], w[p, g] = 1.0 - s, s, 0.0, 0.0
    return cols, w
