"""The partition of an unstructured background (a :class:`~cutfem.geometry.mesh.TetMesh`) across ranks.

Cells.  Recursive coordinate bisection of the cell centroids (:func:`recursive_bisection`): the
ranks are halved, and the cells split along the longest side of their centroids' bounding box at
the matching share of their number, until one rank is left.  Every cell weighs the same: weighting
by the active cells would need phi at every node of the mesh before the partition, on every rank
(for a signed distance to a surface mesh, the dominant cost of the geometry).  Ties are broken by
the cell id, so every rank computes the same partition.  A partition may also be given by hand
(an owner per cell, for ranks without cells).

Ghosts.  Rank r holds its owned cells and one layer of ghost cells: the cells across a facet of an
owned cell that another rank owns.  It cuts two local meshes (:class:`SubMesh`, the cells in
increasing global id, their nodes in increasing global id, so that the local element sets, faces
and unknowns come in the serial order): the owned cells, for every cell integral and the facets
between two owned cells; and its *seam*, the ghost cells with the owned cells next to them, for the
facets between an owned cell and a ghost.  Such a facet is assembled by the owner of its cell with
the larger global id (:meth:`~cutfem.distributed.partition.RankCuts.seam_facets`), so every facet
is assembled once.

Nodal values.  The level set is evaluated at the global coordinates of the rank's nodes and the
zero rule applied with its serial tolerance (:func:`cutfem.geometry.nodal_values._zero_tolerance`:
1e-12 of the largest |phi| over the node's tets, all of them, also those the rank does not hold):
the values are computed on the *ring*, the cells that touch a node of the rank, whose nodes are
the neighbours of every node of the rank (:meth:`CellPartition.local_levelsets`).  The cuts then
take these values, so the nodal values, the pieces of Gamma_h and every element matrix are the
serial ones, with no caveat at the seam.

Nodes.  A node is owned by the owner of the lowest-id cell around it, a rule every rank evaluates
on the whole mesh (:meth:`CellPartition.node_owner`).  Every rank holds the whole mesh (points,
tets, faces, centroids; a mesh file or pytetwild gives it whole): memory O(cells) per rank, the
cut, the assembly and the solve on the rank's share.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from ..geometry.mesh import TetMesh
from ..geometry.nodal_values import snapped_nodal_values

__all__ = ["CellPartition", "SubMesh", "cell_partition", "recursive_bisection"]


def recursive_bisection(points, size: int) -> np.ndarray:
    """(n,) the rank of each of ``points`` (n, 3): ``size`` ranks halved recursively (the left
    half ``size // 2`` ranks), the points split along the longest side of their bounding box at
    the share of the left half (ties by the point's index).  Every rank gets ``n // size`` or one
    more point."""
    points = np.asarray(points, dtype=float)
    owner = np.empty(len(points), dtype=np.int64)
    stack = [(np.arange(len(points)), 0, int(size))]
    while stack:
        ids, first, n = stack.pop()
        if n == 1:
            owner[ids] = first
            continue
        left = n // 2
        x = points[ids]
        axis = int(np.argmax(x.max(axis=0) - x.min(axis=0))) if len(ids) else 0
        order = np.lexsort((ids, x[:, axis]))
        split = len(ids) * left // n
        stack += [(ids[order[:split]], first, left), (ids[order[split:]], first + left, n - left)]
    return owner


class SubMesh(TetMesh):
    """The cells ``tet_ids`` of a mesh ``parent`` as a mesh of their own: the cells in increasing
    global id, their nodes in increasing global id, the coordinates the parent's.  ``h`` is the
    parent's global mesh size."""

    def __init__(self, parent: TetMesh, tet_ids):
        tet_ids = np.unique(np.asarray(tet_ids, dtype=np.int64))
        nodes, local = np.unique(parent.tets[tet_ids], return_inverse=True)
        super().__init__(parent.points[nodes], local.reshape(-1, 4), check=False)
        self.parent, self._nodes, self._tets = parent, nodes, tet_ids

    @property
    def h(self) -> float:
        return self.parent.h

    def global_nodes(self, local_ids) -> np.ndarray:
        return self._nodes[np.asarray(local_ids, dtype=np.int64)]

    def global_tets(self, local_ids) -> np.ndarray:
        return self._tets[np.asarray(local_ids, dtype=np.int64)]


class CellPartition:
    """The cells of ``mesh`` owned by each of ``size`` ranks (``owner`` (M,)), with the ghost
    layer and the nodal values of each rank (see the module docstring)."""

    def __init__(self, mesh: TetMesh, owner, size: int):
        self.mesh, self.owner, self.size = mesh, np.asarray(owner, dtype=np.int64), int(size)

    @cached_property
    def _node_owner(self) -> np.ndarray:
        """(N,) the owner of the lowest-id cell around each node (-1 for points no cell uses)."""
        flat = self.mesh.tets.reshape(-1)
        order = np.argsort(flat, kind="stable")  # stable: a node's first entry is its lowest-id cell
        nodes = flat[order]
        first = np.concatenate([[True], nodes[1:] != nodes[:-1]]) if len(nodes) else np.zeros(0, bool)
        out = np.full(self.mesh.n_points, -1, dtype=np.int64)
        out[nodes[first]] = self.owner[order[first] // 4]
        return out

    def node_owner(self, node_ids) -> np.ndarray:
        """The rank owning each (global) node: the owner of the lowest-id cell around it."""
        return self._node_owner[np.asarray(node_ids, dtype=np.int64)]

    def cell_owner(self, tet_ids) -> np.ndarray:
        return self.owner[np.asarray(tet_ids, dtype=np.int64)]

    def cells(self, rank: int) -> np.ndarray:
        """The global ids of the rank's cells, increasing."""
        return np.flatnonzero(self.owner == rank)

    def ghosts(self, rank: int) -> np.ndarray:
        """The rank's ghost cells: those across a facet of its cells that another rank owns."""
        pairs = self.mesh.face_tets[self.mesh.interior_faces]
        mine = self.owner[pairs] == rank
        across = mine[:, 0] != mine[:, 1]
        return np.unique(np.where(mine[across, 0], pairs[across, 1], pairs[across, 0]))

    def local_meshes(self, rank: int):
        """``(owned, seam)``: the rank's cells, and its ghosts with the owned cells next to them, as
        :class:`SubMesh` (None where the rank has none)."""
        cells = self.cells(rank)
        if not len(cells):
            return None, None
        ghosts = self.ghosts(rank)
        if not len(ghosts):
            return SubMesh(self.mesh, cells), None
        ghost = np.zeros(self.mesh.n_tets, dtype=bool)
        ghost[ghosts] = True
        pairs = self.mesh.face_tets[self.mesh.interior_faces]
        edge = ghost[pairs[:, ::-1]] & (self.owner[pairs] == rank)  # an owned cell with a ghost across the facet
        return SubMesh(self.mesh, cells), SubMesh(self.mesh, np.concatenate([ghosts, pairs[edge]]))

    def local_levelsets(self, rank: int, levelset, meshes):
        """The nodal values (snapped by the zero rule as serially) at the nodes of each of
        ``meshes`` (local meshes of the rank, or None), for :func:`~cutfem.geometry.cut.cut_mesh`:
        computed on the ring, the cells that touch a node of the rank.  ``levelset``: a function or
        the values at every node of the mesh (N,)."""
        held = [m for m in meshes if m is not None]
        mark = np.zeros(self.mesh.n_points, dtype=bool)
        for m in held:
            mark[m.global_nodes(np.arange(m.n_points))] = True
        ring = SubMesh(self.mesh, np.flatnonzero(mark[self.mesh.tets].any(axis=1)))
        nodes = ring.global_nodes(np.arange(ring.n_points))
        if isinstance(levelset, np.ndarray):
            if levelset.size != self.mesh.n_points:
                raise ValueError(f"got {levelset.size} nodal values for a mesh of {self.mesh.n_points} nodes")
            levelset = np.asarray(levelset, dtype=float).reshape(-1)[nodes]
        values = snapped_nodal_values(ring, levelset)
        return [None if m is None else values[np.searchsorted(nodes, m.global_nodes(np.arange(m.n_points)))] for m in meshes]


def cell_partition(mesh: TetMesh, size: int, owner=None) -> CellPartition:
    """The cells of ``mesh`` over ``size`` ranks by recursive coordinate bisection of their
    centroids, or by the ``owner`` given (M,) (a rank in [0, size) for every cell: for ranks
    without cells or without active cells)."""
    if owner is None:
        owner = recursive_bisection(mesh.points[mesh.tets].mean(axis=1), size)
    owner = np.asarray(owner)
    if owner.shape != (mesh.n_tets,) or not np.issubdtype(owner.dtype, np.integer) or np.any((owner < 0) | (owner >= size)):
        raise ValueError(f"owner must give each of the mesh's {mesh.n_tets} cells a rank in [0, {size}), got an array of shape "
                         f"{owner.shape} and dtype {owner.dtype}")
    return CellPartition(mesh, owner, size)
