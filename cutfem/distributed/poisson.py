"""poisson-cut on several ranks: the fictitious-domain Poisson problem of docs/math.md §8, its
forms assembled on each rank's cells (:mod:`cutfem.distributed.partition`) and solved by PETSc.

The forms are the serial problem's (:mod:`cutfem.problems.poisson`): on the rank's owned cells the
stiffness, Nitsche's terms, the load and the ghost penalty of the faces between two owned cells;
on its seam the ghost penalty of the faces between an owned cell and a ghost that the rank
assembles.  Each is assembled by the serial code on the local mesh's own space and moved to the
global numbers (:class:`~cutfem.distributed.system.GlobalNumbering`), so the matrix, the load and
the solution are the serial ones up to the order of the floating-point sums, and so are the errors
(sums of squares over the owned cells, added over the ranks).  At ``order`` 2 (on the structured
box's slabs) the fields are P2 on the cuts lifted by the serial Theta_h (docs/math.md §19), with
the serial order-2 terms and ghost penalty.
"""

from __future__ import annotations

from ..fem.norms import l2_h1_errors
from ..fem.terms import face_jump_penalty, load, nitsche, stiffness
from ..geometry.markers import NEG
from ..problems.common import check_ghost_penalty, check_nitsche_penalty, levelset_for
from ..problems.poisson import GHOST_PENALTY, exact_solution, exact_u, source
from ..runs.runner import Timer
from .launch import engine
from .assembly import rank_pieces
from .levels import shared_background, solve_on_ranks

__all__ = ["poisson_cut_level", "poisson_pieces"]


def poisson_pieces(cuts, gamma: float, gamma_g: float, order: int = 1):
    """The rank's pieces of the poisson-cut system (:func:`~cutfem.distributed.assembly.rank_pieces`):
    stiffness, Nitsche's terms and the load on the owned cells, the ghost penalty on every face once;
    the serial problem's terms of ``order`` (at 2 on the cuts lifted by Theta_h, the Nitsche penalty
    gamma k^2 and the ghost penalty's second-derivative jumps)."""

    def cells(cut, V):
        dx = cut.dx(NEG)
        a, rhs = stiffness(dx), load(source, dx, degree=2)
        if cut.n_tets:  # a slab that the surface misses has no Gamma_h
            N = nitsche(cut.ds(), gamma * order**2, g=exact_u)
            a, rhs = a + N, rhs + N.load
        return a, rhs

    if gamma_g == 0:
        return rank_pieces(cuts, NEG, cells, order=order)
    return rank_pieces(cuts, NEG, cells, lambda cut: cut.ghost_facets(NEG),
                       lambda dF: gamma_g * face_jump_penalty(dF, h_power=1), order=order)


def poisson_cut_level(spacing, surface, background, box, gamma, gamma_g, solver, R, r, radius, axes, order=1, comm=None,
                      counts=None):
    """One level of poisson-cut on the ranks of ``comm`` (default: every rank); the record of the
    serial :func:`cutfem.problems.poisson.poisson_cut` with the engine (PETSc, its KSP and PC) and
    the number of ranks, the same on every rank.  ``background``: "structured", "tetwild" or a
    TetMesh, the same on every rank (:func:`~cutfem.distributed.levels.shared_background`;
    ``order`` 2 on the structured box only); ``counts``: the partition by hand
    (:func:`~cutfem.distributed.partition.partition_for`)."""
    MPI, _ = engine()
    comm = MPI.COMM_WORLD if comm is None else comm
    gamma_g = GHOST_PENALTY[order] if gamma_g is None else gamma_g
    notes = check_ghost_penalty(gamma_g) + check_nitsche_penalty(gamma)
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius, axes)
        bg = shared_background(comm, phi, spacing, background, box)

    def measure(V, u):
        dx = V.cut.dx(NEG)
        l2, h1 = l2_h1_errors(V, u, exact_solution, dx)
        return l2 * l2, h1 * h1, dx.size

    rec = solve_on_ranks(comm, phi, bg, lambda cuts: poisson_pieces(cuts, gamma, gamma_g, order),
                         measure, ("l2_error", "h1_error", "volume"), solver, counts, t, order=order)
    rec["gamma_g"] = gamma_g  # the one used, as the serial record holds it
    if notes:
        rec["warnings"] = notes
    return rec
