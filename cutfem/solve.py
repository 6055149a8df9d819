"""Linear solvers for the symmetric systems of cutfem, and condition number estimates.

* :class:`DirectSolver`: one sparse LU factorization (SuperLU, minimum-degree ordering on A + A^T,
  symmetric mode) reused for several right-hand sides, e.g. the three components of the mean
  curvature vector.  The factorization is checked: a zero diagonal entry, a failed factorization
  or a pivot below ``1e-13`` times the largest (after symmetric diagonal scaling) raises
  :class:`SingularSystemError`, which carries the smallest pivot.
* :func:`cg_solve`: preconditioned conjugate gradients (Jacobi or smoothed-aggregation algebraic
  multigrid from pyamg) for large symmetric positive definite systems, all right-hand sides at once.
* :func:`solve`: picks one of the two by size (``method="auto"``).
* :func:`condition_number`: the 2-norm condition number of the diagonally scaled matrix
  D^{-1/2} A D^{-1/2}, from its extreme eigenvalues (Lanczos; shift-invert for the smallest).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = [
    "SingularSystemError",
    "DirectSolver",
    "cg_solve",
    "solve",
    "condition_number",
    "scaled",
    "SolveInfo",
    "DIRECT_LIMIT",
]

#: systems with at most this many unknowns are solved directly by ``solve(method="auto")``
DIRECT_LIMIT = 60_000


class SingularSystemError(RuntimeError):
    """The matrix is singular or numerically singular; ``smallest`` is the smallest pivot or
    eigenvalue estimate of the diagonally scaled matrix (0 for an exactly zero diagonal)."""

    def __init__(self, message, smallest=0.0):
        super().__init__(message)
        self.smallest = smallest


def scaled(A):
    """(D^{-1/2} A D^{-1/2}, d) with d = diag(A); raises SingularSystemError on a non-positive diagonal."""
    A = sp.csr_matrix(A)
    d = A.diagonal()
    bad = d <= 0
    if np.any(bad):
        k = np.flatnonzero(bad)
        raise SingularSystemError(
            f"{k.size} unknowns have a zero (or negative) diagonal entry, first: unknown {k[0]}; the system is singular. "
            "On a cut surface this means basis functions with no support on S_h: add a stabilization (tau_F > 0).",
            smallest=0.0,
        )
    s = 1.0 / np.sqrt(d)
    return sp.diags(s) @ A @ sp.diags(s), d


@dataclass
class SolveInfo:
    method: str
    iterations: int = 0
    residual: float = 0.0
    seconds: float = 0.0


class DirectSolver:
    """Sparse LU of a symmetric matrix, reused for many right-hand sides; raises
    :class:`SingularSystemError` on (numerical) singularity."""

    def __init__(self, A, pivot_tol: float = 1e-13):
        S, d = scaled(A)
        self._s = 1.0 / np.sqrt(d)
        self.n = A.shape[0]
        try:
            self._lu = spla.splu(
                sp.csc_matrix(S), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
            )
        except RuntimeError as exc:
            raise SingularSystemError(f"the factorization failed: {exc}; the system is singular", smallest=0.0) from exc
        piv = np.abs(self._lu.U.diagonal())
        self.smallest_pivot = float(piv.min())
        if self.smallest_pivot <= pivot_tol * piv.max():
            raise SingularSystemError(
                f"the system is numerically singular: smallest pivot {self.smallest_pivot:.3e} of the diagonally scaled "
                f"matrix (largest {piv.max():.3e}). Add or increase the stabilization.",
                smallest=self.smallest_pivot,
            )

    def solve(self, b):
        """Solve A x = b for b (n,) or (n, c)."""
        b = np.asarray(b, dtype=float)
        s = self._s if b.ndim == 1 else self._s[:, None]
        return s * self._lu.solve(np.ascontiguousarray(s * b))


def _amg(A):
    import pyamg

    return pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), symmetry="symmetric", max_coarse=500).aspreconditioner(cycle="V")


def cg_solve(A, B, preconditioner: str = "amg", tol: float = 1e-10, maxiter: int = 5000):
    """Preconditioned CG for SPD A; B (n,) or (n, c) solved column by column with one preconditioner.

    ``tol`` is relative to ||b||.  Returns (X, SolveInfo).  Raises RuntimeError if CG does not
    converge in ``maxiter`` iterations.
    """
    t0 = time.perf_counter()
    A = sp.csr_matrix(A)
    if preconditioner == "amg":
        M = _amg(A)
    elif preconditioner == "jacobi":
        d = A.diagonal()
        if np.any(d <= 0):
            scaled(A)  # raises with a clear message
        M = sp.diags(1.0 / d)
    elif preconditioner in (None, "none"):
        M = None
    else:
        raise ValueError(f"unknown preconditioner {preconditioner!r}; use 'amg', 'jacobi' or 'none'")
    B = np.asarray(B, dtype=float)
    cols = B.reshape(B.shape[0], -1)
    X = np.zeros_like(cols)
    total = 0
    worst = 0.0
    for c in range(cols.shape[1]):
        b = cols[:, c]
        nb = np.linalg.norm(b)
        if nb == 0:
            continue
        it = [0]

        def count(_):
            it[0] += 1

        x, info = spla.cg(A, b, rtol=tol, atol=0.0, maxiter=maxiter, M=M, callback=count)
        if info != 0:
            raise RuntimeError(f"CG did not converge in {maxiter} iterations (relative tolerance {tol}); try the direct solver")
        X[:, c] = x
        total += it[0]
        worst = max(worst, np.linalg.norm(A @ x - b) / nb)
    return X.reshape(B.shape), SolveInfo(f"cg+{preconditioner}", total, worst, time.perf_counter() - t0)


def solve(A, B, method: str = "auto", tol: float = 1e-10):
    """Solve the SPD system A X = B (B (n,) or (n, c)); returns (X, SolveInfo).

    ``method``: "direct", "cg-amg", "cg-jacobi" or "auto" (direct up to :data:`DIRECT_LIMIT`
    unknowns, CG with AMG above).
    """
    n = A.shape[0]
    if method == "auto":
        method = "direct" if n <= DIRECT_LIMIT else "cg-amg"
    if method == "direct":
        t0 = time.perf_counter()
        X = DirectSolver(A).solve(B)
        res = np.linalg.norm(A @ X - B) / max(np.linalg.norm(B), 1e-300)
        return X, SolveInfo("direct", 0, float(res), time.perf_counter() - t0)
    if method in ("cg-amg", "cg-jacobi"):
        return cg_solve(A, B, preconditioner=method.split("-")[1], tol=tol)
    raise ValueError(f"unknown method {method!r}; use 'auto', 'direct', 'cg-amg' or 'cg-jacobi'")


def condition_number(A, tol: float = 1e-8) -> float:
    """2-norm condition number of D^{-1/2} A D^{-1/2} (A symmetric positive semidefinite).

    Largest eigenvalue by Lanczos; smallest by shift-invert Lanczos around 0 (dense for n <= 400).
    Returns ``inf`` for a singular matrix (zero diagonal or failed factorization).
    """
    try:
        S, _ = scaled(A)
    except SingularSystemError:
        return float("inf")
    n = S.shape[0]
    if n <= 400:
        ev = np.linalg.eigvalsh(S.toarray())
        return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
    lmax = spla.eigsh(S, k=1, which="LA", tol=tol, return_eigenvectors=False)[0]
    try:
        lu = spla.splu(sp.csc_matrix(S), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:
        return float("inf")
    op = spla.LinearOperator(S.shape, matvec=lu.solve, dtype=float)
    inv_min = spla.eigsh(op, k=1, which="LA", tol=tol, return_eigenvectors=False)[0]
    if not np.isfinite(inv_min) or inv_min <= 0:
        return float("inf")
    return float(lmax * inv_min)
