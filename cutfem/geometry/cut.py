"""The cut: the discrete surface S_h = {phi_h = 0} of a P1 level set on a tetrahedral mesh.

Marching tetrahedra
-------------------
phi_h is the nodal interpolant of the level set.  A tet is *cut* when its nodes do not all lie on
the same side.  Its piece K = S_h ∩ T is planar: a triangle when one node is alone on its side, a
quadrilateral (split into two triangles along a diagonal) when the nodes split two and two.  The
point on an edge (i, j) with phi_i < 0 <= phi_j is ``x_i + t (x_j - x_i)``,
``t = phi_i / (phi_i - phi_j)``.  The piece normal is ``n_h = grad phi_h / |grad phi_h|`` (outward,
towards increasing phi) and every triangle of S_h is oriented by it.  A nodal value that is exactly
zero counts as outside, and values zero up to rounding are snapped to zero first: the zero rule of
:mod:`cutfem.geometry.nodal_values`.

Active mesh
-----------
Active tets are the cut tets with a piece of at least three distinct vertices (positive area).  Their
nodes, renumbered 0..n-1 in increasing background id, are the active nodes; ``node_ids`` maps back.
Interior faces are the faces shared by two active tets (``cut.interior_facets(CUT)``); surface
edges are the edges of the pieces (polygons, not the quad diagonals), each shared by the pieces of
two neighbouring tets.

Sides, element sets and measures
--------------------------------
The cut also gives the two sides NEG = {phi_h < 0} and POS of the box, their element sets
(``cut.elements(NEG)``; the cut tets are ``cut.elements(CUT)``), the ghost faces of a side
(``cut.ghost_facets(NEG)``) and the measures ``cut.dx(NEG)``, ``cut.ds()``, ``cut.dF(facets)``:
see :mod:`cutfem.geometry.markers` and :mod:`cutfem.geometry.measures`.  The sides need phi_h at every node of the
background, which the band search does not evaluate; they are computed when first asked for.

Which tets are cut
------------------
On a structured box with a level set that declares a Lipschitz bound, the candidates come from the
band search (:mod:`cutfem.geometry.band_search`), which visits only the cells near the surface and
checks the memory first; otherwise every node is evaluated.  Every cut then checks that S_h is
closed and edge-manifold (every edge of its triangles in exactly two triangles, from the one-sort
edge counts that the Euler characteristic reuses), which also catches cut cells that a bound too
small made the band search drop, and raises :class:`~cutfem.geometry.nodal_values.CutError` with the
likely cause.

Several level sets
------------------
A domain combined from several level sets (:mod:`cutfem.geometry.csg`: ``cf.intersection(ball,
plane)``) is cut by :func:`cutfem.geometry.csg_cut.cut_domain`, which ``cut_mesh`` calls for it: the
tets clipped by each plane, the boundary in parts with their own normals.  Parts of S_h of one level
set are tagged by further level sets with ``cut.ds(where=...)``.

Mesh size ``h = N**(-1/3)`` with N the number of background nodes (docs/math.md §2).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .band_search import (
    _BoundBroken,
    _candidates_structured,
    _check_band_boundary,
    _check_cut_memory,
    _enclosure_function,
)
from .box import KUHN_EDGE_CODES, StructuredBox
from .keys import dense_unique, pair_up, unique_keys
from .csg import Domain
from .csg_cut import CsgCut, cut_domain, tagged_pieces
from .isoparametric import Deformation
from .marching import EDGE_I, EDGE_J, FLIP, NVERT, TRIANGLE_SLOTS
from .markers import CUT, NEG, POS, SIDES, ElementSet, FacetSet, ghost_facets, side_subtetrahedra
from .measures import BoundaryPart, ElementVolume, FacetMeasure, SideVolume, SurfacePieces
from .mesh import TetMesh, barycentric_gradients, triangle_areas
from .nodal_values import (
    CutError,
    _as_values_function,
    _check_boundary,
    _declared_lipschitz,
    _snap_zeros,
    _zero_tolerance,
    nodal_values,
    snapped_nodal_values,
)
from .numbering import index_dtype
from .surface_checks import _crossing_triangles
from . import cut_kernels
from . import mesh_kernels

__all__ = ["CutMesh", "cut_mesh", "NEG", "POS", "CUT"]


# ---------------------------------------------------------------------------------------------
# candidate tets: (global tet ids, global node ids (m,4), coordinates (m,4,3), values (m,4))
# ---------------------------------------------------------------------------------------------


def _mixed(values):
    inside = values < 0
    k = inside.sum(axis=1)
    return (k > 0) & (k < 4)


# A candidate set is (tet ids (m,), node labels (m, 4), nodal values (m, 4), label -> background
# node id (L,) or None when labels are background ids, value of each label (L,)).  Labels are
# increasing with the background ids, so numbering by label is numbering by background id.


def _candidates_full(mesh: TetMesh, values):
    tv = values[mesh.tets]
    cut = np.flatnonzero(_mixed(tv))
    return cut, mesh.tets[cut], tv[cut], None, values


def _mesh_distance_message(levelset, seen: str, crossing_only: bool = False) -> str:
    """The error for the signed distance to a surface mesh (``levelset.mesh``) that is not a
    distance (``seen``: what showed it): nobody declared its bound 1, it is the bound of every
    distance, and a closed mesh whose distance breaks it crosses itself.  With ``crossing_only``, ""
    unless two triangles cross (an open S_h has other causes too).  Names the first pair of
    crossing triangles that share no vertex (found by :func:`cutfem.geometry.surface_checks._crossing_triangles`
    with each triangle its own component: a grid of candidates and exact segment-triangle tests)."""
    points, tri = np.asarray(levelset.mesh.points, dtype=float), np.asarray(levelset.mesh.triangles)
    x = points[tri]
    pairs = _crossing_triangles(points, tri, np.arange(len(tri)), x.min(axis=1), x.max(axis=1))
    apart = ~(tri[pairs[:, 0]][:, :, None] == tri[pairs[:, 1]][:, None, :]).any(axis=(1, 2)) if len(pairs) else np.zeros(0, bool)
    pairs = pairs[apart]
    if len(pairs):
        where = (f"the surface mesh self-intersects: {len(pairs)} pairs of its triangles cross, the first "
                 f"{pairs[0].tolist()} near {np.round(x[pairs[0]].mean(axis=(0, 1)), 6).tolist()}")
    elif crossing_only:
        return ""
    else:
        where = "the surface mesh overlaps or touches itself somewhere (no crossing triangles were found)"
    return (f"the signed distance to the surface mesh is not a distance: {seen}, where a distance changes by at "
            f"most |x - y|. Cause: {where}, so inside and outside are not defined there. Repair the mesh into one "
            "closed surface without self-intersections (e.g. remesh it, or merge the overlapping parts).")


# ---------------------------------------------------------------------------------------------
# the cut mesh
# ---------------------------------------------------------------------------------------------


@dataclass(eq=False)
class CutMesh:
    """S_h and the active mesh T_h of a P1 level set on a background tetrahedral mesh.

    Active mesh (n active tets, p active nodes):
        ``node_ids`` (p,) background ids; ``points`` (p, 3); ``values`` (p,) phi_h;
        ``tets`` (n, 4) local node indices; ``tet_ids`` (n,) background tet ids;
        ``normals`` (n, 3) n_h per piece; ``piece_areas`` (n,).
    Surface S_h (V vertices, T triangles):
        ``vertices`` (V, 3); ``triangles`` (T, 3) oriented by n_h; ``triangle_tets`` (T,) active tet
        of each triangle.
    Mesh size ``h = N**(-1/3)`` of the background mesh; ``background`` is the background mesh.
    """

    background: TetMesh
    node_ids: np.ndarray
    points: np.ndarray
    values: np.ndarray
    tets: np.ndarray
    tet_ids: np.ndarray
    normals: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_tets: np.ndarray
    _gradients: tuple | None = field(default=None, repr=False)  # (basis gradients, volumes) if known
    levelset: object = field(default=None, repr=False)  # what was cut: for the sides' nodal values
    #: Theta_h of a cut made with ``order=2`` (:class:`cutfem.geometry.isoparametric.Deformation`): its
    #: measures dx and ds integrate over the deformed cells; None at order 1
    deformation: Deformation | None = field(default=None, repr=False)

    @property
    def order(self) -> int:
        """The order of the geometry: 1 (the planar S_h) or 2 (S_h lifted by Theta_h)."""
        return 1 if self.deformation is None else self.deformation.order

    # -- sides, element sets, facet sets and measures (cutfem.geometry.markers, cutfem.geometry.measures) ------------
    @cached_property
    def background_values(self) -> np.ndarray:
        """(N,) phi_h at every background node with the zero rule's snap (visits every node; the
        sides need them, S_h alone does not)."""
        if self.levelset is None:
            raise ValueError("this cut was made without its level set; cut with cut_mesh(background, levelset)")
        return snapped_nodal_values(self.background, self.levelset)

    @cached_property
    def _element_sets(self) -> dict:
        return {}

    def elements(self, which=CUT):
        """The element set ``NEG``, ``POS`` or ``CUT`` (:class:`cutfem.geometry.markers.ElementSet`, cached).

        NEG (POS): the tets with a part of positive volume on that side, and the cut tets; CUT: the
        tets that carry a piece of S_h.  See :mod:`cutfem.geometry.markers`."""
        if isinstance(which, ElementSet):
            return which
        sets = self._element_sets
        if which not in sets:
            if which == CUT:
                sets[CUT] = ElementSet(self.background, self.tet_ids, name=CUT, cut=self, tets=self.tets, node_ids=self.node_ids,
                                       points=self.points, gradients=self._grads_volumes[0], volumes=self._grads_volumes[1], normals=self.normals)
            elif which in SIDES:
                v, bg = self.background_values, self.background
                mark = bg.tet_node_counts(v < 0) > 0 if which == NEG else (bg.tet_node_counts(v > 0) > 0) | (bg.tet_node_counts(v == 0) == 4)
                mark[self.tet_ids] = True
                sets[which] = ElementSet(self.background, np.flatnonzero(mark), name=which, cut=self)
            else:
                raise ValueError(f"element sets of a cut are NEG, POS and CUT; got {which!r}")
        return sets[which]

    def interior_facets(self, which=CUT) -> FacetSet:
        """The faces shared by two tets of an element set (default: the cut tets, the faces of J_F)."""
        return self.elements(which).interior_facets

    def ghost_facets(self, side) -> FacetSet:
        """The ghost-penalty faces of a side: interior faces of its element set with at least one
        tet cut (for the bulk ghost penalty of docs/math.md §7; :func:`cutfem.geometry.markers.ghost_facets`)."""
        return ghost_facets(self.elements(side), self.tet_ids, side)

    def side_parts(self, side):
        """The cells of ``dx(side)`` (:class:`~cutfem.geometry.measures.SideVolume`): ``(whole (w,),
        sub (s, 4, 3), parent (s,))``, the tets of the side's element set that lie in the side and
        the side's part of the others as sub-tets, by the sign of phi_h at their nodes
        (:func:`~cutfem.geometry.markers.side_subtetrahedra`)."""
        es = self.elements(side)
        return side_subtetrahedra(es.points, es.tets, self.background_values[es.node_ids], side)

    @cached_property
    def _measures(self) -> dict:
        return {}

    def ds(self, where=None):
        """The measure on S_h = Gamma_h (:class:`cutfem.geometry.measures.SurfacePieces`), normal from NEG to POS.

        ``where``: only the part of S_h in a further domain, a level set's inside {psi_h < 0} (a
        plane, a ball, a callable) or a :class:`~cutfem.geometry.csg.Domain` of several: the pieces
        clipped exactly by the P1 interpolants (:func:`cutfem.geometry.csg_cut.tagged_pieces`), each
        with n_h, as a :class:`~cutfem.geometry.measures.BoundaryPart` (for mixed conditions on
        parts of Gamma_h without hand-made tags; ``where=cf.complement(psi)`` is the rest)."""
        if where is None:
            if "ds" not in self._measures:
                self._measures["ds"] = SurfacePieces(self)
            return self._measures["ds"]
        key = ("ds", id(where))
        hit = self._measures.get(key)
        if hit is None or hit[0] is not where:
            es = self.elements(CUT)
            points, tets, normals = tagged_pieces(es, self.triangle_points, self.triangle_tets, self.normals[self.triangle_tets], where)
            name = "Gamma_h where " + (str(where) if isinstance(where, Domain) else f"{where!r} < 0")
            hit = self._measures[key] = (where, BoundaryPart(es, points, tets, normals, name))
        return hit[1]

    def dx(self, where=NEG):
        """The volume measure of a side (``NEG``/``POS``: the cut volume parts,
        :class:`~cutfem.geometry.measures.SideVolume`) or of an element set (whole tets,
        :class:`~cutfem.geometry.measures.ElementVolume`)."""
        key = ("dx", where if isinstance(where, str) else id(where))
        if key not in self._measures:
            if isinstance(where, str) and where in SIDES:
                self._measures[key] = SideVolume(self, where)
            else:
                self._measures[key] = ElementVolume(self.elements(where))
        return self._measures[key]

    def release_measures(self) -> None:
        """Forget the cached measures (their quadrature points, sub-tets and facet data); the next
        ``dx``, ``ds`` or ``dF`` builds its measure again.  For a caller done with its forms that
        wants their memory for what follows (the distributed levels, for PETSc's matrix and
        preconditioner)."""
        self._measures.clear()

    def dF(self, facets):
        """The facet measure of a facet set (:class:`~cutfem.geometry.measures.FacetMeasure`)."""
        if not isinstance(facets, FacetSet):
            raise TypeError(f"dF takes a FacetSet (cut.interior_facets(...), cut.ghost_facets(...), or a subset of one), "
                            f"got {type(facets).__name__}")
        key = ("dF", id(facets))
        if key not in self._measures:
            self._measures[key] = FacetMeasure(facets)
        return self._measures[key]

    # -- sizes -----------------------------------------------------------------------------
    @property
    def h(self) -> float:
        """Global mesh size N**(-1/3), N = number of background nodes (:attr:`TetMesh.h`)."""
        return self.background.h

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    # -- geometry of S_h ---------------------------------------------------------------------
    @property
    def triangle_points(self) -> np.ndarray:
        """(T, 3, 3) vertex coordinates of each triangle of S_h (gathered on each access, not kept:
        80 MB at a million triangles)."""
        return self.vertices[self.triangles]

    @cached_property
    def triangle_areas(self) -> np.ndarray:
        return triangle_areas(self.vertices, self.triangles)

    @cached_property
    def piece_areas(self) -> np.ndarray:
        """(n,) area of the piece K in each active tet."""
        return np.bincount(self.triangle_tets, weights=self.triangle_areas, minlength=self.n_tets)

    @property
    def area(self) -> float:
        """Area of S_h."""
        return float(self.triangle_areas.sum())

    @cached_property
    def enclosed_volume(self) -> float:
        """Volume enclosed by S_h, by the divergence theorem (1/3) ∫ (x - o)·n: per triangle
        (1/6) a·(b x c), the vertices measured from the mean o of the vertices of S_h (the sum does
        not depend on o on a closed surface; from the origin, a mesh 1e4 away from it in its own
        units lost 3 digits: terms of 1e13 for a volume of 1)."""
        p = self.triangle_points - self.vertices.mean(axis=0)
        return float(np.einsum("ij,ij->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0)

    @cached_property
    def _edge_census(self) -> tuple:
        """(E, B): the number of distinct edges of the triangles of S_h and how many of them are not
        in exactly two triangles (:func:`cutfem.geometry.cut_kernels.edge_census`, one compiled pass; two
        numbers are kept, not a count per edge)."""

        return cut_kernels.edge_census(self.triangles, len(self.vertices))

    @property
    def euler_characteristic(self) -> int:
        """V - E + F of the triangulated S_h."""
        return len(self.vertices) - self._edge_census[0] + self.n_triangles

    @property
    def is_closed(self) -> bool:
        """Every triangle edge of S_h is shared by exactly two triangles."""
        return self._edge_census[1] == 0

    # -- active mesh -------------------------------------------------------------------------
    @cached_property
    def tet_vertices(self) -> np.ndarray:
        """(n, 4, 3) coordinates of the active tets."""
        return self.points[self.tets]

    @cached_property
    def _grads_volumes(self):
        if self._gradients is not None:
            return self._gradients
        grads, vol = barycentric_gradients(self.tet_vertices)
        return grads, np.abs(vol)

    @property
    def basis_gradients(self) -> np.ndarray:
        """(n, 4, 3) gradients of the P1 basis functions on each active tet (on a structured box read
        off the Kuhn table on each access, not kept: see :attr:`cutfem.geometry.markers.ElementSet.gradients`)."""
        return self.elements(CUT).gradients

    @property
    def tet_volumes(self) -> np.ndarray:
        """(n,) volumes of the active tets (on a structured box built on each access, not kept: see
        :attr:`cutfem.geometry.markers.ElementSet.volumes`)."""
        return self.elements(CUT).volumes

    # -- edges of S_h shared by pieces of neighbouring tets -----------------------------------
    @cached_property
    def _surface_edges(self):
        """The edges of the pieces' polygons from the triangles: an edge held by two triangles of
        different tets (a quadrilateral's diagonal is held by two triangles of one tet and is left
        out).  Edges in increasing (lower, upper) vertex order, the two tets in increasing order
        (the triangles are in tet order)."""
        t = self.triangles
        nxt = np.roll(t, -1, axis=1)  # half-edge k of triangle T, from vertex k to k + 1, at 3T + k
        lo = np.minimum(t, nxt).reshape(-1).astype(np.int64)
        hi = np.maximum(t, nxt).reshape(-1).astype(np.int64)
        order, starts, counts = pair_up(lo * len(self.vertices) + hi)
        if np.any(counts != 2):
            bad = int(np.sum(counts != 2))
            warnings.warn(
                f"{bad} edges of S_h are not shared by exactly two pieces (the zero set touches itself); "
                "they are left out of the edge stabilization",
                RuntimeWarning,
                stacklevel=3,
            )
        two = starts[counts == 2]
        a, b = order[two], order[two + 1]
        tets = np.stack([self.triangle_tets[a // 3], self.triangle_tets[b // 3]], axis=1)
        between = tets[:, 0] != tets[:, 1]
        a = a[between]
        return np.stack([lo[a], hi[a]], axis=1), tets[between]

    @property
    def surface_edges(self) -> np.ndarray:
        """(E, 2) vertex indices of the edges of S_h between the pieces of two tets."""
        return self._surface_edges[0]

    @property
    def surface_edge_tets(self) -> np.ndarray:
        """(E, 2) the active tets whose pieces share each surface edge."""
        return self._surface_edges[1]

    @cached_property
    def surface_edge_conormals(self) -> np.ndarray:
        """(E, 2, 3) t_{E,K}: unit, in the plane of piece K, orthogonal to E, pointing out of K."""
        e = self.surface_edges
        p0, p1 = self.vertices[e[:, 0]], self.vertices[e[:, 1]]
        d = p1 - p0
        out = np.empty((len(e), 2, 3))
        # centroid of each piece from its triangles
        cent = np.zeros((self.n_tets, 3))
        cnt = np.bincount(self.triangle_tets, minlength=self.n_tets).astype(float)
        tc = self.triangle_points.mean(axis=1)
        for k in range(3):
            cent[:, k] = np.bincount(self.triangle_tets, weights=tc[:, k], minlength=self.n_tets)
        cent /= cnt[:, None]
        for s in range(2):
            t = np.cross(d, self.normals[self.surface_edge_tets[:, s]])
            t /= np.linalg.norm(t, axis=1)[:, None]
            sign = np.sign(np.einsum("ij,ij->i", t, 0.5 * (p0 + p1) - cent[self.surface_edge_tets[:, s]]))
            out[:, s] = t * sign[:, None]
        return out

    @cached_property
    def surface_edge_lengths(self) -> np.ndarray:
        e = self.surface_edges
        return np.linalg.norm(self.vertices[e[:, 1]] - self.vertices[e[:, 0]], axis=1)

    def to_pyvista(self):
        """S_h as a ``pyvista.PolyData`` (cell data: parent tet)."""
        import pyvista as pv

        faces = np.hstack([np.full((self.n_triangles, 1), 3), self.triangles]).ravel()
        poly = pv.PolyData(self.vertices, faces)
        poly.cell_data["tet"] = self.triangle_tets
        return poly

    def active_mesh_pyvista(self):
        """The active tets as a ``pyvista.UnstructuredGrid``."""
        import pyvista as pv

        return pv.UnstructuredGrid({pv.CellType.TETRA: self.tets}, self.points)

    def __repr__(self) -> str:
        return (
            f"CutMesh(active_tets={self.n_tets}, active_nodes={self.n_nodes}, triangles={self.n_triangles}, "
            f"area={self.area:.6g}, h={self.h:.4g})"
        )


def _marching(tet_ids, labels, vals):
    """Marching tetrahedra on the candidate (cut) tets, tet by tet; see the module docstring.

    The polygon slots of a tet are the edges (i, j) (i inside, j outside) of the case table (:mod:`cutfem.geometry.marching`) of its
    sign code (bit k: node k inside); a slot is the point ``x_i + t (x_j - x_i)``,
    ``t = phi_i / (phi_i - phi_j)``, or the node j itself when phi_j == 0.  Two slots of a tet are
    the same vertex when they are the same node or the same edge; a tet whose piece has fewer than
    three distinct vertices (it collapsed to a point or a segment) is dropped.  One compiled pass
    (:func:`cutfem.geometry.cut_kernels.marching`) that compacts the three arrays in place; returns
    ``(tet_ids, labels, vals, code)`` of the kept tets."""

    n, code = cut_kernels.marching(tet_ids, labels, vals, EDGE_I, EDGE_J)
    return tet_ids[:n], labels[:n], vals[:n], code


def cut_mesh(background: TetMesh, levelset, *, check_boundary: bool = True, solve_bytes_per_tet: float | None = None,
             order: int = 1) -> CutMesh | CsgCut:
    """Cut a background tetrahedral mesh by the zero level set of the P1 interpolant of ``levelset``.

    ``order``: 1, the planar S_h; 2, the isoparametric geometry, the same cut lifted by the P2
    deformation Theta_h (:mod:`cutfem.geometry.isoparametric`): ``cut.dx(NEG|POS)``, ``cut.dx(elements)``
    and ``cut.ds()`` then integrate over the deformed cells (``cut.dF`` stays on the planar faces).
    Order 2 needs one level set given as a function (not a Domain of several, not nodal values).

    ``levelset``: a LevelSet (``value``, optional ``lipschitz``), a callable ``f(x)`` with x (..., 3),
    or an array of nodal values (N,) (not with a structured box's band search).  A
    :class:`~cutfem.geometry.csg.Domain` of several level sets (``cf.intersection(ball, plane)``) is
    cut by :func:`cutfem.geometry.csg_cut.cut_domain` into a :class:`~cutfem.geometry.csg_cut.CsgCut`
    (its level sets evaluated at every node; no band search or memory estimate).
    Raises :class:`~cutfem.geometry.nodal_values.CutError` when the level set does not cut the mesh,
    the surface reaches the box boundary (unless ``check_boundary=False``), the declared Lipschitz
    bound is seen to be broken (:func:`~cutfem.geometry.band_search._band_cells`) or S_h is not
    closed and edge-manifold (:func:`_check_closed`: every edge of its triangles in exactly two
    triangles; with ``check_boundary=False`` S_h may end on the faces of the box); ValueError for
    NaN/inf values.  See :mod:`cutfem.geometry.nodal_values` for the zero rule.

    :class:`cutfem.memory.InsufficientMemoryError` is raised before any large allocation when the
    cut of a structured box would not fit in memory
    (:func:`~cutfem.geometry.band_search.cut_memory_estimate`), naming a spacing that fits.
    ``solve_bytes_per_tet``: what the stages after the cut (space, matrices, solve) add per active
    tet, as :func:`cutfem.problems.common.check_cut_memory` counts it.  When given (the
    problems give theirs), the cut also refuses up front a spacing whose later stages would not fit,
    from the active tets it predicts, and its advice is a spacing at which the cut and those stages
    both fit: one estimate before the cut, with its one advice, instead of a cut that is made and then
    refused.  The check after the cut, on the real active tets, stays for what the prediction does not
    cover (no Lipschitz bound, unstructured backgrounds).
    """
    if order not in (1, 2) or isinstance(order, bool):
        raise ValueError(f"order must be 1 (the planar cut) or 2 (the isoparametric cut), got {order!r}")
    if isinstance(levelset, Domain):
        if order != 1:
            raise ValueError("order=2 lifts the cut of one level set; a Domain of several level sets is cut at order 1 "
                             "(cut each level set apart for an isoparametric geometry)")
        return cut_domain(background, levelset, check_boundary=check_boundary)
    if order == 2 and isinstance(levelset, np.ndarray):
        raise TypeError("order=2 needs the level set as a function (a LevelSet or a callable f(x)): phi_h2 takes its "
                        "values at the edge midpoints, which an array of nodal values does not have")
    lipschitz = _declared_lipschitz(levelset)
    mesh_distance = getattr(levelset, "is_distance", False) and getattr(levelset, "mesh", None) is not None
    structured = isinstance(background, StructuredBox)
    band = structured and lipschitz is not None and not isinstance(levelset, np.ndarray)  # band search used
    if isinstance(levelset, np.ndarray):
        values = nodal_values(background, levelset)
        values = _snap_zeros(values, _zero_tolerance(background, None, values))
        if check_boundary:
            _check_boundary(background, values)
        cand = _candidates_full(background, values)
    elif structured:
        f = _as_values_function(levelset)
        enclose = _enclosure_function(levelset) if band else None
        survey = _check_cut_memory(background, f, lipschitz, solve_bytes_per_tet, enclose=enclose)
        try:
            cand = _candidates_structured(background, f, lipschitz, None if survey is None else (*survey, solve_bytes_per_tet), enclose)
        except _BoundBroken as exc:
            if mesh_distance:  # its bound 1 is no declaration of the user's: say what is wrong with the mesh
                raise CutError(_mesh_distance_message(
                    levelset, f"|phi(x) - phi(y)| / |x - y| reaches {exc.ratio:.3g} between points the cut evaluated")) from None
            raise
        if check_boundary and band:
            _check_band_boundary(background, f, cand[3], cand[4])
        elif check_boundary:
            _check_boundary(background, cand[4])  # every node's snapped value: the cut's own signs
    else:
        values = nodal_values(background, levelset)
        values = _snap_zeros(values, _zero_tolerance(background, lipschitz, values))
        if check_boundary:
            _check_boundary(background, values)
        cand = _candidates_full(background, values)
    tet_ids, labels, vals, label_ids, label_values = cand
    if len(tet_ids) == 0:
        touching = _touching_only(background, label_ids, label_values)
        if touching:
            raise CutError(touching)
        raise CutError(
            "the level set does not cut the background mesh: no tetrahedron has nodal values of both signs. "
            "Check that the surface lies inside the box and is larger than a cell (refine the mesh), and that "
            "the level set is negative inside."
            + (" With the band search, also check that the declared Lipschitz bound (levelset.lipschitz) is "
               "a true bound." if band else "")
        )
    tet_ids, labels, vals, code = _marching(tet_ids, labels, np.ascontiguousarray(vals, dtype=float))
    del cand
    if len(tet_ids) == 0:
        raise CutError(
            "every piece of the cut collapsed to a point or a segment: the level set is negative only at nodes "
            "whose pieces have no area (its zero set meets the mesh in points or lines). Refine the background mesh "
            "if the surface is smaller than a cell; if it touches the box only on its boundary, move the box or "
            "the level set so that the surface lies inside the box.")
    m = len(tet_ids)

    # active nodes, numbered by increasing background id (labels increase with it); the tets' node
    # numbers int32 while they fit (209 MB less for the 13.7 million cut tets at spacing 0.003125)
    uniq, tets = dense_unique(labels, len(label_values))
    del labels
    node_ids = uniq if label_ids is None else label_ids[uniq]
    points = background.node_coordinates(node_ids) if structured else background.points[node_ids]
    values = label_values[uniq]
    p = len(node_ids)

    # basis gradients: the Kuhn table on a structured box (never kept: see ElementSet.gradients),
    # else from the vertices; normals n_h = grad phi_h / |grad phi_h| by a compiled pass

    if structured:
        grads = volumes = None  # every tet has the box's volume (see ElementSet.volumes)
        negative = None
        table, types = background.gradient_table, mesh_kernels.kuhn_types(tet_ids)
    else:
        grads, volumes = barycentric_gradients(points[tets])
        negative = volumes < 0
        volumes = np.abs(volumes)
        table, types = grads, np.arange(m)
    normals = np.empty((m, 3))
    cut_kernels.level_set_normals(vals, table, types, normals)
    if not np.isfinite(normals).all():  # grad phi_h = 0 or not finite: values beyond floating point (the kernel rescales the rest)
        bad = ~np.isfinite(normals).all(axis=1)
        big = float(np.max(np.abs(vals)))
        raise CutError(f"the normals n_h = grad phi_h / |grad phi_h| of {int(np.count_nonzero(bad))} cut tets are not "
                       f"finite: the level set's values (up to {big:.3g} in the cut tets) are too large or too small for "
                       "floating point. Scale the level set to values of the order of the distance to its zero set.")

    # surface vertices: key = active node (on-node vertex) or an edge key, numbered by key.  On a
    # structured box the lattice edge {v, v + e_S} (v = min: the active nodes increase with the
    # background ids) has the key p - 1 + 7 v + c(S) in [p, 8p), ordered as (v, max) (see
    # box.KUHN_EDGE_CODES): numbered by a marker array, with no sort
    key = cut_kernels.slot_keys(tets, code, vals, EDGE_I, EDGE_J, p, lattice=(KUHN_EDGE_CODES, types) if structured else None)
    del types
    vkeys, vinv = dense_unique(key, 8 * p) if structured else unique_keys(key.reshape(-1), return_inverse=True)
    n_vertices = len(vkeys)
    del key, vkeys
    # vertex numbers (and so the triangles) as int32 while they fit: 12 bytes a triangle, 16 a tet less
    vinv = vinv.astype(index_dtype(n_vertices), copy=False).reshape(m, 4)
    # each vertex computed once, from its first slot; triangles (0,1,2) and, for quads, (0,2,3),
    # tet by tet, without those with repeated vertices; orientation by n_h from the sign code (see
    # cutfem.geometry.marching.FLIP)
    vertices, tri, tri_tet = cut_kernels.surface(vinv, n_vertices, tets, code, vals, points, EDGE_I, EDGE_J, NVERT, FLIP,
                                             TRIANGLE_SLOTS, negative=negative)
    del vals, vinv

    cm = CutMesh(
        levelset=levelset,
        background=background,
        node_ids=node_ids,
        points=points,
        values=values,
        tets=tets,
        tet_ids=tet_ids,
        normals=normals,
        vertices=vertices,
        triangles=tri,
        triangle_tets=tri_tet,
        _gradients=(grads, volumes),  # None on a structured box: the Kuhn table and the box's tet volume serve them
    )
    try:
        _check_closed(cm, check_boundary, band)
    except CutError:
        crossing = _mesh_distance_message(levelset, "the cut surface S_h is not closed", True) if mesh_distance else ""
        if crossing:
            raise CutError(crossing) from None
        raise
    if order == 2:
        cm.deformation = Deformation(cm)
    return cm


def _touching_only(mesh: TetMesh, label_ids, label_values) -> str:
    """The message for a level set that is zero at some nodes and negative at none (no cut tet): its
    zero set meets the mesh in a set of zero area (a plane through an edge, a corner or a face of the
    box, a surface touching the box from outside), where no refinement can help; "" otherwise."""
    values = np.asarray(label_values)
    zero = values == 0
    if not np.any(zero) or np.any(values < 0):
        return ""
    ids = np.flatnonzero(zero) if label_ids is None else np.asarray(label_ids)[zero]
    if isinstance(mesh, StructuredBox):
        nx, ny, nz = (int(n) for n in mesh.node_shape)
        i, j, k = ids % nx, (ids // nx) % ny, ids // (nx * ny)
        on = (i == 0) | (i == nx - 1) | (j == 0) | (j == ny - 1) | (k == 0) | (k == nz - 1)
        x = mesh.node_coordinates(ids[:1])[0]
    else:
        on = np.isin(ids, mesh.boundary_nodes)
        x = mesh.points[ids[0]]
    n = f"{ids.size} node{'s' if ids.size != 1 else ''} (first at {np.round(x, 6).tolist()})"
    if np.all(on):
        return (f"the level set does not cut the background mesh: it is zero at {n}, all on the boundary of the mesh, "
                "and negative at none: it touches the box only on its boundary (its zero set meets the box in a point, "
                "a line or a face, a set of zero area, with phi >= 0 inside the box), so S_h is empty and refining the "
                "mesh cannot help. Move the box or the level set so that the surface lies inside the box, with phi < 0 "
                "inside the surface.")
    return (f"the level set does not cut the background mesh: it is zero at {n}, {int(np.count_nonzero(on))} of them on "
            "the boundary of the mesh, and negative at none: its zero set meets the mesh only in a set of zero area "
            "(phi >= 0 on both sides of it, e.g. abs(x) or a surface touching nodes from outside), so S_h is empty. A "
            "level set must be negative inside the surface; refine the mesh only if the surface is smaller than a cell.")


def _on_boundary_faces(cut: CutMesh, ends: np.ndarray, pieces: np.ndarray) -> np.ndarray:
    """(k,) bool: whether each edge of S_h, given by its ends (k, 2, 3) and the cut tet of its
    triangle (``pieces``, (k,) indices into the cut's tets), lies in a face of that tet which is a
    boundary face of the background (one tet).  The edges of a piece lie in the faces of its tet:
    the face is the one opposite to the vertex whose barycentric coordinate vanishes at both ends
    (up to 1e-9; the ends are computed on the tet's edges, so it is round-off there)."""
    bg = cut.background
    tets = cut.tet_ids[pieces]
    x = bg.points[bg.tets[tets]]  # (k, 4, 3)
    grads, _ = barycentric_gradients(x)
    lam = np.einsum("kjd,ked->kej", grads, ends - x[:, None, 0])  # (k, 2, 4): lambda_j at each end
    lam[:, :, 0] += 1.0
    far = np.abs(lam).max(axis=1)  # (k, 4): the larger of the two ends' coordinates of each vertex
    k = np.argmin(far, axis=1)
    faces = bg.tet_faces[tets, k]
    return (far[np.arange(len(k)), k] <= 1e-9) & (bg.face_tets[faces, 1] < 0)


def _check_closed(cut: CutMesh, check_boundary: bool, band: bool) -> None:
    """Raise CutError unless S_h is closed and edge-manifold: every edge of its triangles in
    exactly two triangles.

    Uses the edge census of :attr:`CutMesh._edge_census` (one compiled pass, cached: the Euler
    characteristic and ``is_closed`` reuse it).  With ``check_boundary=False`` the surface may
    leave the mesh: an edge in one triangle is then accepted when it lies on the boundary, on a
    structured box when both its ends lie on the faces of its bounding box (within 1e-9 of its
    diagonal), on any other mesh when it lies in a boundary face of its tet
    (:func:`_on_boundary_faces`: a part of a larger mesh, such as a rank's cells in a distributed
    run, has boundary faces inside the bounding box).  The P1 zero set of values at
    every node is always closed inside the mesh, so an open S_h means that the band search
    (``band``) dropped cut cells: phi changes faster than its declared Lipschitz bound somewhere
    it was not sampled (see :func:`~cutfem.geometry.band_search._band_cells`)."""
    if cut.is_closed:
        return
    t = cut.triangles
    V = len(cut.vertices)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]).astype(np.int64)
    keys = np.minimum(e[:, 0], e[:, 1]) * V + np.maximum(e[:, 0], e[:, 1])
    order, starts, counts = pair_up(keys)
    edges = e[order[starts]]
    open_ = counts == 1
    if not check_boundary and np.any(open_):
        if isinstance(cut.background, StructuredBox):
            lo, hi = (np.asarray(b, float) for b in cut.background.bounds)
            eps = 1e-9 * float(np.linalg.norm(hi - lo))
            x = cut.vertices[edges[open_]]  # (k, 2, 3)
            on_face = np.all(np.any((np.abs(x - lo) <= eps) | (np.abs(x - hi) <= eps), axis=2), axis=1)
        else:
            rows = order[starts[open_]]  # the edge's row in e: triangle rows % len(t)
            on_face = _on_boundary_faces(cut, cut.vertices[edges[open_]], cut.triangle_tets[rows % len(t)])
        open_[np.flatnonzero(open_)[on_face]] = False
    many = counts > 2
    if not (np.any(open_) or np.any(many)):
        return
    first = edges[open_ | many][0]
    where = cut.vertices[first].mean(axis=0)
    cause = (
        "the level set changes faster than its declared Lipschitz bound (levelset.lipschitz), so the band "
        "search dropped cut cells: declare a true bound, or None to evaluate every node"
        if band
        else "the zero set of phi_h touches or crosses itself: refine the background mesh or move the level set"
    )
    raise CutError(
        f"the cut surface S_h is not a closed manifold: {int(open_.sum())} edges lie in one triangle only and "
        f"{int(many.sum())} in more than two (first near {np.round(where, 6).tolist()}). Likely cause: {cause}. "
        "A signed distance to a surface mesh whose closed components overlap or intersect (for example a model "
        "made of overlapping parts) has this defect too: repair the mesh into one closed surface without "
        "self-intersections."
    )
