"""Saddle-point systems on PETSc: MINRES with a block-diagonal field split, or MUMPS (docs/math.md §19).

K = [[A, B^T], [B, -C]] (:mod:`cutfem.solvers.saddle` serially), A the SPD block of the primal field
(a velocity), the other unknowns the constraint fields (a pressure, a multiplier).  The method is
the serial one on PETSc's parts: MINRES preconditioned by diag(A~^{-1}, S~^{-1}), PCFIELDSPLIT of
additive type on a preconditioning matrix P = diag(A, S) that the caller assembles in K's layout
(for Stokes S = (1/nu) M_p plus the pressure stabilization, and the multiplier's Schur number).
MINRES needs each block to be one fixed SPD operator, not an inner solve to a tolerance.  With the
lattice hierarchy (the structured box), each block is two V-cycles of PETSc's PCMG on cutfem's
lattice prolongations (:mod:`~cutfem.distributed.preconditioners`), B_2 = 2B - B A B as the serial
blocks' (:data:`~cutfem.solvers.saddle.CYCLES`): for the primal block the scalar prolongation per
component (a node's 3 components numbered together), for the constraint block the pressure's with
the multiplier kept on every level.  Smoothed by Chebyshev-SOR (symmetric), so each V-cycle is
symmetric.  Without a hierarchy (an unstructured background):

* the primal block: one GAMG V-cycle (PREONLY), the 3 components of a node in one block, with the
  near-null space of each component's constants (:func:`near_null_vectors`; adding the linear
  functions of each component saves a fifth of the iterations but makes GAMG's setup about ten
  times dearer); with the constraint block below, MINRES needs about three times the iterations
  of PCMG on both blocks (docs/math.md §19);
* the constraint block: Chebyshev on the Jacobi-scaled S, a fixed number of iterations
  (:data:`CHEBYSHEV_DEGREE`), a fixed polynomial that stays SPD below its interval.  Jacobi alone
  is not enough: the ghost penalty of the pressure, h^3 [d_n p][d_n q] on the faces, is what
  controls the nodes whose support barely meets Omega_h (without it in S the Schur complement is
  not bounded by S), but its diagonal overstates it on its large kernel (the linear functions), so
  D^{-1} S has a condition number of some hundreds where S^{-1} (Schur complement) has about 3;
  the lattice multigrid holds the linear functions on every level.

MINRES in PETSc 3.18 stops on the preconditioned residual; the record gives the true one.
``solver="direct"`` is an LU factorization of K by MUMPS; ``"auto"`` takes it up to
:data:`~cutfem.solvers.saddle.SADDLE_DIRECT_LIMIT` unknowns, as the serial solve does.  PETSc's
options (``PETSC_OPTIONS``) may change any of it: the splits' prefixes are ``fieldsplit_primal_`` and
``fieldsplit_constraint_`` (``-fieldsplit_primal_pc_type gamg`` takes GAMG for the primal block on the box too).
"""

from __future__ import annotations

import numpy as np

from ..solvers.saddle import CYCLES, SADDLE_DIRECT_LIMIT
from .launch import engine
from .preconditioners import set_multigrid

__all__ = ["saddle_solve", "SADDLE_TOL", "near_null_vectors"]

#: PETSc MINRES's relative tolerance on the preconditioned residual; tighter than the serial 1e-8
#: on the true residual, so that the errors of both agree to 1e-10 relative (see :func:`saddle_solve`)
SADDLE_TOL = 1e-12

#: Chebyshev iterations on the Jacobi-scaled Schur approximation S (a fixed polynomial in D^{-1} S)
CHEBYSHEV_DEGREE = 10

#: the Chebyshev interval, from PETSc's estimate of the largest eigenvalue e of D^{-1} S:
#: [0.01 e, 1.1 e] (-ksp_chebyshev_esteig a,b,c,d: [a e_min + b e, c e_min + d e])
CHEBYSHEV_INTERVAL = "0,0.01,0,1.1"


def near_null_vectors(n: int) -> np.ndarray:
    """(n, 3, 3) the near-null space of a vector Laplacian at n nodes, as values of each node's 3
    components: each component constant."""
    out = np.zeros((n, 3, 3))
    for c in range(3):
        out[:, c, c] = 1.0
    return out


def saddle_solve(system, A, loads, P, primal, near_null, solver: str = "auto", tol: float = SADDLE_TOL,
                 hierarchies=(None, None)):
    """``([x], info)``: the solution of the saddle system A x = b (one load) by PETSc, and what solved
    it (``engine``, ``ksp``, ``pc``, ``iterations``, ``residual`` the true relative one, ``ranks``).

    ``P``: the block-diagonal preconditioning matrix (PETSc, A's layout); ``primal``: the global
    numbers of this rank's primal unknowns, by node with a node's 3 components together;
    ``near_null``: (n_nodes, 3, k) the near-null vectors of the primal block at this rank's primal
    nodes (:func:`near_null_vectors`); ``hierarchies``: for the primal and the constraint split,
    None or a function that returns the lattice prolongations of the split in its own numbering
    (its rows in the order of their global numbers,
    :func:`~cutfem.distributed.preconditioners.lattice_prolongations`) for its PCMG.  ``solver``:
    "minres", "direct" or "auto".  ``tol``: MINRES's
    relative preconditioned residual, :data:`SADDLE_TOL` by default: the serial run stops at a true
    residual of 1e-8 and its errors are then within 1e-10 of the exact solve's (5e-11 to 9e-11 at
    spacings 0.2 and 0.1); a preconditioned residual of 1e-10 leaves the distributed errors up to
    1e-9 away, 1e-12 within about 2e-11, so the two runs agree to 1e-10."""
    _, PETSc = engine()
    comm = system.comm
    N = system.numbering.n_global
    if solver == "auto":
        solver = "direct" if N <= SADDLE_DIRECT_LIMIT else "minres"
    if solver not in ("minres", "direct"):
        raise ValueError(f"solver={solver!r} is not available for a saddle-point system on PETSc; distributed runs take "
                         "auto, minres or direct")
    (b,) = loads
    ksp = PETSc.KSP().create(comm=comm)
    ksp.setOperators(A, A if solver == "direct" else P)  # the factorization is of K itself
    pc = ksp.getPC()
    splits = []
    if solver == "direct":
        ksp.setType("preonly")
        pc.setType("lu")
        pc.setFactorSolverType("mumps")
    else:
        ksp.setType("minres")
        ksp.setTolerances(rtol=tol, atol=0.0, max_it=10_000)
        pc.setType("fieldsplit")
        pc.setFieldSplitType(PETSc.PC.CompositeType.ADDITIVE)
        first, n = system.numbering.first, system.numbering.n_owned
        primal = np.asarray(primal, dtype=PETSc.IntType)
        rest = np.setdiff1d(np.arange(first, first + n, dtype=PETSc.IntType), primal)
        is_primal = PETSc.IS().createGeneral(primal, comm=comm)
        is_primal.setBlockSize(3)
        is_rest = PETSc.IS().createGeneral(rest, comm=comm)
        k = near_null.shape[2]
        vectors = []
        for j in range(k):
            v = PETSc.Vec().createMPI((len(primal), PETSc.DECIDE), bsize=3, comm=comm)
            v.setArray(np.ascontiguousarray(near_null[:, :, j]).reshape(-1))
            vectors.append(v)
        orthonormal = _orthonormalize(vectors)
        space = PETSc.NullSpace().create(constant=False, vectors=orthonormal, comm=comm)
        is_primal.compose("nearnullspace", space)
        pc.setFieldSplitIS(("primal", is_primal), ("constraint", is_rest))
        splits = [is_primal, is_rest, space, *vectors, *orthonormal]
    ksp.setFromOptions()  # PETSC_OPTIONS may change any of it
    if solver == "minres":
        pc.setUp()
        primal_ksp, constraint_ksp = pc.getFieldSplitSubKSP()
        primal_ksp.setType("preonly")
        if not _multigrid(primal_ksp, hierarchies[0], splits):
            primal_ksp.getPC().setType("gamg")
        if not _multigrid(constraint_ksp, hierarchies[1], splits):
            constraint_ksp.setType("chebyshev")
            constraint_ksp.setTolerances(max_it=CHEBYSHEV_DEGREE)
            constraint_ksp.setNormType(PETSc.KSP.NormType.NONE)
            constraint_ksp.getPC().setType("jacobi")
            options = PETSc.Options(constraint_ksp.getOptionsPrefix())
            if not options.hasName("ksp_chebyshev_esteig"):
                options["ksp_chebyshev_esteig"] = CHEBYSHEV_INTERVAL
        for sub in (primal_ksp, constraint_ksp):
            sub.setFromOptions()
    x = A.createVecRight()
    ksp.solve(b, x)
    reason = ksp.getConvergedReason()
    if reason < 0:
        raise RuntimeError(f"PETSc's KSP {ksp.getType()} with PC {pc.getType()} did not converge on the saddle-point system: "
                           f"reason {reason} after {ksp.getIterationNumber()} iterations (see KSPConvergedReason); "
                           "solver='direct' factorizes it")
    r = b.duplicate()
    A.mult(x, r)
    r.aypx(-1.0, b)
    bn = b.norm()
    residual = float(r.norm() / bn) if bn > 0 else float(r.norm())
    if pc.getType() == "lu":
        pc_name = f"lu ({pc.getFactorSolverType()})"
    else:
        subs = [s.getPC().getType() if s.getType() == "preonly" else f"{s.getType()}+{s.getPC().getType()}"
                for s in pc.getFieldSplitSubKSP()]
        pc_name = f"{pc.getType()} ({', '.join(subs)})"
    info = {"engine": f"PETSc {'.'.join(map(str, PETSc.Sys.getVersion()))}", "ksp": ksp.getType(), "pc": pc_name,
            "iterations": int(ksp.getIterationNumber()), "residual": residual, "ranks": int(comm.size)}
    for obj in (r, ksp, *splits):
        obj.destroy()
    return [x], info


def _multigrid(ksp, hierarchy, made) -> bool:
    """Make the split's ``ksp`` one application of PCMG on the prolongations ``hierarchy()``
    (:data:`~cutfem.solvers.saddle.CYCLES` V-cycles, B_2 = 2B - B A B, as the serial blocks'),
    unless there is no hierarchy or PETSc's options name another PC for the split; the
    prolongations and coarse operators are added to ``made`` (for the caller to destroy).  True
    when it did."""
    _, PETSc = engine()
    options = PETSc.Options(ksp.getOptionsPrefix())
    if hierarchy is None or (options.hasName("pc_type") and options.getString("pc_type") != "mg"):
        return False
    ksp.setType("preonly")
    prolongations = hierarchy()
    made += prolongations
    made += set_multigrid(ksp, ksp.getOperators()[1], prolongations)
    if not options.hasName("pc_mg_multiplicative_cycles"):
        options["pc_mg_multiplicative_cycles"] = str(CYCLES)
    return True


def _orthonormalize(vectors):
    """The vectors made orthonormal (modified Gram-Schmidt), as PETSc's MatNullSpace wants them."""
    out = []
    for v in vectors:
        w = v.copy()
        for q in out:
            w.axpy(-q.dot(w), q)
        norm = w.norm()
        if norm > 1e-12 * max(v.norm(), 1e-300):
            w.scale(1.0 / norm)
            out.append(w)
        else:
            w.destroy()
    return out
