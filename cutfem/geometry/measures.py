"""Measures: integration domains that own their quadrature (docs/math.md §7).

A measure is independent of any field: it knows its cells (or facets), the element each cell lies
in, the local size h and, where one exists, the normal.  Forms are written ``integrand * measure``
(:mod:`cutfem.fem.forms`) and a field can be integrated over any measure whose elements it lives on.

====================  ==========================================  ===============================
measure               cells (quadrature)                          made by
====================  ==========================================  ===============================
:class:`SurfacePieces`   the pieces of Gamma_h (S_h), triangles     ``cut.ds()``
:class:`BoundaryPart`    triangles of (a part of) a boundary,       ``cut.ds(part, where=...)``
                         each with its outward normal
:class:`SideVolume`      the part of each tet on one side,          ``cut.dx(NEG)``, ``cut.dx(POS)``
                         sub-tetrahedra
:class:`ElementVolume`   whole tets of an element set               ``cut.dx(cut.elements(CUT))``
:class:`FacetMeasure`    faces of a facet set; two traces           ``cut.dF(facets)``
:class:`MeshedSurface`   the triangles of a surface mesh            ``mesh.ds()``
====================  ==========================================  ===============================

Every measure has ``elements`` (the element set, or the surface mesh, its cells lie in),
``quadrature(degree)`` (a :class:`~cutfem.geometry.quadrature.Quadrature` whose ``parent`` indexes
``elements``; for a facet measure it indexes the facets), ``h`` (local size per element or facet),
``normals`` (per element or facet, or None) and ``surface`` (True for two-dimensional domains, where
gradients in integrands have a tangential part ``tgrad``).  ``blocks(degree)`` gives the same
quadrature a block of cells at a time; the errors and the integrand forms use it, and the volume
measures then map each block's tetrahedra on demand instead of storing the whole quadrature.

On a cut made with ``order=2`` the measures of the cut (all but ``dF``) carry its ``deformation``
Theta_h and map every quadrature they give, whole or by blocks, onto the deformed cells
(:mod:`cutfem.geometry.isoparametric`); at order 1 ``deformation`` is None and nothing changes.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from .markers import CUT, NEG, POS, longest_edges
from .quadrature import Quadrature, map_tetrahedra, map_triangles, signed_volumes

__all__ = ["Measure", "SurfacePieces", "BoundaryPart", "SideVolume", "ElementVolume", "FacetMeasure", "MeshedSurface",
           "surface_measure"]


#: the degree of the quadrature that gives the :attr:`Measure.size` of a deformed measure (its
#: Jacobian factor is no constant on a cell; the error of this rule is O(h^5), below the geometry's)
DEFORMED_SIZE_DEGREE = 4

#: cells per block of :meth:`Measure.blocks`: at degree 4 a block of tets holds 14 points a cell,
#: 22 MB of coordinates, small enough that a block's temporaries stay few and short-lived
BLOCK_CELLS = 1 << 16


class Measure:
    """Base class: quadrature cached per degree; see the module docstring."""

    surface = False
    facets = None
    #: Theta_h of an isoparametric cut (:class:`cutfem.geometry.isoparametric.Deformation`), which maps
    #: every quadrature of the measure (:meth:`_deformed`); None: the planar cells
    deformation = None

    def __init__(self, elements, name: str):
        self.elements = elements
        self.name = name
        self._quadratures: dict = {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    def quadrature(self, degree: int = 2) -> Quadrature:
        """The quadrature of the given degree (cached)."""
        if degree not in self._quadratures:
            self._quadratures[degree] = self._deformed(self._build(degree))
        return self._quadratures[degree]

    def _deformed(self, quad: Quadrature) -> Quadrature:
        """A quadrature of the planar cells mapped by the measure's :attr:`deformation` (itself at order 1)."""
        return quad if self.deformation is None else self.deformation.deform(quad, self.elements, self.surface)

    def _build(self, degree: int) -> Quadrature:  # pragma: no cover - abstract
        raise NotImplementedError

    def blocks(self, degree: int = 2, size: int = BLOCK_CELLS):
        """The quadrature of the given degree in blocks of at most ``size`` cells: (cells, Quadrature)
        pairs, ``cells`` a slice of the cell numbering.  Consumers that go block by block (the
        errors, the assembly of integrand forms) never hold more than one block's points, basis
        values and integrand values.  Here: slices of the cached :meth:`quadrature`; the volume
        measures map each block's tetrahedra on demand instead, so that their quadrature points
        (at degree 4, 14 points a tet, 0.75 GB for 1.6 million tets) are never stored whole."""
        quad = self.quadrature(degree)
        for start in range(0, quad.n_elements, size):
            stop = min(start + size, quad.n_elements)
            yield slice(start, stop), quad.cells(start, stop)

    @property
    def h(self) -> np.ndarray:
        """(m,) local size of the elements (h_T) or facets (h_F)."""
        return self.elements.h

    @property
    def normals(self):
        return None

    def integrate(self, f, degree: int = 4):
        """The integral of ``f(x)`` (x (m, q, 3) -> (m, q) or (m, q, c)) over the measure."""
        quad = self.quadrature(degree)
        return quad.integrate(np.asarray(f(quad.points), dtype=float))

    @property
    def size(self) -> float:
        """The measure of the whole domain (area or volume)."""
        if self.deformation is None:
            return float(self.quadrature(0).weights.sum())
        return float(sum(quad.weights.sum() for _, quad in self.blocks(DEFORMED_SIZE_DEGREE)))


class SurfacePieces(Measure):
    """ds over Gamma_h = S_h: the planar piece of each cut tet, split into triangles, with the
    normal n_h = grad phi_h / |grad phi_h| pointing from NEG to POS."""

    surface = True

    def __init__(self, cut):
        super().__init__(cut.elements(CUT), "Gamma_h")
        self.cut = cut
        self.deformation = cut.deformation

    def _build(self, degree):
        c = self.cut  # the triangles of the pieces from the cut's vertices, with their areas and normals n_h
        return map_triangles(c.vertices, degree, parent=c.triangle_tets, normal=c.normals[c.triangle_tets], areas=c.triangle_areas,
                             triangles=c.triangles)

    @property
    def normals(self):
        return self.cut.normals

    @property
    def piece_areas(self) -> np.ndarray:
        """(m,) area of the piece in each cut tet."""
        return self.cut.piece_areas

    @property
    def size(self) -> float:
        return self.cut.area if self.deformation is None else super().size

    def side_fraction(self, side: str) -> np.ndarray:
        """(m,) |T ∩ side| / |T| for each cut tet T (the cut-volume weights of the interface problem)."""
        volume = self.cut.dx(side)
        local = volume.elements.locate_set(self.elements, what="Gamma_h")
        return volume.part_volumes[local] / self.elements.volumes


class BoundaryPart(Measure):
    """ds over (a part of) the boundary of a cut domain: flat triangles ``points`` (T, 3, 3), each in
    a cut tet ``parent`` (T,) of ``elements`` with its own outward unit normal ``normals`` (T, 3).
    Several parts of a domain with edges meet in one tet at different normals, so the normal is the
    triangle's, not the tet's (``w.n`` in an integrand).  Made by ``cut.ds(part, where=...)`` of a
    cut by several level sets (:class:`cutfem.geometry.csg_cut.CsgCut`) and ``cut.ds(where=...)`` of
    a cut by one (a tagged part of S_h)."""

    surface = True

    def __init__(self, elements, points, parent, normals, name: str):
        super().__init__(elements, name)
        self.deformation = None if elements.cut is None else elements.cut.deformation
        self.points = np.asarray(points, dtype=float).reshape(-1, 3, 3)
        self.parent = np.asarray(parent, dtype=np.int64)
        self.triangle_normals = np.asarray(normals, dtype=float).reshape(-1, 3)

    def _build(self, degree):
        return map_triangles(self.points, degree, parent=self.parent, normal=self.triangle_normals)

    @property
    def n_cells(self) -> int:
        return len(self.parent)

    @cached_property
    def areas(self) -> np.ndarray:
        """(T,) the areas of the triangles."""
        p = self.points
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)

    @property
    def size(self) -> float:
        return float(self.areas.sum()) if self.deformation is None else super().size


class SideVolume(Measure):
    """dx over one side (NEG or POS) of the cut: whole tets inside the side and, in the cut tets, the
    side's part as sub-tetrahedra (from the cut's ``side_parts``: split by one plane,
    :func:`cutfem.geometry.markers.side_subtetrahedra`, or clipped by several,
    :mod:`cutfem.geometry.csg_cut`)."""

    def __init__(self, cut, side: str):
        if side not in (NEG, POS):
            raise ValueError(f"a side is NEG or POS, got {side!r}")
        super().__init__(cut.elements(side), f"{side} side")
        self.cut = cut
        self.side = side
        self.deformation = cut.deformation

    @cached_property
    def _parts(self):
        """(whole (w,), sub (s, 4, 3), parent (s,)): the elements that lie in the side, and the side's
        part of the cut elements as tetrahedra, from the cut (:meth:`cutfem.geometry.cut.CutMesh.side_parts`,
        :meth:`cutfem.geometry.csg_cut.CsgCut.side_parts`)."""
        return self.cut.side_parts(self.side)

    @property
    def whole_cells(self) -> int:
        """The number of leading cells that are whole elements, in their own vertex order (their
        basis values are the rule's barycentric coordinates); the sub-tets of the cut elements follow."""
        return len(self._parts[0])

    @property
    def n_cells(self) -> int:
        return self.whole_cells + len(self._parts[1])

    @cached_property
    def cell_parent(self) -> np.ndarray:
        """(n_cells,) the element of each cell."""
        whole, _, parent = self._parts
        return np.concatenate([whole, parent])

    def cell_vertices(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(stop - start, 4, 3) vertices of the cells start..stop-1: the whole elements' are gathered
        on demand (they are not stored twice), the sub-tets' sliced."""
        whole, sub, _ = self._parts
        w = len(whole)
        stop = self.n_cells if stop is None else stop
        es = self.elements
        head = es.points[es.tets[whole[min(start, w) : min(stop, w)]]]
        tail = sub[max(start - w, 0) : max(stop - w, 0)]
        return tail if len(head) == 0 else head if len(tail) == 0 else np.concatenate([head, tail])

    @property
    def whole_elements(self) -> np.ndarray:
        """(w,) the elements that lie wholly in the side: the first w cells, in this order."""
        return self._parts[0]

    @property
    def sub_tets(self):
        """(vertices (s, 4, 3), parent (s,)): the side's parts of the cut elements as sub-tets, the
        cells after the whole ones, with their :attr:`sub_volumes`."""
        return self._parts[1], self._parts[2]

    @cached_property
    def sub_volumes(self) -> np.ndarray:
        """(s,) the volumes of the sub-tets of the cut elements (the cells after the whole ones)."""
        return np.abs(signed_volumes(self._parts[1]))

    @cached_property
    def cell_volumes(self) -> np.ndarray:
        """(n_cells,) the volume of each cell: the element's own for the whole cells, the triple
        products of the sub-tets (computed once for every quadrature of the measure)."""
        return np.concatenate([self.elements.volumes_of(self._parts[0]), self.sub_volumes])

    @cached_property
    def part_volumes(self) -> np.ndarray:
        """(m,) |T ∩ side| per element: the whole element's volume for the whole cells, the sum of the
        sub-tets' volumes in the others (0 for an element with no part on the side).  Formed from
        the whole cells and the sub-tets apart, without the per-cell arrays (at 2.7 million unknowns
        their concatenations took more than a second, most of it first touches of memory)."""
        whole, _, parent = self._parts
        es = self.elements
        # the cut elements' sums first, then the whole ones (disjoint from them) written in place
        out = np.bincount(parent, weights=self.sub_volumes, minlength=es.n_elements) if len(parent) else np.zeros(es.n_elements)
        out[whole] = es.volumes_of(whole) if es.uniform_volume is None else es.uniform_volume  # no array of a constant
        return out

    def _build(self, degree):
        return map_tetrahedra(self.cell_vertices(), degree, parent=self.cell_parent, whole=self.whole_cells, volumes=self.cell_volumes)

    def blocks(self, degree: int = 2, size: int = BLOCK_CELLS):
        """Blocks of at most ``size`` cells, the whole elements first (their points mapped from the
        element set's nodes, :func:`~cutfem.geometry.quadrature.mapped_points`), then the sub-tets: a block
        never mixes the two, and neither needs the per-cell arrays."""
        whole, sub, parent = self._parts
        es, w = self.elements, len(whole)
        for start in range(0, w, size):
            cells = whole[start : start + size]
            tets = np.take(es.tets, cells, axis=0)  # rows gathered 2.5 times as fast as by fancy indexing
            yield slice(start, start + len(cells)), self._deformed(map_tetrahedra(es.points, degree, parent=cells, whole=len(cells),
                                                                                  volumes=es.volumes_of(cells), tets=tets))
        volumes = self.sub_volumes
        for start in range(0, len(sub), size):
            stop = min(start + size, len(sub))
            yield slice(w + start, w + stop), self._deformed(map_tetrahedra(sub[start:stop], degree, parent=parent[start:stop],
                                                                            whole=0, volumes=volumes[start:stop]))

    @property
    def size(self) -> float:
        return float(self.part_volumes.sum()) if self.deformation is None else super().size


class ElementVolume(Measure):
    """dx over the whole tets of an element set (e.g. the cut tets, for the normal-gradient term)."""

    def __init__(self, elements):
        super().__init__(elements, f"tets of {elements.name}")
        self.whole_cells = elements.n_elements
        self.deformation = None if elements.cut is None else elements.cut.deformation

    def _build(self, degree):
        return map_tetrahedra(self.elements.vertices, degree, whole=self.whole_cells, volumes=self.elements.volumes)

    def blocks(self, degree: int = 2, size: int = BLOCK_CELLS):
        es = self.elements
        for start in range(0, es.n_elements, size):
            stop = min(start + size, es.n_elements)
            yield slice(start, stop), self._deformed(map_tetrahedra(es.points, degree, parent=np.arange(start, stop), whole=stop - start,
                                                                    volumes=es.volumes_of(slice(start, stop)), tets=es.tets[start:stop]))

    @property
    def normals(self):
        return self.elements.normals

    def _deformed(self, quad: Quadrature) -> Quadrature:
        """On a lifted cut the tets' normals are lifted too: at each point J^-T n_h / |J^-T n_h|, J =
        D Theta_h, the normal of the level sets of phi_h1 o Theta_h^-1 (docs/math.md §18); the planar
        n_h is only O(h) from the normal of S there, which the normal-gradient term would see."""
        quad = super()._deformed(quad)
        if quad.jacobians is None or self.normals is None:
            return quad
        n = np.broadcast_to(self.normals[quad.parent][:, None, :, None], quad.jacobians.shape[:2] + (3, 1))
        g = np.linalg.solve(np.swapaxes(quad.jacobians, -1, -2), n)[..., 0]
        quad.normal = g / np.linalg.norm(g, axis=-1, keepdims=True)
        return quad

    @property
    def part_volumes(self) -> np.ndarray:
        return self.elements.volumes

    # the cells are the elements themselves (the same names as a side's volume)
    n_cells = property(lambda self: self.whole_cells)
    cell_volumes = part_volumes
    cell_parent = property(lambda self: np.arange(self.whole_cells))
    whole_elements = cell_parent


class FacetMeasure(Measure):
    """dF over a facet set: each face with its minus and plus tets and the unit normal n_F from the
    minus into the plus tet.  In integrands a field has both traces (``u.minus``, ``u.plus``)."""

    def __init__(self, facets):
        super().__init__(facets.elements, facets.name)
        self.facets = facets

    def _build(self, degree):
        f = self.facets
        return map_triangles(f.vertices, degree, normal=f.normals)

    @property
    def h(self) -> np.ndarray:
        return self.facets.h

    @property
    def normals(self):
        return self.facets.normals


class MeshedSurface(Measure):
    """dS over the triangles of a surface mesh (:class:`cutfem.geometry.surface.SurfaceMesh`); the elements
    are the mesh itself and h is the longest edge of each triangle."""

    surface = True

    def __init__(self, mesh):
        super().__init__(mesh, "surface mesh")
        self.mesh = mesh

    def _build(self, degree):
        m = self.mesh
        # the mesh's own triangles in their vertex order (whole): the basis values are the rule's bary
        return map_triangles(m.points, degree, normal=m.normals, areas=m.areas, triangles=m.triangles, whole=m.n_triangles)

    @property
    def normals(self):
        return self.mesh.normals

    @cached_property
    def h(self) -> np.ndarray:
        return longest_edges(self.mesh.points, self.mesh.triangles)

    @property
    def size(self) -> float:
        return float(self.mesh.areas.sum())


def surface_measure(space) -> Measure:
    """The measure on S_h of a surface field: the pieces of its cut (a field on the cut tets) or the
    triangles of its surface mesh; a clear error for a bulk field."""
    if hasattr(space, "cut"):
        space._require_trace("a measure on S_h")
        return space.cut.ds()
    return space.mesh.ds()
