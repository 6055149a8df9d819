"""Continuous P1 spaces: on a triangulated surface, on the active mesh of a cut, on a cut volume.

Every space exposes the same plain arrays, so that forms are written once:

``n_dofs``; ``element_dofs`` (n_el, k) global dof numbers of each element (triangles, k = 3, or
tets, k = 4); ``element_gradients`` (n_el, k, 3) the constant gradients of the P1 basis functions
(on a surface triangle this is already the surface gradient); ``element_normals`` (n_el, 3) the
discrete normal n_h (surface spaces); ``h`` the global mesh size (SPEC §2); and
``quadrature(measure, degree)`` returning a :class:`~cutfem.quadrature.Quadrature` whose ``parent``
indexes the elements, together with the basis values there, (m, q, k).

Measures: ``"surface"`` (S_h: triangles of a surface mesh, or the pieces of a cut),
``"active"`` (the whole active tets, for volume stabilizations), ``"volume"`` (the region
{phi_h < 0} of a cut volume space).  Vector-valued spaces [V_h]^3 are represented by (n, 3) arrays of
coefficients sharing the scalar matrices.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from .assembly import Pattern, SymmetricPattern
from .quadrature import Quadrature, map_tetrahedra, map_triangles

__all__ = ["SurfaceP1Space", "CutP1Space", "CutVolumeP1Space", "triangle_gradients", "barycentric_at"]


def triangle_gradients(vertices: np.ndarray):
    """Surface gradients of the barycentric coordinates of triangles in R^3.

    ``vertices`` (m, 3, 3).  With unit normal n and area A, ``grad lambda_i = n x (x_{i+2} - x_{i+1}) / (2A)``
    (indices mod 3): tangent to the triangle, orthogonal to the opposite edge, of length 1/height.
    Returns ``(grads (m, 3, 3), normals (m, 3), areas (m,))``.
    """
    v = np.asarray(vertices, dtype=float)
    c = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    twice_area = np.linalg.norm(c, axis=1)
    n = c / twice_area[:, None]
    grads = np.empty_like(v)
    for i in range(3):
        grads[:, i] = np.cross(n, v[:, (i + 2) % 3] - v[:, (i + 1) % 3]) / twice_area[:, None]
    return grads, n, 0.5 * twice_area


def barycentric_at(points: np.ndarray, origin: np.ndarray, grads: np.ndarray) -> np.ndarray:
    """P1 basis values at ``points`` (m, q, 3) of elements with first vertex ``origin`` (m, 3) and
    basis gradients ``grads`` (m, k, 3): ``lambda_k(x) = delta_k0 + grad lambda_k . (x - x_0)``."""
    lam = (points - origin[:, None, :]) @ grads.transpose(0, 2, 1)  # batched matmul: einsum is slower
    lam[..., 0] += 1.0
    return lam


class _P1Space:
    """Shared machinery: cached sparsity patterns and evaluation of discrete functions."""

    element_dofs: np.ndarray
    n_dofs: int

    def _patterns(self):
        if "_pattern_cache" not in self.__dict__:
            self.__dict__["_pattern_cache"] = {}
        return self.__dict__["_pattern_cache"]

    def pattern(self, name: str, dofs: np.ndarray | None = None) -> Pattern:
        """The cached :class:`Pattern` of a named connectivity ("elements", "faces", "edges", ...)."""
        cache = self._patterns()
        if name not in cache:
            if dofs is None:
                if name != "elements":
                    raise KeyError(f"no connectivity named {name!r} cached; pass dofs")
                dofs = self.element_dofs
            cache[name] = Pattern(dofs, self.n_dofs)
        return cache[name]

    def basis_values(self, quad: Quadrature) -> np.ndarray:
        """(m, q, k) P1 basis values at the quadrature points, per parent element."""
        return self.basis_at(quad.points, quad.parent)

    def basis_at(self, points: np.ndarray, parent: np.ndarray) -> np.ndarray:
        """(m, j, k) P1 basis values of element ``parent[i]`` at ``points[i]`` (m, j, 3)."""
        return barycentric_at(points, self.element_origin[parent], self.element_gradients[parent])

    @cached_property
    def tangential_gradients(self) -> np.ndarray:
        """(n_el, k, 3) P_h grad of the basis functions, P_h = I - n_h n_h^T per element."""
        G, n = self.element_gradients, self.element_normals
        return G - np.einsum("mkd,md->mk", G, n)[..., None] * n[:, None, :]

    @cached_property
    def element_origin(self) -> np.ndarray:
        return self.dof_points[self.element_dofs[:, 0]]

    def evaluate(self, coeffs: np.ndarray, quad: Quadrature) -> np.ndarray:
        """Values of the discrete function with ``coeffs`` (n,) or (n, c) at the quadrature points:
        (m, q) or (m, q, c)."""
        phi = self.basis_values(quad)
        local = np.asarray(coeffs)[self.element_dofs[quad.parent]]  # (m, k) or (m, k, c)
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


class SurfaceP1Space(_P1Space):
    """Continuous P1 on a closed triangle surface mesh (meshed case); dofs are the mesh nodes.

    ``h`` defaults to the global ``N**(-1/2)`` of SPEC §2 (N = number of nodes).

    The geometry is computed on demand: the mass, stiffness and edge penalty of
    :mod:`cutfem.forms` use closed forms in the areas and the edge-vector dot products of the
    mesh (:attr:`~cutfem.surface.SurfaceMesh.triangle_edge_dots`) on the node graph
    (:meth:`node_pattern`, :meth:`edge_stencil_pattern`), and need no basis gradients.
    """

    def __init__(self, mesh, h: float | None = None):
        self.mesh = mesh
        self.n_dofs = int(len(mesh.points))
        self.element_dofs = np.asarray(mesh.triangles, dtype=np.int64)
        self.dof_points = np.asarray(mesh.points, dtype=float)
        self.h = float(h) if h is not None else self.n_dofs ** -0.5

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

    @cached_property
    def tangential_gradients(self) -> np.ndarray:
        """The basis gradients themselves: on a flat triangle they are already tangent,
        grad lambda_i = n x (x_{i+2} - x_{i+1}) / (2|T|)."""
        return self.element_gradients

    def node_pattern(self):
        """:class:`~cutfem.assembly.SymmetricPattern` of the nodes and the mesh edges (cached):
        the sparsity of the mass and stiffness matrices."""
        cache = self._patterns()
        if "node graph" not in cache:
            cache["node graph"] = SymmetricPattern(self.mesh.edges, self.n_dofs, presorted=True)
        return cache["node graph"]

    def edge_stencil_pattern(self):
        """:class:`~cutfem.assembly.SymmetricPattern` of the edge penalty (cached): the mesh edges
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
        return self.dof_points, self.element_dofs, np.asarray(coeffs)

    def quadrature(self, measure: str = "surface", degree: int = 2) -> Quadrature:
        if measure != "surface":
            raise ValueError(f"a surface mesh space has only the 'surface' measure, got {measure!r}")
        key = ("surface", degree)
        cache = self._patterns()
        if key not in cache:
            cache[key] = map_triangles(self.dof_points[self.element_dofs], degree, normal=self.element_normals)
        return cache[key]

    def edges(self):
        """Edges for the edge stabilization: (element pairs (E, 2), conormals (E, 2, 3), lengths (E,))."""
        m = self.mesh
        return m.edge_triangles, m.edge_conormals, m.edge_lengths


class CutP1Space(_P1Space):
    """Continuous P1 on the active tets of a cut (traces live on S_h); dofs are the active nodes.

    ``node_ids`` maps dofs back to background nodes.  ``h`` is the background ``N**(-1/3)``.
    """

    def __init__(self, cut, h: float | None = None):
        self.cut = cut
        self.n_dofs = cut.n_nodes
        self.element_dofs = cut.tets
        self.dof_points = cut.points
        self.element_gradients = cut.basis_gradients
        self.element_normals = cut.normals
        self.element_volumes = cut.tet_volumes
        self.node_ids = cut.node_ids
        self.h = float(h) if h is not None else cut.h

    @property
    def n_elements(self) -> int:
        return len(self.element_dofs)

    def quadrature(self, measure: str = "surface", degree: int = 2) -> Quadrature:
        key = (measure, degree)
        cache = self._patterns()
        if key not in cache:
            if measure == "surface":
                cache[key] = self.cut.surface_quadrature(degree)
            elif measure == "active":
                cache[key] = map_tetrahedra(self.cut.tet_vertices, degree)
            else:
                raise ValueError(f"unknown measure {measure!r} for a cut space; use 'surface' or 'active'")
        return cache[key]

    @property
    def element_surface_areas(self) -> np.ndarray:
        """(n_el,) area of the piece of S_h in each active tet."""
        return self.cut.piece_areas

    def surface_triangles(self):
        """(vertices (m, 3, 3), parent active tet (m,), areas (m,)) of the triangles of S_h."""
        c = self.cut
        return c.triangle_points, c.triangle_tets, c.triangle_areas

    def surface_vertex_data(self, coeffs):
        """(points (V, 3), triangles (T, 3), values at the points) of a discrete function on S_h."""
        return self.cut.vertices, self.cut.triangles, self.surface_vertex_values(coeffs)

    @cached_property
    def _vertex_basis(self):
        """(dofs (V, 4), basis values (V, 4)) at each vertex of S_h, in the last tet (in triangle
        order) whose piece has that vertex: the trace is continuous, any of them would do."""
        c = self.cut
        tet_of = np.empty(len(c.vertices), dtype=np.int64)
        tet_of[c.triangles.reshape(-1)] = np.repeat(c.triangle_tets, 3)
        lam = barycentric_at(c.vertices[:, None, :], self.element_origin[tet_of], self.element_gradients[tet_of])[:, 0]
        return self.element_dofs[tet_of], lam

    def surface_vertex_values(self, coeffs) -> np.ndarray:
        """Trace of a discrete function at the vertices of S_h: (V,) or (V, c) (for plots and VTK)."""
        dofs, lam = self._vertex_basis
        local = np.asarray(coeffs)[dofs]
        return np.einsum("vk,vk...->v...", lam, local)

    def edges(self):
        """Edges of S_h between pieces: (element pairs (E, 2), conormals (E, 2, 3), lengths (E,))."""
        c = self.cut
        return c.surface_edge_tets, c.surface_edge_conormals, c.surface_edge_lengths

    def faces(self):
        """Interior faces of the active mesh: (element pairs (F, 2), unit normals out of the first
        element (F, 3), areas (F,))."""
        c = self.cut
        ft = c.interior_face_tets
        opp = c.interior_face_opposite[:, 0]
        # outward normal of face opposite to local vertex k of tet T is -grad(lambda_k)/|grad(lambda_k)|
        g = c.basis_gradients[ft[:, 0], opp]
        gn = np.linalg.norm(g, axis=1)
        normals = -g / gn[:, None]
        # |F| = 3 |T| |grad lambda_k|... from volume = |F| * height / 3 and |grad lambda_k| = 1/height
        areas = 3.0 * c.tet_volumes[ft[:, 0]] * gn
        return ft, normals, areas


class CutVolumeP1Space(_P1Space):
    """Continuous P1 on the background tets that meet the region {phi_h < 0} (a cut volume).

    Elements are those tets; the ``"volume"`` measure integrates over their inside parts only
    (sub-tetrahedra from :func:`cutfem.cut.inside_tetrahedra`).  This visits every background tet.
    """

    def __init__(self, background, levelset):
        from .cut import inside_tetrahedra
        from .mesh import barycentric_gradients, unique_keys

        sub, parent_bg = inside_tetrahedra(background, levelset)
        tet_ids, parent = unique_keys(parent_bg, return_inverse=True)
        nodes = background.tets[tet_ids]
        node_ids, inv = unique_keys(nodes.reshape(-1), return_inverse=True)
        self.background = background
        self.node_ids = node_ids
        self.tet_ids = tet_ids
        self.n_dofs = len(node_ids)
        self.element_dofs = inv.reshape(-1, 4)
        self.dof_points = background.points[node_ids]
        self.element_gradients, vol = barycentric_gradients(self.dof_points[self.element_dofs])
        self.element_volumes = np.abs(vol)
        self._sub, self._sub_parent = sub, parent
        self.h = background.h

    def volume_tetrahedra(self):
        """(vertices (s, 4, 3), parent element (s,), volumes (s,)) of the sub-tetrahedra of {phi_h < 0}."""
        v = self._sub
        vol = np.abs(np.einsum("ij,ij->i", np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), v[:, 3] - v[:, 0])) / 6.0
        return v, self._sub_parent, vol

    def quadrature(self, measure: str = "volume", degree: int = 2) -> Quadrature:
        key = (measure, degree)
        cache = self._patterns()
        if key not in cache:
            if measure == "volume":
                cache[key] = map_tetrahedra(self._sub, degree, parent=self._sub_parent)
            elif measure == "active":
                cache[key] = map_tetrahedra(self.dof_points[self.element_dofs], degree)
            else:
                raise ValueError(f"unknown measure {measure!r} for a cut volume space; use 'volume' or 'active'")
        return cache[key]
