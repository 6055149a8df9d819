"""Compiled sparse kernels of the iterative solvers, for blocks of up to :data:`WIDTH` columns.

Several right-hand sides share one matrix (the three components of the mean curvature vector), and
CG with multigrid is one recurrence per column; scipy's and pyamg's kernels take one vector, so
every column would read the matrix again.  These read a row once for up to three columns stored
side by side ((n, c), row-major), one register accumulator per column: the product, the
Gauss-Seidel sweep, the presmoothing with its residual, the column dots and the CG updates.

Rows are shared between the cores in blocks of :data:`cutfem.jit.SUM_BLOCK` and the partial sums
added in row order, so results are bitwise the same on any number of threads.  A Gauss-Seidel
sweep is sequential; on a matrix whose rows follow a lattice, :func:`sweep_chunks` cuts the rows
into chunks such that chunks of the same parity are not coupled, and the sweep takes the even
chunks together, then the odd ones.  Indices are read as unsigned and the error model is numpy's
(Python's index and division checks in the inner loop doubled a sweep's time).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import prange

from ..jit import SUM_BLOCK, SWEEP_CHUNKS, _add_blocks, parallel_kernel

#: columns served by one pass over the matrix (one register accumulator each)
WIDTH = 3


_COMPILED: dict = {}


def _kernels(c: int):
    """The product and sweep kernels for blocks of exactly ``c`` columns (c <= WIDTH); ``c`` is a
    compile-time constant of the closures, so the unused accumulators vanish."""
    if c in _COMPILED:
        return _COMPILED[c]

    @parallel_kernel
    def product(indptr, indices, data, X, Y, alpha, accumulate, dots):
        """Y = alpha A X (accumulate: Y += alpha A X), X (n_in, c), Y (n_out, c); with ``dots`` (c,)
        not empty (A square), also dots += the column dot products of X and the new Y in double
        precision, summed as :func:`column_dots` sums."""
        n = Y.shape[0]
        with_dots = dots.shape[0] > 0
        nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
        part = np.zeros((nblocks if with_dots else 0, 3))
        for b in prange(nblocks):
            d0 = d1 = d2 = 0.0
            for i in range(b * SUM_BLOCK, min((b + 1) * SUM_BLOCK, n)):
                s0 = s1 = s2 = Y.dtype.type(0)
                for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + 1])):
                    j = np.uint64(indices[k])
                    a = data[k]
                    s0 += a * X[j, 0]
                    if c > 1:
                        s1 += a * X[j, 1]
                    if c > 2:
                        s2 += a * X[j, 2]
                if accumulate:
                    Y[i, 0] += alpha * s0
                    if c > 1:
                        Y[i, 1] += alpha * s1
                    if c > 2:
                        Y[i, 2] += alpha * s2
                else:
                    Y[i, 0] = alpha * s0
                    if c > 1:
                        Y[i, 1] = alpha * s1
                    if c > 2:
                        Y[i, 2] = alpha * s2
                if with_dots:
                    d0 += np.float64(X[i, 0]) * np.float64(Y[i, 0])
                    if c > 1:
                        d1 += np.float64(X[i, 1]) * np.float64(Y[i, 1])
                    if c > 2:
                        d2 += np.float64(X[i, 2]) * np.float64(Y[i, 2])
            if with_dots:
                part[b, 0] = d0
                part[b, 1] = d1
                part[b, 2] = d2
        if with_dots:
            _add_blocks(part, dots)

    @parallel_kernel
    def sweep(indptr, indices, data, X, B, forward, bounds):
        """One Gauss-Seidel sweep for A X = B in place in the chunk order of ``bounds`` (see
        :func:`sweep_chunks`): forward, the even chunks (in parallel, each in increasing row order),
        then the odd ones; backward, the reverse.  A must have its diagonal stored."""
        nch = bounds.shape[0] - 1
        for phase in range(2):
            color = phase if forward else 1 - phase
            for h in prange((nch - color + 1) // 2):
                ch = 2 * h + color
                lo, hi = bounds[ch], bounds[ch + 1]
                for t in range(hi - lo):
                    i = np.uint64(lo + t if forward else hi - 1 - t)
                    d = data[0]
                    s0 = B[i, 0]
                    s1 = B[i, 1] if c > 1 else s0
                    s2 = B[i, 2] if c > 2 else s0
                    for k in range(np.uint64(indptr[i]), np.uint64(indptr[i + 1])):
                        j = np.uint64(indices[k])
                        a = data[k]
                        if j == i:
                            d = a
                        else:
                            s0 -= a * X[j, 0]
                            if c > 1:
                                s1 -= a * X[j, 1]
                            if c > 2:
                                s2 -= a * X[j, 2]
                    X[i, 0] = s0 / d
                    if c > 1:
                        X[i, 1] = s1 / d
                    if c > 2:
                        X[i, 2] = s2 / d

    @parallel_kernel
    def presweep(indptr, indices, data, X, B, R, bounds):
        """One forward Gauss-Seidel sweep (the chunk order of ``bounds``) for A X = B from X = 0
        (X written, not read first) and the residual R = B - A X; A exactly symmetric with sorted
        rows and its diagonal stored.  The entries of row i swept before it: in an even chunk
        [lo, hi), those with lo <= j < i; in an odd one, those with j < i or j >= hi."""
        nch = bounds.shape[0] - 1
        zero = R.dtype.type(0)
        one = np.uint64(1)
        for color in range(2):
            for h in prange((nch - color + 1) // 2):
                ch = 2 * h + color
                lo, hi = np.uint64(bounds[ch]), np.uint64(bounds[ch + 1])
                for i in range(lo, hi):
                    start, stop = np.uint64(indptr[i]), np.uint64(indptr[i + 1])
                    first = start
                    if color == 0:
                        while first < stop and np.uint64(indices[first]) < lo:  # another chunk, not swept yet
                            first += one
                    s0 = B[i, 0]
                    s1 = B[i, 1] if c > 1 else s0
                    s2 = B[i, 2] if c > 2 else s0
                    if color == 1:
                        first = start
                    # the entries before the diagonal, summed while it is found (a search first, then one
                    # loop over both segments as in the residual below, was 10 % slower: 6.2 against 5.5 ms)
                    diag = first
                    while diag < stop:
                        j = np.uint64(indices[diag])
                        if j >= i:
                            break
                        a = data[diag]
                        s0 -= a * X[j, 0]
                        if c > 1:
                            s1 -= a * X[j, 1]
                        if c > 2:
                            s2 -= a * X[j, 2]
                        diag += one
                    d = data[diag] if diag < stop and np.uint64(indices[diag]) == i else data[0]
                    above = stop  # the entries in the chunk after, swept before row i when it is odd
                    if color == 1:
                        while above > diag and np.uint64(indices[above - one]) >= hi:
                            above -= one
                        for k in range(above, stop):
                            j = np.uint64(indices[k])
                            a = data[k]
                            s0 -= a * X[j, 0]
                            if c > 1:
                                s1 -= a * X[j, 1]
                            if c > 2:
                                s2 -= a * X[j, 2]
                    x0, x1, x2 = s0 / d, s1 / d, s2 / d
                    X[i, 0] = x0
                    R[i, 0] = zero
                    if c > 1:
                        X[i, 1] = x1
                        R[i, 1] = zero
                    if c > 2:
                        X[i, 2] = x2
                        R[i, 2] = zero
                    for seg in range(2):  # x_i is final: its term in the rows swept before it
                        for k in range(first, diag) if seg == 0 else range(above, stop):
                            j = np.uint64(indices[k])
                            a = data[k]
                            R[j, 0] -= a * x0
                            if c > 1:
                                R[j, 1] -= a * x1
                            if c > 2:
                                R[j, 2] -= a * x2

    _COMPILED[c] = (product, sweep, presweep)
    return product, sweep, presweep


def _csr(A):
    if not sp.isspmatrix_csr(A) and not isinstance(A, sp.csr_array):
        raise TypeError(f"the compiled kernels take a CSR matrix, got {type(A).__name__}")
    return A.indptr, A.indices, A.data


def _groups(c: int):
    return [slice(g, min(g + WIDTH, c)) for g in range(0, c, WIDTH)]


_NO_DOTS = np.zeros(0)


def matmul(A, X, out=None, alpha: float = 1.0, accumulate: bool = False, dots=None):
    """``out = alpha A X`` (``accumulate``: ``out += alpha A X``) for a CSR matrix A and a block X
    (n, c) of the matrix's dtype, C-contiguous; returns ``out`` (allocated when None).  One pass
    over A for each :data:`WIDTH` columns.

    ``dots``: a float64 array (c,) for a square A, overwritten with the column dot products of X
    and ``out`` computed in the same pass, bitwise :func:`column_dots` (X, out), in double
    precision whatever the blocks' dtype (CG's p^T A p without reading p and A p again: at 4.7
    million unknowns and three columns, 0.23 GB an iteration)."""
    indptr, indices, data = _csr(A)
    if X.ndim != 2 or X.shape[0] != A.shape[1] or X.dtype != data.dtype or not X.flags.c_contiguous:
        raise ValueError(f"X must be a C-contiguous ({A.shape[1]}, c) block of {data.dtype}, got {X.shape} {X.dtype}")
    c = X.shape[1]
    if out is None:
        if accumulate:
            raise ValueError("accumulate=True needs out=")
        out = np.empty((A.shape[0], c), dtype=data.dtype)
    if dots is None:
        dots = _NO_DOTS
    elif dots.shape != (c,) or dots.dtype != np.float64 or A.shape[0] != A.shape[1]:
        raise ValueError(f"dots must be a float64 array ({c},) and A square, got {dots.shape} {dots.dtype} and A {A.shape}")
    else:
        dots[:] = 0.0
    alpha = data.dtype.type(alpha)
    if c <= WIDTH:
        _kernels(c)[0](indptr, indices, data, X, out, alpha, accumulate, dots)
        return out
    for g in _groups(c):
        Y = np.ascontiguousarray(out[:, g]) if accumulate else np.empty((A.shape[0], g.stop - g.start), data.dtype)
        part = dots[g] if dots.shape[0] else _NO_DOTS
        _kernels(g.stop - g.start)[0](indptr, indices, data, np.ascontiguousarray(X[:, g]), Y, alpha, accumulate, part)
        out[:, g] = Y
    return out


@parallel_kernel
def _csr_diagonal(indptr, indices, data, canonical, out):
    for i in prange(out.shape[0]):
        s = data.dtype.type(0)
        lo, hi = indptr[i], indptr[i + 1]
        if canonical:  # sorted, no duplicates: a binary search reads a few indices of the row
            while lo < hi:
                mid = (lo + hi) // 2
                if indices[mid] < i:
                    lo = mid + 1
                else:
                    hi = mid
            if lo < indptr[i + 1] and indices[lo] == i:
                s = data[lo]
        else:
            for k in range(lo, hi):
                if indices[k] == i:
                    s += data[k]
        out[i] = s


def csr_diagonal(A):
    """The diagonal of a CSR matrix (min(n, m),), the entries of a row on the diagonal summed as
    scipy's ``A.diagonal()`` sums them, on all cores; in a matrix flagged canonical (sorted rows
    without duplicates) each row's entry is found by a binary search.  scipy's serial pass took
    29 ms for the 19.8 million entries of the cut torus at spacing 0.00625, and a solve asked for
    it twice."""
    indptr, indices, data = _csr(A)
    out = np.empty(min(A.shape), dtype=data.dtype)
    _csr_diagonal(indptr, indices, data, bool(A.has_canonical_format), out)
    return out


@parallel_kernel
def _column_dots(a, b, c, out, out_c):
    n, k = a.shape
    with_c = c.shape[0] > 0
    nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
    part = np.zeros((nblocks, k))
    part_c = np.zeros((nblocks, k if with_c else 0))
    for blk in prange(nblocks):
        for i in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, n)):
            for l in range(k):
                bi = np.float64(b[i, l])
                part[blk, l] += np.float64(a[i, l]) * bi
                if with_c:
                    part_c[blk, l] += bi * np.float64(c[i, l])
    _add_blocks(part, out)
    if with_c:
        _add_blocks(part_c, out_c)


_NO_BLOCK = np.zeros((0, 0))


def _float_block(a):
    a = np.ascontiguousarray(a)
    return a if a.dtype in (np.float32, np.float64) else a.astype(float)


def column_dots(a, b, c=None):
    """The dot products of the columns of a and b (n, k), in double precision: in blocks of
    :data:`SUM_BLOCK` rows, in row order, so a column's result does not depend on the columns
    beside it (numpy's strided reductions change their order with k; CG's scalars, and so its
    iterates, would differ in the last bits between a column solved alone and in a block).
    float32 and float64 blocks are read as they are (the products are formed in double precision,
    so the result is that of the blocks converted to float64), anything else as float64.

    With ``c`` (n, k): returns ``(a^T b, b^T c)`` column by column, both from one pass over the
    three blocks and each bitwise what it is alone (CG's r^T z and z^T q: one read of z)."""
    a, b = _float_block(a), _float_block(b)
    out = np.zeros(a.shape[1])
    if c is None:
        _column_dots(a, b, _NO_BLOCK, out, out)
        return out
    c = _float_block(c)
    out_c = np.zeros(a.shape[1])
    _column_dots(a, b, c, out, out_c)
    return out, out_c


@parallel_kernel
def _cg_step(x, r, p, q, alpha, act, out):
    n, k = p.shape
    nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
    part = np.zeros((nblocks, k))
    for blk in prange(nblocks):
        for i in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, n)):
            for l in range(k):
                c = act[l]
                x[i, c] += alpha[l] * p[i, l]
                ri = r[i, c] - alpha[l] * q[i, l]
                r[i, c] = ri
                part[blk, l] += ri * ri
    _add_blocks(part, out)


def cg_step(x, r, p, q, alpha, act):
    """The CG update of the active columns ``act`` (k,) of x and r (n, c) in place:
    x[:, act] += alpha p, r[:, act] -= alpha q (p, q (n, k)); returns ||r[:, act]||^2 (k,), summed as
    :func:`column_dots` sums (one pass instead of five numpy operations on (n, c) arrays)."""
    out = np.zeros(len(act))
    _cg_step(x, r, np.ascontiguousarray(p), np.ascontiguousarray(q), np.asarray(alpha, dtype=float),
             np.asarray(act, dtype=np.int64), out)
    return out


@parallel_kernel
def _cg_direction(p, z, beta):
    n, k = p.shape
    for i in prange(n):
        for l in range(k):
            p[i, l] = np.float64(z[i, l]) + beta[l] * p[i, l]


def cg_direction(p, z, beta):
    """p = z + beta p in place (the next CG search directions, (n, k), C-contiguous, float64; z of
    float64 or float32, read as it is)."""
    _cg_direction(p, _float_block(z), np.asarray(beta, dtype=float))
    return p


def _check_blocks(A, names, X, *others):
    """ValueError unless X and ``others`` are C-contiguous (n, c) blocks of A's dtype, all of X's shape."""
    for Z in (X, *others):
        if Z.shape != X.shape or Z.ndim != 2 or Z.shape[0] != A.shape[0] or Z.dtype != A.dtype \
                or not Z.flags.c_contiguous:
            raise ValueError(f"{names} must be C-contiguous ({A.shape[0]}, c) blocks of {A.dtype}, got {Z.shape} {Z.dtype}")


def _bounds(A, chunks):
    if chunks is None:
        return np.array([0, A.shape[0]], dtype=np.int64)
    chunks = np.asarray(chunks, dtype=np.int64)
    if chunks.ndim != 1 or chunks.size < 2 or chunks[0] != 0 or chunks[-1] != A.shape[0] or np.any(np.diff(chunks) < 0) \
            or (chunks.size > 2 and (chunks.size - 1) % 2):
        raise ValueError(f"chunks must be the bounds 0 = b_0 <= ... <= b_k = {A.shape[0]} of 1 or an even number k of row "
                         f"chunks (sweep_chunks(A)), got {chunks!r}")
    return chunks


def gauss_seidel(A, X, B, forward: bool = True, chunks=None):
    """One Gauss-Seidel sweep for ``A X = B`` in place on X (n, c), C-contiguous, of A's dtype: rows in
    increasing order (``forward``) or the reverse.  A is CSR with its diagonal stored (nonzero).

    ``chunks``: the row-chunk bounds of :func:`sweep_chunks` (None: one chunk, the rows in their
    order).  The sweep then takes the rows chunk by chunk, the even chunks first (at the same time on
    the available cores: no two of them are coupled), then the odd ones, each chunk in increasing
    row order; backward, the exact reverse.  It is the Gauss-Seidel sweep of that reordering of the
    rows, whatever the number of threads (bitwise)."""
    indptr, indices, data = _csr(A)
    _check_blocks(A, "X and B", X, B)
    bounds = _bounds(A, chunks)
    c = X.shape[1]
    if c <= WIDTH:
        _kernels(c)[1](indptr, indices, data, X, B, forward, bounds)
        return X
    for g in _groups(c):
        Y = np.ascontiguousarray(X[:, g])
        _kernels(g.stop - g.start)[1](indptr, indices, data, Y, np.ascontiguousarray(B[:, g]), forward, bounds)
        X[:, g] = Y
    return X


def presmooth(A, X, B, R, chunks=None):
    """The first half of a multigrid cycle on one pass over A: X = one forward Gauss-Seidel sweep for
    ``A X = B`` from X = 0 (in the order of ``chunks``, as :func:`gauss_seidel`), and R = B - A X,
    for an exactly symmetric CSR matrix A with sorted rows and its diagonal stored (nonzero); X, B,
    R (n, c) C-contiguous blocks of A's dtype; returns R.

    Row i of the sweep meets only the entries of the rows swept before it (the others' X is still
    zero), and once x_i is known its terms a_ji x_i in those rows j are the only ones they still
    miss: B_j - sum_{i swept up to j} a_ji x_i vanishes row by row, so r_j = -sum_{i swept after j}
    a_ji x_i, added as the rows go (with one chunk, in the order of the columns of row j: bitwise
    the product -U X with the strict upper triangle U that this replaces; the sweep read every
    entry of A, and the product read U again and kept it, 0.3 GB at spacing 0.003125)."""
    indptr, indices, data = _csr(A)
    if not A.has_sorted_indices:
        raise ValueError("presmooth needs a CSR matrix with sorted indices (A.sort_indices())")
    _check_blocks(A, "X, B and R", X, B, R)
    bounds = _bounds(A, chunks)
    c = X.shape[1]
    if c <= WIDTH:
        _kernels(c)[2](indptr, indices, data, X, B, R, bounds)
        return R
    for g in _groups(c):
        Y, Q = np.empty((X.shape[0], g.stop - g.start), X.dtype), np.empty((X.shape[0], g.stop - g.start), X.dtype)
        _kernels(g.stop - g.start)[2](indptr, indices, data, Y, np.ascontiguousarray(B[:, g]), Q, bounds)
        X[:, g], R[:, g] = Y, Q
    return R


@parallel_kernel
def _chunks_apart(indptr, indices, bounds):
    """Whether no row couples two chunks of the same parity, nor more than one chunk besides its own."""
    nch = bounds.shape[0] - 1
    owner = np.empty(indptr.shape[0] - 1, dtype=np.int32)
    for ch in range(nch):
        owner[bounds[ch]:bounds[ch + 1]] = ch
    bad = 0
    for i in prange(owner.shape[0]):
        own, other = owner[i], -1
        for k in range(indptr[i], indptr[i + 1]):
            cj = owner[indices[k]]
            if cj == own:
                continue
            if (cj - own) % 2 == 0 or (other >= 0 and cj != other):
                bad += 1
                break
            other = cj
    return bad == 0


def sweep_chunks(A, counts=SWEEP_CHUNKS):
    """Row-chunk bounds (k + 1,) for the Gauss-Seidel kernels (:func:`gauss_seidel`,
    :func:`presmooth`): the first k of ``counts`` for which k contiguous chunks of about equal
    nonzeros leave no row coupled to another chunk of its parity, nor to two other chunks (so that
    the even chunks can be swept at the same time, then the odd ones, and the residual of
    :func:`presmooth` gets each row's terms from one chunk); [0, n] (the rows in their order) when
    none does.  Rows ordered along a lattice or a grid, as the levels of the geometric multigrid,
    have their couplings within a band of neighbouring rows: chunks wider than the band pass."""
    indptr, indices, _ = _csr(A)
    n = A.shape[0]
    for k in counts:
        if k < 2 or k % 2 or n < 2 * k:
            continue
        bounds = np.searchsorted(indptr, np.arange(k + 1) * (indptr[-1] / k)).astype(np.int64)
        bounds[0], bounds[-1] = 0, n
        if np.all(np.diff(bounds) > 0) and _chunks_apart(indptr, indices, bounds):
            return bounds
    return np.array([0, n], dtype=np.int64)
