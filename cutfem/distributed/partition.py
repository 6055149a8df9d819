"""The partition of a structured box into slabs of cell layers, and each rank's cut of its slab.

The cells of a :class:`~cutfem.geometry.box.StructuredBox` are split in blocks of whole layers
along the slowest axis z: rank r owns the cell layers ``[starts[r], starts[r + 1])``, so its cells
(and tets) have contiguous global ids, and so do the nodes of its layers.  A rank may own no layer
(more ranks than layers, or a split given by hand).

A :class:`SlabBox` is the structured box of some consecutive cell layers whose node coordinates are
computed from the *global* node indices by the global box (``lower + ijk * spacing`` with the global
``lower`` and ``ijk``), so that the level set's nodal values on a slab are bit for bit those of the
serial run, and so are the cut, the quadrature points and the element matrices of every tet.

Each rank cuts two slabs (:func:`rank_cuts`):

* its **owned** slab ``[k0, k1)``: every cell integral (volume, Gamma_h, load) of the rank is over
  these tets, and every facet with both tets in them;
* the **seam** ``[k0 - 1, k0 + 1)``: its lower layer is the rank's layer of ghost cells across the
  facets of its lowest owned layer.  A facet between two layers is assembled by the owner of its
  tet with the larger global id (the upper one), so the seam's facets that cross the plane
  z = z_k0 are this rank's and no other's, and no ghost layer above is needed.

The faces of the upper ghost layer are those of the next rank's seam: every facet is assembled
exactly once.  Which tets are active and which facets are ghost-penalty facets depends only on the
nodal values of the tets concerned, so it is the same on every rank that holds them.  One caveat is
inherited from the zero rule (:func:`cutfem.geometry.nodal_values._zero_tolerance`): the snap
tolerance of a node is 1e-12 of the largest value in its 3 x 3 x 3 block, which a slab truncates at
its faces; a nodal value within 1e-12 of its neighbours' scale of zero may snap differently there.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..geometry.box import StructuredBox
from ..geometry.cut import CutMesh, cut_mesh
from ..geometry.nodal_values import CutError

__all__ = ["Slabs", "SlabBox", "slab_partition", "rank_cuts", "RankCuts"]


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

    def owned_nodes(self, rank: int) -> tuple[int, int]:
        """The global node ids ``[first, stop)`` the rank owns."""
        k0, k1 = self.layers(rank)
        per = int(self.box.node_shape[0] * self.box.node_shape[1])
        if k1 == int(self.box.cells[2]) and k1 > k0:
            k1 += 1  # the top node layer
        return k0 * per, k1 * per


def slab_partition(box: StructuredBox, size: int, counts=None) -> Slabs:
    """The block split of the ``nz`` cell layers of ``box`` over ``size`` ranks (the first
    ``nz % size`` ranks one layer more), or the layer ``counts`` per rank given (any nonnegative
    whole numbers summing to nz: for ranks without cells)."""
    if not isinstance(box, StructuredBox):
        raise TypeError(f"distributed runs partition a structured box (cf.structured_box), got {type(box).__name__}; "
                        "an unstructured background is not distributed yet")
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

    @cached_property
    def layer_tets(self) -> int:
        """Tets per cell layer (6 nx ny)."""
        return 6 * int(self.cells[0]) * int(self.cells[1])


def _no_cut(message: str) -> bool:
    """Whether a CutError of :func:`~cutfem.geometry.cut.cut_mesh` says that no tet carries a piece
    of S_h (the slab lies on one side), which on one slab of a larger box is no error."""
    return message.startswith(("the level set does not cut", "every piece of the cut collapsed"))


def slab_cut(slab: SlabBox, levelset) -> CutMesh:
    """The cut of one slab: :func:`~cutfem.geometry.cut.cut_mesh` with S_h allowed to end on the
    slab's faces; a slab that the surface misses gives a cut without pieces (its sides' element
    sets still come from the nodal values)."""
    try:
        return cut_mesh(slab, levelset, check_boundary=False)
    except CutError as exc:
        if not _no_cut(str(exc)):
            raise
    empty = np.zeros(0, dtype=np.int64)
    return CutMesh(background=slab, node_ids=empty, points=np.zeros((0, 3)), values=np.zeros(0), tets=np.zeros((0, 4), np.int32),
                   tet_ids=empty, normals=np.zeros((0, 3)), vertices=np.zeros((0, 3)), triangles=np.zeros((0, 3), np.int32),
                   triangle_tets=empty, _gradients=(None, None), levelset=levelset)


@dataclass
class RankCuts:
    """The cuts of one rank: ``owned`` (its cell layers, or None without any) and ``seam`` (its
    lowest owned layer and the ghost layer below, or None on the lowest rank)."""

    slabs: Slabs
    rank: int
    owned: CutMesh | None
    seam: CutMesh | None

    def seam_facets(self, facets):
        """The facets of a facet set of the seam cut that cross its middle plane (one tet in the
        ghost layer, one in the owned layer): the seam facets this rank assembles."""
        slab = self.seam.background
        tets = facets.elements.tet_ids[facets.pairs]
        below = tets < slab.layer_tets
        return facets.subset(below[:, 0] != below[:, 1], name=f"{facets.name} across the seam")


def rank_cuts(slabs: Slabs, rank: int, levelset) -> RankCuts:
    """Cut the owned slab and the seam of ``rank`` (see the module docstring)."""
    k0, k1 = slabs.layers(rank)
    if k1 == k0:
        return RankCuts(slabs, rank, None, None)
    owned = slab_cut(SlabBox(slabs.box, k0, k1), levelset)
    seam = slab_cut(SlabBox(slabs.box, k0 - 1, k0 + 1), levelset) if k0 > 0 else None
    return RankCuts(slabs, rank, owned, seam)
