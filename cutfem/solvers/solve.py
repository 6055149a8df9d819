"""The entry of the linear solvers of cutfem's symmetric systems: :func:`solve` checks the input,
chooses the method and returns what it did (:class:`~cutfem.solvers.common.SolveInfo`).

What is used when
-----------------
``solve(method="auto")`` picks, for an SPD matrix with n unknowns:

* n <= :data:`DIRECT_LIMIT` (5 000): :class:`~cutfem.solvers.direct.DirectSolver`, one checked
  factorization of the diagonally scaled matrix reused for all right-hand sides (a banded Cholesky
  after reverse Cuthill-McKee when the band is narrow, else SuperLU);
* n > DIRECT_LIMIT and a geometric hierarchy
  (:func:`~cutfem.solvers.multigrid.multigrid_hierarchy`): conjugate gradients
  (:mod:`cutfem.solvers.krylov`) preconditioned by the multigrid
  :class:`~cutfem.solvers.multigrid.GeometricMultigrid` ("cg-mg"), all right-hand sides at once,
  relative residual :data:`~cutfem.solvers.krylov.DEFAULT_TOL` (1e-8) per column.  The
  hierarchies: the nested Kuhn lattices when the unknowns are nodes of a structured background
  (``space=`` a :class:`~cutfem.fem.spaces.CutSpace` on a
  :class:`~cutfem.geometry.box.StructuredBox`, or ``lattice=`` their integer indices); on a
  surface mesh (``space=`` a :class:`~cutfem.fem.spaces.SurfaceP1Space`) its periodic grid when it
  has one (the torus families) and otherwise a Kuhn lattice around it;
* otherwise: direct up to :data:`DIRECT_LIMIT_NO_MG` (400 000; :data:`DIRECT_LIMIT_NO_MG_BULK`,
  20 000, for bulk fields, whose factorizations fill in like 3-D grids), then CG with smoothed
  aggregation AMG (pyamg, "cg-amg"), with the globally linear functions as near-kernel candidates
  when the dof coordinates are known (``space``).  Callers with a cut space should pass
  ``space=`` so that the multigrid can be used.

DIRECT_LIMIT is about the break-even of the factorization with CG and multigrid on the cut and
meshed tori: above it the factorization's fill grows faster than the multigrid's work, whose
iterations stay nearly independent of h (see :mod:`cutfem.solvers.multigrid` for why).

Systems that are not positive definite are reported, never hidden, on every path:
:class:`~cutfem.solvers.diagnose.SolverError` with its cause ("indefinite", "singular" or
"over-stabilized") and advice that applies (:mod:`cutfem.solvers.diagnose`).  Before an iterative
solve the constants and the caller's candidate null vectors (with a cut ``space``, the nodal
vector of phi_h) are tested, which CG with a consistent right-hand side would converge past
without noticing.  Bad input is refused with a ValueError naming it: an empty, non-square or
non-finite matrix, a complex, misshapen or non-finite right-hand side, a tolerance outside (0, 1).
"""

from __future__ import annotations

import time

import numpy as np

from .common import SolveInfo, _checked_matrix, _checked_rhs, _checked_tol
from .diagnose import _Checks, _check_kernels
from .direct import DirectSolver
from .krylov import DEFAULT_TOL, cg_solve, dof_points_of, mg_solve
from .multigrid import multigrid_hierarchy
from .saddle import saddle_solve

__all__ = ["solve", "DIRECT_LIMIT", "DIRECT_LIMIT_NO_MG", "DIRECT_LIMIT_NO_MG_BULK"]


#: systems with at most this many unknowns are solved directly by ``solve(method="auto")``
DIRECT_LIMIT = 5_000

#: without a geometric hierarchy (no multigrid), ``solve(method="auto")`` stays direct up to this
#: size: SuperLU beats CG with smoothed aggregation on every system measured (cut torus, 293k
#: unknowns: 31 s and 3 GiB against 68 s, or 23 s with the linear candidates)
DIRECT_LIMIT_NO_MG = 400_000

#: ... but only this far for fields that fill a volume (bulk fields of a side, product spaces with
#: one): their direct factorizations fill in like a 3-D grid's.  Fictitious-domain Poisson on a
#: pytetwild background at 39k unknowns took 27-46 s direct against 2.4 s with cg-amg
DIRECT_LIMIT_NO_MG_BULK = 20_000


def _fills_volume(space) -> bool:
    """Whether a field of ``space`` lives on whole volumes (a bulk field of a cut side), as opposed
    to traces on a surface or a surface mesh."""
    fields = getattr(space, "fields", None)
    if fields is not None:
        return any(_fills_volume(f) for f in fields)
    return getattr(space, "is_trace", True) is False


def solve(A, B, method: str = "auto", tol: float | None = None, space=None, lattice=None, kernels=None,
          stabilization=None, indefinite_hint=None, multigrid=None, x0=None, primal=None, schur=None):
    """Solve the SPD system A X = B (B (n,) or (n, c)); returns (X, SolveInfo).

    ``primal`` (and ``schur``) declare a saddle-point system instead: ``primal`` the fields of the
    positive definite block of the product space ``space``, ``schur`` {constraint field: an SPD
    approximation of its Schur complement}; solved by block-preconditioned MINRES ("minres"), GMRES
    when the matrix is not symmetric ("gmres"), or, small, directly (:func:`~cutfem.solvers.saddle.saddle_solve`).

    ``method``: "direct", "cg-mg" (geometric multigrid), "cg-amg", "cg-jacobi" or "auto":
    direct up to :data:`DIRECT_LIMIT` unknowns; above it "cg-mg" when there is a geometric
    hierarchy (``space`` on a StructuredBox or on a surface mesh, see :func:`~cutfem.solvers.multigrid.multigrid_hierarchy`;
    or ``lattice`` given), else direct up to
    :data:`DIRECT_LIMIT_NO_MG` and "cg-amg" above.  ``space`` also provides the dof coordinates for
    the AMG candidates, and must have n unknowns (``space.n_dofs == n``, else a ValueError).
    ``tol``: relative residual of the iterative methods, 0 < tol < 1 (default :data:`~cutfem.solvers.krylov.DEFAULT_TOL`).
    An empty system, a right-hand side without columns, and a non-square or non-finite matrix are
    refused (ValueError).

    A system that is not positive definite raises :class:`~cutfem.solvers.diagnose.SolverError` with its cause, on every
    path.  What the caller knows helps to name it (:func:`~cutfem.solvers.diagnose.diagnose`): ``kernels`` ({name: (n,)
    vector}, candidate null vectors; with a cut ``space`` the nodal vector of phi_h is added as
    "phi_h"), ``stabilization`` (the stabilization matrix contained in A, e.g. tau_F J_F: tells an
    over-stabilized system from an under-stabilized one), ``indefinite_hint`` (the advice for an
    indefinite system, e.g. "raise the Nitsche penalty gamma").  The iterative paths first test
    the constants and the candidates (one product each), which CG with a consistent right-hand
    side would not notice.

    ``multigrid``: options of :class:`~cutfem.solvers.multigrid.GeometricMultigrid` for "cg-mg" (e.g. ``{"augment": phi_h}``
    for a surface operator on a cut band); ignored by the other methods.  ``x0``: a starting guess
    of B's shape for the iterative methods (a column worse than zero is not used, see :func:`~cutfem.solvers.krylov._pcg`);
    ignored by the direct solve.
    """
    A = _checked_matrix(A, "solve")  # before the null-vector checks, whose NaN would read as "singular"
    n = A.shape[0]
    B = _checked_rhs(B, n, "solve")
    tol = DEFAULT_TOL if tol is None else _checked_tol(tol, "solve")
    if space is not None and getattr(space, "n_dofs", n) != n:
        raise ValueError(f"solve: the space has {space.n_dofs} unknowns and the matrix {n}: pass the space the system "
                         "was assembled on (space= gives the multigrid hierarchy, the dof coordinates and phi_h)")
    if primal is not None:
        return saddle_solve(A, B, space, primal, schur, tol=tol, method=method, indefinite_hint=indefinite_hint)
    if schur is not None:
        raise ValueError("solve: schur= belongs to a saddle-point system; name its positive definite fields with primal=")
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
    return cg_solve(A, B, preconditioner=method.split("-")[1], tol=tol, points=dof_points_of(space), _checks=checks, x0=x0)
