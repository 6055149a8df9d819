"""Continuous Lagrange fields: P1 on a triangulated surface, P1 or P2 on an element set of a cut.

Every space exposes the same plain arrays, so that forms are written once:

``n_dofs``; ``order``; ``element_dofs`` (n_el, k) global dof numbers of each element (triangles,
k = 3, or tets, k = 4; P2 tets k = 10, :mod:`cutfem.fem.lagrange`); ``element_gradients`` (n_el, 4 or
3, 3) the constant gradients of the P1 basis functions (the barycentric coordinates)
(on a surface triangle this is already the surface gradient); ``element_normals`` (n_el, 3) the
discrete normal n_h (surface and trace spaces; None for bulk fields); ``elements`` the element set
(or surface mesh) the field lives on, which :mod:`cutfem.fem.forms` matches against the elements of a
measure; ``h`` the global mesh size, the abscissa of convergence tables (docs/math.md §2).

Measures are not owned by spaces: see :mod:`cutfem.geometry.measures`.  A vector field [V_h]^3 is
:class:`VectorSpace` of a scalar space (one block of 3 n unknowns, component-major); a constant, one
unknown (a Lagrange multiplier), is :class:`RealSpace`; several fields together form a
:class:`ProductSpace` with a block numbering of their dofs.  (Several scalar right-hand sides at
once are still (n, c) arrays of coefficients sharing one scalar matrix.)
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from .assembly import SymmetricPattern
from ..geometry.markers import CUT, ElementSet, same_background
from ..geometry.surface import positive_number
from . import element_kernels
from .lagrange import edge_numbering, map_gradients, map_hessians, p2_gradients, p2_hessians, p2_values

__all__ = ["SurfaceP1Space", "CutSpace", "VectorSpace", "RealSpace", "ProductSpace", "triangle_gradients", "barycentric_at"]


def triangle_gradients(vertices: np.ndarray):
    """Surface gradients of the barycentric coordinates of triangles in R^3.

    ``vertices`` (m, 3, 3).  With unit normal n and area A, ``grad lambda_i = n x (x_{i+2} - x_{i+1}) / (2A)``
    (indices mod 3): tangent to the triangle, orthogonal to the opposite edge, of length 1/height.
    Returns ``(grads (m, 3, 3), normals (m, 3), areas (m,))``; one compiled pass
    (:func:`cutfem.fem.element_kernels.triangle_gradients`).
    """

    v = np.ascontiguousarray(vertices, dtype=float)
    if v.ndim != 3 or v.shape[1:] != (3, 3):
        raise ValueError(f"vertices must have shape (m, 3, 3), got {v.shape}")
    m = len(v)
    grads, normals, areas = np.empty((m, 3, 3)), np.empty((m, 3)), np.empty(m)
    element_kernels.triangle_gradients(v, grads, normals, areas)
    return grads, normals, areas


def barycentric_at(points: np.ndarray, origin: np.ndarray, grads: np.ndarray) -> np.ndarray:
    """P1 basis values at ``points`` (m, q, 3) of elements with first vertex ``origin`` (m, 3) and
    basis gradients ``grads`` (m, k, 3): ``lambda_k(x) = delta_k0 + grad lambda_k . (x - x_0)``."""

    points = np.ascontiguousarray(points, dtype=float)
    grads = np.ascontiguousarray(grads, dtype=float)
    lam = np.empty(points.shape[:2] + grads.shape[1:2])
    # compiled: numpy's batched matmul took 0.27 s against 0.05 s for the 73 cut-cell blocks of the
    # fictitious-domain Poisson problem's load and errors at spacing 0.025
    element_kernels.barycentric_values(points, np.ascontiguousarray(origin, dtype=float), grads, lam)
    return lam


def _mesh_size(h, default) -> float:
    """The global mesh size ``h`` of a space (``default`` when None): a positive finite number."""
    return float(default) if h is None else positive_number(h, "h (the mesh size)")


class _ScalarSpace:
    """Shared machinery: cached sparsity patterns (surface meshes) and evaluation of discrete functions."""

    element_dofs: np.ndarray
    n_dofs: int
    order = 1

    def _patterns(self):
        if "_pattern_cache" not in self.__dict__:
            self.__dict__["_pattern_cache"] = {}
        return self.__dict__["_pattern_cache"]

    def gradients_of(self, elements) -> np.ndarray:
        """The basis gradients of the given elements, ``element_gradients[elements]``."""
        return self.element_gradients[elements]

    def _coefficients(self, coeffs) -> np.ndarray:
        """``coeffs`` as an array of shape (n_dofs,) or (n_dofs, c), or a ValueError naming the shapes
        (and, for a longer vector, the block of a product space's vector, which is the usual cause)."""
        coeffs = np.asarray(coeffs)
        if coeffs.ndim not in (1, 2) or len(coeffs) != self.n_dofs:
            hint = ""
            if coeffs.ndim in (1, 2) and len(coeffs) > self.n_dofs:
                hint = ("; a vector of a ProductSpace holds the coefficients of all its fields: pass this field's block, "
                        "W.split(x)[k]")
            raise ValueError(f"coefficients of this space have shape ({self.n_dofs},) or ({self.n_dofs}, c), got {coeffs.shape}{hint}")
        return coeffs

    def gradient_lookup(self):
        """(table, types) with ``gradients_of(i) = table[types[i]]``, for compiled kernels: here the
        element gradients and 0..n_el-1."""
        return self.element_gradients, np.arange(self.n_elements)

    def barycentric_at(self, points: np.ndarray, parent: np.ndarray) -> np.ndarray:
        """(m, j, 4) (3 on triangles) barycentric coordinates of element ``parent[i]`` at ``points[i]`` (m, j, 3)."""
        return barycentric_at(points, self.dof_points[self.element_dofs[parent, 0]], self.gradients_of(parent))

    def basis_at(self, points: np.ndarray, parent: np.ndarray) -> np.ndarray:
        """(m, j, k) basis values of element ``parent[i]`` at ``points[i]`` (m, j, 3): the barycentric
        coordinates (P1), or the P2 basis of them (:func:`~cutfem.fem.lagrange.p2_values`)."""
        lam = self.barycentric_at(points, parent)
        return lam if self.order == 1 else p2_values(lam)

    @property
    def tangential_gradients(self) -> np.ndarray:
        """(n_el, k, 3) P_h grad of the basis functions, P_h = I - n_h n_h^T per element; computed on
        each access, not kept (as large as the gradients); :meth:`tangential_gradients_of` for a
        block of elements."""
        return self.tangential_gradients_of(slice(None))

    def tangential_gradients_of(self, elements) -> np.ndarray:
        """P_h grad of the basis functions on the given elements: (b, k, 3)."""
        G, n = self.gradients_of(elements), self.element_normals[elements]
        return G - np.einsum("mkd,md->mk", G, n)[..., None] * n[:, None, :]

    def local_elements(self, measure, parent=None) -> np.ndarray:
        """The field's element of each cell of ``measure`` (its ``quadrature().parent``, or the given
        ``parent`` ids of the measure's elements); a clear error where the field does not live, and
        for a measure on another background mesh (:meth:`~cutfem.geometry.markers.ElementSet.locate_set`: tet
        ids are compared only on one background)."""
        if parent is None:
            parent = measure.quadrature(0).parent
        if measure.elements is self.elements:
            return parent
        if not isinstance(measure.elements, ElementSet) or not isinstance(self.elements, ElementSet):
            raise ValueError(f"the field on {getattr(self.elements, 'name', self.elements)!r} does not live on the measure {measure.name!r}")
        return self.elements.locate_set(measure.elements, parent, f"the measure {measure.name!r}")

    def _whole(self, measure, quad) -> int:
        """How many first cells of ``quad`` are whole elements of the field (their barycentric
        coordinates the rule's own, :meth:`_barycentric_on`)."""
        return quad.whole if measure.elements is self.elements and quad.bary is not None else 0

    def _barycentric_on(self, measure, quad, elements) -> np.ndarray:
        """(m, q, 4) barycentric coordinates of the points of ``quad`` (a quadrature of ``measure``; its
        ``reference_points`` on a deformed geometry) in the field's ``elements``.  Cells that are whole
        elements of the field (``quad.whole``, the first cells of a side's volume, when the measure's
        elements are the field's) take the reference barycentric coordinates of the rule as they are
        (a broadcast view when all cells are whole); the others are mapped."""
        whole = self._whole(measure, quad)
        m = quad.n_elements
        points = quad.points if quad.reference_points is None else quad.reference_points
        if whole == 0:
            return self.barycentric_at(points, elements)
        if whole == m:
            return np.broadcast_to(quad.bary, (m,) + quad.bary.shape)
        lam = np.empty(points.shape[:2] + (quad.bary.shape[1],))
        lam[:whole] = quad.bary
        lam[whole:] = self.barycentric_at(points[whole:], elements[whole:])
        return lam

    def basis_on(self, measure, quad, elements) -> np.ndarray:
        """(m, q, k) basis values at the points of ``quad`` (a quadrature of ``measure``) in the field's
        ``elements`` (:meth:`_barycentric_on`; of P2, :func:`~cutfem.fem.lagrange.p2_values` of them)."""
        lam = self._barycentric_on(measure, quad, elements)
        if self.order == 1:
            return lam
        if lam.strides[0] == 0:  # whole cells: one table
            return np.broadcast_to(p2_values(lam[0]), lam.shape[:2] + (10,))
        return p2_values(lam, self._whole(measure, quad))

    def derivatives(self, measure, quad, elements, points=None, cells=None, hessians=True):
        """(values (m, q, k), gradients (m, q or 1, k, 3), Hessians (m, q or 1, k, 3, 3) or None) of
        the basis at the points of ``quad`` in the field's ``elements``, or at ``points`` of the
        measure's element ``cells`` (the traces of a facet's two tets).  P1 gradients are constant
        (one point axis of 1) and its Hessians zero (None); P2 from :mod:`cutfem.fem.lagrange`.

        On a deformed geometry the field is composed with Theta_h^-1: its basis is evaluated at the
        undeformed points (``quad.reference_points``), its gradients map as D Theta_h^-T grad^ and
        its Hessians with Theta_h's own (:func:`~cutfem.fem.lagrange.map_hessians`).  D Theta_h is
        ``quad.jacobians`` on cells; on the planar faces of a deformed cut (which stay planar,
        docs/math.md §17) each trace takes its own tet's D Theta_h at the face's points, so that the
        jumps across a face are those of the lifted fields (zero for a smooth function).
        ``hessians=False``: None for the Hessians, not computed."""
        lam = self._barycentric_on(measure, quad, elements) if points is None else self.barycentric_at(points, elements)
        G = self.gradients_of(elements)
        if self.order == 1:
            values, grads = lam, G[:, None]
        else:
            whole = 0 if points is not None else self._whole(measure, quad)
            values, grads = p2_values(lam, whole), p2_gradients(lam, G, whole)
        J, moved = self._jacobians(measure, quad, cells, points)
        if moved is not None:
            grads = np.array(np.broadcast_to(grads, J.shape[:2] + grads.shape[2:]))
            grads[moved] = map_gradients(grads[moved], J[moved])
        hess = self.hessians(measure, quad, elements, grads, cells, points, (J, moved)) if hessians else None
        return values, grads, hess

    def _jacobians(self, measure, quad, cells=None, points=None):
        """(D Theta_h (m, q, 3, 3), the indices of the cells it moves) at the points of ``quad`` (or at
        a face trace's ``points`` of the tets ``cells``), or (None, None) on an undeformed geometry.
        Theta_h is the identity on most cells (all but the cut ones), where the undeformed gradients
        and Hessians are kept as they are (the mapping by I would leave them unchanged)."""
        J = quad.jacobians
        if points is not None:  # a face's trace: the deformation of the cut its tets belong to
            deformation = getattr(getattr(measure.elements, "cut", None), "deformation", None)
            J = None if deformation is None else deformation.map(measure.elements, cells, points)[1]
        if J is None:
            return None, None
        return J, np.flatnonzero(np.any(J != np.eye(3), axis=(1, 2, 3)))

    def hessians(self, measure, quad, elements, grads, cells=None, points=None, jacobians=None):
        """(m, 1 or q, k, 3, 3) the basis Hessians at the points of ``quad`` (arguments as
        :meth:`derivatives`, ``grads`` its mapped gradients, ``jacobians`` its (D Theta_h, moved
        cells) when known); None of P1 (zero).  On the cells that Theta_h moves they map with
        Theta_h's own (:func:`~cutfem.fem.lagrange.map_hessians`)."""
        if self.order == 1:
            return None
        hess = p2_hessians(self.gradients_of(elements))
        J, moved = self._jacobians(measure, quad, cells, points) if jacobians is None else jacobians
        if moved is None or len(moved) == 0:
            return hess
        deformation = getattr(measure, "deformation", None) if points is None else \
            getattr(getattr(measure.elements, "cut", None), "deformation", None)
        curved = None if deformation is None else \
            deformation.hessians(measure.elements, (quad.parent if cells is None else cells)[moved])
        out = np.array(np.broadcast_to(hess, J.shape[:2] + hess.shape[2:]))
        out[moved] = map_hessians(hess[moved], J[moved], grads[moved], curved)
        return out

    def evaluate(self, coeffs: np.ndarray, measure, degree: int = 4) -> np.ndarray:
        """Values of the discrete function with ``coeffs`` (n,) or (n, c) at the quadrature points of
        ``measure`` (cell measures): (m, q) or (m, q, c)."""
        quad = measure.quadrature(degree)
        el = self.local_elements(measure, quad.parent)
        phi = self.basis_on(measure, quad, el)
        local = np.asarray(coeffs)[self.element_dofs[el]]  # (m, k) or (m, k, c)
        if local.ndim == 2:
            return np.einsum("mqk,mk->mq", phi, local)
        return np.einsum("mqk,mkc->mqc", phi, local)

    def element_gradient_of(self, coeffs: np.ndarray) -> np.ndarray:
        """Constant gradient per element of a discrete function: (n_el, 3) or (n_el, c, 3)."""
        local = np.asarray(coeffs)[self.element_dofs]
        if local.ndim == 2:
            return np.einsum("mk,mkd->md", local, self.element_gradients)
        return np.einsum("mkc,mkd->mcd", local, self.element_gradients)

    def interpolate(self, f) -> np.ndarray:
        """Nodal interpolant: f evaluated at the dof points, (n,) or (n, c)."""
        return np.asarray(f(self.dof_points), dtype=float)

    def interpolate_nodal(self, values) -> np.ndarray:
        """The coefficients of the P1 function with the given values at the nodes (n_nodes,) or
        (n_nodes, c) (a level set's phi_h): the values themselves for P1; for P2 the edges' dofs
        follow, the means of their ends (P1 is a prefix of P2)."""
        values = np.asarray(values)
        if getattr(self, "order", 1) == 1:
            return values
        e = self.edge_nodes
        return np.concatenate([values, 0.5 * (values[e[:, 0]] + values[e[:, 1]])])


class SurfaceP1Space(_ScalarSpace):
    """Continuous P1 on a closed triangle surface mesh (meshed case); dofs are the mesh nodes.

    ``h`` defaults to the global ``N**(-1/2)`` of docs/math.md §2 (N = number of nodes); a given
    ``h`` must be a positive finite number.

    The geometry is computed on demand: the mass, stiffness and edge penalty of
    :mod:`cutfem.fem.forms` use closed forms in the areas and the edge-vector dot products of the
    mesh (:attr:`~cutfem.geometry.surface.SurfaceMesh.triangle_edge_dots`) on the node graph
    (:meth:`node_pattern`, :meth:`edge_stencil_pattern`), and need no basis gradients.
    """

    def __init__(self, mesh, h: float | None = None):
        self.mesh = mesh
        self.n_dofs = int(len(mesh.points))
        self.element_dofs = np.asarray(mesh.triangles, dtype=np.int64)
        self.dof_points = np.asarray(mesh.points, dtype=float)
        self.h = _mesh_size(h, self.n_dofs ** -0.5)
        self.elements = mesh

    @cached_property
    def element_gradients(self) -> np.ndarray:
        """(M, 3, 3) surface gradients of the barycentric coordinates (:func:`triangle_gradients`)."""
        return triangle_gradients(self.dof_points[self.element_dofs])[0]

    @cached_property
    def element_normals(self) -> np.ndarray:
        """(M, 3) unit normals n_h of the triangles (those of the mesh)."""
        return self.mesh.normals

    @cached_property
    def element_areas(self) -> np.ndarray:
        """(M,) triangle areas (those of the mesh)."""
        return self.mesh.areas

    @property
    def tangential_gradients(self) -> np.ndarray:
        """The basis gradients themselves: on a flat triangle they are already tangent,
        grad lambda_i = n x (x_{i+2} - x_{i+1}) / (2|T|)."""
        return self.element_gradients

    def tangential_gradients_of(self, elements) -> np.ndarray:
        return self.element_gradients[elements]

    def node_pattern(self):
        """:class:`~cutfem.fem.assembly.SymmetricPattern` of the nodes and the mesh edges (cached):
        the sparsity of the mass and stiffness matrices."""
        cache = self._patterns()
        if "node graph" not in cache:
            cache["node graph"] = SymmetricPattern(self.mesh.edges, self.n_dofs, presorted=True)
        return cache["node graph"]

    def edge_stencil_pattern(self):
        """:class:`~cutfem.fem.assembly.SymmetricPattern` of the edge penalty (cached): the mesh edges
        (first E pairs) and, per edge, the pair of the two vertices opposite to it (next E pairs),
        i.e. all pairs of nodes of the two triangles of an edge."""
        cache = self._patterns()
        if "edge stencil" not in cache:
            pairs = np.concatenate([self.mesh.edges, self.mesh.edge_opposite_vertices])
            cache["edge stencil"] = SymmetricPattern(pairs, self.n_dofs)
        return cache["edge stencil"]

    @property
    def n_elements(self) -> int:
        return len(self.element_dofs)

    @property
    def element_surface_areas(self) -> np.ndarray:
        return self.element_areas

    def surface_triangles(self):
        """(vertices (m, 3, 3), parent element (m,), areas (m,)) of the triangles of S_h."""
        return self.dof_points[self.element_dofs], np.arange(self.n_elements), self.element_areas

    def surface_vertex_data(self, coeffs):
        """(points (V, 3), triangles (T, 3), values at the points) of a discrete function on S_h."""
        return self.dof_points, self.element_dofs, self._coefficients(coeffs)

    def edges(self):
        """Edges for the edge stabilization: (element pairs (E, 2), conormals (E, 2, 3), lengths (E,))."""
        m = self.mesh
        return m.edge_triangles, m.edge_conormals, m.edge_lengths


class CutSpace(_ScalarSpace):
    """Continuous Lagrange fields of ``order`` 1 (P1) or 2 (P2) on an element set of a cut: ``on=CUT``
    (default) the cut tets, whose traces live on S_h (TraceFEM); ``on=NEG`` or ``POS`` the tets of
    one side (a bulk field of CutFEM); or any :class:`~cutfem.geometry.markers.ElementSet` of the
    cut.  The first dofs are the nodes of the set, numbered by increasing background id
    (``node_ids`` maps them back); at order 2 the edges of the set follow, ordered by their pair of
    background node ids (``edge_nodes`` (E, 2) their local node pairs), so that the P1 dofs are a
    prefix of the P2 dofs (:mod:`cutfem.fem.lagrange`).  ``h`` is the background ``N**(-1/3)``
    unless given (a positive finite number).  An element set given as ``on`` must lie on the cut's
    background mesh (:func:`~cutfem.geometry.markers.same_background`).

    ``element_gradients``, ``gradients_of`` and ``gradient_lookup`` are the gradients of the
    barycentric coordinates (the P1 basis; the geometry of a P2 element); the basis of either order
    at quadrature points, with gradients and Hessians, is :meth:`derivatives`.
    """

    def __init__(self, cut, on=CUT, order: int = 1, h: float | None = None):
        if isinstance(order, bool) or order not in (1, 2):
            raise ValueError(f"order must be 1 (P1) or 2 (P2), got {order!r}")
        es = cut.elements(on)
        if not same_background(es.background, cut.background):
            raise ValueError(f"the element set {es.name!r} lies on another background mesh than the cut "
                             f"({es.background!r}, the cut's: {cut.background!r}); build it on the cut's background")
        self.cut = cut
        self.elements = es
        self.order = int(order)
        self.element_normals = es.normals
        self.node_ids = es.node_ids
        self.h = _mesh_size(h, cut.h)
        if self.order == 1:
            self.n_dofs = es.n_nodes
            self.element_dofs = es.tets
            self.dof_points = es.points
        else:
            self.edge_nodes, element_edges = edge_numbering(es.tets, es.n_nodes)
            self.n_dofs = es.n_nodes + len(self.edge_nodes)
            self.element_dofs = np.concatenate([np.asarray(es.tets, dtype=np.int64), es.n_nodes + element_edges], axis=1)
            self.dof_points = np.concatenate([es.points, 0.5 * (es.points[self.edge_nodes[:, 0]] + es.points[self.edge_nodes[:, 1]])])

    def __repr__(self) -> str:
        return f"CutSpace(on={self.elements.name!r}, order={self.order}, dofs={self.n_dofs})"

    @property
    def element_volumes(self) -> np.ndarray:
        """(n_el,) the volumes of the elements (:attr:`cutfem.geometry.markers.ElementSet.volumes`: on a
        structured box built on each access)."""
        return self.elements.volumes

    @property
    def element_gradients(self) -> np.ndarray:
        """(n_el, 4, 3) the basis gradients (:attr:`cutfem.geometry.markers.ElementSet.gradients`: on a
        structured box built on each access; :meth:`gradients_of` for a subset)."""
        return self.elements.gradients

    def gradients_of(self, elements) -> np.ndarray:
        return self.elements.gradients_of(elements)

    def gradient_lookup(self):
        """(table, types) of the element set (:meth:`~cutfem.geometry.markers.ElementSet.gradient_lookup`):
        on a structured box the Kuhn table and the Kuhn types, no gathered gradients."""
        return self.elements.gradient_lookup()

    @property
    def n_elements(self) -> int:
        return len(self.element_dofs)

    @property
    def is_trace(self) -> bool:
        """True for the field on the cut tets (traces on S_h)."""
        return self.elements is self.cut.elements(CUT)

    def _require_trace(self, what):
        if not self.is_trace:
            raise ValueError(f"{what} needs the field on the cut tets (CutSpace(cut, CUT)); this field lives on {self.elements.name!r}")

    @cached_property
    def boundary_dofs(self) -> np.ndarray:
        """Dofs on the boundary of the background box (for strong Dirichlet conditions): its nodes and,
        at order 2, the edges whose two ends lie on one face of the background's bounding box."""
        nodes = self.elements.boundary_nodes
        if self.order == 1:
            return nodes
        lower, upper = self.cut.background.bounds
        p = self.elements.points
        a, b = p[self.edge_nodes[:, 0]], p[self.edge_nodes[:, 1]]
        tol = 1e-12 * float(np.max(np.abs(upper - lower)))
        on_face = np.zeros(len(a), dtype=bool)
        for bound in (lower, upper):
            on_face |= np.any((np.abs(a - bound) <= tol) & (np.abs(b - bound) <= tol), axis=1)
        return np.concatenate([nodes, self.elements.n_nodes + np.flatnonzero(on_face)])

    @property
    def element_surface_areas(self) -> np.ndarray:
        """(n_el,) area of the piece of S_h in each active tet."""
        return self.cut.piece_areas

    def surface_triangles(self):
        """(vertices (m, 3, 3), parent active tet (m,), areas (m,)) of the triangles of S_h."""
        self._require_trace("surface_triangles")
        c = self.cut
        return c.triangle_points, c.triangle_tets, c.triangle_areas

    def surface_vertex_data(self, coeffs):
        """(points (V, 3), triangles (T, 3), values at the points) of a discrete function on S_h."""
        self._require_trace("surface_vertex_data")
        return self.cut.vertices, self.cut.triangles, self.surface_vertex_values(coeffs)

    def surface_vertex_values(self, coeffs) -> np.ndarray:
        """Trace of a discrete function at the vertices of S_h: (V,) or (V, c) (for plots, VTK and the
        errors on S_h of P1).  Each vertex is valued in the tet of the last triangle (in triangle
        order) that has it: the trace is continuous, any of them would do (P1: one compiled pass,
        :func:`cutfem.fem.element_kernels.vertex_values`).  Of a P2 field these are its values at the
        vertices only (a VTK file of them draws the field linear on each triangle of S_h)."""

        c = self.cut
        coeffs = self._coefficients(coeffs)
        flat = coeffs.reshape(len(coeffs), -1)
        if self.order == 1:
            table, types = self.gradient_lookup()
            values = element_kernels.vertex_values(c.vertices, c.triangles, c.triangle_tets, self.dof_points, self.element_dofs,
                                                   table, types, self.element_dofs, flat)
        else:
            tet = np.empty(len(c.vertices), dtype=np.int64)
            tet[c.triangles.reshape(-1)] = np.repeat(c.triangle_tets, 3)  # numpy keeps the last write: the last triangle's tet
            phi = self.basis_at(np.asarray(c.vertices, dtype=float)[:, None], tet)[:, 0]  # (V, 10)
            values = np.einsum("vk,vkc->vc", phi, flat[self.element_dofs[tet]])
        return values.reshape((len(values),) + coeffs.shape[1:])

    def edges(self):
        """Edges of S_h between pieces: (element pairs (E, 2), conormals (E, 2, 3), lengths (E,))."""
        c = self.cut
        return c.surface_edge_tets, c.surface_edge_conormals, c.surface_edge_lengths


class VectorSpace:
    """The vector field [V]^3 of a scalar P1 space ``V`` (a :class:`CutSpace` on any element set of
    a cut, NEG, POS or CUT, or a :class:`SurfaceP1Space`): one block of 3 n unknowns numbered
    component-major, component c's dofs are c n + V's dofs (:meth:`dofs`), a vector of coefficients
    is read as nodal vectors (n, 3) by :meth:`nodal`.

    Why a space of a space, not ``CutSpace(..., components=3)``: it applies to every scalar space
    alike (one class, not an option in each), and leaves the scalar space and its arrays as they
    are, so that the built-in terms that act component by component (mass, stiffness, penalties,
    Nitsche, loads) are the scalar term's matrix on V, kron(I_3, A), built by the scalar exact
    implementations, and the multigrid sees three copies of V's hierarchy.  In an integrand a basis
    function of a vector field is a :class:`~cutfem.fem.pointwise.VectorBasisField` (``value``
    (m, q, 3), ``grad`` (m, 1, 3, 3), ``div``, ``sym_grad``, ``curl``, ``tgrad``).  A field of a
    :class:`ProductSpace` like any other: ``ProductSpace(u=VectorSpace(V), p=Q)``."""

    components = 3

    def __init__(self, scalar):
        if isinstance(scalar, (VectorSpace, ProductSpace, RealSpace)) or not isinstance(scalar, _ScalarSpace):
            raise TypeError(f"VectorSpace(V) takes a scalar P1 space (CutSpace or SurfaceP1Space), got {scalar!r}")
        self.scalar = scalar
        self.n_dofs = 3 * scalar.n_dofs
        self.order = scalar.order
        self.h = scalar.h
        self.elements = scalar.elements

    def __repr__(self) -> str:
        return f"VectorSpace({self.scalar!r})"

    @property
    def cut(self):
        return self.scalar.cut

    @property
    def is_trace(self) -> bool:
        return self.scalar.is_trace

    def dofs(self, c: int) -> np.ndarray:
        """The dofs of component c (0, 1 or 2)."""
        if c not in (0, 1, 2):
            raise ValueError(f"a vector field has the components 0, 1, 2, not {c!r}")
        n = self.scalar.n_dofs
        return np.arange(c * n, (c + 1) * n)

    @property
    def boundary_dofs(self) -> np.ndarray:
        """The dofs of every component at the boundary of the background box."""
        b, n = self.scalar.boundary_dofs, self.scalar.n_dofs
        return np.concatenate([b + c * n for c in range(3)])

    def nodal(self, coeffs) -> np.ndarray:
        """The coefficients (3 n,) as nodal vectors (n, 3) (a view)."""
        coeffs = np.asarray(coeffs)
        if coeffs.shape != (self.n_dofs,):
            raise ValueError(f"coefficients of this vector space have shape ({self.n_dofs},), got {coeffs.shape}")
        return coeffs.reshape(3, -1).T

    def flat(self, nodal) -> np.ndarray:
        """Nodal vectors (n, 3) as the coefficients (3 n,) (the inverse of :meth:`nodal`)."""
        nodal = np.asarray(nodal, dtype=float)
        if nodal.shape != (self.scalar.n_dofs, 3):
            raise ValueError(f"nodal vectors of this space have shape ({self.scalar.n_dofs}, 3), got {nodal.shape}")
        return nodal.T.reshape(-1)

    def interpolate(self, f) -> np.ndarray:
        """Nodal interpolant of ``f`` (points (n, 3) -> values (n, 3)) as coefficients (3 n,)."""
        return self.flat(self.scalar.interpolate(f))

    def evaluate(self, coeffs, measure, degree: int = 4) -> np.ndarray:
        """Values (m, q, 3) of the discrete field at the quadrature points of ``measure``."""
        return self.scalar.evaluate(self.nodal(coeffs), measure, degree)


class RealSpace:
    """One unknown, a constant: a field of a :class:`ProductSpace` for a Lagrange multiplier (a
    mean value, or another global constraint).  Its basis function is 1 on every measure (with
    zero gradients; on a facet both traces), so a constraint is an ordinary integrand, e.g. the
    mean-zero pressure ``p * lam + q * mu`` over ``dx`` (``u[k]``, ``v[k]`` for the fields'
    positions), assembled like any field: block by block of cells, a row of the fields' dofs."""

    n_dofs = 1
    h = None
    order = 0

    def __repr__(self) -> str:
        return "RealSpace()"


class ProductSpace:
    """Several fields together, with a block numbering: field k has the global dofs
    ``offsets[k] : offsets[k + 1]``.  Forms on a product space see tuples of basis functions
    (:mod:`cutfem.fem.forms`), and assemble to one block matrix.

    ``ProductSpace(V_neg, V_pos)`` or with names, ``ProductSpace(bulk=V_B, surface=V_S)``.
    """

    def __init__(self, *fields, **named):
        if fields and named:
            raise ValueError("give the fields either all by position or all by name")
        self.names = list(named) if named else [f"u{k}" for k in range(len(fields))]
        self.fields = list(named.values()) if named else list(fields)
        if not self.fields:
            raise ValueError("a product space needs at least one field")
        for f in self.fields:
            if isinstance(f, ProductSpace):
                raise TypeError("nest product spaces by listing their fields instead")
        self.offsets = np.concatenate([[0], np.cumsum([f.n_dofs for f in self.fields])]).astype(np.int64)
        self.n_dofs = int(self.offsets[-1])
        self.h = next((f.h for f in self.fields if f.h is not None), None)  # a real field has no mesh size
        self.order = max(getattr(f, "order", 1) for f in self.fields)  # the highest order sets the quadrature of a form on all fields

    def __repr__(self) -> str:
        return "ProductSpace(" + ", ".join(f"{n}={f!r}" for n, f in zip(self.names, self.fields)) + ")"

    def __len__(self) -> int:
        return len(self.fields)

    def __getitem__(self, k):
        return self.fields[self.index(k)]

    def index(self, k) -> int:
        """The position of a field given by its position (an int, 0 <= k < number of fields; no
        negative positions, no floats, no bools) or its name.  A KeyError for an unknown name, a
        ValueError for any other position, naming the fields."""
        if isinstance(k, str):
            if k not in self.names:
                raise KeyError(f"no field named {k!r}; the fields are {self.names}")
            return self.names.index(k)
        ok = isinstance(k, (int, np.integer)) and not isinstance(k, (bool, np.bool_))
        if not ok or not 0 <= k < len(self.fields):
            raise ValueError(f"a field is given by its position 0..{len(self.fields) - 1} or its name; got {k!r}, and "
                             f"the fields are {self.names}")
        return int(k)

    def split(self, x) -> list:
        """The coefficient blocks of each field of a global vector (n,) or (n, c)."""
        x = np.asarray(x)
        if x.shape[0] != self.n_dofs:
            raise ValueError(f"a vector of the product space has {self.n_dofs} rows, got {x.shape[0]}")
        return [x[a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:])]

    def join(self, parts) -> np.ndarray:
        """The global vector of per-field blocks (the inverse of :meth:`split`)."""
        if len(parts) != len(self.fields):
            raise ValueError(f"need {len(self.fields)} blocks, got {len(parts)}")
        return np.concatenate([np.asarray(p, dtype=float) for p in parts])

    def dofs(self, k) -> np.ndarray:
        """Global dof numbers of field k."""
        k = self.index(k)
        return np.arange(self.offsets[k], self.offsets[k + 1])
