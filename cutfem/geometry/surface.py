"""Closed triangle surface meshes: the meshed case of docs/math.md §2.

A :class:`SurfaceMesh` is a closed, edge- and vertex-manifold, consistently and outward oriented
triangulation S_h with ``points`` (N, 3) and ``triangles`` (M, 3).  Its topology (unique edges,
the two triangles of each edge, the three edges of each triangle) and its geometry (areas, unit
normals, enclosed volume, edge conormals t_{E,K} of docs/math.md §3) are computed on demand, vectorized,
by sorting integer keys.

Conventions
-----------
* Local edge k of triangle (v_0, v_1, v_2) is the half-edge (v_k, v_{k+1 mod 3}).
* The normal of a triangle is (v_1 - v_0) x (v_2 - v_0) / |...|; a triangle is *outward* when its
  normal points out of the region its connected component encloses.
* Mesh size for tables and for the edge stabilization: the global ``h = N**(-1/2)`` (docs/math.md §2,
  N = number of surface nodes).

Generators: :func:`torus_mesh` (the four families of docs/math.md §6.1) and :func:`sphere_mesh`
(refined icosahedron).  File I/O through meshio: :func:`read_surface`, :func:`write_surface`.
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
from . import mesh_kernels

__all__ = [
    "SurfaceMesh",
    "torus_mesh",
    "sphere_mesh",
    "read_surface",
    "write_surface",
    "TORUS_FAMILIES",
    "DEGENERATE_TOLERANCE",
    "MERGE_TOLERANCE",
    "BYTES_PER_GENERATED_NODE",
    "SPHERE_MAX_LEVEL",
    "LENGTH_RANGE",
    "check_length",
]

#: A triangle is degenerate when |(b - a) x (c - a)| <= DEGENERATE_TOLERANCE * l_max**2, with
#: l_max its longest edge: twice its area is below 1e-12 times that of a right isosceles triangle
#: on its longest edge (the smallest angle is below about 1e-12 rad).
DEGENERATE_TOLERANCE = 1e-12

#: :func:`read_surface` merges points closer than MERGE_TOLERANCE * (diagonal of the bounding
#: box) (:func:`_merge_points`): the tolerance at which a tetrahedral mesh's nodes coincide.
MERGE_TOLERANCE = COINCIDENT_TOLERANCE

#: the torus families drawn at random (their ``seed`` matters)
RANDOM_FAMILIES = ("flipped", "perturbed", "perturbed-flipped")
#: The torus families of docs/math.md §6.1 accepted by :func:`torus_mesh`.
TORUS_FAMILIES = ("structured", *RANDOM_FAMILIES)

#: Peak bytes per node of a generated mesh (:func:`torus_mesh`, :func:`sphere_mesh`, with its
#: validation), checked before allocating: measured 582 (torus, n = 1200) and 656 (sphere, level 9)
#: as the peak resident memory of a fresh process over its baseline, rounded up.
BYTES_PER_GENERATED_NODE = 800

#: The lengths (radii, semi-axes) accepted by the analytic surfaces of :mod:`cutfem.geometry.levelset`
#: (Sphere, Torus, Ellipsoid) and by :func:`sphere_mesh` and :func:`torus_mesh`, as (smallest,
#: largest).  Within it every quantity formed from the lengths up to the fourth power stays a
#: normal float64 (2.2e-308 to 1.8e308), with room for a factor 1e5 of mesh refinement: areas
#: (L**2), volumes (L**3), curvatures (1/L), Hessians (1/L**2), the squared cross products of the
#: triangles' edges in the degeneracy test (L**4), the squared gradient of an ellipsoid.  Outside,
#: they overflow to inf (the area of a sphere of radius 1e200) or underflow to 0 (the triangles of a
#: sphere of radius 1e-160 "have zero area"); rescale the unit of length instead.
LENGTH_RANGE = (1e-50, 1e50)

#: The finest level of :func:`sphere_mesh` (20 * 4**10 = 20,971,520 triangles).
SPHERE_MAX_LEVEL = 10

_READ_EXTENSIONS_HINT = ".stl, .obj, .ply, .off, .vtk, .vtp, .vtu, .msh (Gmsh), .mesh (Medit)"

# names of the VTK cell types a surface file may hold (vtkCellType.h), for read_surface
_VTK_CELL_NAMES = {1: "vertex", 2: "vertex", 3: "line", 4: "line", 5: "triangle", 6: "triangle_strip", 7: "polygon",
                   8: "quad", 9: "quad"}

# local vertex index of the end of local edge k (which starts at vertex k)
_NEXT = np.array([1, 2, 0])


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------


def _examples(items, limit: int = 5) -> str:
    """Format the first ``limit`` entries of a sequence for an error message."""
    shown = ", ".join(str(x) for x in list(items[:limit]))
    if len(items) > limit:
        shown += f", ... ({len(items) - limit} more)"
    return shown


def _pairs(rows, limit: int = 5) -> str:
    """Format the first ``limit`` rows of an integer array as tuples for an error message."""
    rows = np.asarray(rows)
    shown = ", ".join(str(tuple(int(v) for v in row)) for row in rows[:limit])
    if len(rows) > limit:
        shown += f", ... ({len(rows) - limit} more)"
    return shown


def _halfedge_table(triangles: np.ndarray, n_points: int):
    """Unique undirected edges of a triangle list and the edge of every half-edge.

    Half-edge ``3 t + k`` is local edge k of triangle t, from ``triangles[t, k]`` to
    ``triangles[t, (k + 1) % 3]``.  Returns

    * ``edges`` (E, 2) int64, each row sorted (i < j), rows in lexicographic order, unique;
    * ``halfedge_edge`` (3M,) int64, the edge of each half-edge;
    * ``counts`` (E,) int64, the number of half-edges on each edge;
    * ``forward`` (3M,) bool, whether the half-edge runs from the smaller to the larger index.

    The edge {i, j} is encoded as the integer key i * N + j (i < j), so one stable sort of 1-d
    integer keys does all the work (:func:`cutfem.geometry.keys.pair_up`).
    """
    start = triangles.reshape(-1)
    end = triangles[:, _NEXT].reshape(-1)
    lo = np.minimum(start, end)
    hi = np.maximum(start, end)
    n = np.int64(max(n_points, 1))
    order, starts, counts = pair_up(lo * n + hi)
    keys = (lo * n + hi)[order[starts]]
    halfedge_edge = np.empty(start.size, dtype=np.int64)
    halfedge_edge[order] = np.repeat(np.arange(keys.size), counts)
    edges = np.stack([keys // n, keys % n], axis=1)
    return edges, halfedge_edge, counts, start < end


def _closed_halfedge_table(triangles: np.ndarray, n_points: int):
    """The half-edge table and the pairs of a closed, edge-manifold, consistently oriented mesh by
    one sort, or None if the mesh is not one.

    Each half-edge a -> b gets the key 2 (min(a, b) N + max(a, b)) + [a > b].  The mesh is closed,
    edge-manifold and consistently oriented exactly when the sorted keys come in pairs
    (2 k, 2 k + 1): every edge k carries one forward and one backward half-edge and nothing else.
    Then the sort order, read in pairs, is :func:`_pair_halfedges` (forward half-edge first), the
    edges come out in lexicographic order, and ``(table, pairs)`` are returned with ``table`` as
    :func:`_halfedge_table` gives it.  The sort is a compiled counting sort on the smaller node
    (:func:`cutfem.geometry.mesh_kernels.closed_halfedges`).
    """

    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    closed, order, edges, halfedge_edge = mesh_kernels.closed_halfedges(tri, np.int64(max(n_points, 1)))
    if not closed:
        return None
    counts = np.full(len(edges), 2, dtype=np.int64)
    return (edges, halfedge_edge, counts, tri.reshape(-1) < tri[:, _NEXT].reshape(-1)), order.reshape(-1, 2)


def _pair_halfedges(halfedge_edge: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """(E, 2) half-edge ids of each edge (all edges must carry exactly two), forward one first."""
    order = np.lexsort((~forward, halfedge_edge))
    return order.reshape(-1, 2)


def _next_halfedge(h: np.ndarray) -> np.ndarray:
    """Half-edge following h in its triangle: 3 t + k -> 3 t + (k + 1) mod 3."""
    return h + np.where(h % 3 == 2, -2, 1)


def _twin_halfedges(pairs: np.ndarray) -> np.ndarray:
    """(3M,) the other half-edge of the same edge, from the (E, 2) pairs of a closed mesh."""
    twin = np.empty(pairs.size, dtype=np.int64)
    twin[pairs[:, 0]] = pairs[:, 1]
    twin[pairs[:, 1]] = pairs[:, 0]
    return twin


def _opposite_vertex(triangles: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Node opposite to half-edge h = 3 t + k in its triangle: vertex (k + 2) mod 3 of t."""
    return triangles.reshape(-1)[h + np.where(h % 3 == 0, 2, -1)]


# ---------------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------------


def _as_points(points) -> np.ndarray:
    try:
        pts = np.array(points, dtype=np.float64, order="C")
    except (TypeError, ValueError) as err:
        raise ValueError(f"points must be a numeric (N, 3) array; conversion to float failed: {err}") from err
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3); got {pts.shape}. Pass one row of x, y, z per node.")
    return pts


def _as_triangles(triangles) -> np.ndarray:
    tri = np.asarray(triangles)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ValueError(
            f"triangles must have shape (M, 3); got {tri.shape}. Pass one row of three node indices per triangle "
            "(split quadrilaterals/polygons into triangles first)."
        )
    if tri.size and tri.dtype.kind not in "iu":
        raise ValueError(
            f"triangles must hold integer node indices; got dtype {tri.dtype}. Convert with .astype(np.int64) "
            "after checking that the values are whole numbers."
        )
    return np.ascontiguousarray(tri, dtype=np.int64)


def _triangle_geometry(points: np.ndarray, tri: np.ndarray):
    """Cross products, their lengths and edge-vector dot products of the triangles.

    With e_k = x_{k+1} - x_k (indices mod 3) the edge vectors of triangle (x_0, x_1, x_2), returns

    * ``cross`` (M, 3): e_0 x (x_2 - x_0) = (x_1 - x_0) x (x_2 - x_0);
    * ``twice_area`` (M,): |cross| = 2 |T|;
    * ``dots`` (2, M, 3): S[t, k] = e_k . e_k and Q[t, k] = e_k . e_{k+1};
    * ``longest`` (M,): max_k S[t, k], the squared longest edge.

    One compiled pass over the triangles (:func:`cutfem.geometry.mesh_kernels.triangle_geometry`).
    """

    tri = np.ascontiguousarray(tri, dtype=np.int64)
    if tri.size and (tri.min() < 0 or tri.max() >= len(points)):  # the compiled pass does not check its reads
        raise ValueError(f"triangles reference node indices outside [0, {len(points)}); indices must be 0-based rows of points")
    return mesh_kernels.triangle_geometry(np.ascontiguousarray(points, dtype=float), tri)


def _check_elements(points: np.ndarray, tri: np.ndarray):
    """Checks that need no topology: finite points, indices, repeated vertices, zero areas, unused points.

    Returns the cross products (b - a) x (c - a) (M, 3) (twice the area times the normal) and
    the edge-vector dot products (2, M, 3) of :func:`_triangle_geometry`, which the mesh keeps,
    and the number of triangles at each node (N,).  Duplicate triangles are found with
    the topology (:func:`_check_topology`), whose messages come after this function's.
    """
    n = len(points)
    if len(tri) == 0:
        raise ValueError("the surface has no triangles; a closed surface needs at least 4.")
    if not np.isfinite(points).all():
        bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
        raise ValueError(
            f"{bad.size} point(s) have non-finite (NaN or inf) coordinates, first at rows {_examples(bad)}; "
            "fix or remove them before building the surface."
        )
    if tri.min() < 0 or tri.max() >= n:
        bad = np.flatnonzero(((tri < 0) | (tri >= n)).any(axis=1))
        raise ValueError(
            f"{bad.size} triangle(s) reference node indices outside [0, {n}), first triangles {_examples(bad)} "
            f"with nodes {_pairs(tri[bad])}; indices must be 0-based rows of points."
        )
    bad = np.flatnonzero((tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 2] == tri[:, 0]))
    if bad.size:
        raise ValueError(
            f"{bad.size} degenerate triangle(s) repeat a vertex, first triangles {_examples(bad)} with nodes "
            f"{_pairs(tri[bad])}; remove them (collapse the edge they sit on) before building the surface."
        )
    cross, twice_area, dots, longest_sq = _triangle_geometry(points, tri)
    bad = np.flatnonzero(twice_area <= DEGENERATE_TOLERANCE * longest_sq)
    if bad.size:
        raise ValueError(
            f"{bad.size} degenerate triangle(s) have zero area (collinear or coincident vertices), first triangles "
            f"{_examples(bad)} with nodes {_pairs(tri[bad])}; remove or repair them (e.g. merge coincident points, "
            "collapse short edges)."
        )
    degree = np.bincount(tri.reshape(-1), minlength=n)
    unused = np.flatnonzero(degree == 0)
    if unused.size:
        raise ValueError(
            f"{unused.size} point(s) belong to no triangle, first rows {_examples(unused)}; a P1 unknown there would "
            "have no support (singular mass matrix) and would change h = N**(-1/2). Remove them: "
            "keep = np.unique(triangles); points = points[keep]; triangles = np.searchsorted(keep, triangles)."
        )
    return cross, twice_area, dots, degree


def _check_duplicates(tri: np.ndarray) -> None:
    """Raise if two triangles have the same three nodes."""
    srt = np.sort(tri, axis=1)
    order = np.lexsort(srt.T[::-1])
    same = np.flatnonzero((srt[order][1:] == srt[order][:-1]).all(axis=1))
    if same.size:
        pairs = np.stack([order[same], order[same + 1]], axis=1)
        raise ValueError(
            f"{same.size} triangle(s) duplicate another triangle on the same three nodes, first pairs of triangles "
            f"{_pairs(pairs)}; remove the duplicates."
        )


def _diagnose_topology(tri: np.ndarray, n_points: int) -> None:
    """Raise the message for an open, edge-non-manifold or inconsistently oriented mesh."""
    edges, halfedge_edge, counts, forward = _halfedge_table(tri, n_points)
    bad = np.flatnonzero(counts == 1)
    if bad.size:
        raise ValueError(
            f"the surface is open: {bad.size} boundary edge(s) belong to only one triangle, first edges "
            f"{_pairs(edges[bad])}; close the holes (a closed surface needs every edge in exactly two triangles)."
        )
    bad = np.flatnonzero(counts > 2)
    if bad.size:
        raise ValueError(
            f"the surface is non-manifold: {bad.size} edge(s) belong to more than two triangles, first edges "
            f"{_pairs(edges[bad])} (in {_examples(counts[bad])} triangles); split it into separate sheets by "
            "duplicating the shared nodes, so that every edge is in exactly two triangles."
        )
    pairs = _pair_halfedges(halfedge_edge, forward)
    bad = np.flatnonzero(forward[pairs[:, 0]] == forward[pairs[:, 1]])
    if bad.size:
        tris = pairs[bad] // 3
        raise ValueError(
            f"the surface is not consistently oriented: on {bad.size} edge(s) both triangles traverse the edge in "
            f"the same direction, first edges {_pairs(edges[bad])} in triangle pairs {_pairs(tris)}; reorder the "
            "vertices of the offending triangles so that neighbours agree (e.g. pyvista "
            "PolyData.compute_normals(consistent_normals=True, auto_orient_normals=True)); a non-orientable "
            "surface is not supported."
        )
    raise AssertionError("unreachable: the one-sort test and the diagnosis of the topology disagree")


def _check_topology(tri: np.ndarray, n_points: int, degree: np.ndarray):
    """No duplicate triangles; closed, edge-manifold, consistently oriented, vertex-manifold.

    ``degree`` (N,) is the number of triangles at each node.  Returns ``(table, pairs)``, the
    half-edge table of :func:`_halfedge_table` and the (E, 2) half-edge pairs of
    :func:`_pair_halfedges`.  The valid case costs one sort (:func:`_closed_halfedge_table`); the
    slower diagnosis runs only to word the error.

    Duplicate triangles: on a mesh that passes the one-sort test, two triangles on the same three
    nodes are the two triangles of each of their edges, so they show as an edge whose two opposite
    vertices coincide.  (A duplicate that breaks the edge counts is reported before them, too.)

    Vertex manifoldness: the corners (triangle, vertex) around a node must form a single fan.
    Corner ids coincide with half-edge ids (corner 3t+k is vertex k of triangle t, where half-edge
    3t+k starts).  The corner of a across the outgoing half-edge h: a -> b is next(twin(h)), so
    sigma(c) = next(twin(c)) is a permutation of the corners of each node whose cycles are the
    fans.  The cycles are labelled by their smallest corner by pointer doubling (after j steps a
    label is the minimum over 2^j successive corners; a cycle is no longer than the degree of
    its node), and the mesh is vertex-manifold when there are exactly N cycles.
    """
    fast = _closed_halfedge_table(tri, n_points)
    if fast is None:
        _check_duplicates(tri)
        _diagnose_topology(tri, n_points)
    table, pairs = fast
    opposite = _opposite_vertex(tri, pairs)
    if np.any(opposite[:, 0] == opposite[:, 1]):
        _check_duplicates(tri)
    sigma = _next_halfedge(_twin_halfedges(pairs))
    label = np.arange(sigma.size)
    for _ in range(int(degree.max() - 1).bit_length()):
        np.minimum(label, label[sigma], out=label)
        sigma = sigma[sigma]
    first = label == np.arange(label.size)
    if np.count_nonzero(first) != n_points:
        fans_per_vertex = np.bincount(tri.reshape(-1)[first], minlength=n_points)
        bad = np.flatnonzero(fans_per_vertex > 1)
        raise ValueError(
            f"the surface is non-manifold at {bad.size} vertex(es), first nodes {_examples(bad)}: separate fans of "
            "triangles touch at a single point; move the touching parts apart (in arrays, a node duplicated once per fan "
            "also separates them, but a file's coincident points are merged back into one when it is read)."
        )
    return table, pairs


def _components(tri: np.ndarray, pairs: np.ndarray):
    """(number of components, component of each triangle (M,)): the connected components of the
    graph of triangles sharing an edge (``pairs``, the half-edge pairs of a closed mesh).  The
    graph is symmetric, so its strong components are its components."""
    m = len(tri)
    neighbour = _twin_halfedges(pairs) // 3  # the triangle across each half-edge
    graph = sp.csr_matrix((np.ones(3 * m, dtype=np.int8), neighbour, 3 * np.arange(m + 1)), shape=(m, m))
    return connected_components(graph, directed=True, connection="strong")


def _orient_outward(points: np.ndarray, tri: np.ndarray, component: np.ndarray, cross: np.ndarray):
    """Flip the triangles of every connected component whose enclosed signed volume is negative.

    Signed volume of a closed oriented component C: V = (1/6) sum_{K in C} (a - o) . ((b - o) x (c - o)),
    independent of o; o = mean of the points.  Per triangle (a - o) . ((b - o) x (c - o)) =
    (a - o) . ((b - a) x (c - a)), so the cross products ``cross`` (M, 3) of the validation are
    reused.  ``component`` (M,) is the component of each triangle (:func:`_components`).  Returns
    (triangles, cross products, number of flipped components); a flipped triangle (a, c, b) has
    the cross product negated (exactly).
    """
    o = points.mean(axis=0)
    vol6 = np.einsum("ij,ij->i", np.take(points, tri[:, 0], axis=0) - o, cross)
    volume = np.bincount(component, weights=vol6) / 6.0
    flip_component = volume < 0
    if not flip_component.any():
        return tri, cross, 0
    flip = flip_component[component]
    tri = tri.copy()
    tri[flip] = tri[flip][:, [0, 2, 1]]
    cross = cross.copy()
    cross[flip] *= -1.0
    return tri, cross, int(flip_component.sum())


def _overlapping_boxes(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(P, 2) index pairs i < j of the boxes [lo_i, hi_i] (n, 3) that overlap (closed boxes), by a
    sweep along x: sorted by lo_x, box i meets the boxes j after it with lo_x[j] <= hi_x[i]."""
    order = np.argsort(lo[:, 0], kind="stable")
    lo, hi = lo[order], hi[order]
    end = np.searchsorted(lo[:, 0], hi[:, 0], side="right")  # boxes i+1 .. end-1 start before i ends
    count = np.maximum(end - np.arange(len(lo)) - 1, 0)
    i = np.repeat(np.arange(len(lo)), count)
    j = i + 1 + (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count))
    meet = np.all((lo[j] <= hi[i]) & (lo[i] <= hi[j]), axis=1)
    pairs = np.stack([order[i[meet]], order[j[meet]]], axis=1)
    return np.sort(pairs, axis=1)


def _orient(a, b, c, d) -> np.ndarray:
    """(b - a) . ((c - a) x (d - a)) row by row: six times the signed volume of the tet abcd."""
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))


def _segments_cross_triangles(p, q, a, b, c) -> np.ndarray:
    """Whether segment [p, q] meets triangle abc, row by row (all (k, 3)).

    The segment's ends are on opposite sides of the triangle's plane (or on it), and the line pq
    passes the three edges of the triangle on the same side (all three orientations >= 0 or all
    <= 0): the closed segment meets the closed triangle.  A segment lying in the triangle's plane
    (both orientations zero) is not counted: coplanar contact is left to the other edges."""
    sp_, sq = _orient(a, b, c, p), _orient(a, b, c, q)
    straddle = (sp_ * sq <= 0) & ~((sp_ == 0) & (sq == 0))
    u = np.stack([_orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)], axis=1)
    inside = np.all(u >= 0, axis=1) | np.all(u <= 0, axis=1)
    return straddle & inside


def _crossing_triangles(points: np.ndarray, tri: np.ndarray, component: np.ndarray, tlo: np.ndarray, thi: np.ndarray) -> np.ndarray:
    """(P, 2) pairs of triangles of different components that meet (one triangle's edge crosses the
    other triangle): the surfaces of the two components intersect or touch.

    Candidates by a uniform grid: the cell is twice the median extent of the triangles' bounding
    boxes (grown, if needed, to keep the number of (triangle, cell) entries below 16 M + 64 per
    triangle); each triangle enters every cell its bounding box meets, only the cells met by two
    components or more are kept, and two triangles of different components sharing such a cell,
    with overlapping bounding boxes, are tested exactly with
    :func:`_segments_cross_triangles`, all three edges of each against the other.  Two transversal
    triangles meet along a segment whose ends lie on edges of one or the other, so this finds every
    transversal intersection; a contact only within a common plane is not seen.  ``tlo``, ``thi``
    (M, 3) are the triangles' bounding boxes."""
    x = points[tri]  # (M, 3, 3)
    extent = float(np.median(np.max(thi - tlo, axis=1)))
    span = float(np.max(points.max(axis=0) - points.min(axis=0)))
    cell = max(2.0 * extent, 1e-9 * span, np.finfo(float).tiny)
    origin = points.min(axis=0)
    while True:
        c0 = np.floor((tlo - origin) / cell).astype(np.int64)
        c1 = np.floor((thi - origin) / cell).astype(np.int64)
        n = np.prod(c1 - c0 + 1, axis=1)
        if n.sum() <= 16_000_000 + 64 * len(tri):
            break
        cell *= 2.0
    grid = c1.max(axis=0) + 1
    owner = np.repeat(np.arange(len(tri)), n)
    local = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    shape = (c1 - c0 + 1)[owner]
    ijk = c0[owner] + np.stack([local % shape[:, 0], (local // shape[:, 0]) % shape[:, 1], local // (shape[:, 0] * shape[:, 1])], axis=1)
    key = ijk[:, 0] + grid[0] * (ijk[:, 1] + grid[1] * ijk[:, 2])
    order, starts, counts = pair_up(key)
    # only the cells holding triangles of two components or more matter
    comp = component[owner[order]]
    mixed = np.minimum.reduceat(comp, starts) != np.maximum.reduceat(comp, starts)
    order = order[np.repeat(mixed, counts)]
    starts, counts = np.cumsum(counts[mixed]) - counts[mixed], counts[mixed]
    # all pairs (s, t), s before t, within each cell's run of the sorted entries
    pos = np.arange(order.size)
    run_end = np.repeat(starts + counts, counts)
    later = run_end - pos - 1
    first = np.repeat(pos, later)
    second = first + 1 + (np.arange(later.sum()) - np.repeat(np.cumsum(later) - later, later))
    t1, t2 = owner[order[first]], owner[order[second]]
    keep = (component[t1] != component[t2]) & np.all((tlo[t1] <= thi[t2]) & (tlo[t2] <= thi[t1]), axis=1)
    pairs = np.unique(np.sort(np.stack([t1[keep], t2[keep]], axis=1), axis=1), axis=0)
    if len(pairs) == 0:
        return pairs
    hit = np.zeros(len(pairs), dtype=bool)
    for s, t in ((0, 1), (1, 0)):
        P, T = x[pairs[:, s]], x[pairs[:, t]]
        for k in range(3):
            hit |= _segments_cross_triangles(P[:, k], P[:, (k + 1) % 3], T[:, 0], T[:, 1], T[:, 2])
    return pairs[hit]


def _winding_number(point: np.ndarray, tri_points: np.ndarray) -> float:
    """Winding number of a closed oriented triangle surface (triangles (M, 3, 3)) about ``point``
    (3,): (1 / 4 pi) times the sum of the triangles' signed solid angles, tan(Omega / 2) =
    det[a b c] / (|a||b||c| + (a.b)|c| + (b.c)|a| + (c.a)|b|) with a, b, c the vertices minus the
    point.  +-1 inside, 0 outside (up to rounding), for either orientation."""
    a, b, c = (tri_points[:, k] - point for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    return float(np.sum(2.0 * np.arctan2(num, den)) / (4.0 * np.pi))


def _check_disjoint_components(points: np.ndarray, tri: np.ndarray, component: np.ndarray, n_components: int) -> None:
    """Raise ValueError unless the regions enclosed by distinct closed components are disjoint.

    Decision: components must neither intersect (their surfaces cross or touch) nor nest (one
    inside another, a shell inside a shell).  A file of overlapping parts (a model assembled from
    closed pieces pushed into each other) has a signed distance that is not 1-Lipschitz and whose
    sign is wrong inside the overlaps, and a nested shell is ambiguous (a cavity, or a part swallowed
    by another) for the outward orientation per component and for the signed distance; both are
    rejected rather than guessed.  Components whose bounding boxes are disjoint are skipped at once.

    Intersection: :func:`_crossing_triangles` (every transversal crossing of two triangles of
    different components).  Nesting, for components whose boxes overlap and whose surfaces do not
    meet: one surface lies wholly inside or wholly outside the other, so the winding number of one
    vertex decides (:func:`_winding_number`, |w| > 1/2 means inside).
    """
    if n_components < 2:
        return
    order = np.argsort(component, kind="stable")
    starts = np.searchsorted(component[order], np.arange(n_components))
    ends = np.append(starts[1:], len(tri))
    x0, x1, x2 = (points[tri[:, k]] for k in range(3))
    tlo, thi = np.minimum(np.minimum(x0, x1), x2), np.maximum(np.maximum(x0, x1), x2)  # triangle boxes
    lo, hi = np.minimum.reduceat(tlo[order], starts), np.maximum.reduceat(thi[order], starts)
    candidates = _overlapping_boxes(lo, hi)
    if len(candidates) == 0:
        return
    near = np.zeros(len(tri), dtype=bool)  # triangles meeting the box of a component paired with theirs
    for a, b in candidates:  # component pairs (few), each vectorized over the triangles
        for own, other in ((a, b), (b, a)):
            ids = order[starts[own]:ends[own]]
            near[ids] |= np.all((tlo[ids] <= hi[other]) & (lo[other] <= thi[ids]), axis=1)
    cross = _crossing_triangles(points, tri[near], component[near], tlo[near], thi[near])
    if len(cross):
        tri_ids = np.flatnonzero(near)[cross]
        comps = np.unique(np.sort(component[tri_ids], axis=1), axis=0)
        where = points[tri[tri_ids[0, 0]]].mean(axis=0)
        raise ValueError(
            f"closed components of the surface intersect: {len(comps)} pair(s) of components whose surfaces cross "
            f"or touch, first pairs of components {_pairs(comps)} (triangles {_pairs(tri_ids)}), first near "
            f"{np.round(where, 6).tolist()}. Overlapping parts have no single inside and their signed distance is "
            "wrong in the overlaps; merge them into one closed surface without self-intersections (a boolean "
            "union, e.g. with a mesh repair tool) or separate them."
        )
    nested = []
    for a, b in candidates:
        for outer, inner in ((a, b), (b, a)):
            w = _winding_number(points[tri[order[starts[inner]], 0]], points[tri[order[starts[outer]:ends[outer]]]])
            if abs(w) > 0.5:
                nested.append((inner, outer))
    if nested:
        raise ValueError(
            f"closed components of the surface are nested: {len(nested)} component(s) lie inside another, "
            f"first (inner, outer) pairs {_pairs(nested)}. A shell inside a shell is ambiguous (a cavity, or a part "
            "swallowed by another) and is not supported: remove the inner shell, or give the shells as separate "
            "surfaces."
        )


def _closest_on_triangles(x: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The point of triangle abc nearest to x, row by row (all (..., 3)).

    Ericson's region test (Real-Time Collision Detection, 5.1.5): with ab = b - a, ac = c - a and
    the dot products d1 = ab.(x - a), d2 = ac.(x - a), d3 = ab.(x - b), d4 = ac.(x - b),
    d5 = ab.(x - c), d6 = ac.(x - c), the Voronoi region of x among the three vertices, the three
    edges and the face is decided by signs, and the point is a vertex, a + t ab, a + t ac,
    b + t (c - b) with t in [0, 1], or a + v ab + w ac with v, w >= 0, v + w <= 1.  The result lies
    on the triangle to rounding of its corners' coordinates, whatever |x| is (no squares of x).  The
    vectorized form of the region test that :mod:`cutfem.geometry.closest` compiles; the tests' reference."""
    dot = lambda u, v: np.einsum("...i,...i->...", u, v)  # noqa: E731
    ab, ac = b - a, c - a
    d1, d2 = dot(ab, x - a), dot(ac, x - a)
    d3, d4 = dot(ab, x - b), dot(ac, x - b)
    d5, d6 = dot(ab, x - c), dot(ac, x - c)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    with np.errstate(divide="ignore", invalid="ignore"):  # the ratios of the other regions are not used
        t_ab, t_ac = d1 / (d1 - d3), d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        total = va + vb + vc
        v, w = vb / total, vc / total
        choices = [a, b, c, a + t_ab[..., None] * ab, a + t_ac[..., None] * ac, b + t_bc[..., None] * (c - b)]
        face = a + v[..., None] * ab + w[..., None] * ac
    regions = [
        (d1 <= 0) & (d2 <= 0),  # vertex a
        (d3 >= 0) & (d4 <= d3),  # vertex b
        (d6 >= 0) & (d5 <= d6),  # vertex c
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ac
        (va <= 0) & (d4 >= d3) & (d5 >= d6),  # edge bc
    ]
    return np.select([r[..., None] for r in regions], choices, face)


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
      :func:`_check_disjoint_components`, vectorized, skipped for a single component.

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
        (:func:`torus_mesh`): node (i, j) is node i m + j, its grid neighbours are (i +- 1, j) and
        (i, j +- 1) modulo (n, m).  The multigrid solver coarsens along it
        (:func:`cutfem.solvers.solve.grid_hierarchy`); None for any other mesh.

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
        and consistently outward oriented by construction (:func:`torus_mesh`): the element
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
        """One of the arrays of :func:`_triangle_geometry` kept by the validation; without it
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
        :func:`_closest_on_triangles`).  Where the nearest point is not unique (x equidistant from
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
# generators
# ---------------------------------------------------------------------------------------------


def _int_text(value) -> str:
    """An integer for a message: in full up to 18 digits, else in floating notation (str() of an
    integer beyond 4300 digits raises, and writing out a huge one is slow and unreadable)."""
    value = int(value)
    if abs(value) < 10**18:
        return str(value)
    try:
        return f"{float(value):.3g}"
    except OverflowError:
        return f"{'-' if value < 0 else ''}2**{abs(value).bit_length() - 1} or more"


def _check_int(name: str, value, minimum: int, maximum: int | None = None, why: str = "") -> int:
    """``value`` as an int in [minimum, maximum]; ValueError otherwise (``why`` explains the maximum).
    The bounds are compared before anything is computed from ``value``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}.")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {_int_text(value)}.")
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be an integer <= {maximum}; got {_int_text(value)}{why}.")
    return int(value)


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


def _available_bytes() -> int:
    from ..memory import available_memory

    return available_memory()[0]


def _check_generated_memory(nodes: int, what: str, fix: str) -> None:
    """Refuse a generated mesh of ``nodes`` nodes whose peak memory (:data:`BYTES_PER_GENERATED_NODE`
    per node) exceeds the memory available (:func:`cutfem.memory.check_memory`), before allocating."""
    from ..memory import check_memory

    try:
        estimate = BYTES_PER_GENERATED_NODE * float(nodes)
    except OverflowError:  # more than 1e308 nodes
        estimate = float("inf")
    check_memory(estimate, what, fix)


def torus_mesh(n: int, family: str = "structured", R: float = 1.0, r: float = 0.5, seed=0) -> SurfaceMesh:
    """Triangulated torus on an n x n/2 grid in the angles (t, p) (docs/math.md §6.1).

    Node (i, j), i = 0..n-1, j = 0..m-1 with m = n // 2, has grid angles t_i = 2 pi i / n,
    p_j = 2 pi j / m and sits at

        x = (R + r cos p) cos t,  y = (R + r cos p) sin t,  z = r sin p,

    so every node lies exactly on the torus rho = sqrt(z^2 + (sqrt(x^2 + y^2) - R)^2) - r = 0.
    Node index i * m + j.  N = n m nodes, 2 N triangles, 3 N edges, Euler characteristic 0.
    Cell (i, j) has corners v00 = (i, j), v10 = (i+1, j), v11 = (i+1, j+1), v01 = (i, j+1)
    (indices periodic) and is split along the diagonal v00-v11 into (v00, v10, v11),
    (v00, v11, v01), or along v10-v01 into (v00, v10, v01), (v10, v11, v01); both are outward
    since x_t x x_p points out of the torus.

    Families:

    * ``"structured"``: every cell split along v00-v11;
    * ``"flipped"``: each cell's diagonal chosen by a fair coin;
    * ``"perturbed"``: each node's (t, p) moved by independent uniform offsets in
      [-dt/4, dt/4] x [-dp/4, dp/4] (dt = 2 pi / n, dp = 2 pi / m), then placed on the torus;
      structured diagonals (the paper's "unstructured" family);
    * ``"perturbed-flipped"``: both.

    Randomness: one ``numpy.random.default_rng(seed)`` draws, always in this order and for every
    family, the n m diagonal coins and then the (n m, 2) node offsets; each family uses what it
    needs.  Hence the same seed gives identical meshes, and "perturbed-flipped" has the nodes of
    "perturbed" and the diagonals of "flipped" for the same seed.

    Notes: the cells of the unperturbed grid are planar isosceles trapezoids, so "flipped" has the
    same area (and stiffness matrix) as "structured".  Requires n even and >= 6 (so m >= 3 and the
    grid is a simplicial complex) and 0 < r < R (an embedded ring torus).  Memory: the n m nodes
    at :data:`BYTES_PER_GENERATED_NODE` each are compared with the memory available before
    anything is allocated (:class:`cutfem.memory.InsufficientMemoryError` naming the size and an n
    that fits).  R and r must lie in :data:`LENGTH_RANGE`, and an r / R so small that the cells are
    slivers (degenerate by :data:`DEGENERATE_TOLERANCE`) is refused naming r / R.

    Validation: the grid is closed, manifold (six triangles in one fan at every node) and
    outward by construction, for every family (the offsets move nodes by less than half a cell,
    which keeps the signed volume positive), so only what the node positions could break is
    checked: finite, non-degenerate triangles (:meth:`SurfaceMesh._check_generated`).
    """
    n = _check_int("n", n, 6)
    if n % 2:
        raise ValueError(f"n must be even (the grid is n x n/2); got n = {n}. Use n = {n + 1}.")
    if family not in TORUS_FAMILIES:
        raise ValueError(f"unknown torus family {family!r}; allowed: {', '.join(TORUS_FAMILIES)}.")
    R = check_length("R", R, "torus_mesh")
    r = check_length("r", r, "torus_mesh")
    if not r < R:
        raise ValueError(f"the torus needs 0 < r < R (a ring torus without self-contact); got R = {R}, r = {r}.")
    m = n // 2
    fits = 2 * int(np.sqrt(_available_bytes() / BYTES_PER_GENERATED_NODE) / 2)  # n**2 / 2 nodes fit
    _check_generated_memory(
        n * m, f"torus_mesh(n={_int_text(n)}) ({_int_text(n * m)} nodes, {_int_text(2 * n * m)} triangles)",
        f"use a smaller n (the memory grows like n**2; n = {fits} fits)" if fits >= 6 else "free memory",
    )
    rng = np.random.default_rng(seed)
    coins = rng.random(n * m) < 0.5
    offsets = rng.uniform(-0.25, 0.25, size=(n * m, 2))

    # node (and cell) index i * m + j; the angles of the unperturbed grid need only n + m values
    gi, gj = np.arange(n, dtype=float)[:, None], np.arange(m, dtype=float)[None, :]
    if family in ("perturbed", "perturbed-flipped"):
        gi = gi + offsets[:, 0].reshape(n, m)
        gj = gj + offsets[:, 1].reshape(n, m)
    t = 2.0 * np.pi * gi / n
    p = 2.0 * np.pi * gj / m
    ring = R + r * np.cos(p)
    points = np.empty((n, m, 3))
    points[..., 0] = ring * np.cos(t)
    points[..., 1] = ring * np.sin(t)
    points[..., 2] = r * np.sin(p)

    v00 = np.arange(n * m).reshape(n, m)
    v10, v01 = np.roll(v00, -1, axis=0), np.roll(v00, -1, axis=1)
    v11 = np.roll(v10, -1, axis=1)
    triangles = np.empty((n, m, 2, 3), dtype=np.int64)
    for k, v in enumerate((v00, v10, v11)):  # main diagonal: (v00, v10, v11), (v00, v11, v01)
        triangles[:, :, 0, k] = v
    for k, v in enumerate((v00, v11, v01)):
        triangles[:, :, 1, k] = v
    if family in ("flipped", "perturbed-flipped"):  # the other diagonal: (v00, v10, v01), (v10, v11, v01)
        flip = coins.reshape(n, m)
        triangles[flip, 0, 2] = v01[flip]
        triangles[flip, 1] = np.stack([v10[flip], v11[flip], v01[flip]], axis=1)
    points, triangles = points.reshape(-1, 3), triangles.reshape(-1, 3)
    mesh = SurfaceMesh(points, triangles, check=False)
    try:
        mesh._check_generated()  # the grid is a closed, outward torus; only the geometry is checked
    except ValueError as err:  # r / R so small that the cells are slivers
        raise ValueError(
            f"torus_mesh(n={n}, R={R:g}, r={r:g}) makes degenerate triangles: the ratio r / R = {r / R:.3g} is too "
            f"small for the grid (cells about {2 * np.pi * R / n:.3g} by {2 * np.pi * r / m:.3g}, slivers by the test of "
            "DEGENERATE_TOLERANCE); use a larger r / R."
        ) from err
    mesh.grid = (n, m)
    return mesh


def _refine_midpoints(points: np.ndarray, triangles: np.ndarray):
    """Split every triangle into four through its edge midpoints (orientation preserved).

    New node N + e at the midpoint of edge e; (v0, v1, v2) with midpoints m0 = (v0 v1),
    m1 = (v1 v2), m2 = (v2 v0) becomes (v0, m0, m2), (m0, v1, m1), (m2, m1, v2), (m0, m1, m2).
    """
    edges, halfedge_edge, _, _ = _halfedge_table(triangles, len(points))
    mid = len(points) + halfedge_edge.reshape(-1, 3)
    new_points = np.concatenate([points, 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])])
    v0, v1, v2 = triangles.T
    m0, m1, m2 = mid.T
    children = np.stack(
        [
            np.stack([v0, m0, m2], 1),
            np.stack([m0, v1, m1], 1),
            np.stack([m2, m1, v2], 1),
            np.stack([m0, m1, m2], 1),
        ],
        axis=1,
    )
    return new_points, children.reshape(-1, 3)


def sphere_mesh(level: int = 3, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> SurfaceMesh:
    """Icosahedral sphere: the regular icosahedron refined ``level`` times, nodes on the sphere.

    The 12 icosahedron vertices are the cyclic permutations of (0, +-1, +-phi), phi = (1 + sqrt 5)/2,
    scaled to the unit sphere; its 20 faces are the convex hull, oriented outward.  Each refinement
    splits every triangle into four through its edge midpoints and pushes the new nodes radially
    onto the unit sphere; finally x = center + radius * u.  Hence every node satisfies
    |x - center| = radius up to round-off, and

        N = 10 * 4^level + 2,  E = 30 * 4^level,  M = 20 * 4^level,  Euler characteristic 2.

    The area tends to 4 pi radius^2 and the volume to 4/3 pi radius^3 at O(h^2).

    ``radius`` must lie in :data:`LENGTH_RANGE`.  ``level`` must be an integer in
    0..:data:`SPHERE_MAX_LEVEL`, checked before anything is
    computed from it (a huge level is refused at once); the nodes at
    :data:`BYTES_PER_GENERATED_NODE` each must fit in the memory available
    (:class:`cutfem.memory.InsufficientMemoryError` naming a level that fits).
    """
    from scipy.spatial import ConvexHull

    level = _check_int(
        "level", level, 0, SPHERE_MAX_LEVEL,
        f" (level {SPHERE_MAX_LEVEL} has {20 * 4**SPHERE_MAX_LEVEL:,} triangles; each level multiplies them by 4)",
    )
    radius = check_length("radius", radius, "sphere_mesh")
    center = np.asarray(center, dtype=float)
    if center.shape != (3,) or not np.isfinite(center).all():
        raise ValueError(f"center must be 3 finite coordinates; got {center!r}.")
    nodes = 10 * 4**level + 2
    fits = [k for k in range(level) if BYTES_PER_GENERATED_NODE * (10 * 4**k + 2) <= _available_bytes()]
    _check_generated_memory(
        nodes, f"sphere_mesh(level={level}) ({nodes:,} nodes, {20 * 4**level:,} triangles)",
        f"use a smaller level (the memory grows 4 times a level; level {fits[-1]} fits)" if fits else "free memory",
    )
    phi = 0.5 * (1.0 + np.sqrt(5.0))
    base = np.array([[0.0, s1, s2 * phi] for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)])
    verts = np.concatenate([np.roll(base, shift, axis=1) for shift in range(3)])
    verts /= np.linalg.norm(verts, axis=1)[:, None]
    tri = ConvexHull(verts).simplices.astype(np.int64)
    normal = np.cross(verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]])
    inward = np.einsum("ij,ij->i", normal, verts[tri].sum(axis=1)) < 0
    tri[inward] = tri[inward][:, [0, 2, 1]]
    for _ in range(level):
        verts, tri = _refine_midpoints(verts, tri)
        verts /= np.linalg.norm(verts, axis=1)[:, None]
    return SurfaceMesh(center + radius * verts, tri)


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
