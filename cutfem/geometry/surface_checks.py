"""The validation of a triangle surface: what :class:`~cutfem.geometry.surface.SurfaceMesh` checks.

A surface is accepted when it is closed, edge- and vertex-manifold, consistently oriented, without
degenerate or duplicate triangles or unused points, and its connected components neither
intersect nor nest; each component is then oriented outward on its own (the decisions and their
reasons are stated in the SurfaceMesh docstring).  Every check is vectorized and names the count,
the first offenders and the fix.  The half-edge tables that the checks and the mesh's topology
share live here too: half-edge ``3 t + k`` is local edge k of triangle t, from vertex k to vertex
k + 1 mod 3, and one sort of integer edge keys pairs them (:func:`_closed_halfedge_table`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .keys import pair_up
from . import mesh_kernels

__all__ = ["DEGENERATE_TOLERANCE"]

#: A triangle is degenerate when |(b - a) x (c - a)| <= DEGENERATE_TOLERANCE * l_max**2, with
#: l_max its longest edge: twice its area is below 1e-12 times that of a right isosceles triangle
#: on its longest edge (the smallest angle is below about 1e-12 rad).
DEGENERATE_TOLERANCE = 1e-12

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
