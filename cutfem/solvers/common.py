"""What the solvers of :mod:`cutfem.solvers` share, kept below all of them so that their imports
form no circle: the checks of the input (a square, non-empty, finite matrix in canonical CSR form;
a real, finite right-hand side of one or more columns; a tolerance in (0, 1)), the record of a
solve (:class:`SolveInfo`), the product with a sparse matrix and its diagonal by the compiled
kernels (:mod:`cutfem.solvers.sparse_kernels`), and BLAS limited to one thread."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import sparse_kernels

__all__ = ["SolveInfo"]


def _canonical_csr(A):
    """A as CSR with sorted indices and no duplicates; sorting and merging happen on a copy, never
    on the caller's arrays.  A csr_matrix is used as it is (not wrapped anew), so that scipy's
    answer to has_canonical_format, a pass over the indices, is found once and kept on it: a solve
    asks several times (the checks, the solver, the multigrid)."""
    A = A if type(A) is sp.csr_matrix else sp.csr_matrix(A)
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()
    return A


def _check_finite(values, what: str, where: str, fix: str, rows=None):
    """Raise ValueError when ``values`` holds NaN or inf, naming how many, where the first is (its
    row: ``rows`` maps an index of ``values`` to one, default the first axis) and the fix.  One sum
    first (no temporary; NaN and inf make it non-finite), the exact count only when it is not
    finite."""
    v = np.asarray(values)
    if v.size == 0 or np.isfinite(v.sum()):
        return
    bad = ~np.isfinite(v)
    if not bad.any():  # a finite array whose sum overflowed
        return
    first = int(np.flatnonzero(bad.ravel())[0])
    row = int(rows(first)) if rows is not None else int(np.unravel_index(first, v.shape)[0])
    raise ValueError(f"{where}: the {what} has {int(bad.sum())} non-finite entries (NaN or inf) among {v.size}, the "
                     f"first in row {row}; {fix}")


def _diagonal(A):
    """The diagonal of the CSR matrix A by the compiled pass (:func:`cutfem.solvers.sparse_kernels.csr_diagonal`)."""

    return sparse_kernels.csr_diagonal(A)


def _checked_matrix(A, where: str):
    """A as a canonical CSR matrix (:func:`_canonical_csr`), refused (ValueError naming the problem)
    unless it is square, not empty (n >= 1) and with finite values."""
    A = _canonical_csr(A)
    if A.shape[0] != A.shape[1]:
        raise ValueError(f"{where}: the matrix must be square, got shape {A.shape}")
    if A.shape[0] == 0:
        raise ValueError(f"{where}: the system is empty (a 0 x 0 matrix): there are no unknowns to solve for; check the "
                         "space (an element set without elements?)")
    _check_finite(A.data, "matrix", where, "check the assembled forms (a coefficient, a penalty or a level set with "
                  "NaN values)", rows=lambda k: np.searchsorted(A.indptr, k, side="right") - 1)
    return A


def _checked_rhs(B, n: int, where: str):
    """B as a float array of shape (n,) or (n, c) with c >= 1, refused (ValueError naming the
    problem) when it is complex, of another shape, without columns or not finite."""
    B = np.asarray(B)
    if np.iscomplexobj(B):
        raise ValueError(f"{where}: the right-hand side is complex, and the solvers are real; solve its real and "
                         "imaginary parts as two columns")
    B = np.asarray(B, dtype=float)
    if B.ndim not in (1, 2) or B.shape[0] != n:
        raise ValueError(f"{where}: the right-hand side must have shape ({n},) or ({n}, c), got {B.shape}")
    if B.ndim == 2 and B.shape[1] == 0:
        raise ValueError(f"{where}: the right-hand side has no columns (shape {B.shape}); give shape ({n},) or ({n}, c) "
                         "with c >= 1")
    _check_finite(B, "right-hand side", where, "check the loads (a source function or boundary data with NaN values)")
    return B


def _checked_tol(tol, where: str) -> float:
    """The relative residual ``tol`` of an iterative solve: a number with 0 < tol < 1 (at tol >= 1
    the zero vector already passes, and CG would return it after no iteration)."""
    try:
        value = float(tol)
    except (TypeError, ValueError):
        value = np.nan
    if not 0 < value < 1:
        raise ValueError(f"{where}: tol must be a positive relative residual below 1 (e.g. 1e-8), got {tol!r}")
    return value


@dataclass
class SolveInfo:
    """What a solve did: ``method``, CG ``iterations`` (the most over the right-hand sides),
    the largest relative ``residual`` ||A x - b|| / ||b|| over the columns, the wall time
    ``seconds`` (setup included) and the part of it spent in the ``setup`` (factorization or
    multigrid hierarchy)."""

    method: str
    iterations: int = 0
    residual: float = 0.0
    seconds: float = 0.0
    setup: float = 0.0


def _matvec(A):
    """(n, c) -> (n, c) product with the sparse matrix A, one pass over A for up to three columns
    (:func:`cutfem.solvers.sparse_kernels.matmul`, ``dots`` as there; for three columns about a third
    of the time of scipy's three products)."""

    A = sp.csr_matrix(A)
    return lambda X, out=None, dots=None: sparse_kernels.matmul(A, np.ascontiguousarray(X, dtype=A.dtype), out=out, dots=dots)


_BLAS_CONTROLLER = None


def _threadpoolctl():
    """The threadpoolctl module, imported without its process-wide side effect: its import sets
    the environment variable KMP_DUPLICATE_LIB_OK=True (which lets Intel's OpenMP runtime load
    twice); the variable is put back as it was, so that using cutfem changes no environment."""
    import os

    before = os.environ.get("KMP_DUPLICATE_LIB_OK")
    import threadpoolctl as module

    if before is None:
        os.environ.pop("KMP_DUPLICATE_LIB_OK", None)
    else:
        os.environ["KMP_DUPLICATE_LIB_OK"] = before
    return module


def _one_blas_thread():
    """Context limiting BLAS/LAPACK to one thread (threadpoolctl).  The banded factorizations are
    small level-3 kernels: OpenBLAS' threads gain little on them and, when the other core of this
    2-core machine is busy, their synchronization can make a millisecond factorization take hundreds
    of times as long."""
    global _BLAS_CONTROLLER
    if _BLAS_CONTROLLER is None:
        _BLAS_CONTROLLER = _threadpoolctl().ThreadpoolController()
    return _BLAS_CONTROLLER.limit(limits=1, user_api="blas")
