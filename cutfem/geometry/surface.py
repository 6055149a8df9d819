"""Closed triangle surface meshes: the meshed case of docs/math.md §2.

A :class:`SurfaceMesh` is a closed, edge- and vertex-manifold, consistently and outward oriented
triangulation S_h with ``points`` (N, 3) and ``triangles`` (M, 3), validated on construction
(:mod:`cutfem.geometry.surface_checks`).  Its topology (unique edges, the two triangles of each
edge, the three edges of each triangle) and its geometry (areas, unit normals, enclosed volume,
edge conormals t_{E,K} of docs/math.md §3) are computed on demand, vectorized, by sorting integer
keys; its nearest points and signed distance come from a compiled search (:mod:`cutfem.geometry.closest`).

Conventions
-----------
* Local edge k of triangle (v_0, v_1, v_2) is the half-edge (v_k, v_{k+1 mod 3}).
* The normal of a triangle is (v_1 - v_0) x (v_2 - v_0) / |...|; a triangle is *outward* when its
  normal points out of the region its connected component encloses.
* Mesh size for tables and for the edge stabilization: the global ``h = N**(-1/2)`` (docs/math.md §2,
  N = number of surface nodes).

File I/O through meshio: :func:`read_surface`, :func:`write_surface`; the generated tori and spheres
are in :mod:`cutfem.geometry.surface_meshes`.  :func:`check_length` and :data:`LENGTH_RANGE` bound
the lengths of every analytic or generated surface.
"""

from __future__ import annotations

import warnings
from functools import cached_property
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .keys import pair_up, unique_keys
from .mesh import COINCIDENT_TOLERANCE, close_pairs
from .surface_checks import (
    _as_points,
    _as_triangles,
    _check_disjoint_components,
    _check_elements,
    _check_topology,
    _closed_halfedge_table,
    _components,
    _diagnose_topology,
    _examples,
    _halfedge_table,
    _opposite_vertex,
    _orient_outward,
    _pair_halfedges,
    _triangle_geometry,
)

__all__ = [
    "SurfaceMesh",
    "read_surface",
    "write_surface",
    "MERGE_TOLERANCE",
    "LENGTH_RANGE",
    "check_length",
    "positive_number",
]

#: :func:`read_surface` merges points closer than MERGE_TOLERANCE * (diagonal of the bounding
#: box) (:func:`_merge_points`): the tolerance at which a tetrahedral mesh's nodes coincide.
MERGE_TOLERANCE = COINCIDENT_TOLERANCE

#: The lengths (radii, semi-axes) accepted by the analytic surfaces of :mod:`cutfem.geometry.shapes`
#: (Sphere, Torus, Ellipsoid) and by :func:`~cutfem.geometry.surface_meshes.sphere_mesh` and
#: :func:`~cutfem.geometry.surface_meshes.torus_mesh`, as (smallest, largest).  Within it every
#: quantity formed from the lengths up to the fourth power stays a normal float64 (2.2e-308 to
#: 1.8e308), with room for a factor 1e5 of mesh refinement: areas (L**2), volumes (L**3), curvatures
#: (1/L), Hessians (1/L**2), the squared cross products of the triangles' edges in the degeneracy
#: test (L**4), the squared gradient of an ellipsoid.  Outside, they overflow to inf (the area of a
#: sphere of radius 1e200) or underflow to 0 (the triangles of a sphere of radius 1e-160 "have zero
#: area"); rescale the unit of length instead.
LENGTH_RANGE = (1e-50, 1e50)

_READ_EXTENSIONS_HINT = ".stl, .obj, .ply, .off, .vtk, .vtp, .vtu, .msh (Gmsh), .mesh (Medit)"

# names of the VTK cell types a surface file may hold (vtkCellType.h), for read_surface
_VTK_CELL_NAMES = {1: "vertex", 2: "vertex", 3: "line", 4: "line", 5: "triangle", 6: "triangle_strip", 7: "polygon",
                   8: "quad", 9: "quad"}


# ---------------------------------------------------------------------------------------------
# the mesh
# ---------------------------------------------------------------------------------------------


def _check_near(x: np.ndarray, origin: np.ndarray) -> None:
    """ValueError for points farther than 1e150 from ``origin`` (a point of the mesh): the squared
    distances of the nearest-point search overflow there."""
    huge = np.max(np.abs(x - origin), axis=1) > 1e150
    if huge.any():
        raise ValueError(
            f"the nearest points of {int(huge.sum())} point(s) farther than 1e150 from the mesh (first: {x[huge][0]}) "
            "are not computed: the squared distances of the search overflow there."
        )


# ---------------------------------------------------------------------------------------------
# the mesh
# ---------------------------------------------------------------------------------------------


class SurfaceMesh:
    """A closed, manifold, outward oriented triangle surface S_h (docs/math.md §2, meshed case).

    Parameters
    ----------
    points : (N, 3) float array of node coordinates.
    triangles : (M, 3) integer array of 0-based node indices.
    check : bool, default True.
        Validate the input and orient it outward (below).  ``check=False`` trusts the input (use it
        only for meshes built by this package that are valid by construction); topology properties
        still raise if an edge does not have exactly two triangles.

    Validation (``check=True``), each failure a ``ValueError`` naming the count, the first
    offenders and the fix:

    * points of shape (N, 3) with finite coordinates; triangles of shape (M, 3), integer, indices in
      [0, N);
    * no degenerate triangle: no repeated vertex and |(b-a) x (c-a)| > DEGENERATE_TOLERANCE * l_max^2;
    * **no unused points** (decision): every node must belong to a triangle, since an isolated node
      would be a P1 unknown without support (singular mass matrix) and would change
      h = N^(-1/2) and the Euler characteristic;
    * no duplicate triangles (the same three nodes twice);
    * closed: every edge in at least two triangles ("the surface is open", with the number of
      boundary edges);
    * edge-manifold: no edge in more than two triangles; vertex-manifold: the triangles around each
      node form a single fan;
    * consistently oriented: the two triangles of an edge traverse it in opposite directions;
    * **disjoint components** (decision): the regions enclosed by distinct connected components
      neither intersect (surfaces crossing or touching: overlapping parts) nor nest (a shell inside
      a shell, ambiguous between a cavity and a swallowed part); see
      :func:`~cutfem.geometry.surface_checks._check_disjoint_components`, vectorized, skipped for a single component.

    Orientation (decision): after these checks, each connected component whose signed enclosed
    volume (1/6) sum_K a.(b x c) is negative has all its triangles flipped (vertices 1 and 2
    swapped), so that every component's normals point out of the region it encloses.  Flipping per
    component (not globally) keeps every sphere of a set of disjoint spheres outward.
    ``flipped_components`` records how many components were flipped.

    Attributes
    ----------
    points : (N, 3) float64, C-contiguous, read-only copy.
    triangles : (M, 3) int64, C-contiguous, read-only copy (possibly reoriented).
    grid : (n, m) or None.  Set by generators of logically structured, doubly periodic meshes
        (:func:`~cutfem.geometry.surface_meshes.torus_mesh`): node (i, j) is node i m + j, its grid neighbours are (i +- 1, j) and
        (i, j +- 1) modulo (n, m).  The multigrid solver coarsens along it
        (:func:`cutfem.solvers.multigrid.grid_hierarchy`); None for any other mesh.

    Both arrays are read-only because the cached properties depend on them; build a new mesh to
    change the geometry.
    """

    grid = None

    def __init__(self, points, triangles, check: bool = True):
        pts = _as_points(points)
        tri = _as_triangles(triangles)
        self.flipped_components = 0
        if check:
            cross, twice_area, dots, degree = _check_elements(pts, tri)
            table, pairs = _check_topology(tri, len(pts), degree)
            n_components, component = _components(tri, pairs)
            _check_disjoint_components(pts, tri, component, n_components)
            tri, cross, self.flipped_components = _orient_outward(pts, tri, component, cross)
            if self.flipped_components == 0:
                self._keep(cross, twice_area, dots, (table, pairs))
            else:  # a flip changes the half-edges and the local edge order, not |cross|
                self.__dict__.update(_cross=cross, _twice_area=twice_area)
        pts.flags.writeable = False
        tri = np.ascontiguousarray(tri)
        tri.flags.writeable = False
        self.points = pts
        self.triangles = tri

    def _keep(self, cross: np.ndarray, twice_area: np.ndarray, dots: np.ndarray, topology) -> None:
        """Keep what the validation computed: the cross products and their lengths, the edge-vector
        dot products and (table, pairs) of the half-edges."""
        dots.flags.writeable = False
        table, pairs = topology
        pairs.flags.writeable = False
        self.__dict__.update(_cross=cross, _twice_area=twice_area, triangle_edge_dots=dots, _halfedges=table,
                             _edge_halfedges=pairs)

    def _check_generated(self) -> None:
        """Validation for generators whose triangulation is closed, edge- and vertex-manifold
        and consistently outward oriented by construction (:func:`~cutfem.geometry.surface_meshes.torus_mesh`): the element
        checks run, because moved nodes could still make a triangle degenerate, and the one-sort
        half-edge table that the mesh needs anyway confirms closedness and orientation (with the
        usual message otherwise); the vertex fans and the orientation by components are skipped.
        """
        cross, twice_area, dots, _ = _check_elements(self.points, self.triangles)
        fast = _closed_halfedge_table(self.triangles, self.n_points)
        if fast is None:
            _diagnose_topology(self.triangles, self.n_points)
        self._keep(cross, twice_area, dots, fast)

    # -- sizes ---------------------------------------------------------------------------------

    @property
    def n_points(self) -> int:
        """N, the number of nodes."""
        return int(self.points.shape[0])

    @property
    def n_triangles(self) -> int:
        """M, the number of triangles."""
        return int(self.triangles.shape[0])

    @property
    def n_edges(self) -> int:
        """E, the number of (undirected) edges; E = 3M/2 on a closed surface."""
        return int(self.edges.shape[0])

    @property
    def h(self) -> float:
        """Global mesh size h = N^(-1/2), N = number of surface nodes (docs/math.md §2).

        This is a node-count measure, not an edge length: for the n x n/2 torus grid it is several
        times smaller than an edge.  It is the h of the edge stabilization and of the rate tables.
        """
        return float(self.n_points) ** -0.5

    # -- topology ------------------------------------------------------------------------------

    @cached_property
    def _halfedges(self):
        return _halfedge_table(self.triangles, self.n_points)

    @cached_property
    def _edge_halfedges(self) -> np.ndarray:
        """(E, 2) half-edge ids (3 t + k) of each edge; column 0 runs from edges[e,0] to edges[e,1]."""
        _, halfedge_edge, counts, forward = self._halfedges
        if not np.all(counts == 2):
            raise ValueError(
                f"{int(np.sum(counts != 2))} edge(s) do not have exactly two triangles (open or non-manifold "
                "surface); build the SurfaceMesh with check=True for a diagnosis."
            )
        pairs = _pair_halfedges(halfedge_edge, forward)
        pairs.flags.writeable = False
        return pairs

    @property
    def edge_halfedges(self) -> np.ndarray:
        """(E, 2) int64: the half-edges 3 t + k (local edge k of triangle t) of each edge; column 0
        runs from ``edges[e, 0]`` to ``edges[e, 1]``, so ``edge_halfedges // 3`` is
        :attr:`edge_triangles` and ``edge_halfedges % 3`` is :attr:`edge_local_index`."""
        return self._edge_halfedges

    @cached_property
    def edge_opposite_vertices(self) -> np.ndarray:
        """(E, 2) int64: the vertex of ``edge_triangles[e, j]`` opposite to edge e."""
        out = _opposite_vertex(self.triangles, self._edge_halfedges)
        out.flags.writeable = False
        return out

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) int64: the unique edges, each row sorted (i < j), rows in lexicographic order."""
        edges = self._halfedges[0]
        edges.flags.writeable = False
        return edges

    @cached_property
    def edge_triangles(self) -> np.ndarray:
        """(E, 2) int64: the two triangles of each edge.

        ``edge_triangles[e, 0]`` traverses the edge from ``edges[e, 0]`` to ``edges[e, 1]`` (the
        increasing direction), ``edge_triangles[e, 1]`` the other way (on a consistently oriented
        mesh each edge has one of each).
        """
        out = self._edge_halfedges // 3
        out.flags.writeable = False
        return out

    @cached_property
    def edge_local_index(self) -> np.ndarray:
        """(E, 2) int64: k such that edge e is local edge k = (v_k, v_{k+1 mod 3}) of edge_triangles[e, j]."""
        out = self._edge_halfedges % 3
        out.flags.writeable = False
        return out

    @cached_property
    def triangle_edges(self) -> np.ndarray:
        """(M, 3) int64: ``triangle_edges[t, k]`` is the edge index of local edge (v_k, v_{k+1 mod 3})."""
        out = self._halfedges[1].reshape(-1, 3)
        out.flags.writeable = False
        return out

    @cached_property
    def euler_characteristic(self) -> int:
        """chi = V - E + F (2 for a sphere, 0 for a torus, 2 - 2g for genus g, summed over components)."""
        return self.n_points - self.n_edges + self.n_triangles

    # -- geometry ------------------------------------------------------------------------------

    def _geometry(self, name: str) -> np.ndarray:
        """One of the arrays of :func:`~cutfem.geometry.surface_checks._triangle_geometry` kept by the validation; without it
        (check=False) all of them are computed in one pass and kept."""
        if name not in self.__dict__:
            cross, twice_area, dots, _ = _triangle_geometry(self.points, self.triangles)
            dots.flags.writeable = False
            for key, value in (("_cross", cross), ("_twice_area", twice_area), ("triangle_edge_dots", dots)):
                self.__dict__.setdefault(key, value)
        return self.__dict__[name]

    @cached_property
    def _cross(self) -> np.ndarray:
        """(M, 3) (v_1 - v_0) x (v_2 - v_0)."""
        return self._geometry("_cross")

    @cached_property
    def _twice_area(self) -> np.ndarray:
        """(M,) |(v_1 - v_0) x (v_2 - v_0)| = 2 |K|."""
        return self._geometry("_twice_area")

    @cached_property
    def triangle_edge_dots(self) -> np.ndarray:
        """(2, M, 3) edge-vector dot products: with e_k = v_{k+1} - v_k (indices mod 3),
        ``[0, t, k]`` is S = e_k . e_k (squared edge lengths) and ``[1, t, k]`` is
        Q = e_k . e_{k+1}.  Every P1 integral on a flat triangle is a function of these and the
        area: grad lambda_i = n x e_{i+1} / (2|T|), so |T| grad lambda_i . grad lambda_j =
        e_{i+1} . e_{j+1} / (4|T|); the outward conormal of edge k is t_k = e_k / |e_k| x n, so
        t_k . grad lambda_m = -e_k . e_{m+1} / (2|T| |e_k|) (the closed forms of
        :mod:`cutfem.fem.forms`)."""
        return self._geometry("triangle_edge_dots")

    @cached_property
    def areas(self) -> np.ndarray:
        """(M,) triangle areas |K| = |(v_1 - v_0) x (v_2 - v_0)| / 2."""
        out = 0.5 * self._twice_area
        out.flags.writeable = False
        return out

    @cached_property
    def area(self) -> float:
        """|S_h| = sum_K |K|."""
        return float(self.areas.sum())

    @cached_property
    def normals(self) -> np.ndarray:
        """(M, 3) unit normals n_K = (v_1 - v_0) x (v_2 - v_0) / |...|, outward after validation."""
        out = self._cross / self._twice_area[:, None]
        out.flags.writeable = False
        return out

    @cached_property
    def centroids(self) -> np.ndarray:
        """(M, 3) triangle centroids (v_0 + v_1 + v_2) / 3."""
        out = self.points[self.triangles].mean(axis=1)
        out.flags.writeable = False
        return out

    @cached_property
    def enclosed_volume(self) -> float:
        """Volume enclosed by S_h by the divergence theorem, V = (1/3) int_{S_h} x . n.

        Per triangle (1/3) |K| (x_c . n_K) = (1/6) a . (b x c) with a, b, c measured from the
        mean of the points o (the sum does not depend on o for a closed surface; centring reduces
        round-off).  Positive for an outward oriented mesh.
        """
        p = self.points - self.points.mean(axis=0)
        t = self.triangles
        return float(np.einsum("ij,ij->", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]])) / 6.0)

    @cached_property
    def edge_lengths(self) -> np.ndarray:
        """(E,) edge lengths |x_j - x_i|."""
        p = self.points
        out = np.linalg.norm(p[self.edges[:, 1]] - p[self.edges[:, 0]], axis=1)
        out.flags.writeable = False
        return out

    @cached_property
    def edge_conormals(self) -> np.ndarray:
        """(E, 2, 3) unit conormals t_{E,K} (docs/math.md §3).

        For edge E = [a, b] and its k-th triangle K = edge_triangles[e, k] with opposite vertex c,
        t_{E,K} lies in the plane of K, is orthogonal to E and points out of K:

            d = (b - a) / |b - a|,  w = a - c,  t = (w - (w . d) d) / |w - (w . d) d|.

        (The component of a - c orthogonal to the edge; it does not depend on the orientation of
        K.)  Two coplanar triangles on either side of an edge have t_{E,K1} = -t_{E,K2}.
        """
        p = self.points
        opposite = self.edge_opposite_vertices  # (E, 2)
        a = p[self.edges[:, 0]]
        d = p[self.edges[:, 1]] - a
        d /= np.linalg.norm(d, axis=1)[:, None]
        w = a[:, None, :] - p[opposite]  # (E, 2, 3)
        w -= np.einsum("ekj,ej->ek", w, d)[:, :, None] * d[:, None, :]
        w /= np.linalg.norm(w, axis=2)[:, :, None]
        w.flags.writeable = False
        return w

    # -- nearest points --------------------------------------------------------------------------

    @cached_property
    def _triangle_tree(self):
        """The bounding-volume hierarchy of the triangles (:class:`cutfem.geometry.closest.TriangleTree`),
        with the edge tables for the pseudo-normal sign of the signed distance."""
        from .closest import TriangleTree

        return TriangleTree(self.points, self.triangles, self.edge_triangles, self.triangle_edges)

    def closest_points(self, x):
        """Nearest points of the mesh: ``(p, triangle, distance)`` for points x (n, 3), with p (n, 3)
        on triangle ``triangle`` (n,) and ``distance`` = |x - p| (n,).

        Exact over all the triangles: a compiled walk of a bounding-volume hierarchy built once
        (:mod:`cutfem.geometry.closest`) skips only the boxes farther than the nearest triangle found, and
        each triangle it reaches is compared exactly (Ericson's region test, as
        :func:`cutfem.geometry.closest._closest_on_triangles`).  Where the nearest point is not unique (x equidistant from
        several triangles, e.g. the centre of a sphere mesh) one of them is returned.  Points
        farther than 1e150 from the mesh are refused (ValueError): the squared distances of the
        search overflow there.
        """
        x = np.ascontiguousarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != 3 or not np.isfinite(x).all():
            raise ValueError(f"x must be finite points of shape (n, 3); got shape {x.shape}")
        _check_near(x, self.points[0])
        return self._triangle_tree.nearest(x)

    def signed_distance(self, x):
        """``(value (n,), p (n, 3))``: the distance from x (n, 3) to the mesh, negative inside, and
        the nearest points p.  The sign is that of (x - p) . N with N the angle-weighted
        pseudo-normal of the face, edge or vertex p lies on (:mod:`cutfem.geometry.closest`), exact for a
        closed outward oriented manifold mesh; points outside the mesh's bounding box are outside.
        Same checks as :meth:`closest_points`."""
        x = np.ascontiguousarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != 3 or not np.isfinite(x).all():
            raise ValueError(f"x must be finite points of shape (n, 3); got shape {x.shape}")
        _check_near(x, self.points[0])
        value, p = self._triangle_tree.signed_distance(x)
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        outside = np.any((x < lo) | (x > hi), axis=1)
        return np.where(outside, np.abs(value), value), p

    # -- conversion ----------------------------------------------------------------------------

    def ds(self):
        """The measure on this surface: its triangles (:class:`cutfem.geometry.measures.MeshedSurface`, cached)."""
        if "_ds" not in self.__dict__:
            from .measures import MeshedSurface

            self.__dict__["_ds"] = MeshedSurface(self)
        return self.__dict__["_ds"]

    def to_pyvista(self):
        """The mesh as a ``pyvista.PolyData`` of triangles (points copied, faces (M, 3))."""
        import pyvista as pv

        return pv.PolyData.from_regular_faces(np.array(self.points), np.array(self.triangles))

    def __repr__(self) -> str:
        return (
            f"SurfaceMesh(n_points={self.n_points}, n_triangles={self.n_triangles}, "
            f"h={self.h:.4g}, area={self.area:.6g})"
        )


# ---------------------------------------------------------------------------------------------
# the lengths of surfaces
# ---------------------------------------------------------------------------------------------


def positive_number(value, name: str) -> float:
    """``value`` as a float; ValueError naming ``name`` unless it is a finite number > 0 (the check
    of the radii, semi-axes and declared sizes of the surfaces and level sets)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
    return v


def check_length(name: str, value, owner: str) -> float:
    """``value`` as a positive float within :data:`LENGTH_RANGE`; ValueError naming ``owner`` (the
    surface or generator), the length and the fix otherwise."""
    value = positive_number(value, name)
    lo, hi = LENGTH_RANGE
    if not lo <= value <= hi:
        raise ValueError(
            f"{owner}: {name} = {value:.3g} is outside [{lo:g}, {hi:g}], where the areas, volumes and curvatures of "
            f"the surface {'overflow' if value > hi else 'underflow'} in float64; rescale the unit of length."
        )
    return value


# ---------------------------------------------------------------------------------------------
# file I/O
# ---------------------------------------------------------------------------------------------


def _merge_points(points: np.ndarray, triangles: np.ndarray, tolerance: float = MERGE_TOLERANCE):
    """Drop points used by no triangle and merge coincident points.

    With r = tolerance * (diagonal of the bounding box of the used points), two points are
    one node when a chain of points, each within distance r of the next, joins them (single
    linkage; exact duplicates, as in STL, which stores every vertex once per facet, always merge).
    Distances, not coordinates rounded to a grid of step r: two copies of a vertex 1e-11 apart on
    either side of a rounding step would stay two nodes and leave a crack (96 boundary edges in a
    jittered facet soup of sphere_mesh(2)).  A merged node keeps the coordinates and the order of
    its first occurrence.  A used point that is not finite is refused (ValueError with its row).  Returns (points, triangles).
    """
    used = unique_keys(triangles)
    bad = used[~np.isfinite(points[used]).all(axis=1)]
    if bad.size:
        raise ValueError(
            f"{bad.size} point(s) used by triangles have non-finite (NaN or inf) coordinates, first at rows "
            f"{_examples(bad)} of the file (0-based); fix them or remove their triangles."
        )
    points = points[used]
    triangles = np.searchsorted(used, triangles)
    lower = points.min(axis=0)
    diagonal = float(np.linalg.norm(points.max(axis=0) - lower))
    if diagonal == 0.0:
        return points, triangles
    # exact duplicates first (the bulk of an STL's copies), then the pairs within r among the rest
    distinct, label = np.unique(points, axis=0, return_inverse=True)
    label = label.reshape(-1)
    pairs = close_pairs(distinct, tolerance * diagonal)
    if len(pairs):
        graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(distinct),) * 2)
        label = connected_components(graph, directed=False)[1][label]
    first = np.full(label.max() + 1, len(points))
    np.minimum.at(first, label, np.arange(len(points)))
    order = np.argsort(first)  # nodes in order of first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return points[first[order]], rank[label][triangles]


def _unmerged_soup_message(points: np.ndarray, triangles: np.ndarray, tolerance: float) -> str | None:
    """The message for an open surface whose boundary edges are mostly copies of one another: a
    facet soup (STL stores every vertex once per facet) whose copies of a vertex lie further apart
    than the merge distance (``tolerance`` times the bounding-box diagonal).  Boundary vertices
    within 1e-3 of the median edge length of each other are taken as one (single linkage), and a
    boundary edge is a copy when another boundary edge joins the same two: a real hole's rim has
    one edge each.  None when no boundary edge is a copy (the surface has real holes)."""
    edges, _, counts, _ = _halfedge_table(triangles, len(points))
    boundary = edges[counts == 1]
    if not len(boundary):
        return None
    ends = unique_keys(boundary.reshape(-1))
    lengths = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    reach = 1e-3 * float(np.median(lengths))
    pairs = close_pairs(points[ends], reach)
    if not len(pairs):
        return None
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(ends),) * 2)
    label = connected_components(graph, directed=False)[1][np.searchsorted(ends, boundary)]
    _, _, twins = pair_up((np.min(label, axis=1), np.max(label, axis=1)))
    copies = int(twins[twins > 1].sum())
    if not copies:
        return None
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    gap = float(np.max(np.linalg.norm(points[ends[pairs[:, 0]]] - points[ends[pairs[:, 1]]], axis=1)))
    suggest = float(f"{10 * gap / diagonal:.0e}")
    rest = len(boundary) - copies
    return (
        f"the surface is an unmerged triangle soup: {copies} of its {len(boundary)} boundary edges have both ends "
        f"within {gap:.2g} of another vertex (copies of one vertex, as an STL file stores them, that were not merged: "
        f"points are merged when closer than {tolerance:g} times the bounding-box diagonal, {tolerance * diagonal:.2g} "
        f"here){f'; the other {rest} boundary edges are holes' if rest else ''}. Merge the coincident vertices: "
        f"read_surface(path, merge_tolerance={suggest:g}), or in the mesh tool that wrote the file (e.g. pyvista "
        "PolyData.clean(tolerance=...), MeshLab 'Merge Close Vertices'), and write it with shared vertices."
    )


def _is_polydata(path: Path) -> bool:
    """Whether ``path`` holds VTK polygonal data: an XML ``.vtp`` file, or a legacy ``.vtk`` file
    whose fourth header line (ASCII in both the ASCII and the binary variant) is ``DATASET POLYDATA``."""
    suffix = path.suffix.lower()
    if suffix == ".vtp":
        return True
    if suffix != ".vtk":
        return False
    with open(path, "rb") as f:
        head = [f.readline(300) for _ in range(4)]
    return head[-1].split()[:2] == [b"DATASET", b"POLYDATA"]


def _read_polydata(path: Path):
    """Points and cells of a VTK polygonal-data file read with pyvista, in the shape of a meshio
    mesh (``points``, ``cells`` with ``type`` and ``data``), so that :func:`read_surface` checks it
    like any other file; triangle strips are reported as such (not triangulated)."""
    from types import SimpleNamespace

    import pyvista

    if path.suffix.lower() == ".vtp":
        with open(path, "rb") as f:
            head = f.read(1000)
        if b"<VTKFile" not in head or b'"PolyData"' not in head:  # keep VTK's own error log out of the way
            raise ValueError("not a VTK XML PolyData file (no <VTKFile type=\"PolyData\"> header)")
    with pyvista.VtkErrorCatcher(raise_errors=True, send_to_logging=False):
        grid = pyvista.read(path).cast_to_unstructured_grid()
    cells = [SimpleNamespace(type=_VTK_CELL_NAMES.get(int(kind), f"VTK cell type {int(kind)}"),
                             data=np.asarray(data) if int(kind) == 5 else data)
             for kind, data in grid.cells_dict.items()]
    return SimpleNamespace(points=np.asarray(grid.points), cells=cells)


def read_surface(path, merge_tolerance: float = MERGE_TOLERANCE) -> SurfaceMesh:
    """Read a closed triangle surface: STL, OBJ, PLY, OFF, VTK, VTU, Gmsh, ... with meshio, VTK
    polygonal data (``.vtp``, and legacy ``.vtk`` files of ``DATASET POLYDATA``, which pyvista and
    ParaView write for surfaces) with pyvista.

    Only "triangle" cells are used (points, lines and volume cells are ignored); a file holding
    quadrilaterals, polygons or triangle strips is rejected (triangulate it first), and so is one
    without triangles.
    Points used by no triangle are dropped (whatever their coordinates, NaN included; a non-finite
    point that a triangle uses is refused with its row in the file) and coincident points are
    merged (see :func:`_merge_points`: closer than ``merge_tolerance``, by default MERGE_TOLERANCE,
    times the bounding-box diagonal), so that STL facet soups become a connected mesh; a soup whose
    copies of a vertex lie further apart is named as such, with the tolerance that would merge it.  The result is validated and oriented outward
    as in :class:`SurfaceMesh`, which includes the test that distinct closed components neither
    intersect nor nest (a model made of overlapping closed parts is refused with the pairs of
    components named: its signed distance would be wrong inside the overlaps).

    Raises FileNotFoundError when ``path`` does not exist, ValueError (naming ``path``) when the
    file cannot be read or its format is unknown, and ValueError when the surface is invalid.
    """
    import meshio

    if not (isinstance(merge_tolerance, (int, float, np.floating, np.integer)) and 0 <= merge_tolerance < 1e-2):
        raise ValueError(f"merge_tolerance must be a number in [0, 0.01) (relative to the bounding-box diagonal), "
                         f"got {merge_tolerance!r}")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"surface mesh file not found: '{path}'")
    if path.is_dir():
        raise ValueError(f"'{path}' is a directory; pass the path of a surface mesh file.")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = _read_polydata(path) if _is_polydata(path) else meshio.read(path)
    except (Exception, SystemExit) as err:  # meshio calls sys.exit(1) when its reader rejects a file
        detail = "meshio could not parse it" if isinstance(err, SystemExit) else f"{type(err).__name__}: {err}"
        raise ValueError(
            f"cannot read surface mesh '{path}' ({detail}); check the file and its "
            f"extension; supported formats include {_READ_EXTENSIONS_HINT}."
        ) from err
    other_2d = {
        block.type: len(block.data)
        for block in data.cells
        if block.type in ("quad", "polygon", "triangle_strip", "triangle6", "triangle7", "quad8", "quad9") and len(block.data)
    }
    if other_2d:
        raise ValueError(
            f"'{path}' contains non-triangle surface cells ({other_2d}); only 3-node triangles are supported: "
            "triangulate the surface first (e.g. pyvista PolyData.triangulate())."
        )
    if len(data.points) == 0 and not any(len(block.data) for block in data.cells):
        raise ValueError(
            f"'{path}' holds no points and no cells as read by the {path.suffix.lower() or 'default'} reader: the file is "
            "empty or its content is not in the format its extension says (rename it to the extension of its format)."
        )
    blocks = [np.asarray(block.data) for block in data.cells if block.type == "triangle"]
    if not blocks or sum(len(b) for b in blocks) == 0:
        found = sorted({block.type for block in data.cells}) or ["none"]
        raise ValueError(f"'{path}' has no triangle cells (cell types found: {', '.join(found)}).")
    triangles = np.concatenate(blocks).astype(np.int64)
    points = np.asarray(data.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"'{path}' has points of shape {points.shape}; a surface in R^3 needs (N, 3).")
    try:
        if triangles.min() < 0 or triangles.max() >= len(points):
            raise ValueError(f"triangle node indices outside [0, {len(points)})")
        points, triangles = _merge_points(points, triangles, float(merge_tolerance))
        try:
            return SurfaceMesh(points, triangles)
        except ValueError as err:
            soup = _unmerged_soup_message(points, triangles, float(merge_tolerance)) if str(err).startswith("the surface is open") else None
            if soup is None:
                raise
            raise ValueError(soup) from err
    except ValueError as err:
        raise ValueError(f"'{path}': {err}") from err


def write_surface(mesh: SurfaceMesh, path, file_format: str | None = None, **kwargs) -> None:
    """Write ``mesh`` (points and triangle cells) with meshio, or as VTK polygonal data with pyvista
    for a ``.vtp`` path; the format follows the extension.

    ``file_format`` and ``kwargs`` are passed to ``meshio.write`` (e.g. ``binary=True`` for STL).
    Node indices are written as int32 when they fit (portable PLY/VTK).  Binary STL stores
    float32 coordinates; the other common formats (.obj, .ply, .off, .vtk, .vtp, .vtu, ASCII .stl)
    round-trip float64 exactly.  Raises ValueError naming ``path`` for an unknown format and
    FileNotFoundError when the parent directory does not exist.
    """
    import meshio

    if not isinstance(mesh, SurfaceMesh):
        raise TypeError(f"write_surface expects a SurfaceMesh; got {type(mesh).__name__}.")
    path = Path(path)
    if not path.parent.exists():
        raise FileNotFoundError(f"cannot write '{path}': directory '{path.parent}' does not exist.")
    triangles = np.array(mesh.triangles)
    if mesh.n_points < 2**31:
        triangles = triangles.astype(np.int32)
    if path.suffix.lower() == ".vtp" and file_format is None:  # VTK polygonal data, which meshio does not write
        import pyvista

        pyvista.PolyData.from_regular_faces(np.array(mesh.points), triangles).save(path, **kwargs)
        return
    data = meshio.Mesh(np.array(mesh.points), [("triangle", triangles)])
    try:
        meshio.write(path, data, file_format=file_format, **kwargs)
    except (meshio.ReadError, meshio.WriteError, KeyError) as err:
        raise ValueError(
            f"cannot write surface mesh '{path}' ({err}); use a known extension such as {_READ_EXTENSIONS_HINT} "
            "or pass file_format."
        ) from err
