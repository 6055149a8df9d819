"""Why a system declared symmetric positive definite is not: :func:`diagnose`, the
:class:`SolverError` it builds, the tests for null vectors, and :func:`condition_number`.

Every solver reports its failure through :func:`diagnose`, which names the cause from the evidence
the solver has (pivots, curvature, near-null vectors) and what the caller knows (candidate null
vectors, the stabilization matrix, advice for an indefinite system):

* "indefinite": a negative diagonal entry, or a zero one with a nonzero row; negative pivots of
  L D L^T (by Sylvester's law of inertia, as many negative eigenvalues); a direction of negative
  curvature p^T A p < 0 in CG; an indefinite coarsest multigrid level; a negative Lanczos
  estimate of the smallest eigenvalue;
* "singular": a zero row; a named null vector: the constants (a Neumann problem), the nodal vector
  of phi_h (zero on S_h, null for every unstabilized cut system) or a candidate of the caller; or a
  numerically null vector of the forms;
* "over-stabilized": the near-null vector lies in the stabilization's own null space (the globally
  linear functions for the face penalty) while the rest of the form sees it.

The messages give only advice that applies: "raise the stabilization" only when the stabilization
matrix was passed and is too weak on the null vector, "lower it" only when its own null space
dominates, the caller's ``indefinite_hint`` (e.g. "raise the Nitsche penalty gamma") for an
indefinite system, otherwise the possible causes side by side.  The iterative paths test the
constants and the candidates before they start (:func:`_check_kernels`): CG with a consistent
right-hand side would converge past a null vector without noticing.

:func:`condition_number`: the 2-norm condition number of the diagonally scaled matrix
D^{-1/2} A D^{-1/2}, from its extreme eigenvalues (Lanczos; shift-invert for the smallest), as a
:class:`ConditionNumber`: a float that also says whether the matrix is definite, singular,
over-stabilized or indefinite (``cause``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import sparse_kernels
from .common import _canonical_csr, _checked_matrix, _diagonal, _matvec, _one_blas_thread

__all__ = ["SolverError", "diagnose", "ConditionNumber", "condition_number", "scaled"]


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
    "specific system; a saddle-point system (Stokes, a constraint) is indefinite by design: solve it with "
    "solve(K, b, space=W, primal=..., schur=...)."
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
    """u . v of two long vectors by :func:`cutfem.solvers.sparse_kernels.column_dots`, not BLAS (as
    in :mod:`cutfem.solvers.krylov`): OpenBLAS hands a dot of this length to its threads, which then
    spin on the other core for about 0.1 s after the call."""

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
