"""A rank's share of a system: cell terms on its owned cells, facet terms once, in global numbers.

:func:`rank_pieces` assembles, with the serial code (:func:`cutfem.fem.forms.assemble`), the
rank's local matrices and load vectors, each with the global node ids of its rows (its cuts come
from :func:`~cutfem.distributed.partition.rank_cuts`: slabs of a structured box or cells of an
unstructured mesh alike):

* on the owned cells' space (P1 or P2 on the element set ``on``): the cell terms (volume, Gamma_h,
  load) and the facet terms of the faces with both tets owned;
* on the seam's space: the facet terms of the faces between an owned tet and a ghost
  (:meth:`~cutfem.distributed.partition.RankCuts.seam_facets`) that this rank alone assembles.

Summed over the ranks, the pieces are the serial matrix and load (the serial unknowns are the
active nodes, and of P2 the edges of the active tets, which every piece's rows are).  :func:`rank_system` numbers the nodes globally and
hands the pieces to PETSc (:class:`~cutfem.distributed.system.LinearSystem`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..fem.forms import assemble
from ..fem.spaces import CutSpace, VectorSpace
from .partition import P2_SLOTS
from .system import GlobalNumbering, LinearSystem

__all__ = ["Piece", "RankPieces", "global_keys", "rank_pieces", "rank_system"]


@dataclass
class Piece:
    """A local matrix (and load vector, or None) whose row i is the unknown ``keys[i]`` (global
    node id, or P2 node, times the number of fields plus the field: :func:`global_keys`)."""

    keys: np.ndarray
    matrix: object
    vector: np.ndarray | None = None


@dataclass
class RankPieces:
    """The pieces of one rank; ``space`` the owned cells' space (None without owned cells),
    ``faces`` the number of faces the rank assembled and ``order`` the fields' order."""

    pieces: list = field(default_factory=list)
    space: CutSpace | None = None
    faces: int = 0
    order: int = 1

    @property
    def keys(self) -> np.ndarray:
        return np.concatenate([p.keys for p in self.pieces]) if self.pieces else np.zeros(0, dtype=np.int64)


def _scalar_fields(space) -> list:
    """The scalar fields of a space in its dof order: a vector field's components (one copy of its
    scalar space each), a product's fields."""
    fields = getattr(space, "fields", None) or [space]
    return [g for f in fields for g in ([f.scalar] * f.components if isinstance(f, VectorSpace) else [f])]


def _p2_units(space) -> np.ndarray:
    """The global P2 nodes of a P2 field on a slab (:class:`~cutfem.distributed.partition.SlabBox`),
    in its dof order: ``8 v`` for the vertex v, ``8 v + c(S)`` for the midpoint of the lattice edge
    {v, v + e_S} (v its lower end), computable from the two global node ids on every rank (the
    inverse: :meth:`~cutfem.distributed.partition.Slabs.p2_ends`)."""
    box = space.cut.background
    nodes = box.global_nodes(space.node_ids)
    lo, hi = space.node_ids[space.edge_nodes[:, 0]], space.node_ids[space.edge_nodes[:, 1]]  # increasing ids: lo < hi
    step = box.node_index(hi) - box.node_index(lo)
    if np.any((step < 0) | (step > 1)):
        raise ValueError("a P2 field on several ranks needs the Kuhn lattice of a structured box (its edges join v and v + e_S)")
    codes = step @ np.array([1, 2, 4])
    return np.concatenate([P2_SLOTS * nodes, P2_SLOTS * box.global_nodes(lo) + codes])


def global_keys(space) -> np.ndarray:
    """The keys of the unknowns of a P1 or P2 space on a rank's cut or of a product of such spaces,
    a vector field counting as its three components: ``unit * fields + field`` in the space's dof
    order, the unit the global node id (P1) or the global P2 node (:func:`_p2_units`)."""
    fields = _scalar_fields(space)
    F = len(fields)
    return np.concatenate([(_p2_units(f) if f.order == 2 else f.cut.background.global_nodes(f.node_ids)) * F + k
                           for k, f in enumerate(fields)])


def rank_pieces(cuts, on, cells, faces=None, face_form=None, order: int = 1) -> RankPieces:
    """The rank's pieces of a system on P1 (or P2, ``order`` 2) over the element set ``on`` of each
    of its cuts.

    ``cells(cut, space)``: ``(bilinear form, linear form or None)`` of the cell terms over the
    owned cut (called when the owned cells hold active cells; ``cut.n_tets`` is 0 on a rank the
    surface misses), or None for facet terms alone; ``faces(cut)``: the facet set of the facet
    terms on a cut (called only on cuts with pieces), and ``face_form(measure)`` their bilinear form."""
    out = RankPieces(order=order)
    owned, seam = cuts.owned, cuts.seam
    if owned is not None:
        V = out.space = CutSpace(owned, on, order=order)
        if V.n_dofs:
            a, rhs = (None, None) if cells is None else cells(owned, V)
            if faces is not None and owned.n_tets:
                F = faces(owned)
                out.faces += F.n_facets
                if F.n_facets:
                    a = face_form(owned.dF(F)) if a is None else a + face_form(owned.dF(F))
            if a is not None:
                out.pieces.append(Piece(global_keys(V), assemble(a, V), None if rhs is None else assemble(rhs, V)))
    if faces is not None and seam is not None and seam.n_tets:
        F = cuts.seam_facets(faces(seam))
        out.faces += F.n_facets
        if F.n_facets:
            S = CutSpace(seam, on, order=order)
            out.pieces.append(Piece(global_keys(S), assemble(face_form(seam.dF(F)), S)))
    return out


def rank_system(parts: RankPieces, cuts, comm, fields: int = 1, constants: int = 0) -> tuple[LinearSystem, GlobalNumbering]:
    """The global numbering of the pieces' unknowns (``fields`` per node for a product space, and
    ``constants`` one-unknown fields keyed -1, -2, ...) and the system they add up to (not yet on
    PETSc: :meth:`~cutfem.distributed.system.LinearSystem.petsc`); a P2 field has
    :data:`~cutfem.distributed.partition.P2_SLOTS` units a node."""
    slots = P2_SLOTS if parts.order == 2 else 1
    numbering = GlobalNumbering(comm, cuts.partition, cuts.rank, parts.keys, fields, constants, slots)
    system = LinearSystem(comm, numbering)
    for piece in parts.pieces:
        dofs = numbering(piece.keys)
        system.add_matrix(piece.matrix, dofs)
        piece.matrix = None  # moved into the system: the rank's largest arrays are not held twice
        if piece.vector is not None:
            system.add_vector(piece.vector, dofs)
    return system, numbering
