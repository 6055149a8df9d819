"""Preconditioned MINRES for symmetric indefinite systems, and block-diagonal preconditioners.

MINRES (Paige and Saunders, SIAM J. Numer. Anal. 12, 1975) minimizes the residual in the norm
of the inverse preconditioner over the Krylov space of P^{-1} A, with a three-term Lanczos
recurrence: it needs A symmetric (indefinite allowed) and P symmetric positive definite and fixed,
unlike CG (A definite) and unlike GMRES (no recurrence, every direction kept).  The recurrence
below is the one of Elman, Silvester and Wathen (Finite Elements and Fast Iterative Solvers, 2nd
ed., Algorithm 4.1); |eta| is the P^{-1}-norm of the residual, the quantity it minimizes, and the
loop stops on it; the true residual is checked at the end, and the iteration continues from the
current iterate when they disagree.

For a saddle-point system [[A, B^T], [B, -C]] the preconditioner is block-diagonal,
diag(A~^{-1}, S~^{-1}), with A~ spectrally equivalent to the primal block and S~ to the Schur
complement C + B A^{-1} B^T (for Stokes: the viscosity-scaled pressure mass matrix plus the
pressure stabilization).  Then the eigenvalues of P^{-1} K lie in two intervals bounded away from
zero independently of h, and so do MINRES's iterations (Silvester and Wathen, SIAM J. Numer. Anal.
31, 1994).  The dot products are compiled column dots (no BLAS threads: see
:mod:`cutfem.solvers.sparse_kernels`).
"""

from __future__ import annotations

import numpy as np

from . import sparse_kernels

__all__ = ["minres", "BlockDiagonal"]


def _dot(u, v) -> float:
    return float(sparse_kernels.column_dots(u[:, None], v[:, None])[0])


class BlockDiagonal:
    """The preconditioner z = diag(P_1^{-1}, ..., P_k^{-1}) r: ``blocks`` is a list of
    (dofs, apply), ``dofs`` a slice or an index array of the block's unknowns, ``apply`` a function
    of the block's residual (m,) returning P_i^{-1} r_i (m,).  Unknowns in no block are left as they
    are (identity)."""

    def __init__(self, n: int, blocks):
        self.n = int(n)
        self.blocks = list(blocks)

    def __call__(self, r: np.ndarray) -> np.ndarray:
        z = np.array(r, dtype=float)
        for dofs, apply in self.blocks:
            z[dofs] = np.asarray(apply(np.ascontiguousarray(r[dofs])), dtype=float).reshape(-1)
        return z


def minres(A, b, precondition=None, tol: float = 1e-8, maxiter: int = 1000, x0=None, name: str = "MINRES"):
    """Solve A x = b, A symmetric (indefinite allowed), by preconditioned MINRES.

    ``precondition``: a function r -> P^{-1} r with P symmetric positive definite (None: P = I).
    ``tol``: the relative residual ||b - A x|| / ||b|| to reach (2-norm, checked on the true
    residual).  Returns (x, iterations, relative residual).  A preconditioner that is not positive
    definite (r^T P^{-1} r <= 0) raises ValueError naming it; no convergence in ``maxiter``
    iterations raises RuntimeError with the residual reached.
    """

    b = np.ascontiguousarray(b, dtype=float).reshape(-1)
    n = len(b)
    apply = precondition or (lambda r: r.copy())
    nb = np.sqrt(_dot(b, b))
    if nb == 0:
        return np.zeros(n), 0, 0.0
    x = np.zeros(n) if x0 is None else np.array(x0, dtype=float).reshape(-1)
    it = 0
    rel = np.inf
    inner = 0.1 * tol  # the inner loop's target for |eta| / eta0, tightened when the true residual lags
    while it < maxiter:
        v = b - A @ x
        rel = np.sqrt(_dot(v, v)) / nb
        if rel <= tol:
            break
        z = np.asarray(apply(v), dtype=float)
        g2 = _dot(z, v)
        if not g2 > 0:
            raise ValueError(f"{name}: the preconditioner is not positive definite (r^T P^-1 r = {g2:.3e}); MINRES "
                             "needs a symmetric positive definite preconditioner")
        gamma, gamma_old = np.sqrt(g2), 1.0
        eta, eta0 = gamma, gamma
        v_old = np.zeros(n)
        w, w_old = np.zeros(n), np.zeros(n)
        c, c_old, s, s_old = 1.0, 1.0, 0.0, 0.0
        while it < maxiter:
            z = z / gamma
            Az = A @ z
            delta = _dot(Az, z)
            v_new = Az - (delta / gamma) * v - (gamma / gamma_old) * v_old
            z_new = np.asarray(apply(v_new), dtype=float)
            g2 = _dot(z_new, v_new)
            if g2 < 0:
                raise ValueError(f"{name}: the preconditioner is not positive definite (r^T P^-1 r = {g2:.3e} at "
                                 f"iteration {it}); MINRES needs a symmetric positive definite preconditioner")
            gamma_new = np.sqrt(g2)
            a0 = c * delta - c_old * s * gamma
            a1 = np.hypot(a0, gamma_new)
            a2 = s * delta + c_old * c * gamma
            a3 = s_old * gamma
            c_old, s_old = c, s
            c, s = a0 / a1, gamma_new / a1
            w_new = (z - a3 * w_old - a2 * w) / a1
            x += (c * eta) * w_new
            eta = -s * eta
            it += 1
            w_old, w = w, w_new
            v_old, v, z = v, v_new, z_new
            gamma_old, gamma = gamma, gamma_new
            if abs(eta) <= inner * eta0 or gamma_new == 0:
                break
        r = b - A @ x
        rel = np.sqrt(_dot(r, r)) / nb
        if rel <= tol:
            break
        inner *= max(tol / rel, 1e-3)
    if rel > tol:
        raise RuntimeError(f"{name} did not converge in {maxiter} iterations (relative residual {rel:.2e} > {tol}); "
                           "check that the system is nonsingular (a pressure without its mean-value constraint is "
                           "singular) and that the preconditioner matches its blocks")
    return x, it, float(rel)
