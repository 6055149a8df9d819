"""One level of a problem on all ranks: partition, pieces, PETSc solve, sums over the ranks.

:func:`solve_on_slabs` is the skeleton the distributed problems share: the box in slabs and each
rank's cuts (:mod:`~cutfem.distributed.partition`), the problem's pieces
(:func:`~cutfem.distributed.assembly.slab_pieces`), the system on PETSc and its solve
(:mod:`~cutfem.distributed.system`), then the problem's additive measures of the solution on the
owned cells (squared errors, volumes) summed over the ranks.  The record is the same on every rank;
the stage times are the slowest rank's.
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry.markers import CUT
from ..runs.runner import Timer
from ..solvers.krylov import DEFAULT_TOL
from .assembly import global_keys, slab_system
from .launch import engine
from .partition import rank_cuts, slab_partition
from .preconditioners import lattice_prolongations

__all__ = ["solve_on_slabs", "cut_counts", "nodal_levelset", "STAGES"]

#: the stages of a distributed level, timed on each rank (the record keeps the slowest rank's)
STAGES = ("geometry", "assembly", "solve", "errors")


def cut_counts(cuts, parts) -> dict:
    """The rank's share of the cut's sizes (:func:`cutfem.problems.common.cut_record`): added over
    the ranks they are the serial record's."""
    out = {"active_tets": 0, "pieces": 0, "surface_triangles": 0, "interior_faces": 0}
    if cuts.owned is not None:
        c = cuts.owned
        fields = getattr(parts.space, "fields", None) or [parts.space]  # a product space's tets: the union of its fields'
        out["active_tets"] = len(np.unique(np.concatenate([f.elements.tet_ids for f in fields])))
        out["pieces"], out["surface_triangles"] = int(c.n_tets), int(c.n_triangles)
        out["interior_faces"] = c.interior_facets().n_facets if c.n_tets else 0
    if cuts.seam is not None and cuts.seam.n_tets:
        out["interior_faces"] += cuts.seam_facets(cuts.seam.interior_facets(CUT)).n_facets
    return out


def nodal_levelset(cuts, nodes) -> np.ndarray:
    """phi_h at the global background nodes ``nodes`` (active nodes this rank owns), from the owned
    cut and the seam cut, one of which holds every tet around an owned node: the serial nodal values."""
    ids, values = [np.zeros(0, np.int64)], [np.zeros(0)]
    for cut in (cuts.owned, cuts.seam):
        if cut is not None:
            ids.append(cut.background.global_nodes(cut.node_ids))
            values.append(cut.values)
    ids, first = np.unique(np.concatenate(ids), return_index=True)
    return np.concatenate(values)[first][np.searchsorted(ids, nodes)]


def solve_on_slabs(comm, levelset, background, build, measure, keys, solver="auto", counts=None, timer=None,
                   tol: float = DEFAULT_TOL, bulk: bool = True, fields: int = 1, constrain=None) -> dict:
    """Solve one level of a problem on the ranks of ``comm``; returns the record's common part.

    ``build(cuts)``: the rank's :class:`~cutfem.distributed.assembly.SlabPieces`;
    ``measure(space, u)``: additive numbers of the solution ``u`` (the values at the owned space's
    unknowns, (n, k) for k loads) over the owned cells, one for each of ``keys``; keys with
    ``_error`` in them are sums of squares whose square roots are recorded.  ``counts``: the cell layers of
    each rank; ``tol``: the relative residual of CG; ``bulk``: the unknowns fill a volume (for the
    choice of ``solver="auto"``, :meth:`~cutfem.distributed.system.LinearSystem.solve`); ``fields``:
    the fields of a product space; ``constrain(A, loads, numbering, parts)``: strong conditions
    applied to the PETSc system before the solve."""
    MPI, _ = engine()
    t = Timer() if timer is None else timer
    with t("geometry"):
        slabs = slab_partition(background, comm.size, counts)
        cuts = rank_cuts(slabs, comm.rank, levelset)
    with t("assembly"):
        parts = build(cuts)
        system, numbering = slab_system(parts, cuts, comm, fields)
        A, loads = system.petsc()
        if constrain is not None:
            constrain(A, loads, numbering, parts)
    with t("solve"):
        def hierarchy():  # one field on the structured box: the lattice multigrid, doubled by phi_h for a surface field
            nodes = numbering.owned_keys
            return lattice_prolongations(comm, slabs, nodes, None if bulk else nodal_levelset(cuts, nodes))

        xs, info = system.solve(A, loads, solver, tol, bulk, hierarchy if fields == 1 else None)
    with t("errors"):
        sums = np.zeros(len(keys))
        V = parts.space
        has = V is not None and V.n_dofs
        dofs = numbering(global_keys(V)) if has else np.zeros(0, np.int64)
        values = [system.gather(x, dofs) for x in xs]  # a collective scatter: every rank, with or without unknowns
        if has:
            sums[:] = measure(V, np.stack(values, axis=1) if len(xs) > 1 else values[0])
        comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
    for obj in (A, *loads, *xs):
        obj.destroy()
    sizes = {k: int(comm.allreduce(v, op=MPI.SUM)) for k, v in (cut_counts(cuts, parts) | {"stabilized_faces": parts.faces}).items()}
    times = np.array([t.get(k, 0.0) for k in STAGES])
    comm.Allreduce(MPI.IN_PLACE, times, op=MPI.MAX)
    values = {k: math.sqrt(v) if "_error" in k else float(v) for k, v in zip(keys, sums)}
    return {
        "h": background.h,
        "dofs": numbering.n_global,
        **values,
        "solver": f"{info['ksp']}+{info['pc']}",
        "solver_iterations": info.pop("iterations"),
        **info,
        "box": [background.lower.tolist(), background.upper.tolist()],
        "background_nodes": int(background.n_points),
        **sizes,
        "time": dict(zip(STAGES, times.tolist())),
    }
