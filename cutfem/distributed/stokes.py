"""stokes-cut on several ranks (docs/math.md §14, §19): equal-order P1-P1 with Nitsche, the ghost
penalties of the velocity and the pressure on every face once, the Brezzi-Pitkaranta term and the
pressure's mean-value multiplier, solved by PETSc (MINRES with a field split, or MUMPS).

The forms are the serial problem's (:func:`cutfem.problems.stokes.stokes_cut`), assembled on the
product space (u, p) of each local mesh's P1 space (a slab of a structured box, or cells of an
unstructured mesh): on the owned cells the cell terms, the load and the ghost penalties of the
faces between two owned cells, on the seam those of the faces between an owned cell and a ghost
that the rank assembles.  The unknowns are keyed ``node * 4 + field`` (the velocity's components 0, 1, 2 and
the pressure 3: :func:`~cutfem.distributed.assembly.global_keys`), so a rank's block holds the four
unknowns of each of its nodes, a permutation of the serial [u_1 | u_2 | u_3 | p | lam] numbering.

The multiplier lam is kept, the serial matrix's last row and column: one unknown of no node (key
-1, :class:`~cutfem.distributed.system.GlobalNumbering`), owned by the last rank, whose column
m_j = int_{Omega_h} phi_j every rank assembles on its owned cells.  Removing the pressure's
constants by PETSc's null space instead gives the serial solution only for a compatible load:
summing the pressure rows of K x = b (B^T 1 = 0, C 1 = 0) gives lam = 1^T g / |Omega_h| with 1^T g =
(g . n, 1)_{Gamma_h}, so the serial system solves g - lam m where a null space would project g to
g - (1^T g / n_p) 1.  Here g = curl A has no flux through any closed surface and lam vanishes to
round-off, but boundary data whose flux vanishes only on Gamma, not on Gamma_h, would need the load
corrected by lam m and the pressure shifted to mean zero after; and a factorization of the singular
matrix (the direct solve) is not reliable.  With lam kept, the matrix is the serial one entry by entry (up
to the order of sums), MUMPS factorizes it as SuperLU does serially, and the one dense row costs its
owner a gather of the whole pressure per product, negligible at a few ranks.

The preconditioner is the serial one's (:mod:`cutfem.solvers.saddle`): diag(A, S) with S = (1/nu)
M_p + the pressure stabilization and the multiplier's Schur number m^T S^{-1} m = nu |Omega_h|
(exact: the stabilization vanishes on constants, so S 1 = (1/nu) M_p 1 = m / nu), on PETSc's field
split (:func:`~cutfem.distributed.saddle.saddle_solve`), each block by two V-cycles of the lattice
multigrid as serially: the velocity's scalar prolongation per component, the pressure's with the
multiplier kept on every level (:func:`~cutfem.distributed.preconditioners.lattice_prolongations`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..fem.coupling import divergence
from ..fem.forms import assemble
from ..fem.norms import l2_error, l2_h1_errors
from ..fem.spaces import CutSpace, ProductSpace, VectorSpace
from ..fem.terms import basis_integrals, face_jump_penalty, load, mass, nitsche, stiffness
from ..geometry.markers import NEG
from ..problems.common import check_ghost_penalty, check_nitsche_penalty, levelset_for
from ..problems.stokes import PRESSURE, VELOCITY, VELOCITY_GRADIENT, normal_data, source
from ..runs.runner import Timer
from .assembly import Piece, RankPieces, global_keys
from .launch import engine
from .levels import shared_background, solve_on_ranks
from .saddle import SADDLE_TOL, near_null_vectors, saddle_solve
from .system import LinearSystem

__all__ = ["stokes_cut_level", "stokes_pieces", "StokesPieces"]

#: the unknowns of a node: the velocity's three components and the pressure
FIELDS = 4

#: the key of the multiplier (:class:`~cutfem.distributed.system.GlobalNumbering`'s constants)
MULTIPLIER = -1


class StokesPieces(RankPieces):
    """The pieces of the saddle matrix K (with the load) and, in ``preconditioner``, those of the
    block-diagonal preconditioning matrix diag(A, S, nu |Omega_h|) in the same keys."""

    def __init__(self):
        super().__init__()
        self.preconditioner = []


def _with_multiplier(K, S, m, nu):
    """K bordered by the multiplier's column m on the pressure rows, and diag(A, S, nu sum m) (A the
    velocity block of K), on a slab's product space and the multiplier."""
    n = len(m)
    column = sp.csr_matrix(np.concatenate([np.zeros(3 * n), m])[:, None])
    bordered = sp.bmat([[K, column], [column.T, None]], format="csr")
    return bordered, sp.block_diag([K[: 3 * n, : 3 * n], S, sp.csr_matrix([[nu * float(m.sum())]])], format="csr")


def stokes_pieces(cuts, nu, gamma, gamma_u, gamma_p, beta) -> StokesPieces:
    """The rank's pieces of the stokes-cut system on the product space (u, p) of each of its cuts."""
    out = StokesPieces()

    def ghost(cut, facets):
        """The ghost penalties of the faces ``facets`` on K and on S, or (None, None) without faces."""
        out.faces += facets.n_facets
        if not facets.n_facets or (gamma_u == 0 and gamma_p == 0):
            return None, None
        dg = cut.dF(facets)
        a = nu * gamma_u * face_jump_penalty(dg, h_power=1, field="u") if gamma_u > 0 else None
        s = None
        if gamma_p > 0:
            g3 = face_jump_penalty(dg, h_power=3, field="p")
            a = -(gamma_p / nu) * g3 if a is None else a - (gamma_p / nu) * g3
            s = (gamma_p / nu) * face_jump_penalty(dg, h_power=3)
        return a, s

    owned, seam = cuts.owned, cuts.seam
    if owned is not None:
        V = CutSpace(owned, NEG)
        W = out.space = ProductSpace(u=VectorSpace(V), p=V)
        if V.n_dofs:
            dx = owned.dx(NEG)
            a = nu * stiffness(dx, field="u") + divergence(dx, by_parts=True) - (beta / nu) * stiffness(dx, field="p", h_power=2)
            s = (1 / nu) * mass(dx) + (beta / nu) * stiffness(dx, h_power=2)
            rhs = load(source(nu), dx, field="u")
            if owned.n_tets:  # a slab that the surface misses has no Gamma_h and no ghost faces
                ds = owned.ds()
                N = nitsche(ds, gamma, g=VELOCITY, field="u")
                a, rhs = a + nu * N, rhs + nu * N.load + normal_data * ds
                ga, gs = ghost(owned, owned.ghost_facets(NEG))
                a, s = a if ga is None else a + ga, s if gs is None else s + gs
            K, P = _with_multiplier(assemble(a, W), assemble(s, V), np.asarray(assemble(basis_integrals(dx), V), dtype=float), nu)
            keys = np.concatenate([global_keys(W), [MULTIPLIER]])
            out.pieces.append(Piece(keys, K, np.concatenate([assemble(rhs, W), [0.0]])))
            out.preconditioner.append(Piece(keys, P))
    if seam is not None and seam.n_tets:
        ga, gs = ghost(seam, cuts.seam_facets(seam.ghost_facets(NEG)))
        if ga is not None:
            V = CutSpace(seam, NEG)
            W = ProductSpace(u=VectorSpace(V), p=V)
            K = assemble(ga, W)
            S = assemble(gs, V) if gs is not None else sp.csr_matrix((V.n_dofs, V.n_dofs))
            out.pieces.append(Piece(global_keys(W), K))
            out.preconditioner.append(Piece(global_keys(W), sp.block_diag([K[: 3 * V.n_dofs, : 3 * V.n_dofs], S], format="csr")))
    return out


def _saddle(solver, tol):
    """The solve of :func:`~cutfem.distributed.levels.solve_on_ranks`: the preconditioning matrix
    from the pieces, the velocity's unknowns and their near-null vectors, the lattice hierarchies
    (on the structured box) of the velocity, 3 unknowns a node, and of the pressure with the
    multiplier, then :func:`~cutfem.distributed.saddle.saddle_solve`."""

    def solve(system, A, loads, parts, hierarchy):
        numbering = system.numbering
        pre = LinearSystem(system.comm, numbering)
        for piece in parts.preconditioner:
            pre.add_matrix(piece.matrix, numbering(piece.keys))
        P, (zero,) = pre.petsc()
        velocity = np.flatnonzero(numbering.owned_keys % FIELDS < 3)
        nodes = numbering.owned_keys[velocity[::3]] // FIELDS
        lattices = (None, None) if hierarchy is None else (lambda: hierarchy(nodes, components=3),
                                                           lambda: hierarchy(nodes, constants=1))
        try:
            return saddle_solve(system, A, loads, P, numbering.first + velocity, near_null_vectors(len(nodes)), solver, tol,
                                lattices)
        finally:
            P.destroy()
            zero.destroy()

    return solve


def stokes_cut_level(spacing, surface, background, box, nu, gamma, gamma_u, gamma_p, beta, solver, R, r, radius, axes,
                     comm=None, counts=None, tol: float = SADDLE_TOL):
    """One level of stokes-cut on the ranks of ``comm`` (default: every rank): the serial record's
    errors (the pressure's up to its mean over Omega_h), volume and sizes, with the engine (PETSc,
    its KSP and PC), the iterations and the number of ranks.  ``tol``: MINRES's (preconditioned)
    relative residual (:data:`~cutfem.distributed.saddle.SADDLE_TOL`)."""
    MPI, _ = engine()
    comm = MPI.COMM_WORLD if comm is None else comm
    notes = check_ghost_penalty(gamma_u, "--gamma-u") + check_ghost_penalty(gamma_p, "--gamma-p") + check_nitsche_penalty(gamma)
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius, axes)
        bg = shared_background(comm, phi, spacing, background, box)
    mean = np.zeros(2)  # int p and |Omega_h| over the owned cells, then summed: the pressure's mean

    def build(cuts):
        parts = stokes_pieces(cuts, nu, gamma, gamma_u, gamma_p, beta)
        V = parts.space
        if V is not None and V.n_dofs:
            dx = cuts.owned.dx(NEG)
            mean[:] = float(np.sum(assemble(load(PRESSURE, dx), V["p"]))), dx.size
        comm.Allreduce(MPI.IN_PLACE, mean, op=MPI.SUM)
        return parts

    def measure(W, x):
        V = W["p"]
        dx = V.cut.dx(NEG)
        u, p = W.split(x)
        l2u, h1u = l2_h1_errors(V, W["u"].nodal(u), lambda y: (VELOCITY(y), VELOCITY_GRADIENT(y)), dx)
        c = mean[0] / mean[1]
        return l2u * l2u, h1u * h1u, l2_error(V, p, lambda y: PRESSURE(y) - c, dx) ** 2, dx.size

    rec = solve_on_ranks(comm, phi, bg, build, measure, ("l2_error_velocity", "h1_error_velocity", "l2_error_pressure", "volume"),
                         solver, counts, t, fields=FIELDS, constants=1, solve=_saddle(solver, tol))
    if notes:
        rec["warnings"] = notes
    return rec
