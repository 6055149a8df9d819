"""poisson-cut on several ranks: the fictitious-domain Poisson problem of docs/math.md §8, its
forms assembled by slab (:mod:`cutfem.distributed.partition`) and solved by PETSc.

The forms are the serial problem's (:mod:`cutfem.problems.poisson`): on the rank's owned slab the
stiffness, Nitsche's terms, the load and the ghost penalty of the faces inside the slab; on its
seam the ghost penalty of the faces that cross its lowest plane.  Each is assembled by the serial
code on the slab's own space and moved to the global numbers (:class:`~cutfem.distributed.system.
GlobalNumbering`), so the matrix, the load and the solution are the serial ones up to the order of
the floating-point sums, and so are the errors (sums of squares over the owned cells, added over
the ranks).
"""

from __future__ import annotations

import math

import numpy as np

from ..fem.norms import l2_h1_errors
from ..fem.terms import face_jump_penalty, load, nitsche, stiffness
from ..geometry.markers import CUT, NEG
from ..problems.common import background_for, check_ghost_penalty, check_nitsche_penalty, levelset_for
from ..problems.poisson import exact_solution, exact_u, source
from ..runs.runner import Timer
from .launch import engine
from .partition import rank_cuts, slab_partition
from .assembly import slab_pieces, slab_system

__all__ = ["poisson_cut_level", "poisson_pieces", "cut_counts"]


def poisson_pieces(cuts, gamma: float, gamma_g: float):
    """The rank's pieces of the poisson-cut system (:func:`~cutfem.distributed.assembly.slab_pieces`):
    stiffness, Nitsche's terms and the load on the owned slab, the ghost penalty on every face once."""

    def cells(cut, V):
        dx = cut.dx(NEG)
        a, rhs = stiffness(dx), load(source, dx, degree=2)
        if cut.n_tets:  # a slab that the surface misses has no Gamma_h
            N = nitsche(cut.ds(), gamma, g=exact_u)
            a, rhs = a + N, rhs + N.load
        return a, rhs

    if gamma_g == 0:
        return slab_pieces(cuts, NEG, cells)
    return slab_pieces(cuts, NEG, cells, lambda cut: cut.ghost_facets(NEG),
                       lambda dF: gamma_g * face_jump_penalty(dF, h_power=1))


def cut_counts(cuts) -> dict:
    """The rank's share of the cut's sizes (summed over the ranks they are those of the serial
    record, :func:`cutfem.problems.common.cut_record`)."""
    out = {"active_tets": 0, "pieces": 0, "surface_triangles": 0, "interior_faces": 0}
    if cuts.owned is not None:
        c = cuts.owned
        out["active_tets"] = len(c.elements(NEG).tet_ids)
        out["pieces"], out["surface_triangles"] = int(c.n_tets), int(c.n_triangles)
        out["interior_faces"] = c.interior_facets().n_facets if c.n_tets else 0
    if cuts.seam is not None and cuts.seam.n_tets:
        out["interior_faces"] += cuts.seam_facets(cuts.seam.interior_facets(CUT)).n_facets
    return out


def poisson_cut_level(spacing, surface, background, box, gamma, gamma_g, solver, R, r, radius, axes, comm=None, counts=None):
    """One level of poisson-cut on the ranks of ``comm`` (default: every rank); the record of the
    serial :func:`cutfem.problems.poisson.poisson_cut` with the engine (PETSc, its KSP and PC) and
    the number of ranks, the same on every rank.  ``counts``: the cell layers of each rank (see
    :func:`~cutfem.distributed.partition.slab_partition`)."""
    MPI, _ = engine()
    comm = MPI.COMM_WORLD if comm is None else comm
    if background != "structured":
        raise ValueError(f"distributed poisson-cut partitions a structured box; got --background {background}: "
                         "run an unstructured background on one rank")
    notes = check_ghost_penalty(gamma_g) + check_nitsche_penalty(gamma)
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius, axes)
        bg = background_for(phi, spacing, background, box)
        slabs = slab_partition(bg, comm.size, counts)
        cuts = rank_cuts(slabs, comm.rank, phi)
    with t("assembly"):
        parts = poisson_pieces(cuts, gamma, gamma_g)
        system, numbering = slab_system(parts, cuts, comm)
        A, b = system.petsc()
    with t("solve"):
        x, info = system.solve(A, b, solver)
    with t("errors"):
        squares = np.zeros(3)
        V = parts.space
        if V is not None and V.n_dofs:
            u = system.gather(x, numbering(V.cut.background.global_nodes(V.node_ids)))
            dx = V.cut.dx(NEG)
            l2, h1 = l2_h1_errors(V, u, exact_solution, dx)
            squares[:] = l2 * l2, h1 * h1, dx.size
        squares = comm.allreduce(squares, op=MPI.SUM)
    sizes = {k: int(comm.allreduce(v, op=MPI.SUM)) for k, v in (cut_counts(cuts) | {"ghost_faces": parts.faces}).items()}
    times = comm.allreduce(np.array([t.get(k, 0.0) for k in ("geometry", "assembly", "solve", "errors")]), op=MPI.MAX)
    for obj in (A, b, x):
        obj.destroy()
    rec = {
        "h": bg.h,
        "dofs": numbering.n_global,
        "l2_error": math.sqrt(squares[0]),
        "h1_error": math.sqrt(squares[1]),
        "volume": float(squares[2]),
        "solver": f"{info['ksp']}+{info['pc']}",
        "solver_iterations": info["iterations"],
        **info,
        "box": [bg.lower.tolist(), bg.upper.tolist()],
        "background_nodes": int(bg.n_points),
        **sizes,
        "time": dict(zip(("geometry", "assembly", "solve", "errors"), times.tolist())),
    }
    if notes:
        rec["warnings"] = notes
    return rec
