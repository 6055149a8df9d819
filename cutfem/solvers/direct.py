"""Direct solves: :class:`DirectSolver`, one checked factorization of the diagonally scaled matrix
S = D^{-1/2} A D^{-1/2}, reused for every right-hand side (``solve(method="auto")`` uses it up to
:data:`~cutfem.solvers.solve.DIRECT_LIMIT` unknowns).

The factorization is a banded Cholesky (LAPACK dpbtrf, n (b + 1)^2 flops) after reverse
Cuthill-McKee when the band is narrow enough (:data:`BANDED_MAX_WORK`, :data:`BANDED_MAX_ENTRIES`),
else a sparse LU (SuperLU, minimum degree on A + A^T, symmetric mode).  Why both: on the small,
thick cut bands SuperLU is slow for its fill (it factors LU, with little gain from its supernodes
at these sizes), while after reverse Cuthill-McKee their band is narrow.  The banded factorization
runs BLAS on one thread: OpenBLAS' threads gain little on these small level-3 blocks, and when
another process keeps a core busy their synchronization can make a millisecond factorization
take hundreds of times as long.

Both check the matrix at no cost: a Cholesky that succeeds proves S positive definite, and SuperLU
without pivoting is S = L D L^T, whose pivots' signs count the negative eigenvalues (Sylvester's
law of inertia).  A negative pivot (an indefinite matrix), a zero diagonal entry, a failed
factorization or a pivot below 1e-10 times the largest raises
:class:`~cutfem.solvers.diagnose.SolverError`, which carries the cause
(:func:`~cutfem.solvers.diagnose.diagnose`) and the smallest pivot.  The threshold 1e-10 lies
between the pivots of singular and of stabilized systems: the singular unstabilized cut mass
matrix of the torus has its smallest pivot near 1e-13 and the next near 1e-2, the stabilized
torus systems have 0.03-0.09.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .common import _checked_matrix, _checked_rhs, _one_blas_thread
from .diagnose import SolverError, _Checks, _lanczos_smallest, diagnose, scaled

__all__ = ["DirectSolver"]


#: :class:`DirectSolver` uses a banded Cholesky when its work n (b + 1)^2 is at most this (b the
#: bandwidth after reverse Cuthill-McKee): a little below the measured break-even with SuperLU,
#: about 4e9 (the cut torus at spacing 0.07)
BANDED_MAX_WORK = 3e9

#: ... and its band storage n (b + 1) at most this many entries (8 bytes each)
BANDED_MAX_ENTRIES = 1e7


class DirectSolver:
    """Direct solver, factorized once and reused for many right-hand sides.

    For a matrix declared symmetric positive definite (``spd=True``, the default), both
    factorizations work on the diagonally scaled matrix S = D^{-1/2} A D^{-1/2} and check it:

    * ``"banded"``: Cholesky S = U^T U of the band of S after reverse Cuthill-McKee (LAPACK dpbtrf,
      BLAS on one thread), when its work n (b + 1)^2 (b the bandwidth) is at most
      :data:`BANDED_MAX_WORK` and its storage n (b + 1) at most :data:`BANDED_MAX_ENTRIES`.  Its
      success proves S positive definite; when it meets a non-positive pivot, the matrix goes to
      SuperLU, whose pivots tell an indefinite from a singular matrix;
    * ``"superlu"``: sparse LU (SuperLU, minimum degree on A + A^T, symmetric mode, no pivoting)
      otherwise.  Without pivoting (its row and column permutations agree) it is S = L D L^T with
      D the diagonal of U, so by Sylvester's law of inertia the signs of the pivots count the
      negative eigenvalues: definiteness is checked at no cost (a sign count over n pivots), no
      eigenvalue estimate is needed.

    A pivot below -``pivot_tol`` times the largest raises :class:`~cutfem.solvers.diagnose.SolverError` with cause
    "indefinite"; one within +-``pivot_tol`` times the largest, a zero diagonal entry or a failed
    LU, "singular" or "over-stabilized" (:func:`~cutfem.solvers.diagnose.diagnose`, which then gets a near-null vector from
    two steps of inverse iteration with the factorization, or with that of S + 1e-8 I when the LU
    failed).  ``pivot_tol``: a number in [0, 1).  ``kernels``, ``stabilization`` and
    ``indefinite_hint`` let :func:`~cutfem.solvers.diagnose.diagnose` name the cause.  A non-symmetric matrix with
    ``spd=True`` is refused (ValueError), as are an empty (0 x 0), non-square or non-finite matrix.

    ``spd=False``: a general square matrix (indefinite or non-symmetric by design), SuperLU with
    partial pivoting on A scaled by its nonzero |diagonal|; only a failed factorization is
    reported.  ``method`` forces a factorization ("banded" still uses SuperLU when it does not
    apply).  ``smallest_pivot``: the smallest pivot of L D L^T (in magnitude for ``spd=False``);
    ``kind``: the factorization used.
    """

    def __init__(self, A, pivot_tol: float = 1e-10, method: str = "auto", spd: bool = True, kernels=None,
                 stabilization=None, indefinite_hint=None, where: str = "the direct solver", _checks=None):
        if method not in ("auto", "banded", "superlu"):
            raise ValueError(f"unknown factorization {method!r}; use 'auto', 'banded' or 'superlu'")
        try:
            pivot_ok = 0 <= float(pivot_tol) < 1
        except (TypeError, ValueError):
            pivot_ok = False
        if not pivot_ok:
            raise ValueError(f"{where}: pivot_tol must be a number in [0, 1) (a pivot within +-pivot_tol times the "
                             f"largest counts as zero), got {pivot_tol!r}")
        pivot_tol = float(pivot_tol)
        A = _checked_matrix(A, where)
        self.n = A.shape[0]
        if not spd:
            d = np.abs(A.diagonal())
            self._s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
            S = sp.diags(self._s) @ A @ sp.diags(self._s)
            try:
                self._lu = spla.splu(sp.csc_matrix(S))
            except RuntimeError as exc:
                raise SolverError(f"{where}: the factorization failed ({exc}): the matrix is singular", "singular") from exc
            self.kind = "superlu"
            self.smallest_pivot = float(np.abs(self._lu.U.diagonal()).min())
            return
        checks = _checks if _checks is not None else _Checks.of(kernels, stabilization, indefinite_hint, self.n)
        S, d = scaled(A, where, checks)
        self._s = 1.0 / np.sqrt(d)
        if not _is_symmetric(S):
            raise ValueError(
                f"{where}: the matrix is not symmetric, so not symmetric positive definite as declared; assemble a "
                "symmetric form, or pass spd=False for a non-symmetric system"
            )
        piv, failed_at = None, None
        if method != "superlu":
            piv, failed_at = self._banded(S, force=method == "banded")
        if failed_at is not None:
            where = f"{where} (the Cholesky factorization met a non-positive pivot at step {failed_at})"
        if piv is None:
            try:
                piv = self._superlu(S)
            except RuntimeError as exc:
                v = self._near_null_vector(S, shifted=True)
                raise diagnose(A, vectors=[v], smallest=0.0, where=f"{where} (SuperLU: {exc})", _checks=checks) from exc
        top = float(np.abs(piv).max())
        self.smallest_pivot = float(piv.min())
        negative = int((piv < -pivot_tol * top).sum())
        if negative or self.smallest_pivot <= pivot_tol * top:
            v = None if negative else self._near_null_vector(S)
            raise diagnose(A, vectors=[v], smallest=self.smallest_pivot / top, negative_pivots=negative, where=where,
                           _checks=checks)

    def _superlu(self, S):
        self._lu = spla.splu(
            sp.csc_matrix(S), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        self.kind = "superlu"
        if not np.array_equal(self._lu.perm_r, self._lu.perm_c):  # a pivot left the diagonal: no L D L^T
            lam, _ = _lanczos_smallest(S)
            return np.array([min(lam, float(np.abs(self._lu.U.diagonal()).min())), 1.0])
        return self._lu.U.diagonal()

    def _near_null_vector(self, S, shifted=False, steps: int = 2):
        """Two steps of inverse iteration from a seeded random vector (with the factorization of
        S, or of S + 1e-8 I when ``shifted``); returned in the unscaled unknowns (x = D^{-1/2} y)."""
        y = np.random.default_rng(0).normal(size=self.n)
        if shifted:
            try:
                lu = spla.splu(sp.csc_matrix(S + 1e-8 * sp.identity(self.n)), permc_spec="MMD_AT_PLUS_A")
            except RuntimeError:
                return None
            solve = lu.solve
        else:
            solve = lambda b: self._solve_scaled(b)  # noqa: E731
        for _ in range(steps):
            y = solve(y)
            y /= np.linalg.norm(y)
        return self._s * y

    def _banded(self, S, force=False):
        """Banded Cholesky of the symmetric S (canonical CSR) after reverse Cuthill-McKee: (the
        pivots, None), or (None, k) when it does not apply (too wide a band unless ``force``: k =
        None) or meets a non-positive pivot at step k."""
        from scipy.linalg import lapack
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        n = S.shape[0]
        perm = reverse_cuthill_mckee(S, symmetric_mode=True)
        pos = np.empty(n, dtype=np.int64)
        pos[perm] = np.arange(n)
        rows = np.repeat(pos, np.diff(S.indptr))
        cols = pos[S.indices]
        b = int(np.abs(rows - cols).max()) if S.nnz else 0
        if not force and (n * (b + 1) ** 2 > BANDED_MAX_WORK or n * (b + 1) > BANDED_MAX_ENTRIES):
            return None, None
        upper = rows <= cols
        band = np.zeros((b + 1, n))
        band[b + rows[upper] - cols[upper], cols[upper]] = S.data[upper]
        with _one_blas_thread():
            factor, info = lapack.dpbtrf(band, lower=0, overwrite_ab=1)
        if info != 0:
            return None, int(info)
        self._band, self._perm, self.kind = factor, perm, "banded"
        return factor[b] ** 2, None

    def _solve_scaled(self, y):
        """Solve S z = y (the scaled system)."""
        if self.kind == "superlu":
            return self._lu.solve(np.ascontiguousarray(y))
        from scipy.linalg import lapack

        with _one_blas_thread():
            z, info = lapack.dpbtrs(self._band, y[self._perm], lower=0)
        out = np.empty_like(z)
        out[self._perm] = z
        return out

    def solve(self, b):
        """Solve A x = b for b (n,) or (n, c)."""
        b = _checked_rhs(b, self.n, "the direct solver")
        s = self._s if b.ndim == 1 else self._s[:, None]
        return s * self._solve_scaled(s * b)


def _is_symmetric(S, atol: float = 1e-13):
    """S (canonical CSR, unit diagonal) equals its transpose up to ``atol``."""
    T = S.T.tocsr()
    T.sort_indices()
    same = np.array_equal(T.indptr, S.indptr) and np.array_equal(T.indices, S.indices)
    return bool(same and np.allclose(T.data, S.data, rtol=0.0, atol=atol))
