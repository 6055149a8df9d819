"""laplace-beltrami-cut on several ranks (docs/math.md §4): TraceFEM on the cut tets of each rank,
J_F on every interior face of the cut tets once, solved by PETSc.

The forms are the serial problem's (:class:`cutfem.problems.laplace_beltrami.LaplaceBeltramiCut`):
on the owned cells the tangential stiffness, the mass and the load over their pieces of Gamma_h
(and the normal-gradient term over their cut tets), and the face stabilization tau_F h^a J_F of
the faces between two owned cells; on the seam J_F of the faces between an owned cell and a ghost
that the rank assembles (:meth:`~cutfem.distributed.partition.RankCuts.seam_facets`).  At ``order``
2 (on the structured box's slabs) P2 trace fields on S_h lifted by the serial Theta_h
(docs/math.md §19), with the serial order-2 ``auto`` stabilization.
"""

from __future__ import annotations

from ..fem.forms import assemble
from ..fem.norms import h1_error, l2_error
from ..fem.terms import basis_integrals, face_jump_penalty, load, mass, normal_gradient_penalty, tangential_stiffness
from ..geometry.markers import CUT
from ..problems.common import check_face_stabilization, check_normal_stabilization, levelset_for
from ..problems.laplace_beltrami import LaplaceBeltramiCut, manufactured
from ..runs.runner import Timer
from .assembly import rank_pieces
from .launch import engine
from .levels import shared_background, solve_on_ranks

__all__ = ["laplace_beltrami_cut_level", "laplace_beltrami_pieces"]


def laplace_beltrami_pieces(cuts, sol, stabilization, tau_f, face_h_power, tau_n, normal_h_power, order=1):
    """The rank's pieces of the laplace-beltrami-cut system (:func:`~cutfem.distributed.assembly.rank_pieces`),
    of P1 or P2 (``order`` 2, on the cuts lifted by Theta_h) trace fields."""

    def cells(cut, V):
        dS = cut.ds()
        a = tangential_stiffness(dS) + mass(dS)
        if stabilization == "normal" and tau_n > 0:
            a = a + tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=normal_h_power)
        return a, load(sol.f, dS, degree=4)

    if stabilization == "face" and tau_f > 0:
        return rank_pieces(cuts, CUT, cells, lambda cut: cut.interior_facets(CUT),
                           lambda dF: tau_f * face_jump_penalty(dF, h_power=face_h_power), order=order)
    return rank_pieces(cuts, CUT, cells, order=order)


def laplace_beltrami_cut_level(spacing, surface, background, box, stabilization, tau_f, face_h_power, tau_n, normal_h_power,
                               solver, R, r, radius, order=1, comm=None, counts=None):
    """One level of laplace-beltrami-cut on the ranks of ``comm`` (default: every rank): the serial
    record's errors, area and sizes, with the engine and the number of ranks.  Without
    stabilization the system is singular (phi_h is a null vector) and PETSc's solve fails.
    ``background``, ``order`` and ``counts`` as for :func:`~cutfem.distributed.poisson.poisson_cut_level`."""
    MPI, _ = engine()
    comm = MPI.COMM_WORLD if comm is None else comm
    auto = stabilization == "auto"  # the serial problem's choice at the order
    stabilization, tau_n, normal_h_power = LaplaceBeltramiCut.stabilization_for(stabilization, order, tau_f, face_h_power, tau_n,
                                                                               normal_h_power)
    notes = (check_face_stabilization(tau_f, face_h_power, spacing) if stabilization == "face" else
             check_normal_stabilization(tau_n, normal_h_power, spacing, warn=not auto) if stabilization == "normal" else [])
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius)
        sol = manufactured(phi)
        bg = shared_background(comm, phi, spacing, background, box)

    def measure(V, u):
        return l2_error(V, u, sol.u) ** 2, h1_error(V, u, sol.grad) ** 2, float(assemble(basis_integrals(V.cut.ds()), V).sum())

    rec = solve_on_ranks(comm, phi, bg,
                         lambda cuts: laplace_beltrami_pieces(cuts, sol, stabilization, tau_f, face_h_power, tau_n, normal_h_power,
                                                              order),
                         measure, ("l2_error", "h1_error", "area"), solver, counts, t, bulk=False, order=order)
    if notes:
        rec["warnings"] = notes
    return rec
