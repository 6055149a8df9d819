"""Linear solvers for the symmetric systems of cutfem, and condition number estimates.

What is used when
-----------------
:func:`solve` (``method="auto"``) picks, for an SPD matrix with n unknowns:

* n <= :data:`DIRECT_LIMIT` (5 000): :class:`DirectSolver`, one factorization of the diagonally
  scaled matrix reused for all right-hand sides: a banded Cholesky (LAPACK, after reverse
  Cuthill-McKee) when the band is narrow enough (:data:`BANDED_MAX_WORK`), else a sparse LU
  (SuperLU, minimum degree on A + A^T, symmetric mode).  It is checked: a zero diagonal entry, a
  failed factorization or a pivot below ``1e-10`` times the largest raises
  :class:`SingularSystemError`, which carries the smallest pivot (1e-10: the singular
  unstabilized cut mass matrix of the torus at spacing 0.05 has its smallest pivot at 1.3e-13, the
  next at 1.8e-2; the stabilized torus systems at spacings 0.1-0.04 have 0.03-0.09).
* n > DIRECT_LIMIT and a geometric hierarchy (:func:`multigrid_hierarchy`): conjugate gradients
  preconditioned by the multigrid :class:`GeometricMultigrid` ("cg-mg"), all right-hand sides at
  once, relative residual :data:`DEFAULT_TOL` (1e-6) per column.  The hierarchies: the nested
  Kuhn lattices when the unknowns are nodes of a structured background (``space=`` a
  :class:`~cutfem.spaces.CutP1Space` on a :class:`~cutfem.mesh.StructuredBox`, or ``lattice=``
  their integer indices); on a surface mesh (``space=`` a :class:`~cutfem.spaces.SurfaceP1Space`)
  its periodic grid when it has one (the torus families) and otherwise a Kuhn lattice around it.
* otherwise: direct up to :data:`DIRECT_LIMIT_NO_MG` (400 000), then CG with smoothed aggregation
  AMG (pyamg, "cg-amg"), with the globally linear functions as near-kernel candidates when the dof
  coordinates are known (``space``).  Callers with a cut space should pass ``space=`` so that the
  multigrid can be used.

Singular systems are reported, never hidden: zero diagonals (any method), small pivots (direct),
loss of positive definiteness in CG, and, when ``space`` is a cut space, the null vector that
every unstabilized cut system has (the nodal vector of phi_h, zero on S_h: a consistent
right-hand side would let CG converge without noticing).  CG with multigrid warns when it needs
more than :data:`MG_WARN_ITERATIONS` iterations.

Why geometric multigrid
-----------------------
The cut systems are dominated by the face penalty: for K = M + tau_F J_F the entries of J_F are
O(1) per face while those of the surface mass matrix M are O(h^2).  The kernel of J_F is the
globally linear functions on the band, its near-kernel the *locally* linear ones: a function with
slowly varying gradient has face jumps O(h |D^2 u|), so J_F acts like h^2 times a biharmonic along
the surface (and a second-order operator across the band, for functions vanishing on S_h, which M
does not see).  The diagonally scaled spectrum runs from O(h^2) to O(1) with a fourth-order
character.  Aggregation AMG with constant candidates is poor on it (pyamg's default smoothed
aggregation: 119 / 231 / 455 CG iterations at spacings 0.05 / 0.025 / 0.0125), better but still
growing with the linear functions as candidates (49 / 72 / 99); classical AMG is worse (177 / 369 /
764).  A sparse direct factorization is expensive because the band is a thick surface: at
spacing 0.0125 (293 244 unknowns) the Cholesky factor has 50M nonzeros, 39 GFlop (MKL Pardiso
5 s, CHOLMOD 5-12 s, SuperLU 31 s and 3 GiB).

The structured Kuhn meshes are nested: the Kuhn triangulation of the lattice 2h Z^3 is made of
unions of tets of that of h Z^3 (both are the arrangements of the planes x_i = k s, x_i - x_j = k s).
So the P1 space of the coarse lattice restricted to the band is a subspace of the fine one and its
prolongation is exact and trivial (:func:`kuhn_prolongation`): a fine node with lattice index i
takes the value of the coarse node i/2 (all indices even) or the mean of the two coarse nodes
(i -/+ o)/2 at the ends of the coarse Kuhn edge it halves (o = i mod 2, a 0/1 vector).  It
reproduces linear functions, the near-kernel of J_F, on every level.  The coarse matrices are
Galerkin products P^T A P (each level has about 4 times fewer unknowns and nonzeros, the band
being two-dimensional: operator complexity 1.33).  Cycle: one forward Gauss-Seidel sweep, coarse
correction, one backward sweep (so the preconditioner is symmetric); V-cycle on the finest level,
W-cycles below (iterations 18 / 21 / 23 at 1e-6, nearly independent of h, where a V-cycle
everywhere needs 19 / 27 / 37 at 1e-8); :class:`DirectSolver` on the coarsest level (<= 1500 unknowns).  The
residual after the forward sweep from zero is -U x (U the strictly upper part): half a product.

Measured on this machine (2 cores), cut torus of SPEC section 6, K = M + 0.1 J_F, the three
right-hand sides A @ x_k; times in s (wall; the machine is noisy, +-30 %), "its" per column:

=======  =======  =================================  =============================
spacing  n        cg-mg, tol 1e-6 (1e-8)             SuperLU (previous default)
=======  =======  =================================  =============================
0.05     18 024   0.05 + 0.07 s, 18 its (0.10, 24)   0.22 + 0.02 s
0.025    72 928   0.16 + 0.51 s, 21 its (0.52, 28)   2.0 + 0.24 s
0.0125   293 244  0.3 + 1.7-2.3 s, 23 its (2.6, 31)  25 + 6 s, 3 GiB
=======  =======  =================================  =============================

cg-mg needs 0.16 GiB besides the matrix at spacing 0.0125.  Its solutions differ from the direct
ones by about 3e-3 times the tolerance (relative 2-norm: 3e-9 at 1e-6, 3e-11 at 1e-8); the L2
errors of H_h agree to all printed digits (0.193480, 0.064852, 0.018655).  DIRECT_LIMIT is the
measured break-even with the direct solver (banded Cholesky or SuperLU, see below), best of 5, in ms:

===================  ======  ======  =====================
system               n       direct  cg-mg (its)
===================  ======  ======  =====================
cut torus 0.1        4 364   25      25 (15)
cut torus 0.08       7 296   69      51 (19)
cut torus 0.06       12 776  218     85 (19)
meshed torus 96      4 608   21      25 (17)
meshed torus 128     8 192   62      34 (19)
meshed torus 192     18 432  238     107 (20)
===================  ======  ======  =====================

Meshed surfaces
---------------
The meshed system M + tau_E J_E has the same fourth-order character (J_E penalizes the jumps of
the conormal derivatives, O(1) per edge against O(h^2) for the mass; CG with Jacobi needs 430 /
1 900 iterations on the torus with n = 192 / 768).  Measured on the perturbed torus 768 x 384
(294 912 unknowns, 13 nonzeros per row, three right-hand sides; machine under load 1-2):
SuperLU 15-42 s and 2.8-3.1 GiB; SuperLU after a METIS nested-dissection ordering 7.4 s plus
2.1 s ordering (84M nonzeros in L + U); smoothed aggregation with the linear candidates 46
iterations, 21 s; multigrid through a Kuhn lattice of spacing twice the mean edge
(:func:`surface_hierarchy`) 55 iterations, 4-5 s.  The lattice is uniform while the torus grid's
edges vary 3:1 (inner against outer equator): the slowest multigrid error lives on the inner
equator, where the first coarse space is six fine edges wide.  On the near-uniform icosphere the
same hierarchy needs 15-18 iterations.  Along the torus grid (:func:`grid_hierarchy`: every second
node, weights from the node positions reproducing linear functions) the iterations are 18
(flipped) and 23 (perturbed) at n = 768, 17-20 at n = 192: 1.8-2.6 s with the setup (0.35-0.45 s),
0.6 GiB for the whole run.  Break-even with the direct solver (grid): about 5 000 unknowns (table
above); with SuperLU through the lattice on the torus: about 30 000.  The L2 errors of H_h agree with the direct ones to 6 digits
(0.00321778 perturbed, 0.00220570 flipped).

Small systems: SuperLU is slow for its fill on the thick cut bands (it factors LU, with little
gain from its supernodes at these sizes).  After reverse Cuthill-McKee the band is narrow (cut
torus: bandwidth 139 at spacing 0.2, 263 at 0.1; meshed torus n = 128: 373), and LAPACK's banded
Cholesky (dpbtrf, n (b + 1)^2 flops) wins up to a work of about 4e9.  Factorization times in ms,
RCM and band set-up included:

======================  ======  =====  ======  =======
system                  n       b      banded  SuperLU
======================  ======  =====  ======  =======
cut torus 0.2           1 160   139    2-4     7
cut torus 0.1           4 364   263    16-21   39
cut sphere 0.1          2 932   228    11      24
cut torus 0.07          9 588   571    114     116
cut torus 0.05          18 024  1 041  545     298
meshed torus 64         2 048   179    4-6     6
meshed torus 128        8 192   373    46-52   59-65
meshed icosphere 80     2 562   161    6       14
======================  ======  =====  ======  =======

The banded factorization runs with BLAS on one thread (threadpoolctl): OpenBLAS' threads gain
little on these small level-3 blocks, and whenever the other core was busy their synchronization
made a 2 ms factorization take up to 0.5 s.

BLAS threads: the iteration loops use no BLAS calls (column dot products by ``einsum``): on this
machine's 2 virtual cores, OpenBLAS' threaded level-1 calls on vectors of 10^5 entries are up to
20 times slower than serial ones, which made scipy's ``cg`` erratic (0.2 s to 3.7 s for the same
300 iterations).

* :func:`condition_number`: the 2-norm condition number of the diagonally scaled matrix
  D^{-1/2} A D^{-1/2}, from its extreme eigenvalues (Lanczos; shift-invert for the smallest).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .mesh import unique_keys

__all__ = [
    "SingularSystemError",
    "DirectSolver",
    "GeometricMultigrid",
    "lattice_indices",
    "kuhn_prolongation",
    "surface_lattice_prolongation",
    "grid_prolongation",
    "lattice_hierarchy",
    "surface_hierarchy",
    "grid_hierarchy",
    "multigrid_hierarchy",
    "cg_solve",
    "mg_solve",
    "solve",
    "condition_number",
    "scaled",
    "SolveInfo",
    "DIRECT_LIMIT",
]

#: systems with at most this many unknowns are solved directly by ``solve(method="auto")``
DIRECT_LIMIT = 5_000

#: :class:`DirectSolver` uses a banded Cholesky when its work n (b + 1)^2 is at most this (b the
#: bandwidth after reverse Cuthill-McKee): measured break-even with SuperLU at about 4e9 (cut torus
#: at spacing 0.07, n = 9 588, b = 571: 114 against 116 ms)
BANDED_MAX_WORK = 3e9

#: ... and its band storage n (b + 1) at most this many entries (8 bytes each)
BANDED_MAX_ENTRIES = 1e7

#: without a geometric hierarchy (no multigrid), ``solve(method="auto")`` stays direct up to this
#: size: SuperLU beats CG with smoothed aggregation on every system measured (cut torus, 293k
#: unknowns: 31 s and 3 GiB against 68 s, or 23 s with the linear candidates)
DIRECT_LIMIT_NO_MG = 400_000

#: CG with multigrid warns (RuntimeWarning) when it needs more iterations than this: the stabilized
#: cut systems need 15-40 at any spacing, an unstabilized (singular) one hundreds
MG_WARN_ITERATIONS = 100

#: default relative residual of the iterative methods of :func:`solve`
DEFAULT_TOL = 1e-6


class SingularSystemError(RuntimeError):
    """The matrix is singular or numerically singular; ``smallest`` is the smallest pivot or
    eigenvalue estimate of the diagonally scaled matrix (0 for an exactly zero diagonal)."""

    def __init__(self, message, smallest=0.0):
        super().__init__(message)
        self.smallest = smallest


def _check_diagonal(d):
    bad = d <= 0
    if np.any(bad):
        k = np.flatnonzero(bad)
        raise SingularSystemError(
            f"{k.size} unknowns have a zero (or negative) diagonal entry, first: unknown {k[0]}; the system is singular. "
            "On a cut surface this means basis functions with no support on S_h: add a stabilization (tau_F > 0).",
            smallest=0.0,
        )


def _canonical_csr(A):
    """A as CSR with sorted indices and no duplicates; sorting and merging happen on a copy, never
    on the caller's arrays."""
    A = sp.csr_matrix(A)
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()
    return A


def scaled(A):
    """(D^{-1/2} A D^{-1/2}, d) with d = diag(A), CSR in canonical form (sorted, no duplicates);
    raises SingularSystemError on a non-positive diagonal."""
    A = _canonical_csr(A)
    d = A.diagonal()
    _check_diagonal(d)
    s = 1.0 / np.sqrt(d)
    rows = np.repeat(s, np.diff(A.indptr))
    S = sp.csr_matrix((A.data * rows * s[A.indices], A.indices.copy(), A.indptr.copy()), shape=A.shape)
    S.has_canonical_format = True
    return S, d


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


class DirectSolver:
    """Direct solver for a symmetric positive definite matrix, factorized once and reused for many
    right-hand sides; raises :class:`SingularSystemError` on (numerical) singularity.

    Both factorizations work on the diagonally scaled matrix S = D^{-1/2} A D^{-1/2}:

    * ``"banded"``: Cholesky S = U^T U of the band of S after reverse Cuthill-McKee (LAPACK dpbtrf,
      BLAS on one thread), when its work n (b + 1)^2 (b the bandwidth) is at most
      :data:`BANDED_MAX_WORK` and its storage n (b + 1) at most :data:`BANDED_MAX_ENTRIES`;
    * ``"superlu"``: sparse LU (SuperLU, minimum degree on A + A^T, symmetric mode, no pivoting)
      otherwise, and whenever S is not symmetric or the Cholesky factorization breaks down.

    ``method`` forces one ("banded" still falls back to SuperLU when it does not apply).  The
    pivots are those of S = L D L^T (U_ii^2 for Cholesky, the diagonal of U for LU); a pivot below
    ``pivot_tol`` times the largest raises SingularSystemError, as does a zero diagonal entry or a
    failed LU.  ``smallest_pivot``: the smallest pivot; ``kind``: the factorization used.
    """

    def __init__(self, A, pivot_tol: float = 1e-10, method: str = "auto"):
        if method not in ("auto", "banded", "superlu"):
            raise ValueError(f"unknown factorization {method!r}; use 'auto', 'banded' or 'superlu'")
        S, d = scaled(A)
        self._s = 1.0 / np.sqrt(d)
        self.n = A.shape[0]
        piv = None
        if method != "superlu":
            piv = self._banded(S, force=method == "banded")
        if piv is None:
            piv = self._superlu(S)
        self.smallest_pivot = float(piv.min())
        if self.smallest_pivot <= pivot_tol * piv.max():
            raise SingularSystemError(
                f"the system is numerically singular: smallest pivot {self.smallest_pivot:.3e} of the diagonally scaled "
                f"matrix (largest {piv.max():.3e}). Add or increase the stabilization.",
                smallest=self.smallest_pivot,
            )

    def _superlu(self, S):
        try:
            self._lu = spla.splu(
                sp.csc_matrix(S), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
            )
        except RuntimeError as exc:
            raise SingularSystemError(f"the factorization failed: {exc}; the system is singular", smallest=0.0) from exc
        self.kind = "superlu"
        return np.abs(self._lu.U.diagonal())

    def _banded(self, S, force=False):
        """Banded Cholesky of S (canonical CSR) after reverse Cuthill-McKee; the pivots, or None
        when it does not apply (S not symmetric, too wide a band unless ``force``, S not positive
        definite)."""
        from scipy.linalg import lapack
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        n = S.shape[0]
        T = S.T.tocsr()
        T.sort_indices()
        same = np.array_equal(T.indptr, S.indptr) and np.array_equal(T.indices, S.indices)
        if not (same and np.allclose(T.data, S.data, rtol=0.0, atol=1e-13)):  # S has a unit diagonal
            return None
        perm = reverse_cuthill_mckee(S, symmetric_mode=True)
        pos = np.empty(n, dtype=np.int64)
        pos[perm] = np.arange(n)
        rows = np.repeat(pos, np.diff(S.indptr))
        cols = pos[S.indices]
        b = int(np.abs(rows - cols).max()) if S.nnz else 0
        if not force and (n * (b + 1) ** 2 > BANDED_MAX_WORK or n * (b + 1) > BANDED_MAX_ENTRIES):
            return None
        upper = rows <= cols
        band = np.zeros((b + 1, n))
        band[b + rows[upper] - cols[upper], cols[upper]] = S.data[upper]
        with _one_blas_thread():
            factor, info = lapack.dpbtrf(band, lower=0, overwrite_ab=1)
        if info != 0:
            return None
        self._band, self._perm, self.kind = factor, perm, "banded"
        return factor[b] ** 2

    def solve(self, b):
        """Solve A x = b for b (n,) or (n, c)."""
        b = np.asarray(b, dtype=float)
        s = self._s if b.ndim == 1 else self._s[:, None]
        if self.kind == "superlu":
            return s * self._lu.solve(np.ascontiguousarray(s * b))
        from scipy.linalg import lapack

        with _one_blas_thread():
            y, info = lapack.dpbtrs(self._band, (s * b)[self._perm], lower=0)
        x = np.empty_like(y)
        x[self._perm] = y
        return s * x


_BLAS_CONTROLLER = None


def _one_blas_thread():
    """Context limiting BLAS/LAPACK to one thread (threadpoolctl).  The banded factorizations are
    small level-3 kernels: OpenBLAS' threads gain little on them and, when the other core of this
    2-core machine is busy, their synchronization made a 2 ms factorization take up to 0.5 s."""
    global _BLAS_CONTROLLER
    if _BLAS_CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _BLAS_CONTROLLER = ThreadpoolController()
    return _BLAS_CONTROLLER.limit(limits=1, user_api="blas")


# ---------------------------------------------------------------------------------------------
# preconditioned conjugate gradients on several right-hand sides at once
# ---------------------------------------------------------------------------------------------


def _columns_dot(a, b):
    """Column-wise dot products of (c, n) arrays without BLAS (see the module docstring)."""
    return np.einsum("ij,ij->i", a, b)


def _pcg(matvec, precond, B, tol, maxiter, name, warn_after=10**9):
    """CG on the columns of B (n, c) at once (independent recurrences, one preconditioner).

    ``matvec`` and ``precond`` map (c, n) -> (c, n).  Stops when every column has a true relative
    residual <= tol (the recursive residual is checked against the true one, and CG restarted
    from the current iterate when they disagree).  Returns (X (n, c), iterations, residuals (c,)).
    """
    b = np.ascontiguousarray(np.asarray(B, dtype=float).T)
    nb = np.sqrt(_columns_dot(b, b))
    active = nb > 0
    nb = np.where(active, nb, 1.0)
    x = np.zeros_like(b)
    r = b.copy()
    it = 0
    rel = np.sqrt(_columns_dot(r, r)) / nb
    while it < maxiter and np.any(rel > tol):
        z = precond(r)
        rz = _columns_dot(r, z)
        p = z
        while it < maxiter:
            q = matvec(p)
            pq = _columns_dot(p, q)
            todo = rel > tol
            if np.any(pq[todo] <= 0) or np.any(rz[todo] <= 0):
                raise SingularSystemError(
                    f"{name}: the matrix or the preconditioner is not positive definite (p^T A p = "
                    f"{pq[todo].min():.3e}); the system is singular or indefinite. Add or increase the stabilization.",
                    smallest=0.0,
                )
            alpha = np.where(todo, rz / np.where(todo, pq, 1.0), 0.0)
            x += alpha[:, None] * p
            r -= alpha[:, None] * q
            it += 1
            rel = np.sqrt(_columns_dot(r, r)) / nb
            if np.all(rel <= tol):
                break
            z = precond(r)
            rz_new = _columns_dot(r, z)
            beta = np.where(todo, rz_new / np.where(todo, rz, 1.0), 0.0)
            p = z + beta[:, None] * p
            rz = rz_new
        # true residual: restart from x if the recursion drifted
        r = b - matvec(x)
        rel = np.sqrt(_columns_dot(r, r)) / nb
    if it > warn_after and np.all(rel <= tol):
        warnings.warn(
            f"{name} needed {it} iterations (well-conditioned systems need fewer than {warn_after}): the system is "
            "probably ill-conditioned or singular (e.g. unstabilized); the solution may not be unique",
            RuntimeWarning,
            stacklevel=3,
        )
    if np.any(rel > tol):
        raise RuntimeError(
            f"{name} did not converge in {maxiter} iterations (relative residual {rel.max():.2e} > {tol}); the system "
            "may be (nearly) singular or ill-conditioned: check the stabilization, or try the direct solver"
        )
    return x.T, it, rel


def _rowwise(A):
    """(c, n) -> (c, n) product with a sparse matrix, column by column (scipy's multi-vector
    product is no faster than separate ones)."""
    return lambda X: np.stack([A @ X[k] for k in range(X.shape[0])])


# ---------------------------------------------------------------------------------------------
# geometric multigrid on nested Kuhn lattices
# ---------------------------------------------------------------------------------------------


def lattice_indices(space):
    """Integer lattice indices (n, 3) of the dofs of a space on a structured box, or None.

    Works for spaces whose dofs are background nodes (``node_ids``) of a
    :class:`~cutfem.mesh.StructuredBox` (``space.cut.background`` or ``space.background``).
    """
    from .mesh import StructuredBox

    node_ids = getattr(space, "node_ids", None)
    cut = getattr(space, "cut", None)
    box = getattr(cut, "background", None) if cut is not None else getattr(space, "background", None)
    if node_ids is None or not isinstance(box, StructuredBox):
        return None
    return box.node_index(node_ids)


def kuhn_prolongation(ijk):
    """Prolongation from the lattice 2Z^3 to the nodes ``ijk`` (m, 3) of Z^3 (Kuhn meshes).

    Row i interpolates the coarse P1 function at fine node ijk[i]: weight 1 on the coarse node
    ijk/2 when every index is even, otherwise 1/2 on each end (ijk -/+ o)/2, o = ijk mod 2, of the
    coarse Kuhn edge whose midpoint it is.  Returns (P (m, mc) CSR, coarse indices (mc, 3)); the
    coarse nodes are those the rows use, in lexicographic (z, y, x) order.
    """
    ijk = np.asarray(ijk, dtype=np.int64)
    o = ijk & 1
    lo = (ijk - o) >> 1
    hi = lo + o
    m = len(ijk)
    cols, cijk = _number_lattice_nodes(np.concatenate([lo, hi]))
    rows = np.concatenate([np.arange(m), np.arange(m)])
    P = sp.csr_matrix((np.full(2 * m, 0.5), (rows, cols)), shape=(m, len(cijk)))
    P.sum_duplicates()
    return P, cijk


def _number_lattice_nodes(ijk):
    """Number the distinct lattice nodes among ``ijk`` (m, 3) in lexicographic (z, y, x) order:
    returns (number of each row (m,), the distinct nodes (mc, 3)).  A dense marker array over the
    bounding box when it is not much larger than the input, else one sort (:func:`unique_keys`)."""
    base = ijk.min(axis=0)
    rel = ijk - base
    dims = rel.max(axis=0) + 1
    code = rel[:, 0] + dims[0] * (rel[:, 1] + dims[1] * rel[:, 2])
    if int(np.prod(dims)) <= 8 * code.size + 1_000_000:
        mark = np.zeros(int(np.prod(dims)), dtype=np.int64)
        mark[code] = 1
        keys = np.flatnonzero(mark)
        mark[keys] = np.arange(keys.size)
        cols = mark[code]
    else:
        keys, cols = unique_keys(code, return_inverse=True)
    nodes = np.stack([keys % dims[0], (keys // dims[0]) % dims[1], keys // (dims[0] * dims[1])], axis=1) + base
    return cols, nodes


def surface_lattice_prolongation(points, spacing: float):
    """Prolongation from the Kuhn lattice ``spacing`` Z^3 to the nodes ``points`` (N, 3) of a
    surface mesh: row i holds the barycentric coordinates of points[i] in the Kuhn tet of the
    lattice that contains it, so P reproduces every linear function of R^3 exactly.

    The lattice is anchored half a spacing below the smallest coordinates.  In a unit cube with
    local coordinates t (Freudenthal/Kuhn: the tets of the cube are t_s1 >= t_s2 >= t_s3 for the
    permutations s), the point with sorted coordinates u1 >= u2 >= u3 has the weights
    1 - u1, u1 - u2, u2 - u3, u3 at the corners 0, e_s1, e_s1 + e_s2, (1, 1, 1).  These are the
    tets of :func:`kuhn_prolongation`, so the lattice levels below are nested as usual.  Columns of
    lattice nodes that get no weight are dropped.  Returns (P (N, mc) CSR, lattice indices (mc, 3)).
    """
    X = np.asarray(points, dtype=float)
    y = (X - (X.min(axis=0) - 0.5 * spacing)) / spacing
    cell = np.floor(y).astype(np.int64)
    t = y - cell
    order = np.argsort(-t, axis=1, kind="stable")
    u = np.take_along_axis(t, order, axis=1)
    w = np.column_stack([1.0 - u[:, 0], u[:, 0] - u[:, 1], u[:, 1] - u[:, 2], u[:, 2]])
    unit = np.eye(3, dtype=np.int64)[order]  # (N, 3, 3): unit[:, k] = e_{s_k}
    corner = np.stack([np.zeros_like(cell), unit[:, 0], unit[:, 0] + unit[:, 1], np.ones_like(cell)], axis=1)
    keep = w.reshape(-1) > 0
    cols, cijk = _number_lattice_nodes((cell[:, None, :] + corner).reshape(-1, 3)[keep])
    rows = np.repeat(np.arange(len(X)), 4)[keep]
    P = sp.csr_matrix((w.reshape(-1)[keep], (rows, cols)), shape=(len(X), len(cijk)))
    P.sum_duplicates()
    return P, cijk


def grid_prolongation(points, shape):
    """Prolongation on a logically structured, doubly periodic surface grid (e.g. the torus
    families of :func:`~cutfem.surface.torus_mesh`).

    ``shape`` = (n, m), both even: node (i, j) has index i m + j and neighbours (i +- 1, j),
    (i, j +- 1) modulo (n, m).  The coarse grid keeps the nodes (2a, 2b), index a (m/2) + b.  A
    coarse node keeps its value; any other fine node x takes the minimum-norm weights w on the four
    corners x_1..x_4 of its coarse cell (2a, 2b) + {0, 2}^2 that reproduce the functions linear in
    the plane of the cell's diagonals d = x_3 - x_1, e = x_4 - x_2:

        min |w|^2  subject to  sum_k w_k = 1,  sum_k w_k (x_k - x).d = 0,  sum_k w_k (x_k - x).e = 0.

    With C the 3 x 4 matrix of the constraints (rows 1, u_k = (x_k - x).d, v_k = (x_k - x).e),
    w = C^T G^{-1} (1, 0, 0)^T, G = C C^T, whose first column is the first row of adj(G) / det G.
    Constants are reproduced exactly, linear functions of R^3 up to the offsets of the corners
    from that plane, O(H^2) times the curvature; weights from the node positions, not from the grid
    indices, keep this true on perturbed grids.  Returns (P (n m, n m / 4) CSR, coarse points,
    coarse shape).
    """
    n, m = (int(v) for v in shape)
    X = np.asarray(points, dtype=float)
    if n % 2 or m % 2 or X.shape != (n * m, 3):
        raise ValueError(f"grid_prolongation needs an even grid shape matching the points; got {shape} and {X.shape}")
    nc, mc = n // 2, m // 2
    i, j = np.divmod(np.arange(n * m), m)
    a, b = i // 2, j // 2
    a1, b1 = (a + 1) % nc, (b + 1) % mc
    cols = np.empty((n * m, 4), dtype=np.int64)
    cols[:, 0], cols[:, 1], cols[:, 2], cols[:, 3] = a * mc + b, a1 * mc + b, a1 * mc + b1, a * mc + b1
    D = X[2 * (cols // mc) * m + 2 * (cols % mc)] - X[:, None, :]  # the corners (2a, 2b) minus x
    d, e = D[:, 2] - D[:, 0], D[:, 3] - D[:, 1]
    u, v = np.einsum("nkc,nc->nk", D, d), np.einsum("nkc,nc->nk", D, e)
    su, sv = u.sum(axis=1), v.sum(axis=1)
    suu, svv, suv = (u * u).sum(axis=1), (v * v).sum(axis=1), (u * v).sum(axis=1)
    c0 = suu * svv - suv * suv
    c1 = suv * sv - su * svv
    c2 = su * suv - suu * sv
    det = 4.0 * c0 + su * c1 + sv * c2
    w = (c0[:, None] + c1[:, None] * u + c2[:, None] * v) / det[:, None]
    w[(i % 2 == 0) & (j % 2 == 0)] = (1.0, 0.0, 0.0, 0.0)
    P = sp.csr_matrix((w.reshape(-1), cols.reshape(-1), np.arange(0, 4 * n * m + 1, 4)), shape=(n * m, nc * mc))
    P.eliminate_zeros()
    coarse_points = X[(2 * np.arange(nc))[:, None] * m + 2 * np.arange(mc)[None, :]].reshape(-1, 3)
    return P, coarse_points, (nc, mc)


def lattice_hierarchy(lattice):
    """The prolongations of :func:`kuhn_prolongation`, level after level, from lattice indices."""
    ijk = np.asarray(lattice)
    while True:
        P, ijk = kuhn_prolongation(ijk)
        yield P


def surface_hierarchy(points, spacing: float):
    """Surface nodes -> Kuhn lattice of ``spacing`` (:func:`surface_lattice_prolongation`), then
    the nested Kuhn lattices."""
    P, ijk = surface_lattice_prolongation(points, spacing)
    yield P
    yield from lattice_hierarchy(ijk)


def grid_hierarchy(points, shape):
    """:func:`grid_prolongation` level after level while both grid dimensions are even and at
    least 6 (a coarser doubly periodic grid would not be a simplicial complex any more)."""
    X, shape = np.asarray(points, dtype=float), tuple(shape)
    while shape[0] % 2 == 0 and shape[1] % 2 == 0 and min(shape) >= 12:
        P, X, shape = grid_prolongation(X, shape)
        yield P


class GeometricMultigrid:
    """Galerkin multigrid for an SPD matrix with a geometric hierarchy of prolongations.

    The hierarchy is either ``lattice`` (n, 3), integer indices of unknowns that are nodes of a Kuhn
    lattice (see :func:`lattice_indices`; levels by :func:`kuhn_prolongation`), or
    ``prolongations``, an iterable giving P_0, P_1, ... lazily (:func:`surface_hierarchy`,
    :func:`grid_hierarchy`, :func:`multigrid_hierarchy`).  Levels A_{l+1} = P_l^T A_l P_l are built
    until at most ``coarse_size`` unknowns remain, the hierarchy ends, or coarsening stalls; the
    coarsest system is solved by :class:`DirectSolver` (a pseudo-inverse if that level is singular
    only because of the coarse space).
    The cycle: one forward Gauss-Seidel sweep, coarse correction (``visits[l]`` recursive cycles
    on level l+1: 1 = V, 2 = W; default V on the finest level and W below), one backward sweep;
    symmetric positive definite, so usable as a CG preconditioner.  ``apply(R)`` acts on (c, n).
    """

    def __init__(self, A, lattice=None, coarse_size: int = 1500, visits=(1, 2), max_levels: int = 20, prolongations=None):
        from pyamg.amg_core import gauss_seidel

        self._gs = gauss_seidel
        A = sp.csr_matrix(A, dtype=float)
        n = A.shape[0]
        if (lattice is None) == (prolongations is None):
            raise ValueError("give either lattice= (Kuhn lattice indices) or prolongations= (a hierarchy), not both")
        if lattice is not None:
            lattice = np.asarray(lattice)
            if lattice.shape != (n, 3) or not np.issubdtype(lattice.dtype, np.integer):
                raise ValueError(f"lattice must be integer indices of shape ({n}, 3), got {lattice.shape} {lattice.dtype}")
            prolongations = lattice_hierarchy(lattice)
        _check_diagonal(A.diagonal())
        self.levels = []
        prolongations = iter(prolongations)
        while A.shape[0] > coarse_size and len(self.levels) < max_levels:
            P = next(prolongations, None)
            if P is None or P.shape[1] >= 0.9 * P.shape[0]:
                break
            if P.shape[0] != A.shape[0]:
                raise ValueError(f"prolongation {len(self.levels)} has {P.shape[0]} rows for {A.shape[0]} unknowns")
            A = self._prepare(A)
            P = sp.csr_matrix(P)
            Ac = (P.T @ (A @ P)).tocsr()
            self.levels.append(dict(A=A, U=sp.triu(A, 1, format="csr"), P=P, R=P.T.tocsr()))
            A = Ac
        self.coarse_n = A.shape[0]
        try:
            self._coarse = ("lu", DirectSolver(A))
        except SingularSystemError as exc:
            self._coarse = ("pinv", self._coarse_pseudo_inverse(A, exc))
        self.visits = [visits[min(k, len(visits) - 1)] for k in range(len(self.levels))]
        self.sizes = [lv["A"].shape[0] for lv in self.levels] + [self.coarse_n]
        self.nnz = [lv["A"].nnz for lv in self.levels] + [A.nnz]

    def _coarse_pseudo_inverse(self, A, exc, tol: float = 1e-10):
        """Pseudo-inverse of a singular coarsest matrix, after checking that its null vectors are not
        null vectors of the finest matrix (then the system itself is singular: SingularSystemError).

        A coarse matrix P^T A P is singular either because A is (a null vector of the coarse matrix,
        prolongated, has zero energy) or because the coarse space is rank-deficient (two coarse
        nodes seen only through one fine node, possible at the edge of the band: its prolongation
        vanishes); only the second is harmless.
        """
        d = A.diagonal()
        s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        w, V = np.linalg.eigh(s[:, None] * A.toarray() * s[None, :])
        null = w <= tol * max(w.max(), 1e-300)
        U = s[:, None] * V[:, null]
        for lv in reversed(self.levels):
            U = lv["P"] @ U
        A0 = self.levels[0]["A"] if self.levels else A
        d0 = A0.diagonal()
        for k in range(U.shape[1]):
            u = U[:, k]
            norm = float(u @ (d0 * u))
            if norm > 0:
                rayleigh = float(u @ (A0 @ u)) / norm
                if rayleigh <= tol:
                    raise SingularSystemError(
                        f"the system is numerically singular: it has a null vector (Rayleigh quotient {rayleigh:.3e} of "
                        "the diagonally scaled matrix, found on the coarsest multigrid level). Add or increase the "
                        "stabilization.",
                        smallest=max(rayleigh, 0.0),
                    ) from exc
        keep = ~null
        return (s[:, None] * (V[:, keep] / w[keep])) @ (V[:, keep].T * s[None, :])

    @staticmethod
    def _prepare(A):
        A = _canonical_csr(A)
        if A.indices.dtype != np.int32 and A.shape[0] < 2**31 and A.nnz < 2**31:
            A.indices = A.indices.astype(np.int32)
            A.indptr = A.indptr.astype(np.int32)
        return A

    @property
    def operator_complexity(self) -> float:
        return sum(self.nnz) / self.nnz[0]

    def __repr__(self) -> str:
        return f"GeometricMultigrid(levels={self.sizes}, operator_complexity={self.operator_complexity:.2f})"

    def _coarse_solve(self, b):
        kind, f = self._coarse
        return f.solve(b) if kind == "lu" else f @ b

    def cycle(self, b, level: int = 0):
        """One cycle for A_level x = b from x = 0 (b a 1-d array)."""
        if level == len(self.levels):
            return self._coarse_solve(b)
        lv = self.levels[level]
        A = lv["A"]
        n = A.shape[0]
        x = np.zeros(n)
        self._gs(A.indptr, A.indices, A.data, x, b, 0, n, 1)
        r = -(lv["U"] @ x)  # residual after a forward sweep from zero: b - (L + D + U) x = -U x
        rc = lv["R"] @ r
        xc = self.cycle(rc, level + 1)
        for _ in range(1, self.visits[level]):
            if level + 1 == len(self.levels):
                break  # the coarsest solve is exact
            xc += self.cycle(rc - self.levels[level + 1]["A"] @ xc, level + 1)
        x += lv["P"] @ xc
        self._gs(A.indptr, A.indices, A.data, x, b, n - 1, -1, -1)
        return x

    def apply(self, R):
        """The preconditioner on the rows of R (c, n)."""
        return np.stack([self.cycle(np.ascontiguousarray(R[k], dtype=float)) for k in range(R.shape[0])])


def multigrid_hierarchy(space):
    """The geometric hierarchy of prolongations for the unknowns of ``space``, or None.

    * a space whose dofs are nodes of a structured Kuhn box (cut spaces on a
      :class:`~cutfem.mesh.StructuredBox`): the nested Kuhn lattices (:func:`lattice_hierarchy`);
    * a surface space whose mesh carries a doubly periodic grid (``mesh.grid = (n, m)``, set by
      :func:`~cutfem.surface.torus_mesh`): the coarser grids (:func:`grid_hierarchy`);
    * any other surface space (dofs = the nodes of ``space.mesh``): the Kuhn lattice of spacing
      twice the mean edge length, then the nested lattices (:func:`surface_hierarchy`).  This
      needs a roughly uniform mesh: where the edges are much shorter than the mean, the first
      coarse space is too coarse (the torus grid, whose edges vary 3:1, needs 50-60 iterations
      this way against 18-23 with its grid).
    """
    fields = getattr(space, "fields", None)
    if fields is not None:  # a product space: one hierarchy per field, block-diagonal prolongations
        hierarchies = [multigrid_hierarchy(f) for f in fields]
        return None if any(h is None for h in hierarchies) else _block_hierarchy(hierarchies)
    ijk = lattice_indices(space)
    if ijk is not None:
        return lattice_hierarchy(ijk)
    mesh = getattr(space, "mesh", None)
    points = getattr(space, "dof_points", None)
    if mesh is None or points is None or len(points) != len(getattr(mesh, "points", ())):
        return None
    grid = getattr(mesh, "grid", None)
    if grid is not None:
        return grid_hierarchy(points, grid)
    return _mean_edge_hierarchy(points, np.asarray(mesh.triangles))


def _block_hierarchy(hierarchies):
    """The block-diagonal prolongations diag(P_1, ..., P_k) of the fields' hierarchies, level by
    level (a monolithic multigrid: the coarse operators P^T A P keep the couplings between fields)."""
    while True:
        Ps = [next(h, None) for h in hierarchies]
        if any(P is None for P in Ps):
            return
        yield sp.block_diag(Ps, format="csr")


def _mean_edge_hierarchy(points, triangles):
    edges = np.linalg.norm(points[triangles] - points[np.roll(triangles, 1, axis=1)], axis=2)
    yield from surface_hierarchy(points, 2.0 * float(edges.mean()))


def mg_solve(A, B, lattice=None, tol: float = DEFAULT_TOL, maxiter: int = 300, prolongations=None, **mg_options):
    """CG preconditioned by :class:`GeometricMultigrid`; B (n,) or (n, c), all columns at once.

    The hierarchy: ``lattice`` (Kuhn lattice indices of the unknowns) or ``prolongations`` (see
    :func:`multigrid_hierarchy`).  ``tol`` is the relative residual ||A x - b|| / ||b|| of every
    column.  Returns (X, SolveInfo).  Raises SingularSystemError (zero diagonal, loss of positive
    definiteness) or RuntimeError (no convergence in ``maxiter`` iterations).
    """
    t0 = time.perf_counter()
    A = GeometricMultigrid._prepare(A)
    mg = GeometricMultigrid(A, lattice, prolongations=prolongations, **mg_options)
    t1 = time.perf_counter()
    B = np.asarray(B, dtype=float)
    cols = B.reshape(B.shape[0], -1)
    X, it, rel = _pcg(_rowwise(A), mg.apply, cols, tol, maxiter, "CG with geometric multigrid", warn_after=MG_WARN_ITERATIONS)
    return X.reshape(B.shape), SolveInfo("cg-mg", it, float(rel.max()), time.perf_counter() - t0, t1 - t0)


# ---------------------------------------------------------------------------------------------
# algebraic preconditioners
# ---------------------------------------------------------------------------------------------


def _amg(A, points=None):
    import pyamg

    kw = dict(symmetry="symmetric", max_coarse=500)
    if points is not None:
        # the near-kernel of the face penalty: the globally linear functions
        P = np.asarray(points, dtype=float)
        kw["B"] = np.column_stack([np.ones(len(P)), P - P.mean(axis=0)])
    M = pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), **kw).aspreconditioner(cycle="V")
    return lambda R: np.stack([M @ R[k] for k in range(R.shape[0])])


def cg_solve(A, B, preconditioner: str = "amg", tol: float = 1e-10, maxiter: int = 5000, points=None, lattice=None):
    """Preconditioned CG for SPD A; B (n,) or (n, c), all columns at once with one preconditioner.

    ``preconditioner``: "mg" (geometric multigrid, needs ``lattice``), "amg" (smoothed aggregation;
    with ``points`` (n, 3) the linear functions are its near-kernel candidates), "jacobi" or "none".
    ``tol`` is relative to ||b|| per column.  Returns (X, SolveInfo).  Raises RuntimeError if CG
    does not converge in ``maxiter`` iterations.
    """
    t0 = time.perf_counter()
    A = sp.csr_matrix(A)
    if preconditioner == "mg":
        if lattice is None:
            raise ValueError("preconditioner 'mg' needs the lattice indices of the unknowns (lattice=...)")
        X, info = mg_solve(A, B, lattice, tol=tol, maxiter=maxiter)
        info.method = "cg+mg"
        return X, info
    if preconditioner == "amg":
        M = _amg(A, points)
    elif preconditioner == "jacobi":
        d = A.diagonal()
        _check_diagonal(d)
        inv = 1.0 / d
        M = lambda R: R * inv  # noqa: E731
    elif preconditioner in (None, "none"):
        M = lambda R: R.copy()  # noqa: E731
    else:
        raise ValueError(f"unknown preconditioner {preconditioner!r}; use 'mg', 'amg', 'jacobi' or 'none'")
    t1 = time.perf_counter()
    B = np.asarray(B, dtype=float)
    cols = B.reshape(B.shape[0], -1)
    X, it, rel = _pcg(_rowwise(A), M, cols, tol, maxiter, "CG")
    return X.reshape(B.shape), SolveInfo(f"cg+{preconditioner}", it, float(rel.max()), time.perf_counter() - t0, t1 - t0)


def _check_levelset_null_vector(A, space, tol: float = 1e-10):
    """Raise SingularSystemError if the nodal vector of phi_h is a null vector of A.

    phi_h vanishes on S_h, so every form that only integrates over S_h (mass, tangential stiffness,
    load) annihilates it: an unstabilized cut system (tau = 0) is singular with this null vector,
    and an iterative solver with a consistent right-hand side would converge without noticing.  The
    face penalty J_F does not vanish on it.  Costs one matrix-vector product.
    """
    cut = getattr(space, "cut", None)
    u = getattr(cut, "values", None)
    if u is None or np.shape(u) != (A.shape[0],):
        return
    d = A.diagonal()
    norm = float(u @ (d * u))
    if norm <= 0:
        return
    rayleigh = float(u @ (A @ u)) / norm
    if rayleigh <= tol:
        raise SingularSystemError(
            f"the system is singular: the nodal vector of phi_h (zero on S_h) is a null vector (Rayleigh quotient "
            f"{rayleigh:.3e} of the diagonally scaled matrix). Add a stabilization (tau_F > 0).",
            smallest=max(rayleigh, 0.0),
        )


def solve(A, B, method: str = "auto", tol: float | None = None, space=None, lattice=None):
    """Solve the SPD system A X = B (B (n,) or (n, c)); returns (X, SolveInfo).

    ``method``: "direct", "cg-mg" (geometric multigrid), "cg-amg", "cg-jacobi" or "auto":
    direct up to :data:`DIRECT_LIMIT` unknowns; above it "cg-mg" when there is a geometric
    hierarchy (``space`` on a StructuredBox or on a surface mesh, see :func:`multigrid_hierarchy`;
    or ``lattice`` given), else direct up to
    :data:`DIRECT_LIMIT_NO_MG` and "cg-amg" above.  ``space`` also provides the dof coordinates for
    the AMG candidates.  ``tol``: relative residual of the iterative methods (default
    :data:`DEFAULT_TOL`).
    """
    n = A.shape[0]
    tol = DEFAULT_TOL if tol is None else tol
    hierarchy = None
    if lattice is None and space is not None:
        hierarchy = multigrid_hierarchy(space)
    has_mg = lattice is not None or hierarchy is not None
    if method == "auto":
        if n <= DIRECT_LIMIT:
            method = "direct"
        elif has_mg:
            method = "cg-mg"
        else:
            method = "direct" if n <= DIRECT_LIMIT_NO_MG else "cg-amg"
    if method == "direct":
        t0 = time.perf_counter()
        solver = DirectSolver(A)
        t1 = time.perf_counter()
        X = solver.solve(B)
        R = np.asarray(A @ X - B).reshape(n, -1)
        nb = np.linalg.norm(np.asarray(B).reshape(n, -1), axis=0)
        res = float(np.max(np.linalg.norm(R, axis=0) / np.where(nb > 0, nb, 1.0)))
        return X, SolveInfo("direct", 0, res, time.perf_counter() - t0, t1 - t0)
    if space is not None and method != "direct":
        _check_levelset_null_vector(A, space)
    if method == "cg-mg":
        if not has_mg:
            raise ValueError(
                "method 'cg-mg' needs a geometric hierarchy: a space on a structured box or on a surface mesh (space=...), "
                "or lattice indices (lattice=...)"
            )
        return mg_solve(A, B, lattice, tol=tol, prolongations=hierarchy)
    if method in ("cg-amg", "cg-jacobi"):
        points = getattr(space, "dof_points", None) if space is not None else None
        X, info = cg_solve(A, B, preconditioner=method.split("-")[1], tol=tol, points=points)
        info.method = method
        return X, info
    raise ValueError(f"unknown method {method!r}; use 'auto', 'direct', 'cg-mg', 'cg-amg' or 'cg-jacobi'")


def condition_number(A, tol: float = 1e-8) -> float:
    """2-norm condition number of D^{-1/2} A D^{-1/2} (A symmetric positive semidefinite).

    Largest eigenvalue by Lanczos; smallest by shift-invert Lanczos around 0 (dense for n <= 400).
    Lanczos starts from a seeded random vector, so the same matrix gives the same digits on every
    run (ARPACK's own start vector varies).  Returns ``inf`` for a singular matrix (zero diagonal or failed factorization).
    """
    try:
        S, _ = scaled(A)
    except SingularSystemError:
        return float("inf")
    n = S.shape[0]
    if n <= 400:
        ev = np.linalg.eigvalsh(S.toarray())
        return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
    v0 = np.random.default_rng(0).standard_normal(n)
    lmax = spla.eigsh(S, k=1, which="LA", tol=tol, v0=v0, return_eigenvectors=False)[0]
    try:
        lu = spla.splu(sp.csc_matrix(S), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:
        return float("inf")
    op = spla.LinearOperator(S.shape, matvec=lu.solve, dtype=float)
    # largest *magnitude* eigenvalue of S^{-1}: for a singular S whose near-null eigenvalue comes out
    # slightly negative in round-off, 'LA' would return 1/lambda_min over the positive ones only
    inv_min = spla.eigsh(op, k=1, which="LM", tol=tol, v0=v0, return_eigenvectors=False)[0]
    if not np.isfinite(inv_min) or inv_min <= 0:
        return float("inf")
    return float(lmax * inv_min)
