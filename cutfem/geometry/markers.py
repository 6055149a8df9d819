"""Sides, element sets and facet sets of a cut (docs/math.md §7).

One P1 level set phi_h splits the background box into two sides, ``NEG = {phi_h < 0}`` (inside) and
``POS = {phi_h > 0}`` (outside), with the interface Gamma_h = {phi_h = 0} between them.  Nodal values
that are exactly zero follow the zero rule of :mod:`cutfem.geometry.nodal_values`: they count as
outside.  Per tet T:

* all nodes < 0: T lies in NEG;  all nodes >= 0: T lies in POS (also when every node is zero);
* otherwise (mixed signs) T is split by the plane of its piece of Gamma_h into the two sides.

So ``|T ∩ NEG| + |T ∩ POS| = |T|`` for every tet and Gamma_h is the common boundary of the sides.

Element sets (:class:`ElementSet`, tets of the background with a node numbering of their own):

* ``NEG``: the tets with ``|T ∩ NEG| > 0`` (a node < 0) together with the cut tets;
* ``POS``: the tets with ``|T ∩ POS| > 0`` (a node > 0, or all nodes zero) together with the cut tets;
* ``CUT``: the cut tets, those that carry a piece of Gamma_h of positive area (the active mesh of
  :class:`cutfem.geometry.cut.CutMesh`).

The cut tets belong to both sides even in the rare case where a zero rule makes one side's part of
the tet empty (a piece lying in a face of the tet): then every field of a side is defined on the
whole of Gamma_h, which the Nitsche terms need; the ghost penalty controls the extra nodes.

Facet sets (:class:`FacetSet`): the interior faces of an element set (faces shared by two of its
tets), the ghost-penalty faces of a side (interior faces of the side's set with at least one tet
cut) and the interior faces of the cut tets (the face stabilization J_F of §3).

Local sizes: ``h_T`` is the longest edge of T; ``h_F`` the longest edge of the face F.  These enter
penalties; the global ``N**(-1/3)`` serves only as the abscissa of convergence tables.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from .box import StructuredBox, kuhn_face_pairs
from .keys import dense_unique, pair_up, tet_face_keys, unique_keys
from .mesh import barycentric_gradients
from .numbering import TET_FACES, index_dtype
from . import cut_kernels
from . import mesh_kernels

__all__ = ["NEG", "POS", "CUT", "SIDES", "ElementSet", "FacetSet", "interior_facets", "ghost_facets", "side_subtetrahedra",
           "longest_edges", "same_background"]

NEG = "neg"
POS = "pos"
CUT = "cut"
SIDES = (NEG, POS)


def same_background(a, b) -> bool:
    """Whether two background meshes have the same tets under the same ids: the same object, or two
    structured boxes with equal corners, cells and spacing (their tets follow from these).  Tet ids
    of element sets, measures and fields are compared only on the same background."""
    if a is b:
        return True
    if isinstance(a, StructuredBox) and isinstance(b, StructuredBox):
        return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("lower", "upper", "cells", "spacing"))
    return False


def longest_edges(points: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """(m,) the longest edge of each simplex: ``simplices`` (m, k) node numbers of ``points``
    (N, 3), k = 3 or 4.  One compiled pass (:func:`cutfem.geometry.mesh_kernels.longest_edges`), the vertices
    gathered in it (numpy gathered (m, k, 3) blocks and took six norms: 0.06 s for the 3.5 million
    tets of the solid torus at spacing 0.02)."""

    simplices = np.ascontiguousarray(simplices)
    if simplices.ndim != 2 or simplices.shape[1] not in (3, 4):
        raise ValueError(f"simplices must have shape (m, 3) or (m, 4), got {simplices.shape}")
    out = np.empty(len(simplices))
    mesh_kernels.longest_edges(np.ascontiguousarray(points, dtype=float), simplices, out)
    return out


def interior_facets(tets: np.ndarray, n_nodes: int, kuhn=None):
    """The faces shared by two of the tets (m, 4) (node numbers below ``n_nodes``).

    Returns ``(pairs (F, 2), opposite (F, 2))``: the two tets of each face (first the one that comes
    first in ``tets``) and, in each, the local index of the vertex opposite to the face; faces in
    increasing order of their sorted node triples.  The face keys: the sorted node triples
    (:func:`~cutfem.geometry.keys.tet_face_keys`, grouped by one sort), or, for tets of a structured box
    given with their Kuhn types ``kuhn`` (m,) (background tet id % 6), the lattice keys
    :func:`~cutfem.geometry.box.kuhn_face_keys`, below 12 ``n_nodes``, computed on the fly and paired by two
    marker arrays (:func:`~cutfem.geometry.box.kuhn_face_pairs`, no sort); both give the same faces in the
    same order when
    the node numbers increase with the background ids.
    """
    if kuhn is not None:
        return kuhn_face_pairs(tets, kuhn, n_nodes)
    order, starts, counts = pair_up(tet_face_keys(tets, n_nodes))
    two = counts == 2
    rows = np.stack([order[starts[two]], order[starts[two] + 1]], axis=1)
    # row 4 t + k of the keys: the face opposite to local vertex k of tet t
    return rows >> 2, (rows & 3).astype(np.int8)


def _integer_ids(tet_ids) -> np.ndarray:
    """``tet_ids`` as int64 (m,), or a ValueError unless they are a 1-D array of integers."""
    ids = np.asarray(tet_ids)
    if ids.ndim != 1:
        raise ValueError(f"tet_ids must be a 1-D array of background tet ids, got shape {ids.shape}")
    if ids.size and ids.dtype.kind not in "iu":
        what = "a boolean mask (use np.flatnonzero(mask))" if ids.dtype.kind == "b" else f"an array of dtype {ids.dtype}"
        raise ValueError(f"tet_ids must be integer background tet ids, got {what}")
    return ids.astype(np.int64, copy=False)


class ElementSet:
    """A set of tets of a background mesh with a node numbering of its own.

    ``tet_ids`` (m,) background tet ids; ``tets`` (m, 4) local node numbers; ``node_ids`` (p,)
    background ids of the nodes (increasing), ``points`` (p, 3); ``gradients`` (m, 4, 3) of the
    barycentric coordinates; ``volumes`` (m,); ``h`` (m,) the longest edge of each tet.
    ``name`` says which set it is (``"neg"``, ``"pos"``, ``"cut"`` or a user's name); ``cut`` is the
    cut it comes from (or None).  ``normals`` (m, 3): n_h of the cut tets (only for the set of cut tets).

    ``tet_ids`` must be a 1-D array of integers (not floats, not a boolean mask: use
    ``np.flatnonzero(mask)``), each in ``[0, background.n_tets)`` and none twice (a repeated tet would
    be integrated again); anything else is refused with a ValueError.
    """

    def __init__(self, background, tet_ids, *, name="elements", cut=None, tets=None, node_ids=None, points=None,
                 gradients=None, volumes=None, normals=None):
        self.background = background
        self.tet_ids = _integer_ids(tet_ids)
        self._check_ids()  # before any use of the ids: one out of range reads outside the mesh
        self.name = name
        self.cut = cut
        structured = isinstance(background, StructuredBox)
        if tets is None:
            if structured:
                nodes = background.kuhn_tet_nodes(self.tet_ids)
            else:
                nodes = background.tets[self.tet_ids]
            node_ids, tets = dense_unique(nodes, background.n_points)  # int32 numbers while they fit
        self.tets = tets
        self.node_ids = node_ids
        if points is None:
            points = background.node_coordinates(node_ids) if structured else background.points[node_ids]
        self.points = points
        if gradients is None and not structured:
            gradients, volumes = barycentric_gradients(points[tets])
            volumes = np.abs(volumes)
        self._gradients = gradients  # None on a structured box: read off the Kuhn table on access
        self._volumes = None if structured else volumes  # on a structured box every tet has the box's volume
        self.normals = normals

    def _check_ids(self):
        """A ValueError unless the ids lie in [0, n_tets) and none repeats: on the sorted ids kept for
        the searches (:attr:`_lookup`; the sides' sets come sorted, no sort), the ends and the
        neighbours."""
        sorted_ids, n_tets = self._lookup[1], self.background.n_tets
        if len(sorted_ids) and (sorted_ids[0] < 0 or sorted_ids[-1] >= n_tets):
            bad = int(sorted_ids[0] if sorted_ids[0] < 0 else sorted_ids[-1])
            raise ValueError(f"tet_ids must lie in [0, {n_tets}) (the tets of the background mesh), got {bad}")
        same = sorted_ids[1:] == sorted_ids[:-1]
        if same.any():
            dup = sorted_ids[1:][same]
            raise ValueError(f"tet_ids of an element set must not repeat a tet (it would be integrated again); "
                             f"{len(np.unique(dup))} repeated, the first {int(dup[0])}")

    @property
    def volumes(self) -> np.ndarray:
        """(m,) the volumes of the tets.  On a structured box every tet has the box's tet volume, and
        the array is built on each access, not kept (8 bytes a tet: 105 MB for the 13.7 million cut
        tets of the torus at spacing 0.003125); for a subset use :meth:`volumes_of`."""
        return self.volumes_of(slice(None))

    @property
    def uniform_volume(self) -> float | None:
        """The volume every tet of the set has (a structured box's tet volume), or None."""
        return self.background.tet_volume if self._volumes is None else None

    def volumes_of(self, idx) -> np.ndarray:
        """The volumes of the tets ``idx`` (local indices: a slice, integers or a mask)."""
        if self._volumes is None:  # the selection's length from a zero-width view (indices checked, nothing gathered)
            return np.full(np.empty((len(self.tet_ids), 0))[idx].shape[:-1], self.background.tet_volume)
        return self._volumes[idx]

    @property
    def gradients(self) -> np.ndarray:
        """(m, 4, 3) gradients of the barycentric coordinates.  On a structured box they are the
        Kuhn table of each tet's type over the spacing (:attr:`~cutfem.geometry.box.StructuredBox.gradient_table`),
        built on each access and not kept (96 bytes a tet: 1.25 GiB for the 13.7 million cut tets of
        the torus at spacing 0.003125); for a subset use :meth:`gradients_of`."""
        return self.gradients_of(slice(None))

    def gradients_of(self, idx) -> np.ndarray:
        """The gradients of the tets ``idx`` (local indices): (..., 4, 3)."""
        if self._gradients is None:
            return self.background.gradient_table[self.kuhn_types[idx]]
        return self._gradients[idx]

    def gradient_lookup(self):
        """(table, types) with ``gradients_of(i) = table[types[i]]``: the Kuhn table (6, 4, 3) and
        the Kuhn types on a structured box, the stored gradients (m, 4, 3) and 0..m-1 otherwise
        (for compiled kernels, which then need no gathered copy)."""
        if self._gradients is None:
            return self.background.gradient_table, self.kuhn_types
        return self._gradients, np.arange(len(self.tet_ids))

    def __repr__(self) -> str:
        return f"ElementSet({self.name!r}, tets={self.n_elements}, nodes={self.n_nodes})"

    @property
    def n_elements(self) -> int:
        return len(self.tet_ids)

    @property
    def n_nodes(self) -> int:
        return len(self.node_ids)

    @property
    def vertices(self) -> np.ndarray:
        """(m, 4, 3) coordinates of the tets, gathered on each call (not stored: 0.15 GB at 1.6 million
        tets, where most users need only a block or a subset)."""
        return self.points[self.tets]

    @cached_property
    def h(self) -> np.ndarray:
        """(m,) local size h_T: the longest edge of each tet."""
        return longest_edges(self.points, self.tets)

    @cached_property
    def _lookup(self):
        ids = self.tet_ids
        if len(ids) < 2 or np.all(ids[1:] >= ids[:-1]):  # the sides' sets come sorted (np.flatnonzero): no sort
            return np.arange(len(ids)), ids
        order = np.argsort(ids, kind="stable")
        return order, ids[order]

    def _find(self, tet_ids):
        """(local index candidates, found mask) of background tets ``tet_ids``, by one binary search."""
        order, sorted_ids = self._lookup
        tet_ids = np.asarray(tet_ids, dtype=np.int64)
        if not len(sorted_ids):
            return np.zeros(tet_ids.shape, np.int64), np.zeros(tet_ids.shape, bool)
        pos = np.minimum(np.searchsorted(sorted_ids, tet_ids), len(sorted_ids) - 1)
        return order[pos], sorted_ids[pos] == tet_ids

    def locate(self, tet_ids, what: str = "the measure") -> np.ndarray:
        """Local indices of background tets ``tet_ids`` in this set; a clear error when some are not in it."""
        tet_ids = np.asarray(tet_ids, dtype=np.int64)
        return self._found(*self._find(tet_ids), what, tet_ids)

    def locate_set(self, other: "ElementSet", rows=None, what: str = "the measure") -> np.ndarray:
        """:meth:`locate` of the tets ``other.tet_ids[rows]`` (all when None; ``other`` must lie on the
        same background, :func:`same_background`, else a ValueError), by one binary search of
        all of ``other``'s tets, kept for the next call: the measures on the cut tets ask a side's set
        for their elements block by block and term by term (at spacing 0.01, three searches of the
        1.3 million cut tets in the 29 million tets of a side took 0.14 s each)."""
        if not same_background(self.background, other.background):
            raise ValueError(
                f"{what} lies on another background mesh than the element set {self.name!r} ({other.background!r}, "
                f"the set's: {self.background!r}): tet ids of different meshes do not name the same tets. Integrate "
                "a field over measures of its own cut (or of a cut of the same background)."
            )
        key = id(other)
        hit = self._positions.get(key)
        if hit is None or hit[0] is not other:
            hit = self._positions[key] = (other, *self._find(other.tet_ids))
        _, local, found = hit
        if rows is None:
            return self._found(local, found, what, other.tet_ids)
        if not np.all(found[rows]):  # counted over the whole measure, not the block of cells that asked
            self._found(local, found, what, other.tet_ids)
        return local[rows]

    @cached_property
    def _positions(self) -> dict:
        return {}

    def _found(self, local, found, what, tet_ids):
        """``local`` where every one of the background tets ``tet_ids`` was ``found``; else a ValueError
        counting the distinct tets missing (a measure's cells repeat their tet: sub-tets, pieces)."""
        if not np.all(found):
            missing = np.unique(tet_ids[~found])
            raise ValueError(
                f"{missing.size} elements (background tets {', '.join(str(int(t)) for t in missing[:3])}"
                f"{', ...' if missing.size > 3 else ''}) of {what} are not in the element set {self.name!r}: a field on "
                f"{self.name!r} does not live there. Integrate over a measure inside the field's elements, or define "
                "the field on a larger element set."
            )
        return local

    def contains(self, tet_ids) -> np.ndarray:
        """Boolean mask: which background tets ``tet_ids`` are in this set."""
        return self._find(tet_ids)[1]

    def to_pyvista(self, **point_data):
        """The tets as a ``pyvista.UnstructuredGrid`` with point data phi_h (when the set comes from a
        cut), cell data ``cut`` (1 on the cut tets) and the given per-node arrays."""
        import pyvista as pv

        grid = pv.UnstructuredGrid({pv.CellType.TETRA: self.tets}, self.points)
        if self.cut is not None:
            if self.levelset_values is not None:
                grid.point_data["phi_h"] = self.levelset_values
            grid.cell_data["cut"] = self.contains_cut.astype(np.uint8)
        for name, values in point_data.items():
            grid.point_data[name] = np.asarray(values)
        return grid

    @property
    def levelset_values(self):
        """phi_h at the nodes of the set (None without a cut)."""
        if self.cut is None:
            return None
        if self.name == CUT:
            return self.cut.values
        return self.cut.background_values[self.node_ids]

    @property
    def contains_cut(self) -> np.ndarray:
        """(m,) whether each tet is a cut tet."""
        return self.cut.elements(CUT).contains(self.tet_ids) if self.name != CUT else np.ones(self.n_elements, bool)

    @cached_property
    def interior_facets(self) -> "FacetSet":
        """The faces shared by two tets of the set."""
        pairs, opposite = interior_facets(self.tets, self.n_nodes, self.kuhn_types)
        return FacetSet(self, pairs, opposite, name=f"interior faces of {self.name}")

    @cached_property
    def kuhn_types(self):
        """(m,) int8 the Kuhn type (background tet id % 6) of each tet on a structured box, else None."""
        if not isinstance(self.background, StructuredBox):
            return None

        return mesh_kernels.kuhn_types(self.tet_ids)

    @cached_property
    def boundary_nodes(self) -> np.ndarray:
        """Local numbers of the nodes of the set that lie on the boundary of the background mesh."""
        bnodes = self.background.boundary_nodes
        mark = np.zeros(self.background.n_points, dtype=bool)
        mark[bnodes] = True
        return np.flatnonzero(mark[self.node_ids])


class FacetSet:
    """Faces shared by two tets of an :class:`ElementSet`.

    ``pairs`` (F, 2) local element indices (the minus and the plus tet), ``opposite`` (F, 2) the
    local vertex opposite to the face in each.  ``normals`` (F, 3) unit, pointing out of the minus tet
    into the plus tet; ``areas`` (F,); ``vertices`` (F, 3, 3); ``h`` (F,) the longest edge of each face.
    """

    def __init__(self, elements: ElementSet, pairs, opposite, name="facets"):
        self.elements = elements
        # element indices as int32 while they fit: half the bytes
        self.pairs = np.asarray(pairs, dtype=index_dtype(elements.n_elements)).reshape(-1, 2)
        self.opposite = np.asarray(opposite, dtype=np.int8).reshape(-1, 2)  # 0..3: one byte, not eight
        self.name = name

    def __repr__(self) -> str:
        return f"FacetSet({self.name!r}, faces={self.n_facets})"

    @property
    def n_facets(self) -> int:
        return len(self.pairs)

    def subset(self, selection, name=None) -> "FacetSet":
        """The facets where the boolean ``selection`` (F,) is true, or the facets of the integer
        indices ``selection`` (in [0, F), kept in the order given, none twice).  Anything else (a
        mask of another length, floats, indices out of range or repeated) is refused with a
        ValueError."""
        sel = np.asarray(selection)
        F = self.n_facets
        if sel.ndim != 1 or not (sel.dtype.kind in "biu" or sel.size == 0):
            raise ValueError(f"subset takes a boolean mask of shape ({F},) or integer facet indices, got an array of "
                             f"shape {sel.shape} and dtype {sel.dtype}")
        if sel.dtype.kind == "b":
            if len(sel) != F:
                raise ValueError(f"a boolean mask of the facets must have shape ({F},), got ({len(sel)},)")
        else:
            sel = sel.astype(np.int64, copy=False)
            if sel.size and (sel.min() < 0 or sel.max() >= F):
                raise ValueError(f"facet indices must lie in [0, {F}), got {int(sel.min() if sel.min() < 0 else sel.max())}")
            if len(unique_keys(sel)) != len(sel):
                raise ValueError("facet indices must not repeat a facet (it would be integrated again); for a 0/1 "
                                 "mask pass booleans")
        return FacetSet(self.elements, self.pairs[sel], self.opposite[sel], name=name or self.name)

    def normals_areas(self):
        """(unit normals (F, 3) out of the minus tet, areas (F,)), computed on each call from the
        minus tet's gradients, not kept (32 bytes a face: 0.7 GB for the 22 million interior faces
        of the cut torus at spacing 0.003125, where they are used once).

        The face opposite to vertex k has the outward normal -grad(lambda_k) / |grad(lambda_k)|, and
        |F| = 3 |T| |grad lambda_k| (volume = |F| height / 3, |grad lambda_k| = 1 / height); one
        compiled pass (:func:`cutfem.geometry.mesh_kernels.face_normals_areas`) from the gradient table."""

        es = self.elements
        table, types = es.gradient_lookup()
        normals, areas = np.empty((self.n_facets, 3)), np.empty(self.n_facets)
        mesh_kernels.face_normals_areas(self.pairs, self.opposite, np.ascontiguousarray(table, dtype=float), types,
                                   np.ascontiguousarray(es.volumes, dtype=float), normals, areas)
        return normals, areas

    @property
    def normals(self) -> np.ndarray:
        """(F, 3) unit normals out of the minus tet (see :meth:`normals_areas`)."""
        return self.normals_areas()[0]

    @property
    def areas(self) -> np.ndarray:
        """(F,) face areas (see :meth:`normals_areas`)."""
        return self.normals_areas()[1]

    @cached_property
    def nodes(self) -> np.ndarray:
        """(F, 3) the face's nodes (those of the minus tet without the opposite one)."""
        local = TET_FACES[self.opposite[:, 0]]  # (F, 3)
        return np.take_along_axis(self.elements.tets[self.pairs[:, 0]], local, axis=1)

    @property
    def vertices(self) -> np.ndarray:
        """(F, 3, 3) the face's vertices, gathered on each call."""
        return self.elements.points[self.nodes]

    @cached_property
    def h(self) -> np.ndarray:
        """(F,) local size h_F: the longest edge of each face."""
        return longest_edges(self.elements.points, self.nodes)


def ghost_facets(elements: ElementSet, cut_tet_ids, side: str) -> FacetSet:
    """The ghost-penalty faces of a side (docs/math.md §7): the interior faces of its element set
    ``elements`` with at least one of their two tets among the background tets ``cut_tet_ids``
    (the cut tets, all of them in the set).

    Both tets of such a face touch a node of a cut tet, so the faces are looked for only among
    those tets (a band around the cut, marked in one compiled pass,
    :func:`cutfem.geometry.cut_kernels.tets_near`) instead of sorting every face of the side."""
    es = elements
    cut_mark = np.zeros(es.n_elements, dtype=bool)
    cut_mark[es.locate(cut_tet_ids, "the cut tets")] = True
    near = np.empty(es.n_elements, dtype=bool)
    cut_kernels.tets_near(es.tets, cut_mark, es.n_nodes, near)
    band = np.flatnonzero(near)
    kuhn = es.kuhn_types
    pairs, opposite = interior_facets(es.tets[band], es.n_nodes, None if kuhn is None else kuhn[band])
    pairs = band[pairs]
    keep = cut_mark[pairs[:, 0]] | cut_mark[pairs[:, 1]]
    return FacetSet(es, pairs[keep], opposite[keep], name=f"ghost faces of {side}")


def side_subtetrahedra(points: np.ndarray, tets: np.ndarray, values: np.ndarray, side: str):
    """The part of each tet on one side of its level-set plane: the tets that lie in the side, and
    the side's part of the others as sub-tetrahedra.

    ``points`` (n, 3), ``tets`` (m, 4) into them, ``values`` (n,) phi_h at the points (zero rule
    already applied).  NEG = {phi_h < 0}; POS is its complement in the tet, {phi_h > 0} up to a set
    of measure zero.  A tet whose nodes all lie on the side is whole; otherwise the side's nodes (1, 2
    or 3 of them) give one tet, a prism (three tets) or the tet minus a corner (a prism, three tets),
    cut at the points x_i + t (x_j - x_i), t = phi_i / (phi_i - phi_j), of the edges that change
    side.  Some sub-tets have zero volume under the zero rule; they integrate to zero.

    Returns ``(whole (w,), sub (s, 4, 3), parent (s,))``: the indices of the whole tets (their
    vertices are not copied) and the sub-tets of the others with the tet each lies in.
    """

    if side not in (NEG, POS):
        raise ValueError(f"side must be NEG or POS, got {side!r}")
    tets = np.ascontiguousarray(tets)
    values = np.ascontiguousarray(values, dtype=float)
    m = len(tets)
    whole, partial, k = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int8)
    nw, npart = cut_kernels.side_split(tets, values, side == NEG, whole, partial, k)  # one pass over the tets
    whole, partial, k = whole[:nw], partial[:npart], k[:npart]
    # the sub-tets a group of counts at a time (1, 2, 3 nodes on the side), sub-tet by sub-tet,
    # each group's tets in increasing order: one compiled pass writes each at its place
    sizes = np.array([0] + [int(np.count_nonzero(k == c)) for c in (1, 2, 3)], dtype=np.int64)
    base = np.array([0, 0, sizes[1], sizes[1] + 3 * sizes[2]], dtype=np.int64)
    rank = np.empty(npart, dtype=np.int64)
    for c in (1, 2, 3):  # the three groups, not the tets
        rank[k == c] = np.arange(sizes[c])
    total = int(sizes[1] + 3 * sizes[2] + 3 * sizes[3])
    sub, parent = np.empty((total, 4, 3)), np.empty(total, dtype=np.int64)
    cut_kernels.side_pieces(np.ascontiguousarray(points, dtype=float), tets, values, side == NEG, partial, k.astype(np.int64),
                        rank, base, sizes, sub, parent)
    return whole, sub, parent
