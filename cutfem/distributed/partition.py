"""The partition of the background across ranks, and each rank's cuts.

Two partitions, one contract (:func:`partition_for`): a structured box in slabs of cell layers
(:class:`Slabs`, below), any other :class:`~cutfem.geometry.mesh.TetMesh` by recursive coordinate
bisection of its cells (:class:`~cutfem.distributed.unstructured.CellPartition`).  Each gives a rank
two local meshes, its **owned** cells and its **seam** (a layer of ghost cells across the facets
of its owned cells, with the owned cells next to them), the owner of every cell and node, and the
nodal values its cuts take; :func:`rank_cuts` cuts both, and a facet between an owned cell and a
ghost is assembled by the owner of its cell with the larger global id
(:meth:`RankCuts.seam_facets`), so every facet once.  The box keeps its slabs rather than becoming
a case of the cell partition: the slabs never form the box's tets, coordinates, centroids or faces
(the cell partition holds them whole on every rank, O(cells) memory, 6 n^3 tets for n^3 cells) and
their cuts take the lattice's path (the band search evaluates the level set near the surface only,
the Kuhn tables replace per-tet gradients); the rest (the seam rule, the numbering, the assembly)
is one code path for both.

Slabs
-----
The cells of a :class:`~cutfem.geometry.box.StructuredBox` are split in blocks of whole layers
along the slowest axis z: rank r owns the cell layers ``[starts[r], starts[r + 1])``, so its cells
(and tets) have contiguous global ids, and so do the nodes of its layers.  A rank may own no layer
(more ranks than layers, or a split given by hand).

A :class:`SlabBox` is the structured box of some consecutive cell layers whose node coordinates are
computed from the *global* node indices by the global box (``lower + ijk * spacing`` with the global
``lower`` and ``ijk``), so that the level set's nodal values on a slab are bit for bit those of the
serial run, and so are the cut, the quadrature points and the element matrices of every tet.

Each rank cuts two slabs: its **owned** slab ``[k0, k1)`` and the **seam** ``[k0 - 1, k0 + 1)``,
whose lower layer is the rank's layer of ghost cells across the facets of its lowest owned layer.
The facets between two layers belong to the owner of the upper tet (the larger global id), so the
seam's facets across the plane z = z_k0 are this rank's, and no ghost layer above is needed: the
faces of the upper ghost layer are those of the next rank's seam.  Which tets are active and which
facets are ghost-penalty facets depends only on the nodal values of the tets concerned, so it is
the same on every rank that holds them.  One caveat is inherited from the zero rule
(:func:`cutfem.geometry.nodal_values._zero_tolerance`): the snap tolerance of a node is 1e-12 of
the largest value in its 3 x 3 x 3 block, which a slab truncates at its faces; a nodal value within
1e-12 of its neighbours' scale of zero may snap differently there (the cell partition evaluates the
tolerance on all the node's cells and has no such caveat).

At order 2 the cuts are lifted by Theta_h, whose shift of a P2 node is a mean over the node's cut
tets, which for a node on a slab's top plane lie in the next rank's layer too: each rank computes
Theta_h on its :meth:`Slabs.lifting_mesh` (its layers, the seam's ghost layer and one more layer
above) and moves it onto both cuts, so the shifts it uses are the serial ones (docs/math.md §19).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.box import StructuredBox
from ..geometry.cut import CutMesh, cut_mesh
from ..geometry.mesh import TetMesh
from ..geometry.nodal_values import CutError
from .unstructured import cell_partition

__all__ = ["P2_SLOTS", "Slabs", "SlabBox", "slab_partition", "partition_for", "rank_cuts", "RankCuts", "local_cut"]


#: the unknowns of a P2 field per lattice node of a structured box, keyed ``8 v + c``: the node v
#: (c = 0) and the midpoints of the Kuhn edges {v, v + e_S} above it (c = c(S) in 1..7,
#: :data:`cutfem.geometry.box.KUHN_EDGE_CODES`)
P2_SLOTS = 8


@dataclass(frozen=True)
class Slabs:
    """The cell layers of each rank: rank r owns z-layers ``starts[r]`` to ``starts[r + 1] - 1``."""

    box: StructuredBox
    starts: np.ndarray  # (size + 1,) nondecreasing, starts[0] = 0, starts[-1] = nz

    @property
    def size(self) -> int:
        return len(self.starts) - 1

    def layers(self, rank: int) -> tuple[int, int]:
        return int(self.starts[rank]), int(self.starts[rank + 1])

    def layer_owner(self, layers) -> np.ndarray:
        """The rank owning each cell layer (the last rank whose start is at or below it: ranks
        without layers own none)."""
        return np.searchsorted(self.starts, np.asarray(layers), side="right") - 1

    def node_owner(self, node_ids) -> np.ndarray:
        """The rank owning each (global) node: the owner of the cell layer of the node's z index
        (the top node layer goes to the owner of the top cell layer)."""
        k = np.asarray(node_ids, dtype=np.int64) // int(self.box.node_shape[0] * self.box.node_shape[1])
        return self.layer_owner(np.minimum(k, int(self.box.cells[2]) - 1))

    def p2_ends(self, units):
        """The global node ids (v, w) of the ends of the P2 nodes ``units`` (``8 v + c``,
        :data:`P2_SLOTS`): w = v + e_S for the midpoint of the edge of code c = c(S), w = v for
        the vertex (c = 0)."""
        units = np.asarray(units, dtype=np.int64)
        v, c = units // P2_SLOTS, units % P2_SLOTS
        nx, ny = (int(n) for n in self.box.node_shape[:2])
        return v, v + (c & 1) + nx * ((c >> 1) & 1) + nx * ny * (c >> 2)

    def cell_owner(self, tet_ids) -> np.ndarray:
        """The rank owning each (global) tet: the owner of its cell layer."""
        return self.layer_owner(np.asarray(tet_ids, dtype=np.int64) // (6 * int(self.box.cells[0]) * int(self.box.cells[1])))

    def local_meshes(self, rank: int):
        """``(owned, seam)``: the rank's slab ``[k0, k1)`` and its seam ``[k0 - 1, k0 + 1)`` (None
        without layers, and the seam None on the lowest layer)."""
        k0, k1 = self.layers(rank)
        if k1 == k0:
            return None, None
        return SlabBox(self.box, k0, k1), SlabBox(self.box, k0 - 1, k0 + 1) if k0 > 0 else None

    def lifting_mesh(self, rank: int):
        """The slab on which the rank computes Theta_h at order 2: its layers with one more below
        and one more above (within the box), so that every P2 node of its owned and seam cells has
        all its cut tets there (module docstring)."""
        k0, k1 = self.layers(rank)
        return SlabBox(self.box, max(k0 - 1, 0), min(k1 + 1, int(self.box.cells[2])))

    def local_levelsets(self, rank: int, levelset, meshes):
        """What the cut of each local mesh takes: the level set itself (a slab evaluates it at the
        global coordinates of its nodes)."""
        return [levelset for _ in meshes]


def slab_partition(box: StructuredBox, size: int, counts=None) -> Slabs:
    """The block split of the ``nz`` cell layers of ``box`` over ``size`` ranks (the first
    ``nz % size`` ranks one layer more), or the layer ``counts`` per rank given (any nonnegative
    whole numbers summing to nz: for ranks without cells)."""
    if not isinstance(box, StructuredBox):
        raise TypeError(f"slabs split a structured box (cf.structured_box), got {type(box).__name__}: partition_for "
                        "splits any background")
    nz = int(box.cells[2])
    if counts is None:
        counts = [nz // size + (r < nz % size) for r in range(size)]
    counts = np.asarray(counts, dtype=np.int64)
    if counts.shape != (size,) or np.any(counts < 0) or int(counts.sum()) != nz:
        raise ValueError(f"counts must be {size} nonnegative whole numbers of cell layers summing to the box's {nz} layers, "
                         f"got {counts.tolist()}")
    return Slabs(box, np.concatenate([[0], np.cumsum(counts)]))


class SlabBox(StructuredBox):
    """The cell layers ``[k0, k1)`` of a structured box ``parent``, as a structured box of its own
    (local ids: node (i, j, k) of the slab is node (i, j, k0 + k) of the parent), whose coordinates
    are the parent's of the global indices, bit for bit.  ``h`` is the parent's global mesh size."""

    def __init__(self, parent: StructuredBox, k0: int, k1: int):
        nx, ny, nz = (int(c) for c in parent.cells)
        if not 0 <= k0 < k1 <= nz:
            raise ValueError(f"a slab needs 0 <= k0 < k1 <= {nz} cell layers, got [{k0}, {k1})")
        self.parent, self.k0, self.k1 = parent, int(k0), int(k1)
        self.node_offset = self.k0 * (nx + 1) * (ny + 1)
        self.tet_offset = 6 * self.k0 * nx * ny
        lower, upper = parent.coordinates(np.array([[0, 0, k0], [nx, ny, k1]]))
        super().__init__(lower, upper, (nx, ny, k1 - k0), spacing=parent.spacing)

    def node_coordinates(self, ids) -> np.ndarray:
        return self.parent.node_coordinates(np.asarray(ids, dtype=np.int64) + self.node_offset)

    def coordinates(self, ijk) -> np.ndarray:
        return self.parent.coordinates(np.asarray(ijk) + np.array([0, 0, self.k0]))

    @property
    def h(self) -> float:
        return self.parent.h

    def global_nodes(self, local_ids) -> np.ndarray:
        return np.asarray(local_ids, dtype=np.int64) + self.node_offset

    def global_tets(self, local_ids) -> np.ndarray:
        return np.asarray(local_ids, dtype=np.int64) + self.tet_offset


def partition_for(background, size: int, given=None):
    """The partition of ``background`` over ``size`` ranks: a structured box in slabs
    (:func:`slab_partition`, ``given`` the cell layers of each rank), any other TetMesh by
    recursive coordinate bisection (:func:`~cutfem.distributed.unstructured.cell_partition`,
    ``given`` the owner of each cell)."""
    if isinstance(background, StructuredBox):
        return slab_partition(background, size, given)
    if isinstance(background, TetMesh):
        return cell_partition(background, size, given)
    raise TypeError(f"a distributed run partitions a background TetMesh (a structured box or an unstructured mesh), got "
                    f"{type(background).__name__}")


def _no_cut(message: str) -> bool:
    """Whether a CutError of :func:`~cutfem.geometry.cut.cut_mesh` says that no tet carries a piece
    of S_h (the local mesh lies on one side), which on a part of a larger mesh is no error."""
    return message.startswith(("the level set does not cut", "every piece of the cut collapsed"))


def local_cut(mesh, levelset, order: int = 1) -> CutMesh:
    """The cut of one rank's local mesh: :func:`~cutfem.geometry.cut.cut_mesh` (of ``order``) with
    S_h allowed to end on the mesh's boundary; a mesh that the surface misses gives a cut without
    pieces (its sides' element sets still come from the nodal values) and without Theta_h."""
    try:
        return cut_mesh(mesh, levelset, check_boundary=False, order=order)
    except CutError as exc:
        if not _no_cut(str(exc)):
            raise
    empty = np.zeros(0, dtype=np.int64)
    return CutMesh(background=mesh, node_ids=empty, points=np.zeros((0, 3)), values=np.zeros(0), tets=np.zeros((0, 4), np.int32),
                   tet_ids=empty, normals=np.zeros((0, 3)), vertices=np.zeros((0, 3)), triangles=np.zeros((0, 3), np.int32),
                   triangle_tets=empty, _gradients=(None, None) if isinstance(mesh, StructuredBox) else None, levelset=levelset)


@dataclass
class RankCuts:
    """The cuts of one rank: ``owned`` (its cells, or None without any) and ``seam`` (its ghost
    cells with the owned cells next to them, or None without ghosts)."""

    partition: object  # Slabs or CellPartition
    rank: int
    owned: CutMesh | None
    seam: CutMesh | None

    def seam_facets(self, facets):
        """The facets of a facet set of the seam cut between an owned tet and a ghost whose owned
        tet has the larger global id: the seam facets this rank assembles."""
        tets = self.seam.background.global_tets(facets.elements.tet_ids[facets.pairs])
        mine = self.partition.cell_owner(tets) == self.rank
        larger = np.where(mine[:, 0], tets[:, 0] > tets[:, 1], tets[:, 1] > tets[:, 0])
        return facets.subset((mine[:, 0] != mine[:, 1]) & larger, name=f"{facets.name} across the seam")


def rank_cuts(partition, rank: int, levelset, order: int = 1) -> RankCuts:
    """Cut the owned cells and the seam of ``rank`` (see the module docstring); ``order`` 2 lifts
    both by the Theta_h of the rank's :meth:`Slabs.lifting_mesh` (slabs only)."""
    if order == 2 and not isinstance(partition, Slabs):
        raise ValueError("order 2 runs on several ranks on the slabs of a structured box (background='structured'); an "
                         "unstructured mesh is P1 on several ranks: run order 2 on it on one rank")
    meshes = partition.local_meshes(rank)
    if meshes[0] is None:
        return RankCuts(partition, rank, None, None)
    phis = partition.local_levelsets(rank, levelset, meshes)
    owned, seam = (None if m is None else local_cut(m, phi) for m, phi in zip(meshes, phis))
    if order == 2:
        wide = partition.lifting_mesh(rank)
        theta = local_cut(wide, levelset, order=2).deformation  # None where the surface misses the wider slab
        for cut in (owned, seam):
            if cut is not None and theta is not None:
                cut.deformation = theta.on(cut.background, cut.background.global_nodes(np.arange(cut.background.n_points))
                                           - wide.node_offset)
    return RankCuts(partition, rank, owned, seam)
