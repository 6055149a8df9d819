"""Linear solvers for the symmetric systems of cutfem, and condition number estimates.

What is used when
-----------------
:func:`solve` (``method="auto"``) picks, for an SPD matrix with n unknowns:

* n <= :data:`DIRECT_LIMIT` (5 000): :class:`DirectSolver`, one factorization of the diagonally
  scaled matrix reused for all right-hand sides: a banded Cholesky (LAPACK, after reverse
  Cuthill-McKee) when the band is narrow enough (:data:`BANDED_MAX_WORK`), else a sparse LU
  (SuperLU, minimum degree on A + A^T, symmetric mode).  It is checked: a negative pivot of
  L D L^T (an indefinite matrix), a zero diagonal entry, a failed factorization or a pivot below
  ``1e-10`` times the largest raises :class:`SolverError`, which carries the cause and the smallest
  pivot (1e-10: the singular
  unstabilized cut mass matrix of the torus at spacing 0.05 has its smallest pivot at 1.3e-13, the
  next at 1.8e-2; the stabilized torus systems at spacings 0.1-0.04 have 0.03-0.09).
* n > DIRECT_LIMIT and a geometric hierarchy (:func:`multigrid_hierarchy`): conjugate gradients
  preconditioned by the multigrid :class:`GeometricMultigrid` ("cg-mg"), all right-hand sides at
  once, relative residual :data:`DEFAULT_TOL` (1e-8) per column.  The hierarchies: the nested
  Kuhn lattices when the unknowns are nodes of a structured background (``space=`` a
  :class:`~cutfem.fem.spaces.CutP1Space` on a :class:`~cutfem.geometry.mesh.StructuredBox`, or ``lattice=``
  their integer indices); on a surface mesh (``space=`` a :class:`~cutfem.fem.spaces.SurfaceP1Space`)
  its periodic grid when it has one (the torus families) and otherwise a Kuhn lattice around it.
* otherwise: direct up to :data:`DIRECT_LIMIT_NO_MG` (400 000; :data:`DIRECT_LIMIT_NO_MG_BULK`,
  20 000, for bulk fields, whose factorizations fill in like 3-D grids), then CG with smoothed aggregation
  AMG (pyamg, "cg-amg"), with the globally linear functions as near-kernel candidates when the dof
  coordinates are known (``space``).  Callers with a cut space should pass ``space=`` so that the
  multigrid can be used.

Systems that are not positive definite are reported, never hidden, with their cause
(:class:`SolverError`, ``cause`` "indefinite", "singular" or "over-stabilized", see
:func:`diagnose`): non-positive diagonals (any method); the signs of the pivots of L D L^T
(direct: a failed Cholesky goes to SuperLU, whose pivots count the negative eigenvalues) and
small pivots; negative curvature p^T A p < 0 or another breakdown in CG; an indefinite coarsest
multigrid level; and, on the iterative paths, the null vectors a consistent right-hand side would
let CG converge past without noticing: the constants (a Neumann problem) and the caller's
candidates, among them, when ``space`` is a cut space, the nodal vector of phi_h (zero on S_h,
null for every unstabilized cut system).  The messages only give advice that applies: "raise
the stabilization" only when the stabilization matrix was passed and is too weak on the null
vector, "lower it" only when its own null space dominates, the caller's ``indefinite_hint``
(e.g. "raise the Nitsche penalty gamma") for an indefinite system, otherwise the possible causes
side by side.  CG with multigrid warns when it needs more than :data:`MG_WARN_ITERATIONS`
iterations.

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
being two-dimensional: operator complexity 1.33), built by one compiled pass that sums the upper
triangle and mirrors it, so they are exactly symmetric (:func:`cutfem.solvers.multigrid_kernels.galerkin`).  Cycle:
one forward Gauss-Seidel sweep, coarse correction, one backward sweep; V-cycle on the finest
level, K-cycles below (two coarse cycles combined by two steps of flexible CG, see
:class:`GeometricMultigrid`; CG then takes flexible directions).  Iterations at 1e-6 on the cut
torus: 18 / 20 / 20 / 21 / 21 at spacings 0.05 / 0.025 / 0.0125 / 0.00625 / 0.003125, nearly
independent of h (with W-cycles below the finest level 18 / 21 / 23 / 25 / 28, with V-cycles
everywhere 34 at 0.0125 and 48 at 0.00625); :class:`DirectSolver` on the coarsest level (<= 1500
unknowns).  The residual after the forward sweep from zero is -U x (U the strictly upper part):
half a product.

Measured on this machine (2 cores), cut torus of docs/math.md §6, K = M + 0.1 J_F, the three
right-hand sides A @ x_k; times in s (wall; the machine is noisy, +-30 %), "its" per column:

=======  =======  =================================  =============================
spacing  n        cg-mg, tol 1e-6 (1e-8)             SuperLU (previous default)
=======  =======  =================================  =============================
0.05     18 024   0.05 + 0.07 s, 18 its (0.10, 24)   0.22 + 0.02 s
0.025    72 928   0.16 + 0.51 s, 21 its (0.52, 28)   2.0 + 0.24 s
0.0125   293 244  0.3 + 1.7-2.3 s, 23 its (2.6, 31)  25 + 6 s, 3 GiB
=======  =======  =================================  =============================

(measured with W-cycles below the finest level, when the multigrid path was introduced)

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

BLAS threads: the iteration loops and the null-vector checks before them use no BLAS calls (column
dot products by a compiled kernel, :func:`cutfem.solvers.sparse_kernels.column_dots`): on this machine's 2 virtual cores, OpenBLAS' threaded level-1 calls on vectors of 10^5 entries are up to
20 times slower than serial ones, which made scipy's ``cg`` erratic (0.2 s to 3.7 s for the same
300 iterations).

* :func:`condition_number`: the 2-norm condition number of the diagonally scaled matrix
  D^{-1/2} A D^{-1/2}, from its extreme eigenvalues (Lanczos; shift-invert for the smallest), as a
  :class:`ConditionNumber`: a float that also says whether the matrix is definite, singular,
  over-stabilized or indefinite (``cause``).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..geometry.keys import dense_unique, unique_keys
from ..geometry.numbering import index_dtype
from . import multigrid_kernels
from . import sparse_kernels

__all__ = [
    "SolverError",
    "diagnose",
    "ConditionNumber",
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
    "CGSolver",
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

#: ... but only this far for fields that fill a volume (bulk fields of a side, product spaces with
#: one): their direct factorizations fill in like a 3-D grid's.  Fictitious-domain Poisson on a
#: pytetwild background at 39k unknowns took 27-46 s direct against 2.4 s with cg-amg
DIRECT_LIMIT_NO_MG_BULK = 20_000

#: CG with multigrid warns (RuntimeWarning) when it needs more iterations than this: the stabilized
#: cut systems need 15-40 at any spacing, an unstabilized (singular) one hundreds
MG_WARN_ITERATIONS = 100

#: default relative residual of the iterative methods of :func:`solve`.  Against 1e-6, measured at
#: spacing 0.05: the L2 errors of interface-poisson-cut move by 0.5 % at 1e-6 (poisson-cut 3.5e-5,
#: bulk-surface-cut 7e-6, the surface problems 1e-7 or less), so the bulk problems need 1e-8.
#: Invariants that are sums of the residual (the integral of the mean curvature vector, 1^T M H =
#: -1^T r) hold to round-off at any tolerance: CG ends with the Galerkin correction on the
#: constants (:func:`_constant_correction`)
DEFAULT_TOL = 1e-8


class SolverError(ValueError):
    """A system declared symmetric positive definite is not, and why.

    ``cause`` is one of :data:`SolverError.CAUSES`:

    * ``"indefinite"``: the matrix has a negative eigenvalue (a negative pivot of L D L^T, a
      failed Cholesky confirmed by the signs of L D L^T, a negative curvature p^T A p < 0 in CG,
      a negative diagonal entry, or a zero diagonal entry with a nonzero row);
    * ``"singular"``: a (numerical) null vector, named in ``kernel`` when it is known
      (``"constants"``, ``"phi_h"``, a name given in ``kernels=``), or a zero row;
    * ``"over-stabilized"``: numerically singular because the stabilization dominates: the
      near-null vector lies in the stabilization's own null space while the rest of the form sees
      it (only told when the caller passes the stabilization matrix, see :func:`diagnose`).

    ``smallest``: the smallest pivot, Rayleigh quotient or eigenvalue estimate of the diagonally
    scaled matrix behind the verdict (0 for an exactly zero row).
    """

    CAUSES = ("indefinite", "singular", "over-stabilized")

    def __init__(self, message, cause, smallest=0.0, kernel=None):
        if cause not in self.CAUSES:
            raise ValueError(f"unknown cause {cause!r}; one of {self.CAUSES}")
        super().__init__(message)
        self.cause = cause
        self.smallest = float(smallest)
        self.kernel = kernel


#: relative size (of the diagonally scaled matrix, whose diagonal is 1) below which a pivot,
#: Rayleigh quotient or eigenvalue counts as zero; below minus it, as negative
ZERO_TOL = 1e-10

#: a candidate null vector u is one when ||D^{-1/2} A u|| <= KERNEL_TOL ||D^{1/2} u||
KERNEL_TOL = 1e-8

#: a part of the form "sees" a vector v when its scaled Rayleigh quotient exceeds this
SEEN_TOL = 1e-6

GENERIC_INDEFINITE_ADVICE = (
    "A symmetric positive definite system was expected. Check the signs of the terms (a negative zero-order term, "
    "as in -Lap u - k^2 u, is indefinite) and the penalty parameters (a Nitsche penalty gamma below its stability "
    "bound makes the Nitsche systems indefinite: raise gamma); pass indefinite_hint= to name the cause of a "
    "specific system, or spd=False to the direct solver for a system that is indefinite by design."
)


@dataclass
class _Checks:
    """What the caller knows about the system, for the diagnosis of a failure (see :func:`diagnose`)."""

    kernels: dict
    stabilization: object = None
    indefinite_hint: str | None = None

    @classmethod
    def of(cls, kernels=None, stabilization=None, indefinite_hint=None, n=None):
        named = {}
        for name, u in (kernels or {}).items():
            u = np.asarray(u, dtype=float)
            if n is not None and u.shape != (n,):
                raise ValueError(f"candidate null vector {name!r} has shape {u.shape}; expected ({n},)")
            named[str(name)] = u
        if stabilization is not None:
            stabilization = _canonical_csr(stabilization)
            if n is not None and stabilization.shape != (n, n):
                raise ValueError(f"stabilization has shape {stabilization.shape}; expected ({n}, {n})")
        return cls(named, stabilization, indefinite_hint)


def _dot(u, v) -> float:
    """u . v of two long vectors by :func:`cutfem.solvers.sparse_kernels.column_dots`, not BLAS (see the module
    docstring): OpenBLAS hands a dot of this length to its threads, which then spin on the other
    core for about 0.1 s after the call (each of the two dots of a solve at 293k unknowns cost
    0.11-0.13 s of CPU beside the caller)."""

    return float(sparse_kernels.column_dots(u[:, None], v[:, None])[0])


def _product(A, v):
    """A v for a vector v, by :func:`cutfem.solvers.sparse_kernels.matmul` (on all cores) for a float64 CSR matrix."""
    if sp.isspmatrix_csr(A) and A.dtype == np.float64:
        return _matvec(A)(np.asarray(v, dtype=float)[:, None])[:, 0]
    return A @ v


def _scaled_rayleigh(A, d, v):
    """v^T A v / v^T D v (the Rayleigh quotient of D^{-1/2} A D^{-1/2} at D^{1/2} v)."""
    den = _dot(v, d * v)
    return _dot(v, _product(A, v)) / den if den > 0 else np.inf


def _kernel_residual(A, d, u):
    """||D^{-1/2} A u|| / ||D^{1/2} u||: zero exactly when u is a null vector."""
    s = 1.0 / np.sqrt(d)
    den = np.sqrt(_dot(u, d * u))
    r = s * _product(A, u)
    return float(np.sqrt(_dot(r, r))) / den if den > 0 else np.inf


def _lanczos_smallest(S, seed: int = 0):
    """A Ritz estimate (value, vector) of the smallest eigenvalue of the symmetric S (Lanczos,
    loose tolerance).  A Ritz value is an upper bound of lambda_min, so a negative one proves
    that S is indefinite.  Dense for n <= 500."""
    n = S.shape[0]
    if n <= 500:
        with _one_blas_thread():
            w, V = np.linalg.eigh(S.toarray())
        return float(w[0]), V[:, 0]
    v0 = np.random.default_rng(seed).normal(size=n)
    try:
        w, V = spla.eigsh(S, k=1, which="SA", tol=1e-3, maxiter=min(n, 3000), v0=v0)
    except spla.ArpackNoConvergence as exc:
        if len(exc.eigenvalues) == 0:
            return np.inf, None
        w, V = exc.eigenvalues, exc.eigenvectors
    return float(w[0]), V[:, 0]


def diagnose(A, vectors=(), smallest=None, where="the solver", negative_pivots=0, kernels=None, stabilization=None,
             indefinite_hint=None, _checks=None) -> SolverError:
    """Why the symmetric matrix A, declared positive definite, is not: a :class:`SolverError`
    (returned, not raised) with its cause and a message that gives only advice that applies.

    Evidence from the failing solver: ``smallest`` (smallest pivot of L D L^T, or Rayleigh
    quotient, of the diagonally scaled matrix S = D^{-1/2} A D^{-1/2}), ``negative_pivots`` (the
    number of pivots below -:data:`ZERO_TOL`: by Sylvester's law of inertia, of negative
    eigenvalues), ``vectors`` (near-null or negative-curvature vectors, e.g. the CG direction at a
    breakdown).  What the caller knows: ``kernels`` ({name: (n,) vector}, candidate null vectors,
    e.g. {"phi_h": nodal values of the level set}), ``stabilization`` (the stabilization matrix as
    contained in A, e.g. tau_F J_F), ``indefinite_hint`` (the advice for an indefinite system, e.g.
    "raise the Nitsche penalty gamma").  The tests, in order:

    1. the diagonal: a negative entry, or a zero entry with a nonzero row, proves indefiniteness
       (a 1x1 or 2x2 principal minor is negative); a zero row is a singular unknown;
    2. the candidate null vectors, the constants first: ||D^{-1/2} A u|| <= KERNEL_TOL ||D^{1/2} u||;
    3. negative pivots, or a Rayleigh quotient or ``smallest`` below -ZERO_TOL: indefinite;
    4. otherwise (and, without evidence, after a Lanczos estimate of lambda_min(S), negative ->
       indefinite) singular at the vector v of smallest Rayleigh quotient.  With ``stabilization``
       (A = R + G): the scaled Rayleigh quotients rho_R(v) = v^T R v / v^T D_R v and
       rho_G(v) likewise; rho_G <= SEEN_TOL < rho_R: "over-stabilized" (v lies in the
       stabilization's own null space, e.g. the globally linear functions for the face penalty,
       and the rest of the form sees it only relative to a much larger diagonal: lower the
       stabilization); rho_R <= SEEN_TOL < rho_G: singular, raise the stabilization; both small:
       singular, a null vector of both.  Without it the message names these possibilities
       conditionally: the two cannot be told apart from A alone.
    """
    checks = _checks if _checks is not None else _Checks.of(kernels, stabilization, indefinite_hint)
    A = _canonical_csr(A)
    d = A.diagonal()
    hint = checks.indefinite_hint or GENERIC_INDEFINITE_ADVICE
    # 1. the diagonal
    if np.any(d < 0):
        k = int(np.argmin(d))
        return SolverError(
            f"{where}: the matrix is indefinite: {int((d < 0).sum())} negative diagonal entries (first at unknown "
            f"{int(np.flatnonzero(d < 0)[0])}, smallest {d[k]:.3e}). {hint}",
            "indefinite", smallest=float(d[k]),
        )
    if np.any(d == 0):
        zero = d == 0
        row_norm = np.sqrt(np.asarray(A.multiply(A).sum(axis=1)).ravel())
        mixed = zero & (row_norm > 0)
        if np.any(mixed):
            return SolverError(
                f"{where}: the matrix is indefinite: {int(mixed.sum())} unknowns have a zero diagonal entry but a "
                f"nonzero row (first: unknown {int(np.flatnonzero(mixed)[0])}), so a 2x2 principal minor is negative. {hint}",
                "indefinite", smallest=0.0,
            )
        k = np.flatnonzero(zero)
        return SolverError(f"{where}: the system is singular: {k.size} unknowns appear in no term (zero rows; first: "
                           f"unknown {k[0]}). {_zero_rows_cause(k, checks)}", "singular", smallest=0.0)
    # 2. named candidate null vectors
    err = _named_kernel_error(A, d, checks, where)
    if err is not None:
        return err
    # 3. inertia and curvature
    vectors = [np.asarray(v, dtype=float) for v in vectors if v is not None and np.any(v)]
    quotients = [_scaled_rayleigh(A, d, v) for v in vectors]
    low = min([q for q in quotients] + ([smallest] if smallest is not None else []), default=None)
    if negative_pivots > 0 or (low is not None and low < -ZERO_TOL):
        what = (f"{negative_pivots} negative pivots of L D L^T, so as many negative eigenvalues" if negative_pivots > 0
                else f"a direction of negative curvature, scaled Rayleigh quotient {low:.3e}")
        return SolverError(f"{where}: the matrix is indefinite ({what}). {hint}", "indefinite", smallest=low if low is not None else -1.0)
    # 4. singular: find a near-null vector if the evidence has none
    if low is None or low > ZERO_TOL:
        S, _ = scaled(A)
        lam, w = _lanczos_smallest(S)
        if lam < -ZERO_TOL:
            return SolverError(f"{where}: the matrix is indefinite (Lanczos estimate of the smallest eigenvalue of the "
                               f"diagonally scaled matrix: {lam:.3e}). {hint}", "indefinite", smallest=lam)
        if w is not None:
            vectors.append(w / np.sqrt(d))
            quotients.append(_scaled_rayleigh(A, d, vectors[-1]))
        low = min(quotients + ([smallest] if smallest is not None else []), default=lam)
    v = vectors[int(np.argmin(np.abs(quotients)))] if vectors else None
    if checks.stabilization is not None and v is not None:
        return _stabilization_verdict(A, v, low, checks, where, "near-null vector")
    return SolverError(
        f"{where}: the system is numerically singular (smallest pivot or Rayleigh quotient {low:.3e} of the diagonally "
        "scaled matrix, whose diagonal is 1). Possible causes: too little stabilization (basis functions barely seen by "
        "the forms: raise it), too much (its own null space, e.g. the linear functions for the face penalty, dominates: "
        "lower it), or a null space of the problem itself. Pass stabilization= (the stabilization matrix contained in "
        "the system) and kernels= (candidate null vectors) to tell them apart.",
        "singular", smallest=low,
    )


def _zero_rows_cause(rows, checks) -> str:
    """The cause and the fix of the unknowns ``rows`` that no term reaches (zero rows).

    With the nodal values of phi_h (a cut space) it is told from the geometry.  A node off S_h
    (phi_h != 0) whose row is zero has a basis function that vanishes on every piece of S_h in its
    tets, so those pieces lie in the faces opposite the node: S_h runs along faces of the
    background mesh (a level set zero on whole grid faces, e.g. a cube or a flat cap on grid
    planes; such a piece is counted once, in the tet on one side of its face).  A zero row also
    means that no face at the node is shared by two active tets, so the face stabilization does
    not reach it, whatever tau_F: fixing such unknowns (their values change nothing on S_h) or
    moving S_h off the grid planes does.  A zero row at a node on S_h, or without phi_h, is a
    basis function that no term sees: a stabilization acting on it is missing."""
    phi = checks.kernels.get("phi_h")
    if phi is not None and np.all(phi[rows] != 0):
        return ("These are nodes off S_h (phi_h != 0) of active tets whose piece of S_h lies in the face opposite the "
                "node: S_h runs along faces of the background mesh (the level set is zero on whole faces, e.g. a cube or "
                "a flat cap lying on grid planes). Their basis functions vanish on S_h, and no face at them is shared by "
                "two active tets, so the face stabilization (any tau_F) does not reach them either. Their values "
                "change nothing on S_h: fix them at 0 (cutfem.problems.common.pin_unseen_nodes, as mean-curvature-cut "
                "does), or move the surface off the grid planes: shift the background box by a fraction of the spacing "
                "(--box, e.g. its corners moved by spacing / 3), or the surface itself.")
    return ("On a cut surface these are basis functions with no support on S_h: add a stabilization that acts on them "
            "(e.g. tau_F > 0) or leave them out of the space.")


def _split_quotients(A, G, v):
    """Scaled Rayleigh quotients (rho_R, rho_G) of v for A = R + G (each scaled by its own diagonal)."""
    R = A - G
    return _scaled_rayleigh(R, np.abs(R.diagonal()), v), _scaled_rayleigh(G, np.abs(G.diagonal()), v)


def _stabilization_verdict(A, v, low, checks, where, what, kernel=None):
    """SolverError for a (numerically) null vector v of A = R + G, G = checks.stabilization."""
    rho_r, rho_g = _split_quotients(A, checks.stabilization, v)
    detail = (f"scaled Rayleigh quotients at the {what}: {low:.3e} for the system, {rho_r:.3e} without the "
              f"stabilization, {rho_g:.3e} for the stabilization")
    if rho_g <= SEEN_TOL < rho_r:
        return SolverError(
            f"{where}: the system is numerically singular because it is over-stabilized ({detail}): the null space of "
            "the stabilization (e.g. the globally linear functions for the face penalty), which dominates the diagonal, "
            f"contains the {what}, which the rest of the form sees. Lower the stabilization parameter.",
            "over-stabilized", smallest=low, kernel=kernel,
        )
    if rho_r <= SEEN_TOL < rho_g:
        return SolverError(
            f"{where}: the system is numerically singular ({detail}): the forms barely see the {what} and the "
            "stabilization is too weak on it. Raise the stabilization parameter.",
            "singular", smallest=low, kernel=kernel,
        )
    return SolverError(
        f"{where}: the system is numerically singular ({detail}): a null vector of both the forms and the "
        "stabilization, so changing the stabilization parameter does not help; a term or a constraint acting on it "
        "is missing.",
        "singular", smallest=low, kernel=kernel,
    )


def _named_kernel_error(A, d, checks, where):
    """SolverError when the constants or a candidate of ``checks.kernels`` is a numerical null
    vector (||D^{-1/2} A u|| <= KERNEL_TOL ||D^{1/2} u||), else None.  With a stabilization G,
    a candidate that only G annihilates while the rest of the form sees it is not a null vector
    of the problem but the sign of over-stabilization (a large G makes it look null)."""
    for name, u in {"constants": np.ones(A.shape[0]), **checks.kernels}.items():
        res = _kernel_residual(A, d, u)
        if res > KERNEL_TOL:
            continue
        if checks.stabilization is not None:
            rho_r, rho_g = _split_quotients(A, checks.stabilization, u)
            if not (rho_r <= SEEN_TOL and rho_g <= SEEN_TOL):
                label = "constant functions" if name == "constants" else f"candidate null vector {name!r}"
                return _stabilization_verdict(A, u, _scaled_rayleigh(A, d, u), checks, where, label, kernel=name)
        return SolverError(f"{where}: {_kernel_message(name, res, checks)}", "singular", smallest=res, kernel=name)
    return None


def _kernel_message(name, res, checks):
    stab = checks.stabilization is not None
    if name == "constants":
        return (
            f"the system is singular: the constant functions are a null vector (||D^-1/2 A 1|| / ||D^1/2 1|| = {res:.1e}): "
            "the solution is determined only up to a constant, as in a pure Neumann problem or -Lap_S u = f on a closed "
            "surface without the zero-order term. Fix the constant (a zero-order term, a mean-value constraint or a "
            "Dirichlet condition); no stabilization removes this null vector. "
            + ("" if stab else "(Unless the system holds a stabilization with a very large parameter, whose own null space "
               "contains the constants: then lower it; pass stabilization= to tell.)")
        )
    lead = (
        "the nodal vector of phi_h (zero on S_h) is a null vector: the forms only see S_h"
        if name == "phi_h"
        else f"the candidate null vector {name!r} is a null vector"
    )
    tail = (
        "The stabilization passed vanishes on it too: raising it does not help; use a term that acts on it."
        if stab
        else "Add a stabilization that acts on it (for phi_h: tau_F > 0, or the normal-gradient term when phi_h is "
        "linear, on which the face penalty vanishes); if the system has one already, it vanishes on this vector and "
        "raising it does not help."
    )
    return f"the system is singular: {lead} (relative residual {res:.1e}). {tail}"


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


def scaled(A, where: str = "the solver", _checks=None):
    """(D^{-1/2} A D^{-1/2}, d) with d = diag(A), CSR in canonical form (sorted, no duplicates);
    raises :class:`SolverError` (see :func:`diagnose`) on a non-positive diagonal."""
    A = _canonical_csr(A)
    d = A.diagonal()
    if np.any(d <= 0):
        raise diagnose(A, where=where, _checks=_checks)
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

    A pivot below -``pivot_tol`` times the largest raises :class:`SolverError` with cause
    "indefinite"; one within +-``pivot_tol`` times the largest, a zero diagonal entry or a failed
    LU, "singular" or "over-stabilized" (:func:`diagnose`, which then gets a near-null vector from
    two steps of inverse iteration with the factorization, or with that of S + 1e-8 I when the LU
    failed).  ``pivot_tol``: a number in [0, 1).  ``kernels``, ``stabilization`` and
    ``indefinite_hint`` let :func:`diagnose` name the cause.  A non-symmetric matrix with
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
    2-core machine is busy, their synchronization made a 2 ms factorization take up to 0.5 s."""
    global _BLAS_CONTROLLER
    if _BLAS_CONTROLLER is None:
        _BLAS_CONTROLLER = _threadpoolctl().ThreadpoolController()
    return _BLAS_CONTROLLER.limit(limits=1, user_api="blas")


# ---------------------------------------------------------------------------------------------
# preconditioned conjugate gradients on several right-hand sides at once
# ---------------------------------------------------------------------------------------------


def _pcg(A, precond, B, tol, maxiter, name, checks, warn_after=10**9, x0=None, cache=None):
    """Preconditioned CG on the columns of B (n, c) at once: independent recurrences, one
    preconditioner, each iteration one product with A and one preconditioner application for the
    block of the columns that have not converged (a column stops updating once its relative
    residual is <= tol; the product (:func:`cutfem.solvers.sparse_kernels.matmul`, one pass over A for the block)
    and ``precond`` act on (n, k) blocks).  The search directions are flexible (Polak-Ribiere):
    beta = z_new^T (r_new - r_old) / z_old^T r_old = -z_new^T q / p^T q with q = A p, which is
    the usual z_new^T r_new / z_old^T r_old for a fixed SPD preconditioner in exact arithmetic
    and keeps each direction A-orthogonal to the previous one when the preconditioner varies
    from one application to the next (the multigrid's K-cycle); it costs one column dot more.
    The columns are independent recurrences: each gives, bitwise, what it gives alone.  Why not a block CG, whose search directions the columns share:
    it needed as many iterations (28 at spacing 0.025, tolerance 1e-8, on the cut torus) as three
    independent recurrences, as the multigrid leaves no isolated small eigenvalues for the shared
    space to remove.

    Stops when every column has a true relative residual <= tol (the recursive residual is checked
    against the true one, and CG restarted from the current iterate when they disagree).  A
    breakdown, p^T A p <= 0 or r^T M r <= 0, raises :class:`SolverError` (:func:`diagnose` with the
    search directions: a scaled Rayleigh quotient p^T A p / p^T D p below -ZERO_TOL is a direction
    of negative curvature, so "indefinite").  At convergence the iterates get the Galerkin
    correction on the constants (:func:`_constant_correction`; ``cache``, a dict the caller keeps
    for later solves with A, holds the product A 1 it needs).  ``x0`` (n, c): the starting iterates
    (default zero); a column of x0 whose residual is larger than its right-hand side's norm starts
    from zero instead (a guess worse than none, as the lumped-mass guess of a mean curvature
    vector on a perturbed mesh: residuals 4e3 times |b|, 38 iterations against 25 from zero).
    Returns (X (n, c), iterations, residuals (c,)).
    """

    matvec = _matvec(A)
    b = np.ascontiguousarray(B, dtype=float)
    nb = np.sqrt(sparse_kernels.column_dots(b, b))
    nb = np.where(nb > 0, nb, 1.0)
    if x0 is None:
        x = np.zeros_like(b)
        r = b.copy()
    else:
        x = np.array(x0, dtype=float, order="C").reshape(b.shape)
        r = np.empty_like(b)
        np.subtract(b, matvec(x, r), out=r)  # r = b - A x0 (A x0 written into r first)
    it = 0
    rel = np.sqrt(sparse_kernels.column_dots(r, r)) / nb
    worse = np.flatnonzero(rel > 1.0)
    if x0 is not None and worse.size:  # a guess farther than zero (by the residual): those columns from zero
        x[:, worse], r[:, worse], rel[worse] = 0.0, b[:, worse], 1.0
    while it < maxiter and np.any(rel > tol):
        act = np.flatnonzero(rel > tol)
        ra = r if act.size == r.shape[1] else r[:, act]  # no copy of r when every column goes on
        z = precond(ra)
        rz = sparse_kernels.column_dots(ra, z)
        p = np.array(z, dtype=float)  # a copy: the preconditioner may hand out its own array again
        q = np.empty_like(p)
        while it < maxiter:
            if q.shape != p.shape:
                q = np.empty_like(p)
            pq = np.empty(p.shape[1])
            q = matvec(p, q, dots=pq)  # and pq = p^T q in the same pass, bitwise sparse_kernels.column_dots(p, q)
            if np.any(pq <= 0) or np.any(rz <= 0):
                curvature = pq / np.maximum(sparse_kernels.column_dots(p * A.diagonal()[:, None], p), 1e-300)
                raise diagnose(A, vectors=list(p.T), smallest=float(curvature.min()),
                               where=f"{name} (breakdown at iteration {it}: p^T A p / p^T D p = {curvature.min():.3e}, "
                               f"r^T M r = {rz.min():.3e})", _checks=checks)
            rel_a = np.sqrt(sparse_kernels.cg_step(x, r, p, q, rz / pq, act)) / nb[act]  # x, r updated in place
            it += 1
            rel[act] = rel_a
            keep = rel_a > tol
            if not np.any(keep):
                break
            if not np.all(keep):  # freeze the converged columns
                # C order (a column selection comes out in Fortran order): the kernels keep one signature
                act, p, q, pq = act[keep], np.ascontiguousarray(p[:, keep]), np.ascontiguousarray(q[:, keep]), pq[keep]
            ra = r if act.size == r.shape[1] else r[:, act]
            z = precond(ra)
            rz, zq = sparse_kernels.column_dots(ra, z, q)  # one pass over the three blocks
            sparse_kernels.cg_direction(p, z, -zq / pq)  # flexible: beta = -z^T q / p^T q
        del p, q  # made again on a restart; freed here for the check and the correction below
        # true residual: restart from x if the recursion drifted
        np.subtract(b, matvec(x, r), out=r)  # r = b - A x in place (A x written into r first)
        rel = np.sqrt(sparse_kernels.column_dots(r, r)) / nb
        if np.all(rel <= tol):
            r, rel = _constant_correction(A, x, r, nb, tol, cache)
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
    return x, it, rel


def _constant_correction(A, x, r, nb, tol, cache=None):
    """The Galerkin correction of the iterates ``x`` (n, c) on the constants, in place, where it keeps
    the relative residual within ``tol``: x += alpha 1, alpha = 1^T r / 1^T A 1 (r = b - A x).

    This is the A-orthogonal projection of the error onto span{1}, so it never increases the error in
    the energy norm, and it makes 1^T r = 0: the discrete solution's conservation laws that are sums
    of the residual hold to round-off whatever the tolerance.  For the mean curvature problem,
    int_{S_h} H_h = 1^T M H = 1^T B - 1^T r with 1^T B = 0 and J 1 = 0 (docs/math.md §3): on the cut
    torus at spacing 0.0125 it is 3e-13 after the correction at tolerance 1e-6, where it was 9e-10
    at 1e-6 and 2e-11 at 1e-8 without it.  ``cache`` (a dict, or None): A 1 is taken from its
    "ones_product" (with the vector 1 in "ones") or computed and kept there.  Returns (r, rel) updated."""

    cache = {} if cache is None else cache
    if cache.get("ones_product") is None:
        cache["ones"] = np.ones((A.shape[0], 1), dtype=A.dtype)
        cache["ones_product"] = sparse_kernels.matmul(A, cache["ones"])  # A 1 (a third of A.sum's time)
    ones, a1 = cache["ones"], cache["ones_product"]
    denom = float(a1.ravel().sum())  # 1^T A 1 > 0 for SPD A
    if not denom > 0:
        return r, np.sqrt(sparse_kernels.column_dots(r, r)) / nb
    # column by column (each bitwise what it is in the block, see sparse_kernels.column_dots), so that the
    # temporaries are single columns: a block of three is 113 MB at 4.7 million unknowns, and this
    # runs where the solve's memory peaks
    rel = np.empty(r.shape[1])
    for l in range(r.shape[1]):
        col = r[:, l : l + 1]
        alpha = sparse_kernels.column_dots(col, ones)[0] / denom  # 1^T r
        new = col - alpha * a1
        rel[l] = np.sqrt(sparse_kernels.column_dots(new, new)[0]) / nb[l]
        if rel[l] <= tol:
            x[:, l] += alpha
            col[...] = new
        else:
            rel[l] = np.sqrt(sparse_kernels.column_dots(col, col)[0]) / nb[l]
    return r, rel


def _matvec(A):
    """(n, c) -> (n, c) product with the sparse matrix A, one pass over A for up to three columns
    (:func:`cutfem.solvers.sparse_kernels.matmul`, ``dots`` as there; the CG products of the cut torus at spacing
    0.0125, three columns in double precision: 9.5 ms against 29-31 ms for scipy's three
    products)."""

    A = sp.csr_matrix(A)
    return lambda X, out=None, dots=None: sparse_kernels.matmul(A, np.ascontiguousarray(X, dtype=A.dtype), out=out, dots=dots)


# ---------------------------------------------------------------------------------------------
# geometric multigrid on nested Kuhn lattices
# ---------------------------------------------------------------------------------------------


def lattice_indices(space):
    """Integer lattice indices (n, 3) of the dofs of a space on a structured box, or None.

    Works for spaces whose dofs are background nodes (``node_ids``) of a
    :class:`~cutfem.geometry.mesh.StructuredBox` (``space.cut.background`` or ``space.background``).
    """
    from ..geometry.box import StructuredBox

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
    coarse nodes are those the rows use, in lexicographic (z, y, x) order.  Compiled passes
    (:func:`cutfem.solvers.multigrid_kernels.kuhn_ends_bounds`, :func:`~cutfem.solvers.multigrid_kernels.kuhn_ends_codes`,
    :func:`~cutfem.solvers.multigrid_kernels.kuhn_prolongation_csr`) give the bounding box of the edge ends, their
    lexicographic numbers and the CSR arrays (one or two entries a row, the lower end first: its
    number is the smaller), with the numbering between them (:func:`_number_lattice_codes`); numpy
    needed a dozen (m, 3) integer arrays and axis reductions over them: 2.7 s of the 6.1 s of
    multigrid setup at spacing 0.003125 (4.7 million unknowns), against 0.5-0.6 s.
    """

    ijk = np.ascontiguousarray(ijk, dtype=np.int64)
    m = len(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3 or m == 0:
        raise ValueError(f"kuhn_prolongation needs lattice indices of shape (m, 3), m >= 1; got {ijk.shape}")
    bounds = np.empty((2, 3), dtype=np.int64)
    multigrid_kernels.kuhn_ends_bounds(ijk, bounds)
    base, dims = bounds[0], bounds[1] - bounds[0] + 1
    codes = np.empty(2 * m, dtype=np.int64)
    multigrid_kernels.kuhn_ends_codes(ijk, base, dims, codes)
    cols, cijk = _number_lattice_codes(codes, base, dims)
    index = index_dtype(2 * m)
    indptr = np.empty(m + 1, dtype=index)
    indices, data = np.empty(2 * m, dtype=index), np.empty(2 * m)
    multigrid_kernels.kuhn_prolongation_csr(ijk, cols, indptr, indices, data)
    nnz = int(indptr[-1])
    P = sp.csr_matrix((data[:nnz], indices[:nnz], indptr), shape=(m, len(cijk)))
    P.has_sorted_indices = True
    P.has_canonical_format = True
    return P, cijk


def _number_lattice_nodes(ijk):
    """Number the distinct lattice nodes among ``ijk`` (m, 3) in lexicographic (z, y, x) order:
    returns (number of each row (m,), the distinct nodes (mc, 3)); see :func:`_number_lattice_codes`."""
    base = ijk.min(axis=0)
    rel = ijk - base
    dims = rel.max(axis=0) + 1
    return _number_lattice_codes(rel[:, 0] + dims[0] * (rel[:, 1] + dims[1] * rel[:, 2]), base, dims)


def _number_lattice_codes(code, base, dims):
    """Number the distinct lattice nodes given by their lexicographic numbers ``code`` (m,) in the
    box ``base`` + [0, dims): returns (number of each (m,), the distinct nodes (mc, 3)).  A bitmap
    over the box (:func:`~cutfem.geometry.mesh.dense_unique`, a bit a lattice point) when it is not much
    larger than the input, else one sort (:func:`unique_keys`)."""
    if int(np.prod(dims)) <= 64 * code.size + 10_000_000:
        keys, cols = dense_unique(code, int(np.prod(dims)))
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


#: the weights of a node on a coarse edge off that edge below which the grid prolongation drops
#: them (:func:`grid_prolongation`)
GRID_DROP = 0.01


def grid_prolongation(points, shape, drop: float = GRID_DROP):
    """Prolongation on a logically structured, doubly periodic surface grid (e.g. the torus
    families of :func:`~cutfem.geometry.surface.torus_mesh`).

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
    indices, keep this true on perturbed grids.

    A node on a coarse edge (one index odd) whose two weights off that edge are both below
    ``drop`` in magnitude takes the weights (1 - s, s) of its projection x_1 + s (x_2 - x_1) on the
    edge instead.  On an unperturbed curved grid those two weights only answer the curvature (the
    corners off the plane: 1e-3 on the torus 768 x 384, where the nodes of the perturbed families
    have 4.5e-2 in the median), yet they make every coarse operator a 25-point stencil.  Dropped,
    the node reproduces linear functions up to its offset from the edge, at most about
    ``drop`` times the cell, and a planar grid stays exact where the node lies on its edge.
    Measured on the meshed torus 768 x 384 (the mean curvature system, tolerance 1e-6, medians of
    5): the same CG iterations in every family (17, 18, 25, 26); the solve of the structured and
    flipped families 0.37 and 0.47 s against 0.49 and 0.60 s with ``drop=0``, the perturbed ones
    unchanged (0.63 and 0.77 s).  ``drop=0`` keeps the minimum-norm weights everywhere.  Returns (P (n m, n m / 4) CSR, coarse points, coarse shape).
    """
    n, m = (int(v) for v in shape)
    X = np.asarray(points, dtype=float)
    if n % 2 or m % 2 or X.shape != (n * m, 3):
        raise ValueError(f"grid_prolongation needs an even grid shape matching the points; got {shape} and {X.shape}")
    if not 0 <= drop < 0.5:
        raise ValueError(f"drop must be in [0, 0.5) (0 keeps the minimum-norm weights), got {drop!r}")

    nc, mc = n // 2, m // 2
    cols, w = multigrid_kernels.grid_weights(np.array(X, order="C"), n, m, float(drop))  # a writable copy: one compiled signature
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


def augmented_hierarchy(prolongations, w):
    """The hierarchy ``prolongations`` with every coarse space doubled by the products with the
    nodal vector w (n,): P_0 becomes [P_0, diag(w) P_0] (n, 2 n_1) and P_l, l >= 1, becomes
    diag(P_l, P_l), so level l holds the fine functions P_0..P_{l-1} v + w P_0..P_{l-1} v'.

    Why (w = phi_h, the surface operators of a cut band, docs/math.md §4): the functions w g, g
    smooth, are normally linear with zero trace on Gamma_h, so only the face penalty sees them,
    through the gradient jumps of their interpolant, O(h) times the curvature.  The coarse Kuhn
    lattice of spacing H interpolates them with jumps O(H) on its faces instead: their energy grows
    with H / h and each level adds a cluster of small eigenvalues to the preconditioned operator.
    Measured on the cut unit sphere at spacing 0.1 with A_Gamma + M + 0.1 J_F: smallest eigenvalue
    of the V-cycle preconditioned matrix 0.21 with two levels, 0.074 with three, 0.044 with four,
    its eigenvector 96 % face energy and correlated 0.99 with |phi_h|.  With the products w v in
    the coarse spaces the w g are represented on every level (with g coarse P1) and CG needs 10, 11,
    11 iterations at spacings 0.05, 0.025, 0.0125 instead of 27, 38, 51.  The price: the coarse
    levels have twice the unknowns and four times the nonzeros (operator complexity 2.3 instead of
    1.3).  Where the face penalty dominates the whole operator (M + tau_F J_F, the mean curvature
    system) the plain hierarchy already needs 17-22 iterations and the larger coarse levels made it
    slower, hence an option.
    """
    prolongations = iter(prolongations)
    P = next(prolongations, None)
    if P is None:
        return
    P = sp.csr_matrix(P)
    yield sp.hstack([P, sp.diags(w) @ P], format="csr")
    for P in prolongations:
        yield sp.block_diag([P, P], format="csr")


def _single(M):
    """M as a CSR matrix of float32 values, sharing M's index arrays."""
    M = M if type(M) is sp.csr_matrix else sp.csr_matrix(M)
    out = sp.csr_matrix((M.data.astype(np.float32), M.indices, M.indptr), shape=M.shape)
    out.has_sorted_indices = M.has_sorted_indices
    return out


class GeometricMultigrid:
    """Galerkin multigrid for an SPD matrix with a geometric hierarchy of prolongations (docs/math.md §12).

    The hierarchy is either ``lattice`` (n, 3), integer indices of unknowns that are nodes of a Kuhn
    lattice (see :func:`lattice_indices`; levels by :func:`kuhn_prolongation`), or
    ``prolongations``, an iterable giving P_0, P_1, ... lazily (:func:`surface_hierarchy`,
    :func:`grid_hierarchy`, :func:`multigrid_hierarchy`).  Levels A_{l+1} = P_l^T A_l P_l are built
    until at most ``coarse_size`` unknowns remain, the hierarchy ends, or coarsening stalls; the
    coarsest system is solved by :class:`DirectSolver` (a pseudo-inverse if that level is singular
    only because of the coarse space).
    The cycle: one forward Gauss-Seidel sweep, coarse correction on level l+1, one backward sweep
    (the rows of each level in the chunk order of :func:`cutfem.solvers.sparse_kernels.sweep_chunks`, so that both
    cores sweep: the same iterations as in the natural order, the same bits on any number of threads).
    The coarse correction is ``visits[l]`` recursive cycles: 1 is a V-cycle; 2 is a K-cycle
    (Notay and Vassilevski, Numer. Linear Algebra Appl. 15, 2008): the two cycles are combined by
    two steps of flexible CG on level l+1 (:meth:`_krylov_correction`), where a W-cycle would add
    them as stationary iterations.  Default: V on the finest level, K below.  A K-cycle is not a
    linear operator, so the CG it preconditions takes flexible directions (:func:`_pcg`).  On the
    cut torus (tolerance 1e-6) the K-cycle needs 20, 21 and 21 CG iterations at spacings 0.0125,
    0.00625 and 0.003125 where the W-cycle needed 23, 25 and 28, at about the W-cycle's cost per
    iteration (one coarse product more per visit).  ``apply(R)`` acts on (n, c).

    ``augment`` (n,), a nodal vector w: every coarse space holds, beside the prolongated coarse
    functions v, their products w v (:func:`augmented_hierarchy`).  For a surface operator on a cut
    band, w = phi_h: see :func:`augmented_hierarchy` for why and what it costs.

    The cycle runs in single precision: the smoothed levels' matrices, transfers and vectors are
    float32 (the Galerkin products and the coarsest solve stay in double).  A preconditioner's
    rounding at 1e-7 relative is far below what CG asks of it: on the cut torus (spacings 0.0125 and
    0.00625, tolerances 1e-6 and 1e-8) CG needs the same iterations as with a double-precision cycle,
    and the cycle moves a third less memory (8 instead of 12 bytes a nonzero; solve 10-40 % faster,
    measured on a loaded 2-core machine).
    """

    def __init__(self, A, lattice=None, coarse_size: int = 1500, visits=(1, 2), max_levels: int = 20, prolongations=None,
                 augment=None, _checks=None):
        if not len(visits) or any(v not in (1, 2) for v in visits):
            raise ValueError(f"visits must be a non-empty sequence of 1 (V-cycle) and 2 (K-cycle) per level, got {visits!r}")
        # used as it is when already a double CSR matrix: a new wrapper would scan its indices again
        # for scipy's format flags
        A = A if type(A) is sp.csr_matrix and A.dtype == np.float64 else sp.csr_matrix(A, dtype=float)
        self._finest = A  # in double precision, for the null-vector checks
        n = A.shape[0]
        if (lattice is None) == (prolongations is None):
            raise ValueError("give either lattice= (Kuhn lattice indices) or prolongations= (a hierarchy), not both")
        if lattice is not None:
            lattice = np.asarray(lattice)
            if lattice.shape != (n, 3) or not np.issubdtype(lattice.dtype, np.integer):
                raise ValueError(f"lattice must be integer indices of shape ({n}, 3), got {lattice.shape} {lattice.dtype}")
            prolongations = lattice_hierarchy(lattice)
        if augment is not None:
            augment = np.asarray(augment, dtype=float)
            if augment.shape != (n,) or not np.all(np.isfinite(augment)) or not np.any(augment):
                raise ValueError(f"augment must be a finite, nonzero nodal vector of shape ({n},) (e.g. the level-set values "
                                 f"phi_h of a cut space), got shape {augment.shape}; pass augment=None for the plain hierarchy")
            prolongations = augmented_hierarchy(prolongations, augment)
        self._checks = _checks if _checks is not None else _Checks.of(n=n)
        if np.any(_diagonal(A) <= 0):
            raise diagnose(A, where="the geometric multigrid", _checks=self._checks)

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
            R = sp.csr_matrix(P.T)
            Ac = multigrid_kernels.galerkin(A, P, R)  # exactly symmetric
            self.levels.append(dict(A=_single(A), P=_single(P), R=_single(R), chunks=sparse_kernels.sweep_chunks(A)))
            A = Ac
        close = getattr(prolongations, "close", None)
        if close is not None:  # a generator: its frame holds the lattice of a level (108 MB at 4.7 million unknowns)
            close()
        self.coarse_n = A.shape[0]
        where = "the coarsest multigrid level (a Galerkin product P^T A P: a negative direction there is one of A)"
        try:
            self._coarse = ("lu", DirectSolver(A, where=where, _checks=_Checks({}, None, self._checks.indefinite_hint)))
        except SolverError as exc:
            if exc.cause == "indefinite":
                raise
            self._coarse = ("pinv", self._coarse_pseudo_inverse(A, exc))
        self.visits = [visits[min(k, len(visits) - 1)] for k in range(len(self.levels))]
        self._work = {}
        self.sizes = [lv["A"].shape[0] for lv in self.levels] + [self.coarse_n]
        self.nnz = [lv["A"].nnz for lv in self.levels] + [A.nnz]

    def _coarse_pseudo_inverse(self, A, exc, tol: float = 1e-10):
        """Pseudo-inverse of a singular coarsest matrix, after checking that its null vectors are not
        null vectors of the finest matrix (then the system itself is singular: :class:`SolverError`
        from :func:`diagnose` with that vector).

        A coarse matrix P^T A P is singular either because A is (a null vector of the coarse matrix,
        prolongated, has zero energy) or because the coarse space is rank-deficient (two coarse
        nodes seen only through one fine node, possible at the edge of the band: its prolongation
        vanishes); only the second is harmless.
        """
        d = A.diagonal()
        s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        with _one_blas_thread():
            w, V = np.linalg.eigh(s[:, None] * A.toarray() * s[None, :])
        null = w <= tol * max(w.max(), 1e-300)
        U = s[:, None] * V[:, null]
        for lv in reversed(self.levels):
            U = lv["P"] @ U
        A0 = self._finest
        d0 = A0.diagonal()
        for k in range(U.shape[1]):
            u = U[:, k]
            norm = float(u @ (d0 * u))
            if norm > 0:
                rayleigh = float(u @ (A0 @ u)) / norm
                if rayleigh <= tol:
                    raise diagnose(A0, vectors=[u], smallest=rayleigh, _checks=self._checks,
                                   where="the geometric multigrid (a null vector found on the coarsest level)") from exc
        keep = ~null
        return (s[:, None] * (V[:, keep] / w[keep])) @ (V[:, keep].T * s[None, :])

    @staticmethod
    def _prepare(A):
        A = _canonical_csr(A)
        if A.indices.dtype != np.int32 and A.shape[0] < 2**31 and A.nnz < 2**31:
            A = sp.csr_matrix((A.data, A.indices.astype(np.int32), A.indptr.astype(np.int32)), shape=A.shape)
            A.has_canonical_format = True  # a new object (the caller's keeps its arrays), with the same order
        return A

    @property
    def operator_complexity(self) -> float:
        return sum(self.nnz) / self.nnz[0]

    def __repr__(self) -> str:
        return f"GeometricMultigrid(levels={self.sizes}, operator_complexity={self.operator_complexity:.2f})"

    def _coarse_solve(self, b):
        # column by column: SuperLU's solve with several right-hand sides, and a matrix product, sum in
        # another order than with one, and a column would not give what it gives alone
        kind, f = self._coarse
        apply = f.solve if kind == "lu" else f.__matmul__
        return np.column_stack([apply(np.ascontiguousarray(b[:, k])) for k in range(b.shape[1])])

    def _buffers(self, level: int, c: int) -> dict:
        """The work arrays of a cycle on ``level`` for blocks of c columns, made on first use and
        kept: at 4.7 million unknowns a block is 56 MB, and arrays that large come fresh from the
        system on every allocation (page faults and zeroing each time, not reuse)."""
        key = (level, c)
        if key not in self._work:
            n = self.sizes[level]
            w = {"X": np.empty((n, c), np.float32), "r": np.empty((n, c), np.float32)}
            nc = self.sizes[level + 1]
            w["rc"] = np.empty((nc, c), np.float32)
            if self.visits[level] > 1 and level + 1 < len(self.levels):
                for name in ("c1", "v1", "rt", "v2"):
                    w[name] = np.empty((nc, c), np.float32)
            self._work[key] = w
        return self._work[key]

    def cycle(self, B, level: int = 0):
        """One cycle for A_level X = B from X = 0 on a block B (n, c) of columns (single precision,
        see the class; the sweeps and products pass over each matrix once for all columns,
        :mod:`cutfem.solvers.sparse_kernels`).  Returns the level's work array X (:meth:`_buffers`): valid until
        the next cycle on that level."""
        if level == len(self.levels):
            return np.ascontiguousarray(self._coarse_solve(B.astype(float)), dtype=np.float32)

        lv = self.levels[level]
        A = lv["A"]
        w = self._buffers(level, B.shape[1])
        X = w["X"]
        r = sparse_kernels.presmooth(A, X, B, w["r"], lv["chunks"])  # forward sweep from zero and its residual, one pass
        rc = sparse_kernels.matmul(lv["R"], r, out=w["rc"])
        xc = self.cycle(rc, level + 1)
        if "c1" in w:
            xc = self._krylov_correction(level, rc, xc, w)
        sparse_kernels.matmul(lv["P"], xc, out=X, accumulate=True)
        sparse_kernels.gauss_seidel(A, X, B, forward=False, chunks=lv["chunks"])
        return X

    def _krylov_correction(self, level, rc, first, w):
        """The K-cycle's coarse correction on level l + 1 (A_c = A_{l+1}, right-hand sides rc):
        two steps of flexible CG from zero, each preconditioned by a recursive cycle, ``first`` the
        first cycle's output.  Per column, with c1 = B rc, v1 = A_c c1, rho1 = c1.v1, a1 = c1.rc,
        rt = rc - (a1/rho1) v1, c2 = B rt, v2 = A_c c2, g = c2.v1, b = c2.v2, a2 = c2.rt and
        rho2 = b - g^2/rho1 (the energy of c2 made A_c-orthogonal to c1):

            x = (a1/rho1 - g a2/(rho1 rho2)) c1 + (a2/rho2) c2,

        the A_c-energy-minimal combination of the two cycles (where rho1 or rho2 is not positive,
        the term is dropped).  Scalars in double precision, vectors in single.  Returned in the
        work array c1."""

        Ac = self.levels[level + 1]["A"]
        c1, v1, rt, v2 = w["c1"], w["v1"], w["rt"], w["v2"]
        np.copyto(c1, first)  # the next cycle on level l + 1 overwrites its output
        rho1 = np.empty(rc.shape[1])
        sparse_kernels.matmul(Ac, c1, out=v1, dots=rho1)
        ok1 = rho1 > 0
        rho1 = np.where(ok1, rho1, 1.0)  # a zero column: its terms vanish below
        s1 = np.where(ok1, sparse_kernels.column_dots(c1, rc) / rho1, 0.0)
        np.multiply(v1, (-s1).astype(np.float32), out=rt)
        rt += rc
        c2 = self.cycle(rt, level + 1)
        b = np.empty(rc.shape[1])
        sparse_kernels.matmul(Ac, c2, out=v2, dots=b)
        g = np.where(ok1, sparse_kernels.column_dots(c2, v1), 0.0)
        rho2 = b - g * g / rho1
        ok2 = rho2 > 0
        s2 = np.where(ok2, sparse_kernels.column_dots(c2, rt) / np.where(ok2, rho2, 1.0), 0.0)
        s1 = s1 - g * s2 / rho1
        c1 *= s1.astype(np.float32)
        np.multiply(c2, s2.astype(np.float32), out=v2)
        c1 += v2
        return c1

    def apply(self, R, out=None, single: bool = False):
        """The preconditioner on the columns of R (n, c), returned in double precision (n, c), in
        ``out`` when given (an (n, c) float64 array).  ``single=True`` returns the finest level's
        float32 work array itself (R 2-D), valid until the next application: for a caller that
        reads it once (CG, whose dot products and directions take float32 blocks without a copy;
        at 4.7 million unknowns and three columns that saves writing and reading a 113 MB
        double-precision block an iteration)."""
        R = np.asarray(R)
        shape = R.shape
        R = R.reshape(shape[0], -1)
        key = ("B", R.shape[1])
        if key not in self._work:
            self._work[key] = np.empty(R.shape, np.float32)
        block = self._work[key]
        np.copyto(block, R, casting="same_kind")
        X = self.cycle(block)
        if single:
            return X
        if out is None:
            return X.astype(float).reshape(shape)
        np.copyto(out.reshape(X.shape), X)
        return out


def multigrid_hierarchy(space):
    """The geometric hierarchy of prolongations for the unknowns of ``space``, or None.

    * a space whose dofs are nodes of a structured Kuhn box (cut spaces on a
      :class:`~cutfem.geometry.mesh.StructuredBox`): the nested Kuhn lattices (:func:`lattice_hierarchy`);
    * a surface space whose mesh carries a doubly periodic grid (``mesh.grid = (n, m)``, set by
      :func:`~cutfem.geometry.surface.torus_mesh`): the coarser grids (:func:`grid_hierarchy`);
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


def mg_solve(A, B, lattice=None, tol: float = DEFAULT_TOL, maxiter: int = 300, prolongations=None, kernels=None,
             stabilization=None, indefinite_hint=None, _checks=None, x0=None, **mg_options):
    """CG preconditioned by :class:`GeometricMultigrid`; B (n,) or (n, c), all columns at once, from
    ``x0`` (default zero): ``CGSolver(A, "mg", ...).solve(B, x0)`` (see :class:`CGSolver`).

    The hierarchy: ``lattice`` (Kuhn lattice indices of the unknowns) or ``prolongations`` (see
    :func:`multigrid_hierarchy`); ``mg_options`` go to :class:`GeometricMultigrid`.  ``tol`` is the
    relative residual ||A x - b|| / ||b|| of every column.  Returns (X, SolveInfo).  Raises
    :class:`SolverError` (a non-positive diagonal, an indefinite coarsest level, a null vector found
    there, a CG breakdown; ``kernels``, ``stabilization``, ``indefinite_hint`` as for
    :func:`diagnose`) or RuntimeError (no convergence in ``maxiter`` iterations).
    """
    return CGSolver(A, "mg", tol=tol, maxiter=maxiter, lattice=lattice, prolongations=prolongations, multigrid=mg_options,
                    kernels=kernels, stabilization=stabilization, indefinite_hint=indefinite_hint, _checks=_checks).solve(B, x0)


# ---------------------------------------------------------------------------------------------
# algebraic preconditioners
# ---------------------------------------------------------------------------------------------


def _fills_volume(space) -> bool:
    """Whether a field of ``space`` lives on whole volumes (a bulk field of a cut side), as opposed
    to traces on a surface or a surface mesh."""
    fields = getattr(space, "fields", None)
    if fields is not None:
        return any(_fills_volume(f) for f in fields)
    return getattr(space, "is_trace", True) is False


def _amg(A, points=None):
    import pyamg

    # the coarsest level by sparse LU: pyamg's default pseudo-inverse (an SVD of the dense coarsest
    # matrix) took 9 s of a 5.7k-unknown solve whose hierarchy stopped at 1 728 unknowns
    kw = dict(symmetry="symmetric", max_coarse=500, coarse_solver="splu")
    if points is not None:
        # the near-kernel of the face penalty: the globally linear functions
        P = np.asarray(points, dtype=float)
        kw["B"] = np.column_stack([np.ones(len(P)), P - P.mean(axis=0)])
    M = pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), **kw).aspreconditioner(cycle="V")
    return lambda R: np.column_stack([M @ R[:, k] for k in range(R.shape[1])])


class CGSolver:
    """Preconditioned conjugate gradients for the SPD matrix A, the preconditioner built once and
    reused for every right-hand side given to :meth:`solve`.

    ``preconditioner``: "mg" (:class:`GeometricMultigrid` on the hierarchy ``lattice`` or
    ``prolongations``, see :func:`multigrid_hierarchy`; ``multigrid``: its options), "amg" (smoothed
    aggregation, pyamg; with ``points`` (n, 3) the linear functions are its near-kernel
    candidates), "jacobi" (the inverse diagonal) or "none".  ``tol``: the relative residual
    ||A x - b|| / ||b|| of every column, 0 < tol < 1; ``maxiter``: the most iterations.  ``setup``: the seconds
    the construction took.

    Sequences of systems with one matrix (time steps, continuation) pass a starting guess to
    :meth:`solve`: CG then only removes the guess's error.  A guess extrapolated from the previous
    solutions of a smooth evolution is close (backward Euler for the surface heat equation at
    spacing 0.025, Jacobi, tolerance 1e-12: 60 iterations a step from zero, 44 from the previous
    solution, 12.4 on average from the quadratic through the last three; docs/math.md §11).

    Raises :class:`SolverError` on a non-positive diagonal (here) or a breakdown (in
    :meth:`solve`), with the cause named by :func:`diagnose` (``kernels``, ``stabilization``,
    ``indefinite_hint`` as there); RuntimeError if CG does not converge in ``maxiter`` iterations.
    """

    PRECONDITIONERS = ("mg", "amg", "jacobi", "none")

    def __init__(self, A, preconditioner: str, tol: float = DEFAULT_TOL, maxiter: int = 5000, points=None,
                 lattice=None, prolongations=None, multigrid=None, kernels=None, stabilization=None, indefinite_hint=None,
                 _checks=None):
        t0 = time.perf_counter()
        preconditioner = "none" if preconditioner is None else preconditioner
        if preconditioner not in self.PRECONDITIONERS:
            raise ValueError(f"unknown preconditioner {preconditioner!r}; use 'mg', 'amg', 'jacobi' or 'none'")
        tol = _checked_tol(tol, "CG")
        A = _checked_matrix(A, "CG")
        checks = _checks if _checks is not None else _Checks.of(kernels, stabilization, indefinite_hint, A.shape[0])
        self.warn_after = 10**9
        if preconditioner == "mg":
            if lattice is None and prolongations is None:
                raise ValueError("preconditioner 'mg' needs the lattice indices of the unknowns (lattice=...) or a "
                                 "hierarchy of prolongations (prolongations=..., see multigrid_hierarchy)")
            A = GeometricMultigrid._prepare(A)
            # the closures hold the multigrid, not self: no reference cycle keeps a solver's hierarchy
            # alive after its last use (a one-call cg_solve or mg_solve frees it on return)
            mg = self.multigrid = GeometricMultigrid(A, lattice, prolongations=prolongations, _checks=checks,
                                                     **(multigrid or {}))
            precond = lambda R: mg.apply(R, single=True)  # noqa: E731  (CG reads the float32 output as it is)
            self.warn_after = MG_WARN_ITERATIONS
            name = "CG with geometric multigrid"
        else:
            d = _diagonal(A)
            if np.any(d <= 0):
                raise diagnose(A, where="CG", _checks=checks)
            if preconditioner == "amg":
                precond = _amg(A, points)
            elif preconditioner == "jacobi":
                inv = 1.0 / d
                precond = lambda R: R * inv[:, None]  # noqa: E731
            else:
                precond = lambda R: R.copy()  # noqa: E731
            name = f"CG ({preconditioner})"
        self.A, self.preconditioner, self.tol, self.maxiter = A, preconditioner, float(tol), int(maxiter)
        self.method = f"cg-{preconditioner}"
        self._precond, self._name, self._checks, self._cache, self._first = precond, name, checks, {}, True
        self.setup = time.perf_counter() - t0

    def solve(self, B, x0=None):
        """X with A X = B to the relative residual ``tol`` per column, B (n,) or (n, c), all columns at
        once (:func:`_pcg`), from ``x0`` (B's shape; default zero).  Returns (X, SolveInfo); the
        info's ``setup`` is the construction's, counted in ``seconds`` only by the first solve."""
        t0 = time.perf_counter()
        n = self.A.shape[0]
        B = _checked_rhs(B, n, self._name)
        cols = B.reshape(n, -1)
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float)
            if x0.shape != B.shape:
                raise ValueError(f"x0 must be a finite array of the right-hand side's shape {B.shape}, got {x0.shape}")
            if not np.all(np.isfinite(x0)):
                raise ValueError(f"x0 must be a finite array: it has {int(np.sum(~np.isfinite(x0)))} non-finite entries "
                                 f"(NaN or inf) among {x0.size}")
            x0 = x0.reshape(cols.shape)
        X, it, rel = _pcg(self.A, self._precond, cols, self.tol, self.maxiter, self._name, self._checks,
                          warn_after=self.warn_after, x0=x0, cache=self._cache)
        setup, self._first = (self.setup if self._first else 0.0), False
        return X.reshape(B.shape), SolveInfo(self.method, it, float(rel.max()), time.perf_counter() - t0 + setup, setup)


def cg_solve(A, B, preconditioner: str = "amg", tol: float = 1e-10, maxiter: int = 5000, points=None, lattice=None,
             kernels=None, stabilization=None, indefinite_hint=None, _checks=None, x0=None):
    """Preconditioned CG for SPD A; B (n,) or (n, c), all columns at once with one preconditioner,
    from ``x0`` (default zero): ``CGSolver(A, preconditioner, ...).solve(B, x0)`` (see
    :class:`CGSolver`; "mg" needs ``lattice``).  Returns (X, SolveInfo)."""
    return CGSolver(A, preconditioner, tol=tol, maxiter=maxiter, points=points, lattice=lattice, kernels=kernels,
                    stabilization=stabilization, indefinite_hint=indefinite_hint, _checks=_checks).solve(B, x0)


def _check_kernels(A, checks, where):
    """Raise :class:`SolverError` when the constants or a candidate of ``checks.kernels`` is a null
    vector of A (||D^{-1/2} A u|| <= KERNEL_TOL ||D^{1/2} u||; a non-positive diagonal is left to
    the solvers).  An iterative solver with a consistent right-hand side would converge without
    noticing a null vector.  One product with A per candidate."""
    d = _diagonal(A)
    if np.any(d <= 0):
        return
    err = _named_kernel_error(A, d, checks, where)
    if err is not None:
        raise err


def solve(A, B, method: str = "auto", tol: float | None = None, space=None, lattice=None, kernels=None,
          stabilization=None, indefinite_hint=None, multigrid=None, x0=None):
    """Solve the SPD system A X = B (B (n,) or (n, c)); returns (X, SolveInfo).

    ``method``: "direct", "cg-mg" (geometric multigrid), "cg-amg", "cg-jacobi" or "auto":
    direct up to :data:`DIRECT_LIMIT` unknowns; above it "cg-mg" when there is a geometric
    hierarchy (``space`` on a StructuredBox or on a surface mesh, see :func:`multigrid_hierarchy`;
    or ``lattice`` given), else direct up to
    :data:`DIRECT_LIMIT_NO_MG` and "cg-amg" above.  ``space`` also provides the dof coordinates for
    the AMG candidates, and must have n unknowns (``space.n_dofs == n``, else a ValueError).
    ``tol``: relative residual of the iterative methods, 0 < tol < 1 (default :data:`DEFAULT_TOL`).
    An empty system, a right-hand side without columns, and a non-square or non-finite matrix are
    refused (ValueError).

    A system that is not positive definite raises :class:`SolverError` with its cause, on every
    path.  What the caller knows helps to name it (:func:`diagnose`): ``kernels`` ({name: (n,)
    vector}, candidate null vectors; with a cut ``space`` the nodal vector of phi_h is added as
    "phi_h"), ``stabilization`` (the stabilization matrix contained in A, e.g. tau_F J_F: tells an
    over-stabilized system from an under-stabilized one), ``indefinite_hint`` (the advice for an
    indefinite system, e.g. "raise the Nitsche penalty gamma").  The iterative paths first test
    the constants and the candidates (one product each), which CG with a consistent right-hand
    side would not notice.

    ``multigrid``: options of :class:`GeometricMultigrid` for "cg-mg" (e.g. ``{"augment": phi_h}``
    for a surface operator on a cut band); ignored by the other methods.  ``x0``: a starting guess
    of B's shape for the iterative methods (a column worse than zero is not used, see :func:`_pcg`);
    ignored by the direct solve.
    """
    A = _checked_matrix(A, "solve")  # before the null-vector checks, whose NaN would read as "singular"
    n = A.shape[0]
    B = _checked_rhs(B, n, "solve")
    tol = DEFAULT_TOL if tol is None else _checked_tol(tol, "solve")
    if space is not None and getattr(space, "n_dofs", n) != n:
        raise ValueError(f"solve: the space has {space.n_dofs} unknowns and the matrix {n}: pass the space the system "
                         "was assembled on (space= gives the multigrid hierarchy, the dof coordinates and phi_h)")
    kernels = dict(kernels or {})
    phi = getattr(getattr(space, "cut", None), "values", None)
    if phi is not None and np.shape(phi) == (n,):
        kernels.setdefault("phi_h", phi)
    checks = _Checks.of(kernels, stabilization, indefinite_hint, n)
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
            limit = DIRECT_LIMIT_NO_MG_BULK if _fills_volume(space) else DIRECT_LIMIT_NO_MG
            method = "direct" if n <= limit else "cg-amg"
    if method == "direct":
        t0 = time.perf_counter()
        solver = DirectSolver(A, _checks=checks)
        t1 = time.perf_counter()
        X = solver.solve(B)
        R = np.asarray(A @ X - B).reshape(n, -1)
        nb = np.linalg.norm(np.asarray(B).reshape(n, -1), axis=0)
        res = float(np.max(np.linalg.norm(R, axis=0) / np.where(nb > 0, nb, 1.0)))
        return X, SolveInfo("direct", 0, res, time.perf_counter() - t0, t1 - t0)
    if method not in ("cg-mg", "cg-amg", "cg-jacobi"):
        raise ValueError(f"unknown method {method!r}; use 'auto', 'direct', 'cg-mg', 'cg-amg' or 'cg-jacobi'")
    _check_kernels(A, checks, f"solve ({method})")
    if method == "cg-mg":
        if not has_mg:
            raise ValueError(
                "method 'cg-mg' needs a geometric hierarchy: a space on a structured box or on a surface mesh (space=...), "
                "or lattice indices (lattice=...); an unstructured background (e.g. --background tetwild) has none: use "
                "'cg-amg' (algebraic multigrid), 'direct' or 'auto'"
            )
        return mg_solve(A, B, lattice, tol=tol, prolongations=hierarchy, _checks=checks, x0=x0, **(multigrid or {}))
    points = getattr(space, "dof_points", None) if space is not None else None
    return cg_solve(A, B, preconditioner=method.split("-")[1], tol=tol, points=points, _checks=checks, x0=x0)


class ConditionNumber(float):
    """The 2-norm condition number max |lambda| / min |lambda| of S = D^{-1/2} A D^{-1/2} (a float,
    ``inf`` when S is exactly singular or cannot be scaled), with the verdict on definiteness:
    ``cause`` None (positive definite), "singular", "over-stabilized" (both: min |lambda| <=
    :data:`ZERO_TOL` max |lambda|, told apart by :func:`diagnose`) or "indefinite" (a negative
    eigenvalue below -ZERO_TOL max |lambda|: the number is then that of an indefinite matrix, and
    CG does not apply); ``smallest`` (signed) and ``largest`` eigenvalues of S; ``error``: the
    :class:`SolverError` with the full message, or None."""

    def __new__(cls, value, cause=None, smallest=np.nan, largest=np.nan, error=None):
        obj = super().__new__(cls, value)
        obj.cause, obj.smallest, obj.largest, obj.error = cause, float(smallest), float(largest), error
        return obj

    def __repr__(self) -> str:
        return f"ConditionNumber({float(self)!r}, cause={self.cause!r})"


def condition_number(A, tol: float = 1e-8, kernels=None, stabilization=None) -> ConditionNumber:
    """2-norm condition number of S = |D|^{-1/2} A |D|^{-1/2} (A symmetric, D = diag A; |D| = D for a
    positive diagonal, and a negative entry makes A indefinite) and whether S is positive definite: a :class:`ConditionNumber` (a float with ``cause``), never an exception, so that
    studies can tabulate singular and indefinite systems next to the definite ones.

    Dense eigenvalues for n <= 400.  Otherwise: largest magnitude by Lanczos; S = L D L^T by
    SuperLU (no pivoting), whose negative pivots count the negative eigenvalues (Sylvester); the
    smallest magnitude by shift-invert Lanczos around 0 with that factorization.  A failed
    factorization gives ``inf``.  ``kernels`` and ``stabilization``: as for :func:`diagnose`.

    "Never an exception" is about the system: a singular or indefinite matrix gives its verdict.
    Bad input is refused with a ValueError before any eigenvalue is sought: a matrix that is not
    square, is empty, has a NaN or inf entry (no spectrum to tabulate), or is not symmetric (beyond
    1e-8 of the scaled entries: round-off is averaged away).
    """
    A = _checked_matrix(A, "condition_number")
    checks = _Checks.of(kernels, stabilization, None, A.shape[0])
    d = A.diagonal()
    if np.any(d == 0):
        err = diagnose(A, where="condition_number", _checks=checks)
        return ConditionNumber(np.inf, err.cause, err.smallest, np.nan, err)
    # a negative diagonal entry is a basis function of negative energy (indefinite); scaling by |d|
    # still measures the spread of the spectrum, which studies of unstabilized systems tabulate
    d = np.abs(d)
    S = sp.diags(1.0 / np.sqrt(d)) @ A @ sp.diags(1.0 / np.sqrt(d))
    skew = abs(S - S.T).max() if S.nnz else 0.0
    if skew > 1e-8:  # the mean below only removes round-off; a nonsymmetric A has no such verdict
        raise ValueError(f"condition_number: the matrix is not symmetric (|S - S^T| reaches {skew:.3g} with S scaled to a "
                         "unit diagonal); it measures symmetric matrices (use numpy.linalg.cond on a dense "
                         "nonsymmetric one)")
    S = (0.5 * (S + S.T)).tocsr()
    n = S.shape[0]
    negative = 0
    if n <= 400:
        with _one_blas_thread():
            w, V = np.linalg.eigh(S.toarray())
        k = int(np.argmin(np.abs(w)))
        small, v, big = float(w[k]), V[:, k], float(np.abs(w).max())
        lowest = float(w[0])
    else:
        start = np.random.default_rng(0).normal(size=n)  # seeded: the same matrix gives the same digits
        big = float(np.abs(spla.eigsh(S, k=1, which="LM", tol=tol, v0=start, return_eigenvectors=False)[0]))
        try:
            lu = spla.splu(sp.csc_matrix(S), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError:
            err = diagnose(A, smallest=0.0, where="condition_number (the factorization failed)", _checks=checks)
            return ConditionNumber(np.inf, err.cause, err.smallest, big, err)
        piv = lu.U.diagonal()
        negative = int((piv < -ZERO_TOL * np.abs(piv).max()).sum())
        op = spla.LinearOperator(S.shape, matvec=lu.solve, dtype=float)
        # largest magnitude eigenvalue of S^{-1}: the eigenvalue of S closest to 0, with its sign
        # a seeded random start: a symmetric start vector (the constants) can be orthogonal to the
        # wanted eigenvector on a symmetric surface, and Lanczos then converges to another one
        inv, W = spla.eigsh(op, k=1, which="LM", tol=tol, v0=start)
        small = 1.0 / float(inv[0]) if inv[0] != 0 else 0.0
        v, lowest = W[:, 0], small
    value = big / abs(small) if small != 0 else np.inf
    if negative or lowest < -ZERO_TOL * big or abs(small) <= ZERO_TOL * big:
        err = diagnose(A, vectors=[v / np.sqrt(d)], smallest=min(lowest, small) / big, negative_pivots=negative,
                       where="condition_number", _checks=checks)
        return ConditionNumber(value, err.cause, small, big, err)
    return ConditionNumber(value, None, small, big)
