"""Saddle-point solves: symmetric indefinite block systems

    K = [[A, B^T], [B, -C]],

A the symmetric positive definite block of the *primal* fields (a velocity, a displacement), B the
constraint coupling, C >= 0 the constraint fields' own block (a pressure stabilization).  Stokes
with equal-order P1-P1 (docs/math.md §14) is the example: A = nu (grad u, grad v) + Nitsche +
ghost penalty, B = -(div u, q) + (u . n, q)_Gamma, C the pressure stabilization and ghost penalty.

The method is preconditioned MINRES (:mod:`cutfem.solvers.minres`) with the block-diagonal
preconditioner diag(A~^{-1}, S~^{-1}): A~^{-1} one V-cycle of the geometric multigrid of the primal
fields (symmetric: a forward and a backward Gauss-Seidel sweep around the coarse correction; the
K-cycle CG uses is not a fixed operator, which MINRES needs), or of smoothed-aggregation AMG when
the fields have no geometric hierarchy; S~ the caller's spectrally equivalent approximation of the
Schur complement C + B A^{-1} B^T for each constraint field (for Stokes (1/nu) M_p plus the pressure
stabilization), applied by one V-cycle too (or a factorization when small).  Then MINRES's
iterations are bounded independently of h and of the cut position (Silvester and Wathen 1994; the
ghost penalties make the blocks' constants uniform in the cut).

A one-unknown field (a Lagrange multiplier for a mean value) needs no matrix: its Schur complement
is the number b^T S~^{-1} b of its coupling row b, computed once.  A constraint field whose
constants are a null vector of K (a pressure without its mean-value constraint) is refused with
that cause, as is a constraint field without its own block C (equal-order pairs are unstable
without a pressure stabilization).  Small systems (at most :data:`SADDLE_DIRECT_LIMIT` unknowns)
are factorized directly (SuperLU with a minimum degree ordering on K + K^T).

A system whose matrix is not symmetric (an Oseen or advection term in the primal block, a
non-symmetric Nitsche variant) is solved by restarted GMRES (scipy's) with the same block-diagonal
preconditioner, the primal block's V-cycles built on its symmetric part (A + A^T) / 2: a fixed
SPD operator that stays spectrally equivalent to A while the advection is moderate (iterations grow
with the cell Peclet number; a convection-aware smoother is the next step there).  MINRES is
refused on such a matrix, naming its asymmetry.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .common import SolveInfo
from .diagnose import SolverError, _Checks
from .direct import DirectSolver
from .krylov import _amg, dof_points_of
from .minres import BlockDiagonal, minres
from .multigrid import GeometricMultigrid, multigrid_hierarchy

__all__ = ["saddle_solve", "SADDLE_DIRECT_LIMIT"]

#: saddle systems with at most this many unknowns are factorized (SuperLU) by ``solve``'s "auto"
SADDLE_DIRECT_LIMIT = 5_000

#: V-cycles per application of a block's multigrid preconditioner: on the cut Stokes problem MINRES needs
#: 75-83 iterations with one, 51-55 with two (spacings 0.1, 0.05), at the same time
CYCLES = 2

#: block preconditioners of at most this many unknowns are factorized instead of a V-cycle
FACTOR_BLOCK_LIMIT = 2_000

#: |K - K^T| / |K| (largest entries) above which a saddle system is treated as non-symmetric (GMRES)
ASYMMETRY_TOL = 1e-12

#: GMRES restart length (Krylov vectors kept); the preconditioned iterations of the cut Oseen test stay below it
GMRES_RESTART = 200


def _field_dofs(space, k):
    return np.arange(space.offsets[k], space.offsets[k + 1])


def _subspace(space, ks):
    """The product space of the fields ``ks`` of ``space`` (for their multigrid hierarchy)."""
    fields = [space.fields[k] for k in ks]
    return fields[0] if len(fields) == 1 else type(space)(*fields)


def _block_preconditioner(M, field_space, what, indefinite_hint=None):
    """An SPD fixed approximation of M^{-1}: a factorization when small, else V-cycles of the
    geometric multigrid of ``field_space`` (or smoothed-aggregation AMG without a hierarchy).  A
    block that is not positive definite raises SolverError with ``indefinite_hint`` (the form's
    advice: a Nitsche penalty below its bound makes the primal block indefinite)."""
    M = sp.csr_matrix(M, dtype=float)
    checks = _Checks.of(indefinite_hint=indefinite_hint)
    if M.shape[0] <= FACTOR_BLOCK_LIMIT:
        return DirectSolver(M, where=what, _checks=checks).solve
    hierarchy = multigrid_hierarchy(field_space) if field_space is not None else None
    if hierarchy is not None:
        mg = GeometricMultigrid(M, prolongations=hierarchy, visits=(1,), _checks=checks)
        cycles = CYCLES

        def apply(r):
            z = mg.apply(r[:, None])[:, 0]
            for _ in range(cycles - 1):  # B_2 = 2B - B M B: symmetric, and SPD while the cycle contracts
                z += mg.apply((r - M @ z)[:, None])[:, 0]
            return z

        return apply
    amg = _amg(M, dof_points_of(field_space))  # one V-cycle, with the linear functions as candidates
    return lambda r: amg(r[:, None])[:, 0]


def _check_constraint_fields(K, space, primal, constraint):
    """The causes of a singular saddle matrix that the blocks show at no cost."""
    scale = float(np.abs(K.data).max()) if K.nnz else 0.0
    for k in constraint:
        dofs = _field_dofs(space, k)
        name = space.names[k]
        if len(dofs) == 1:
            continue
        C = K[dofs][:, dofs]
        if C.nnz == 0 or not np.any(C.data):
            raise SolverError(
                f"the saddle system's field {name!r} has no block of its own (-C = 0): an equal-order pair (P1-P1) is "
                f"unstable without a stabilization of {name!r}; add one (e.g. -beta/nu h^2 (grad p, grad q) over the "
                "domain, or a face penalty on its jumps) and pass its Schur approximation in schur=", "singular")
        z = np.zeros(K.shape[0])
        z[dofs] = 1.0
        Kz = K @ z
        if np.linalg.norm(Kz) <= 1e-10 * scale * np.sqrt(len(dofs)):
            raise SolverError(
                f"the saddle system is singular: the constants of field {name!r} are a null vector (K z = 0 with z = 1 on "
                f"{name!r}), so {name!r} is determined only up to a constant; add its mean-value constraint (a one-unknown "
                f"field in the product space and the term {name} * lam + q * mu over the domain) or fix one value",
                "singular", kernel=z)


def saddle_solve(K, B, space, primal, schur=None, tol: float = 1e-8, maxiter: int = 1000, method: str = "auto",
                 indefinite_hint=None):
    """Solve the saddle-point system K x = B on the product space ``space`` (MINRES when K is
    symmetric, GMRES when not).

    ``primal``: the fields (names or positions) of the positive definite block A; the other fields
    are the constraint fields.  ``schur``: {field: matrix}, for each constraint field with more
    than one unknown an SPD matrix spectrally equivalent to its Schur complement (for a Stokes
    pressure: (1/nu) M_p plus the pressure stabilization); a one-unknown field (a multiplier) needs
    none.  ``method``: "minres" (block-preconditioned MINRES), "gmres" (the same preconditioner, for a
    non-symmetric K), "direct" (SuperLU) or "auto" (direct up to :data:`SADDLE_DIRECT_LIMIT` unknowns,
    then MINRES or GMRES by K's symmetry).  ``indefinite_hint``: the advice when the primal
    block is not positive definite (e.g. the form's, naming its Nitsche penalty).  Returns (x,
    SolveInfo); B of shape (n,) or (n, 1).
    """
    K = sp.csr_matrix(K, dtype=float)
    n = K.shape[0]
    b = np.asarray(B, dtype=float).reshape(n, -1)
    if b.shape[1] != 1:
        raise ValueError(f"a saddle-point solve takes one right-hand side, got {b.shape[1]} columns: solve them one by one")
    b = b[:, 0]
    fields = getattr(space, "fields", None)
    if fields is None:
        raise ValueError("a saddle-point solve needs space= a ProductSpace whose fields are the primal and the constraint "
                         "fields (e.g. ProductSpace(u=V, p=Q, mean=RealSpace()))")
    primal_k = sorted({space.index(k) for k in ([primal] if isinstance(primal, (str, int)) else primal)})
    constraint = [k for k in range(len(fields)) if k not in primal_k]
    if not primal_k or not constraint:
        raise ValueError(f"primal= must name some but not all of the fields {space.names}; the others are the constraint "
                         "fields (pressure, multipliers)")
    schur = {space.index(k): v for k, v in (schur or {}).items()}
    for k in constraint:
        if space.offsets[k + 1] - space.offsets[k] > 1 and k not in schur:
            raise ValueError(f"schur= needs a matrix for the constraint field {space.names[k]!r} (an SPD approximation of "
                             "its Schur complement, for a Stokes pressure (1/nu) M_p plus its stabilization)")
    _check_constraint_fields(K, space, primal_k, constraint)
    t0 = time.perf_counter()
    scale = abs(K).max()
    asymmetry = float(abs(K - K.T).max() / scale) if scale > 0 else 0.0
    symmetric = asymmetry <= ASYMMETRY_TOL
    if method == "auto":
        method = "direct" if n <= SADDLE_DIRECT_LIMIT else ("minres" if symmetric else "gmres")
    if method == "minres" and not symmetric:
        raise ValueError(f"MINRES needs a symmetric matrix, and this saddle system's is not (|K - K^T| / |K| = {asymmetry:.1e}, "
                         "an advection term or a non-symmetric coupling): use method='gmres' (or 'auto')")
    pdofs = np.concatenate([_field_dofs(space, k) for k in primal_k])
    primal_block = K[pdofs][:, pdofs]
    if not symmetric:
        primal_block = (0.5 * (primal_block + primal_block.T)).tocsr()
    if method == "direct":
        # the primal block (its symmetric part) must be positive definite (a Nitsche penalty below its bound is
        # not): checked by its own factorization, which names the cause; the saddle matrix alone would not tell
        DirectSolver(primal_block, where="the primal block", _checks=_Checks.of(indefinite_hint=indefinite_hint))
        solver = DirectSolver(K, spd=False, where="the saddle-point system")
        t1 = time.perf_counter()
        x = solver.solve(b)
        res = float(np.linalg.norm(K @ x - b) / max(np.linalg.norm(b), 1e-300))
        return x, SolveInfo("direct", 0, res, time.perf_counter() - t0, t1 - t0)
    if method not in ("minres", "gmres"):
        raise ValueError(f"unknown method {method!r} for a saddle-point system; use 'auto', 'minres', 'gmres' or 'direct'")
    blocks = [(pdofs, _block_preconditioner(primal_block, _subspace(space, primal_k), "the primal block", indefinite_hint))]
    applies = {}
    for k in constraint:
        dofs = _field_dofs(space, k)
        if len(dofs) > 1:
            S = sp.csr_matrix(schur[k], dtype=float)
            if S.shape != (len(dofs), len(dofs)):
                raise ValueError(f"schur[{space.names[k]!r}] has shape {S.shape}, the field has {len(dofs)} unknowns")
            applies[k] = _block_preconditioner(S, fields[k], f"the Schur approximation of {space.names[k]!r}")
            blocks.append((dofs, applies[k]))
    for k in constraint:
        dofs = _field_dofs(space, k)
        if len(dofs) == 1:  # a multiplier: b^T S~^{-1} b of its coupling row, through the others' S~
            row = np.asarray(K[dofs].todense()).reshape(-1)
            value = 0.0
            for j, apply in applies.items():
                bj = row[_field_dofs(space, j)]
                if np.any(bj):
                    value += float(bj @ apply(bj))
            if value <= 0:
                raise SolverError(f"the multiplier {space.names[k]!r} couples to no constraint field with a Schur "
                                  "approximation: constrain a field that has one", "singular")
            blocks.append((dofs, lambda r, v=value: r / v))
    t1 = time.perf_counter()
    if method == "gmres":
        x, it, res = _gmres(K, b, BlockDiagonal(n, blocks), tol, maxiter)
    else:
        x, it, res = minres(K, b, BlockDiagonal(n, blocks), tol=tol, maxiter=maxiter, name="MINRES (saddle point)")
    return x, SolveInfo(method, it, res, time.perf_counter() - t0, t1 - t0)


def _gmres(K, b, preconditioner, tol, maxiter):
    """Restarted GMRES (scipy) with the block preconditioner; (x, iterations, relative residual), or a
    RuntimeError (as MINRES's) when it does not reach ``tol`` within ``maxiter`` iterations."""
    n = K.shape[0]
    M = spla.LinearOperator((n, n), matvec=preconditioner, dtype=float)
    count = [0]

    def callback(_residual):
        count[0] += 1

    x, status = spla.gmres(K, b, M=M, rtol=tol, atol=0.0, restart=GMRES_RESTART, maxiter=max(1, maxiter // GMRES_RESTART + 1),
                           callback=callback, callback_type="pr_norm")
    res = float(np.linalg.norm(K @ x - b) / max(np.linalg.norm(b), 1e-300))
    if status != 0 or not np.isfinite(res) or res > 10 * tol:
        raise RuntimeError(f"GMRES (saddle point) did not converge: relative residual {res:.1e} after {count[0]} iterations "
                           f"(tol {tol:.0e}); the advection may be too strong for the symmetric-part preconditioner: refine the "
                           "mesh (smaller cell Peclet number) or use method='direct'")
    return x, count[0], res
