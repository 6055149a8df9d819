"""Preconditioned conjugate gradients on several right-hand sides at once: :class:`CGSolver` (the
preconditioner built once and reused for every solve), :func:`cg_solve` and :func:`mg_solve`.

Each column of the right-hand side is its own CG recurrence (bitwise what it gives alone); the
columns share each product with A and each application of the preconditioner (one pass over A for
the block of the columns not yet converged).  The search directions are flexible
(Polak-Ribiere), as the multigrid's K-cycle is not a linear operator.  A column stops at the
relative residual ``tol`` (the recursive residual checked against the true one), and the iterates
end with the Galerkin correction on the constants, so that the conservation laws that are sums of
the residual hold to round-off (:func:`_constant_correction`).  A breakdown, p^T A p <= 0 or
r^T M r <= 0, is named by :func:`~cutfem.solvers.diagnose.diagnose` (a direction of negative
curvature: indefinite); CG with multigrid warns past :data:`MG_WARN_ITERATIONS` iterations.

Preconditioners: "mg" (:class:`~cutfem.solvers.multigrid.GeometricMultigrid`), "amg" (smoothed
aggregation, pyamg, with the globally linear functions as near-kernel candidates when the dof
coordinates are known), "jacobi" (the inverse diagonal) and "none".

The loops and the null-vector checks before them make no BLAS calls: their dot products and
products are compiled kernels (:func:`cutfem.solvers.sparse_kernels.column_dots`,
:func:`~cutfem.solvers.sparse_kernels.matmul`).  On a 2-core machine OpenBLAS' threaded level-1
calls on long vectors were many times slower than serial ones, which made scipy's ``cg`` erratic.
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import scipy.sparse as sp

from . import sparse_kernels
from .common import SolveInfo, _checked_matrix, _checked_rhs, _checked_tol, _diagonal, _matvec
from .diagnose import _Checks, diagnose
from .multigrid import GeometricMultigrid

__all__ = ["CGSolver", "cg_solve", "mg_solve", "DEFAULT_TOL"]


#: CG with multigrid warns (RuntimeWarning) when it needs more iterations than this: the stabilized
#: cut systems need 15-40 at any spacing, an unstabilized (singular) one hundreds
MG_WARN_ITERATIONS = 100

#: default relative residual of the iterative methods of :func:`~cutfem.solvers.solve.solve`.  Against 1e-6, measured at
#: spacing 0.05: the L2 errors of interface-poisson-cut move by 0.5 % at 1e-6 (poisson-cut 3.5e-5,
#: bulk-surface-cut 7e-6, the surface problems 1e-7 or less), so the bulk problems need 1e-8.
#: Invariants that are sums of the residual (the integral of the mean curvature vector, 1^T M H =
#: -1^T r) hold to round-off at any tolerance: CG ends with the Galerkin correction on the
#: constants (:func:`_constant_correction`)
DEFAULT_TOL = 1e-8


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
    The columns are independent recurrences: each gives, bitwise, what it gives alone.  (A block
    CG, whose search directions the columns share, gains no iterations here: the multigrid leaves
    no isolated small eigenvalues for the shared space to remove.)

    Stops when every column has a true relative residual <= tol (the recursive residual is checked
    against the true one, and CG restarted from the current iterate when they disagree).  A
    breakdown, p^T A p <= 0 or r^T M r <= 0, raises :class:`~cutfem.solvers.diagnose.SolverError` (:func:`~cutfem.solvers.diagnose.diagnose` with the
    search directions: a scaled Rayleigh quotient p^T A p / p^T D p below -ZERO_TOL is a direction
    of negative curvature, so "indefinite").  At convergence the iterates get the Galerkin
    correction on the constants (:func:`_constant_correction`; ``cache``, a dict the caller keeps
    for later solves with A, holds the product A 1 it needs).  ``x0`` (n, c): the starting iterates
    (default zero); a column of x0 whose residual is larger than its right-hand side's norm starts
    from zero instead (a guess worse than none, as the lumped-mass guess of a mean curvature
    vector on a perturbed mesh, costs iterations).
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
    int_{S_h} H_h = 1^T M H = 1^T B - 1^T r with 1^T B = 0 and J 1 = 0 (docs/math.md §3): after
    the correction it is at round-off, where without it it followed the tolerance.  ``cache`` (a
    dict, or None): A 1 is taken from its
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


def dof_points_of(space):
    """The coordinates of the dofs that the AMG candidates are built on: a scalar space's
    ``dof_points``, a vector field's scalar space's (each component then has its own linear
    functions); None when the space has none (a product of several fields, a real field)."""
    return getattr(getattr(space, "scalar", space), "dof_points", None) if space is not None else None


def _amg(A, points=None):
    """Smoothed-aggregation AMG of A; with the dof coordinates ``points`` (n_s, 3) the globally linear
    functions are its near-kernel candidates: of each of the n / n_s components of a vector field
    (numbered component-major) when A is larger than the points, which for elasticity span the rigid
    motions."""
    import pyamg

    # the coarsest level by sparse LU: pyamg's default pseudo-inverse (an SVD of the dense coarsest
    # matrix) took most of a solve whose hierarchy stopped at a few thousand unknowns
    kw = dict(symmetry="symmetric", max_coarse=500, coarse_solver="splu")
    if points is not None:
        # the near-kernel of the face penalty: the globally linear functions
        P = np.asarray(points, dtype=float)
        linear = np.column_stack([np.ones(len(P)), P - P.mean(axis=0)])
        c = A.shape[0] // len(P)
        if c * len(P) != A.shape[0]:
            raise ValueError(f"AMG: {len(P)} dof points do not fit a matrix of {A.shape[0]} unknowns (one point per "
                             "unknown, or per unknown of each component of a vector field)")
        kw["B"] = linear if c == 1 else sp.block_diag([linear] * c).toarray()
    M = pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), **kw).aspreconditioner(cycle="V")
    return lambda R: np.column_stack([M @ R[:, k] for k in range(R.shape[1])])


class CGSolver:
    """Preconditioned conjugate gradients for the SPD matrix A, the preconditioner built once and
    reused for every right-hand side given to :meth:`solve`.

    ``preconditioner``: "mg" (:class:`~cutfem.solvers.multigrid.GeometricMultigrid` on the hierarchy ``lattice`` or
    ``prolongations``, see :func:`~cutfem.solvers.multigrid.multigrid_hierarchy`; ``multigrid``: its options), "amg" (smoothed
    aggregation, pyamg; with ``points`` (n, 3) the linear functions are its near-kernel
    candidates), "jacobi" (the inverse diagonal) or "none".  ``tol``: the relative residual
    ||A x - b|| / ||b|| of every column, 0 < tol < 1; ``maxiter``: the most iterations.  ``setup``: the seconds
    the construction took.

    Sequences of systems with one matrix (time steps, continuation) pass a starting guess to
    :meth:`solve`: CG then only removes the guess's error.  A guess extrapolated from the previous
    solutions of a smooth evolution is close (for the surface heat equation the quadratic through
    the last three solutions needs a fraction of the iterations from zero; docs/math.md §11).

    Raises :class:`~cutfem.solvers.diagnose.SolverError` on a non-positive diagonal (here) or a breakdown (in
    :meth:`solve`), with the cause named by :func:`~cutfem.solvers.diagnose.diagnose` (``kernels``, ``stabilization``,
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


def mg_solve(A, B, lattice=None, tol: float = DEFAULT_TOL, maxiter: int = 300, prolongations=None, kernels=None,
             stabilization=None, indefinite_hint=None, _checks=None, x0=None, **mg_options):
    """CG preconditioned by :class:`~cutfem.solvers.multigrid.GeometricMultigrid`; B (n,) or (n, c), all columns at once, from
    ``x0`` (default zero): ``CGSolver(A, "mg", ...).solve(B, x0)`` (see :class:`CGSolver`).

    The hierarchy: ``lattice`` (Kuhn lattice indices of the unknowns) or ``prolongations`` (see
    :func:`~cutfem.solvers.multigrid.multigrid_hierarchy`); ``mg_options`` go to :class:`~cutfem.solvers.multigrid.GeometricMultigrid`.  ``tol`` is the
    relative residual ||A x - b|| / ||b|| of every column.  Returns (X, SolveInfo).  Raises
    :class:`~cutfem.solvers.diagnose.SolverError` (a non-positive diagonal, an indefinite coarsest level, a null vector found
    there, a CG breakdown; ``kernels``, ``stabilization``, ``indefinite_hint`` as for
    :func:`~cutfem.solvers.diagnose.diagnose`) or RuntimeError (no convergence in ``maxiter`` iterations).
    """
    return CGSolver(A, "mg", tol=tol, maxiter=maxiter, lattice=lattice, prolongations=prolongations, multigrid=mg_options,
                    kernels=kernels, stabilization=stabilization, indefinite_hint=indefinite_hint, _checks=_checks).solve(B, x0)
