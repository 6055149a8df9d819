"""One level of a problem on all ranks: background, partition, pieces, PETSc solve, sums over the ranks.

:func:`solve_on_ranks` is the skeleton the distributed problems share: the background partitioned
(a structured box in slabs, an unstructured mesh by recursive bisection of its cells) and each
rank's cuts (:mod:`~cutfem.distributed.partition`), the problem's pieces
(:func:`~cutfem.distributed.assembly.rank_pieces`), the system on PETSc and its solve
(:mod:`~cutfem.distributed.system`), then the problem's additive measures of the solution on the
owned cells (squared errors, volumes) summed over the ranks.  The record is the same on every rank;
the stage times are the slowest rank's.  :func:`shared_background` gives every rank the same
background mesh.
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry.box import StructuredBox
from ..geometry.markers import CUT
from ..geometry.mesh import TetMesh
from ..problems.common import active_tets, background_for
from ..runs.runner import Timer
from ..solvers.krylov import DEFAULT_TOL
from .assembly import global_keys, rank_system
from .launch import engine
from .partition import Slabs, partition_for, rank_cuts
from .preconditioners import lattice_prolongations

__all__ = ["solve_on_ranks", "shared_background", "cut_counts", "nodal_levelset", "p2_levelset", "p2_points", "STAGES"]

#: the stages of a distributed level, timed on each rank (the record keeps the slowest rank's)
STAGES = ("geometry", "assembly", "solve", "errors")


def cut_counts(cuts, parts) -> dict:
    """The rank's share of the cut's sizes (:func:`cutfem.problems.common.cut_record`): added over
    the ranks they are the serial record's."""
    out = {"active_tets": 0, "pieces": 0, "surface_triangles": 0, "interior_faces": 0}
    if cuts.owned is not None:
        c = cuts.owned
        out["active_tets"] = active_tets(c, parts.space)
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


def p2_points(slabs, units) -> np.ndarray:
    """The points of the P2 nodes ``units`` of the structured box of ``slabs``
    (:meth:`~cutfem.distributed.partition.Slabs.p2_ends`): the node, or the mean of the edge's
    ends, bit for bit the serial space's ``dof_points``."""
    v, w = slabs.p2_ends(units)
    x = slabs.box.node_coordinates(v)
    return np.where((w > v)[:, None], 0.5 * (x + slabs.box.node_coordinates(w)), x)


def p2_levelset(cuts, units) -> np.ndarray:
    """phi_h (the P1 interpolant) at the P2 nodes ``units`` this rank owns: the nodal value at a
    vertex, the mean of the ends' at an edge's midpoint, as the serial ``interpolate_nodal``."""
    v, w = cuts.partition.p2_ends(units)
    a, b = nodal_levelset(cuts, v), nodal_levelset(cuts, w)
    return np.where(w > v, 0.5 * (a + b), a)


def solve_on_ranks(comm, levelset, background, build, measure, keys, solver="auto", counts=None, timer=None,
                   tol: float = DEFAULT_TOL, bulk: bool = True, fields: int = 1, constrain=None, constants: int = 0,
                   solve=None, order: int = 1) -> dict:
    """Solve one level of a problem on the ranks of ``comm``; returns the record's common part.

    ``build(cuts)``: the rank's :class:`~cutfem.distributed.assembly.RankPieces`;
    ``measure(space, u)``: additive numbers of the solution ``u`` (the values at the owned space's
    unknowns, (n, k) for k loads) over the owned cells, one for each of ``keys``; keys with
    ``_error`` in them are sums of squares whose square roots are recorded.  ``counts``: the cell
    layers of each rank (a structured box) or the owner of each cell (an unstructured mesh), given
    by hand (:func:`~cutfem.distributed.partition.partition_for`); ``tol``: the relative residual
    of CG; ``bulk``: the unknowns fill a volume (for the choice of ``solver="auto"``,
    :meth:`~cutfem.distributed.system.LinearSystem.solve`); ``fields``: the fields of a product
    space; ``constrain(A, loads, numbering, parts)``: strong conditions applied to the PETSc system
    before the solve; ``constants``: the one-unknown fields (keyed -1, -2, ...:
    :class:`~cutfem.distributed.system.GlobalNumbering`); ``solve(system, A, loads, parts,
    hierarchy)``: ``([x, ...], info)`` in place of :meth:`~cutfem.distributed.system.LinearSystem.solve`
    (a saddle-point system's, :mod:`cutfem.distributed.saddle`), ``hierarchy(nodes, components, constants)``
    the lattice prolongations of a field at its owned nodes on the structured box, None on an
    unstructured mesh; ``order`` 2: the cuts lifted by Theta_h
    (:func:`~cutfem.distributed.partition.rank_cuts`) for the P2 fields of ``build``."""
    MPI, _ = engine()
    t = Timer() if timer is None else timer
    with t("geometry"):
        cuts = rank_cuts(partition_for(background, comm.size, counts), comm.rank, levelset, order)
    with t("assembly"):
        parts = build(cuts)
        for cut in (cuts.owned, cuts.seam):  # the forms are assembled: their measures' memory serves PETSc's matrix and solve
            if cut is not None:
                cut.release_measures()
        system, numbering = rank_system(parts, cuts, comm, fields, constants)
        A, loads = system.petsc()
        if constrain is not None:
            constrain(A, loads, numbering, parts)
    with t("solve"):
        def hierarchy(nodes=None, components=1, constants=0):
            """The lattice multigrid below ``nodes`` (the owned nodes of a field, default: the one
            field's unknowns), each coarse space doubled by w v (:func:`augment`)."""
            nodes = numbering.owned_keys if nodes is None else nodes
            return lattice_prolongations(comm, cuts.partition, nodes, augment(nodes), components=components,
                                         constants=constants, order=order)

        def augment(nodes):  # as the serial problems: a surface field phi_h (P1) or phi_h and phi_h^2 (P2), a P2
            if bulk:         # bulk field (phi)_+, a P1 bulk field none
                return np.maximum(levelset.value(p2_points(cuts.partition, nodes)), 0.0) if order == 2 else None
            if order == 1:
                return nodal_levelset(cuts, nodes)
            w = p2_levelset(cuts, nodes)
            return np.column_stack([w, w**2])

        lattice = isinstance(cuts.partition, Slabs)  # an unstructured mesh has no lattice hierarchy
        xs, info = (system.solve(A, loads, solver, tol, bulk, hierarchy if lattice and fields == 1 else None) if solve is None
                    else solve(system, A, loads, parts, hierarchy if lattice else None))
    for obj in (A, *loads):  # before the errors, whose measure is built again in the memory they free
        obj.destroy()
    with t("errors"):
        sums = np.zeros(len(keys))
        V = parts.space
        has = V is not None and V.n_dofs
        dofs = numbering(global_keys(V)) if has else np.zeros(0, np.int64)
        values = [system.gather(x, dofs) for x in xs]  # a collective scatter: every rank, with or without unknowns
        if has:
            sums[:] = measure(V, np.stack(values, axis=1) if len(xs) > 1 else values[0])
        comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
    for x in xs:
        x.destroy()
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
        **({"box": [background.lower.tolist(), background.upper.tolist()]} if isinstance(background, StructuredBox) else {}),
        "background_nodes": int(background.n_used_points),
        **sizes,
        "time": dict(zip(STAGES, times.tolist())),
    }


def shared_background(comm, levelset, spacing, background, box) -> TetMesh:
    """The background of a level, the same on every rank of ``comm``: a TetMesh given (a script's
    mesh, e.g. :func:`~cutfem.geometry.mesh.read_mesh` of one file on every rank; refused unless
    its sizes and sums agree on all ranks), the structured box built by each rank (a few numbers),
    or pytetwild's mesh (``"tetwild"``) built by rank 0 and broadcast: two meshings of the same box
    by pytetwild differ."""
    MPI, _ = engine()
    if isinstance(background, TetMesh):
        signature = ((background.lower.tolist(), background.upper.tolist(), background.cells.tolist())
                     if isinstance(background, StructuredBox) else  # its numbers, never its coordinates
                     (background.n_points, background.n_tets, float(background.points.sum()), int(background.tets.sum())))
        if any(other != signature for other in comm.allgather(signature)):
            raise ValueError("the ranks were given different background meshes (their sizes or sums differ): give every rank "
                             "the same mesh, e.g. read the same file on every rank")
        return background
    if background == "structured" or comm.size == 1:
        return background_for(levelset, spacing, background, box)
    mesh = background_for(levelset, spacing, background, box) if comm.rank == 0 else None
    shapes = comm.bcast(None if mesh is None else (mesh.points.shape, mesh.tets.shape), root=0)
    points = mesh.points if mesh is not None else np.empty(shapes[0])
    tets = mesh.tets if mesh is not None else np.empty(shapes[1], dtype=np.int64)
    comm.Bcast([points, MPI.DOUBLE], root=0)
    comm.Bcast([tets, MPI.INT64_T], root=0)
    return mesh if mesh is not None else TetMesh(points, tets, check=False)  # rank 0 checked and oriented it
