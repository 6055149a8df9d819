"""Nearest points of a triangle mesh and the signed distance to it: one compiled pass per query.

The triangles are put in a bounding-volume hierarchy once: a complete binary tree in heap order
(node k has children 2k and 2k + 1; root 1) with leaves of :data:`LEAF` triangles, built top down
by median splits of the triangles' centroids along the longest side of each node's box (one
vectorized partition per level), and boxes that are the unions of their children's.

A query walks the tree from the root, nearer child first, and skips a subtree whose box is farther
than the nearest triangle found so far (the box contains its triangles, so none of them can be
nearer): the result is the exact nearest point over all triangles, the same as comparing every
triangle, in about ``log M`` box tests and a few triangle tests per point for points near the
surface.  The points are shared between the cores (``prange``); each point's walk is independent,
so the results do not depend on the number of threads.

The sign of the distance to a closed, outward oriented, manifold mesh is that of
``(x - p) . N`` with p the nearest point and N the angle-weighted pseudo-normal of the feature p
lies on (Baerentzen and Aanaes, IEEE TVCG 11, 2005): the triangle's normal inside a face, the sum
of the two triangles' unit normals on an edge, and at a vertex the sum of its triangles' unit
normals weighted by their angles there.  That choice makes the sign exact for every point not on
the mesh, also where the nearest point is an edge or a vertex (the face normal of one of the
triangles there can point the wrong way).

:func:`_closest_on_triangles` is the same region test in numpy, over arrays of rows: the tests' reference.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from cutfem.jit import parallel_kernel

__all__ = ["TriangleTree", "LEAF"]

#: triangles per leaf of the hierarchy
LEAF = 4


def _median_split_order(c: np.ndarray, slots: int) -> np.ndarray:
    """The order of the triangles (centroids c (M, 3)) in the leaves of the complete tree of
    ``slots`` = 2**depth * LEAF places: top down, each node's places are split at their middle by
    the centroids' coordinate along the longest side of their bounding box (a median split by
    ``argpartition``, one vectorized call per level over all its nodes).  The empty places (NaN
    centroids, which partition after every number) go right at each split, so at every level one
    node at most holds both triangles and empty places, with only triangles to its left; sorting
    that leaf's places puts the triangles in the places 0 to M - 1."""
    m = len(c)
    ids = np.concatenate([np.arange(m), np.full(slots - m, -1)])
    cc = np.concatenate([c, np.full((slots - m, 3), np.nan)])
    nodes = 1
    while slots // nodes > LEAF:
        size = slots // nodes
        seg = cc[ids].reshape(nodes, size, 3)
        extent = np.fmax.reduce(seg, axis=1) - np.fmin.reduce(seg, axis=1)  # fmax, fmin skip the NaN
        axis = np.argmax(np.where(np.isnan(extent), -1.0, extent), axis=1)  # (nodes,)
        key = np.take_along_axis(seg, axis[:, None, None], axis=2)[..., 0]
        ids = np.take_along_axis(ids.reshape(nodes, size), np.argpartition(key, size // 2 - 1, axis=1), axis=1).ravel()
        nodes *= 2
    ids = np.take_along_axis(ids.reshape(-1, LEAF), np.argsort(ids.reshape(-1, LEAF) < 0, axis=1, kind="stable"), axis=1).ravel()
    return ids[ids >= 0]


@njit(cache=True, error_model="numpy", inline="always")
def _closest_on_triangle(x0, x1, x2, a0, a1, a2, b0, b1, b2, c0, c1, c2):
    """(p0, p1, p2, feature): Ericson's region test (Real-Time Collision Detection, 5.1.5) for one
    point and one triangle abc, as :func:`_closest_on_triangles`; feature 0 for the
    face, 1 2 3 for the vertices a b c, 4 5 6 for the edges ab bc ca."""
    ab0, ab1, ab2 = b0 - a0, b1 - a1, b2 - a2
    ac0, ac1, ac2 = c0 - a0, c1 - a1, c2 - a2
    d1 = ab0 * (x0 - a0) + ab1 * (x1 - a1) + ab2 * (x2 - a2)
    d2 = ac0 * (x0 - a0) + ac1 * (x1 - a1) + ac2 * (x2 - a2)
    if d1 <= 0.0 and d2 <= 0.0:
        return a0, a1, a2, 1
    d3 = ab0 * (x0 - b0) + ab1 * (x1 - b1) + ab2 * (x2 - b2)
    d4 = ac0 * (x0 - b0) + ac1 * (x1 - b1) + ac2 * (x2 - b2)
    if d3 >= 0.0 and d4 <= d3:
        return b0, b1, b2, 2
    d5 = ab0 * (x0 - c0) + ab1 * (x1 - c1) + ab2 * (x2 - c2)
    d6 = ac0 * (x0 - c0) + ac1 * (x1 - c1) + ac2 * (x2 - c2)
    if d6 >= 0.0 and d5 <= d6:
        return c0, c1, c2, 3
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return a0 + t * ab0, a1 + t * ab1, a2 + t * ab2, 4
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return a0 + t * ac0, a1 + t * ac1, a2 + t * ac2, 6
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 >= d3 and d5 >= d6:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return b0 + t * (c0 - b0), b1 + t * (c1 - b1), b2 + t * (c2 - b2), 5
    total = va + vb + vc
    v, w = vb / total, vc / total
    return a0 + v * ab0 + w * ac0, a1 + v * ab1 + w * ac1, a2 + v * ab2 + w * ac2, 0


@njit(cache=True, error_model="numpy", inline="always")
def _box_distance2(lo, hi, k, x0, x1, x2):
    """Squared distance from x to the box k (0 inside it, inf for an empty box)."""
    s = 0.0
    d = max(lo[k, 0] - x0, x0 - hi[k, 0], 0.0)
    s += d * d
    d = max(lo[k, 1] - x1, x1 - hi[k, 1], 0.0)
    s += d * d
    d = max(lo[k, 2] - x2, x2 - hi[k, 2], 0.0)
    s += d * d
    return s


@parallel_kernel
def _nearest(x, points, triangles, lo, hi, depth, out_p, out_t, out_f, out_d):
    """For each point x[i]: the nearest point out_p[i] of the triangles (sorted in leaf order),
    its triangle out_t[i] (index in the sorted order), its feature out_f[i] (see
    :func:`_closest_on_triangle`) and the distance out_d[i].  Among equally near triangles the
    lowest sorted index wins; a box is skipped only when it is farther than the best distance by a
    relative 1e-12, so that rounding never skips the nearest triangle."""
    m = triangles.shape[0]
    first_leaf = 1 << depth
    for i in prange(x.shape[0]):
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        stack = np.empty(depth + 2, dtype=np.int64)
        stack_d = np.empty(depth + 2)
        top = 0
        stack[0] = 1
        stack_d[0] = _box_distance2(lo, hi, 1, x0, x1, x2)
        best = np.inf
        bt = -1
        bf = 0
        p0 = p1 = p2 = 0.0
        while top >= 0:
            node = stack[top]
            dn = stack_d[top]
            top -= 1
            if dn > best * (1.0 + 1e-12):
                continue
            if node >= first_leaf:
                start = (node - first_leaf) * LEAF
                for t in range(start, min(start + LEAF, m)):
                    ia, ib, ic = triangles[t, 0], triangles[t, 1], triangles[t, 2]
                    q0, q1, q2, f = _closest_on_triangle(x0, x1, x2, points[ia, 0], points[ia, 1], points[ia, 2],
                                                         points[ib, 0], points[ib, 1], points[ib, 2],
                                                         points[ic, 0], points[ic, 1], points[ic, 2])
                    e0, e1, e2 = x0 - q0, x1 - q1, x2 - q2
                    d = e0 * e0 + e1 * e1 + e2 * e2
                    if d < best or (d == best and t < bt):
                        best, bt, bf = d, t, f
                        p0, p1, p2 = q0, q1, q2
                continue
            left, right = 2 * node, 2 * node + 1
            dl = _box_distance2(lo, hi, left, x0, x1, x2)
            dr = _box_distance2(lo, hi, right, x0, x1, x2)
            if dl <= dr:  # push the farther first: the nearer is taken next
                near, far, dnear, dfar = left, right, dl, dr
            else:
                near, far, dnear, dfar = right, left, dr, dl
            if dfar <= best * (1.0 + 1e-12):
                top += 1
                stack[top] = far
                stack_d[top] = dfar
            if dnear <= best * (1.0 + 1e-12):
                top += 1
                stack[top] = near
                stack_d[top] = dnear
        out_p[i, 0], out_p[i, 1], out_p[i, 2] = p0, p1, p2
        out_t[i] = bt
        out_f[i] = bf
        e0, e1, e2 = x0 - p0, x1 - p1, x2 - p2
        out_d[i] = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


@parallel_kernel
def _signs(x, p, t, f, face_n, edge_n, vertex_n, triangles, out):
    """out[i] = +1 or -1, the sign of (x - p) . N with N the angle-weighted pseudo-normal of the
    feature f of triangle t (0 face, 1-3 vertices, 4-6 edges); +1 where x = p or the product is 0."""
    for i in prange(x.shape[0]):
        k = t[i]
        fi = f[i]
        if fi == 0:
            n0, n1, n2 = face_n[k, 0], face_n[k, 1], face_n[k, 2]
        elif fi <= 3:
            v = triangles[k, fi - 1]
            n0, n1, n2 = vertex_n[v, 0], vertex_n[v, 1], vertex_n[v, 2]
        else:
            n0, n1, n2 = edge_n[k, fi - 4, 0], edge_n[k, fi - 4, 1], edge_n[k, fi - 4, 2]
        s = (x[i, 0] - p[i, 0]) * n0 + (x[i, 1] - p[i, 1]) * n1 + (x[i, 2] - p[i, 2]) * n2
        out[i] = -1.0 if s < 0.0 else 1.0


class TriangleTree:
    """The bounding-volume hierarchy of a triangle mesh (see the module), built once.

    ``points`` (N, 3) and ``triangles`` (M, 3) as in :class:`cutfem.geometry.surface.SurfaceMesh`; for
    :meth:`signed_distance` the mesh must be closed, manifold and oriented outward, with
    ``edge_triangles`` (E, 2) and ``triangle_edges`` (M, 3) its edge tables (local edge k of a
    triangle runs from its vertex k to vertex k + 1)."""

    def __init__(self, points, triangles, edge_triangles=None, triangle_edges=None):
        self.points = np.ascontiguousarray(points, dtype=float)
        triangles = np.asarray(triangles, dtype=np.int64)
        corners = self.points[triangles]  # (M, 3, 3)
        m = len(triangles)
        self.depth = max(0, int(np.ceil(np.log2(-(-m // LEAF)))))
        n_leaves = 1 << self.depth
        self.order = _median_split_order(corners.mean(axis=1), n_leaves * LEAF)
        self.triangles = np.ascontiguousarray(triangles[self.order])
        sorted_corners = corners[self.order]
        tlo, thi = sorted_corners.min(axis=1), sorted_corners.max(axis=1)
        pad = n_leaves * LEAF - m
        tlo = np.concatenate([tlo, np.full((pad, 3), np.inf)]).reshape(n_leaves, LEAF, 3).min(axis=1)
        thi = np.concatenate([thi, np.full((pad, 3), -np.inf)]).reshape(n_leaves, LEAF, 3).max(axis=1)
        lo, hi = np.empty((2 * n_leaves, 3)), np.empty((2 * n_leaves, 3))
        lo[n_leaves:], hi[n_leaves:] = tlo, thi
        level = n_leaves
        while level > 1:  # parents of the nodes level..2 level - 1 are level/2..level - 1
            half = level // 2
            lo[half:level] = np.minimum(lo[level:2 * level:2], lo[level + 1:2 * level:2])
            hi[half:level] = np.maximum(hi[level:2 * level:2], hi[level + 1:2 * level:2])
            level = half
        lo[0], hi[0] = np.inf, -np.inf
        self.lo, self.hi = lo, hi
        self._normals = None
        if edge_triangles is not None:
            self._normals = self._pseudo_normals(triangles, np.asarray(edge_triangles), np.asarray(triangle_edges))

    def _pseudo_normals(self, triangles, edge_triangles, triangle_edges):
        """(face (M, 3), edge (M, 3, 3), vertex (N, 3)) pseudo-normals in the sorted triangle order:
        unit face normals, on each local edge the sum of its two triangles' unit normals, at each
        vertex the sum of its triangles' unit normals times their angles there."""
        pts = self.points
        corners = pts[triangles]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        face = cross / np.linalg.norm(cross, axis=1)[:, None]
        edge = face[edge_triangles[triangle_edges, 0]] + face[edge_triangles[triangle_edges, 1]]  # (M, 3, 3)
        vertex = np.zeros_like(pts)
        for k in range(3):
            u = corners[:, (k + 1) % 3] - corners[:, k]
            w = corners[:, (k + 2) % 3] - corners[:, k]
            angle = np.arctan2(np.linalg.norm(np.cross(u, w), axis=1), np.einsum("ij,ij->i", u, w))
            for axis in range(3):
                vertex[:, axis] += np.bincount(triangles[:, k], weights=angle * face[:, axis], minlength=len(pts))
        return (np.ascontiguousarray(face[self.order]), np.ascontiguousarray(edge[self.order]),
                np.ascontiguousarray(vertex))

    def _query(self, x):
        x = np.ascontiguousarray(x, dtype=float)
        n = len(x)
        p, t, f, d = np.empty((n, 3)), np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64), np.empty(n)
        if n:
            _nearest(x, self.points, self.triangles, self.lo, self.hi, self.depth, p, t, f, d)
        return x, p, t, f, d

    def nearest(self, x):
        """``(p (n, 3), triangle (n,), distance (n,))``: the nearest points of the triangles to x
        (n, 3), the index of their triangle in the caller's numbering, and |x - p|."""
        _, p, t, _, d = self._query(x)
        return p, self.order[t], d

    def signed_distance(self, x):
        """The distance from x (n, 3) to the mesh, negative inside (pseudo-normal sign), and the
        nearest points ``(value (n,), p (n, 3))``."""
        x, p, t, f, d = self._query(x)
        sign = np.empty(len(x))
        if len(x):
            face, edge, vertex = self._normals
            _signs(x, p, t, f, face, edge, vertex, self.triangles, sign)
        return sign * d, p


def _closest_on_triangles(x: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The point of triangle abc nearest to x, row by row (all (..., 3)).

    Ericson's region test (Real-Time Collision Detection, 5.1.5): with ab = b - a, ac = c - a and
    the dot products d1 = ab.(x - a), d2 = ac.(x - a), d3 = ab.(x - b), d4 = ac.(x - b),
    d5 = ab.(x - c), d6 = ac.(x - c), the Voronoi region of x among the three vertices, the three
    edges and the face is decided by signs, and the point is a vertex, a + t ab, a + t ac,
    b + t (c - b) with t in [0, 1], or a + v ab + w ac with v, w >= 0, v + w <= 1.  The result lies
    on the triangle to rounding of its corners' coordinates, whatever |x| is (no squares of x).  The
    vectorized form of the region test that :func:`_closest_on_triangle` compiles (numpy, for any
    shape of rows); the tests' reference."""
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
