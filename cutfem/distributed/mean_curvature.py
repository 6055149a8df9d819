"""mean-curvature-cut on several ranks (docs/math.md §3): (M + tau_F L^(2-a) J_F) H = A x on the cut
tets of each rank, J_F on every interior face of the cut tets once, the three components solved by
one PETSc KSP.

The forms are the serial problem's (:class:`cutfem.problems.mean_curvature.MeanCurvatureCut`,
:func:`~cutfem.problems.mean_curvature.mean_curvature_form`): on the owned cells the mass and the
position load over their pieces of Gamma_h and J_F of the faces between two owned cells, on the
seam J_F of the faces between an owned cell and a ghost that the rank assembles.  The length-scale
check takes the area of the whole S_h (summed over the ranks).  Not distributed: the edge
stabilization tau_E (refused on several ranks) and the pinning of unknowns that no term sees (S_h
along grid faces: the solve refuses a zero diagonal and names the fix).
"""

from __future__ import annotations

from ..fem.forms import assemble
from ..fem.norms import l2_error
from ..fem.terms import basis_integrals, face_jump_penalty, mass, position_load
from ..geometry.markers import CUT
from ..problems.common import check_face_stabilization, has_exact, levelset_for
from ..problems.mean_curvature import SOLVER_TOL, MeanCurvatureCut, check_length_scale
from ..runs.registry import ProblemError
from ..runs.runner import Timer
from .assembly import rank_pieces
from .launch import engine
from .levels import shared_background, solve_on_ranks

__all__ = ["mean_curvature_cut_level", "mean_curvature_pieces"]


def mean_curvature_pieces(cuts, tau_f, face_h_power, length_scale):
    """The rank's pieces of the mean-curvature-cut system: K = M + tau_F L^(2-a) J_F and the three
    loads A x (:func:`~cutfem.distributed.assembly.rank_pieces`)."""

    def cells(cut, V):
        dS = cut.ds()
        return mass(dS), position_load(dS)

    if tau_f > 0:
        weight = tau_f * length_scale ** (2.0 - face_h_power)
        return rank_pieces(cuts, CUT, cells, lambda cut: cut.interior_facets(CUT),
                           lambda dF: weight * face_jump_penalty(dF, h_power=face_h_power))
    return rank_pieces(cuts, CUT, cells)


def mean_curvature_cut_level(spacing, surface, background, box, stabilization, tau_f, face_h_power, tau_n, normal_h_power, tau_e,
                             solver, length_scale, R, r, radius, axes, comm=None, counts=None):
    """One level of mean-curvature-cut on the ranks of ``comm`` (default: every rank): the serial
    record's l2_error, area, area_error, integral_H and sizes, with the engine and the number of
    ranks.  CG stops at the serial problem's relative residual (1e-6).  ``background`` and
    ``counts`` as for :func:`~cutfem.distributed.poisson.poisson_cut_level`."""
    MPI, _ = engine()
    comm = MPI.COMM_WORLD if comm is None else comm
    if MeanCurvatureCut.stabilization_for(stabilization, 1, tau_f, face_h_power, tau_n, normal_h_power)[0] != "face":
        raise ProblemError("mean-curvature-cut's normal-gradient stabilization is not distributed: use --stabilization face "
                           "(the default at order 1) or run on one rank")
    if tau_e > 0:
        raise ProblemError("mean-curvature-cut's edge stabilization --tau-e is not distributed: leave it at 0 (the face "
                           "stabilization --tau-f is) or run on one rank")
    notes = check_face_stabilization(tau_f, face_h_power, spacing, length_scale)
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius, axes)
        bg = shared_background(comm, phi, spacing, background, box)
    exact = phi if has_exact(phi) else None

    def build(cuts):
        if tau_f > 0:  # the stabilization's weight against the mass term is set by the whole surface's size
            area = comm.allreduce(cuts.owned.area if cuts.owned is not None and cuts.owned.n_tets else 0.0, op=MPI.SUM)
            check_length_scale(area, length_scale, 2.0 - face_h_power)
        return mean_curvature_pieces(cuts, tau_f, face_h_power, length_scale)

    def measure(V, H):
        ones_M = assemble(basis_integrals(V.cut.ds()), V)
        error = l2_error(V, H, exact.exact_mean_curvature_vector) ** 2 if exact is not None else 0.0
        return (error, float(ones_M.sum()), *(ones_M @ H))

    rec = solve_on_ranks(comm, phi, bg, build, measure, ("l2_error", "area", "integral_Hx", "integral_Hy", "integral_Hz"),
                         solver, counts, t, tol=SOLVER_TOL, bulk=False)
    rec["integral_H"] = [rec.pop(k) for k in ("integral_Hx", "integral_Hy", "integral_Hz")]
    if exact is None:
        rec.pop("l2_error")
    if exact is not None and getattr(phi, "area", None) is not None:
        rec["area_error"] = abs(rec["area"] - phi.area)
    if notes:
        rec["warnings"] = notes
    return rec
