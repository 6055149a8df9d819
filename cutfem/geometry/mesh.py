"""Background tetrahedral meshes: structured boxes, unstructured meshes through pytetwild, topology, I/O.

A :class:`TetMesh` holds ``points`` (N, 3) and positively oriented ``tets`` (M, 4) that cover
their domain once (checked on construction: no fold, no overlap).  Its topology
(unique faces with their one or two tets, edges, boundary) is computed on demand, vectorized, by
sorting integer keys.  A :class:`StructuredBox` is a tetrahedral mesh of an axis-aligned box made
of cubes (cuboids), each split into the six Kuhn tetrahedra that share the main diagonal; the split
is the same in every cube, so the mesh is conforming.  A structured box never needs to store its
whole point or tet arrays: the cut (:mod:`cutfem.geometry.cut`) asks it only for the cells near the
surface.  ``points``/``tets`` are built lazily if a user wants the whole mesh.  Its edges and faces
have an arithmetic numbering (lowest node and lattice direction: :data:`KUHN_EDGE_CODES`,
:func:`kuhn_face_keys`) in the order of their sorted node ids, which the cut uses instead of sorting.

Mesh size: the global value ``h = N**(-1/3)`` (N = number of background nodes), as in docs/math.md §2.
"""

from __future__ import annotations

import math
import os
import tempfile
from fractions import Fraction
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np

from .numbering import TET_EDGES, TET_FACES, index_dtype
from . import mesh_kernels

__all__ = [
    "TetMesh",
    "StructuredBox",
    "COINCIDENT_TOLERANCE",
    "SPACING_TOLERANCE",
    "close_pairs",
    "structured_box",
    "unstructured_box",
    "unstructured_around",
    "read_mesh",
    "write_mesh",
    "barycentric_gradients",
    "cross",
    "triangle_areas",
    "dense_unique",
    "stable_argsort",
    "sorted_row_keys",
    "tet_face_keys",
    "KUHN_EDGE_CODES",
    "kuhn_face_keys",
    "kuhn_face_pairs",
    "kuhn_neighbour_offsets",
    "pair_up",
    "unique_keys",
]

# The six Kuhn tetrahedra of the unit cube: each follows a monotone path 000 -> 111 along the
# axes in one of the 3! orders.  Corner c of the cube has offset ((c>>0)&1, (c>>1)&1, (c>>2)&1).
_PERMS = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]


def _kuhn_local_tets() -> np.ndarray:
    tets = []
    corner = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], float)
    for perm in _PERMS:
        path = [0]
        code = 0
        for axis in perm:
            code |= 1 << axis
            path.append(code)
        a, b, c, d = corner[path]
        if np.linalg.det(np.array([b - a, c - a, d - a])) < 0:
            path[2], path[3] = path[3], path[2]
        tets.append(path)
    return np.array(tets, dtype=np.int64)


KUHN_TETS = _kuhn_local_tets()  # (6, 4) local cube-corner indices, positively oriented
CUBE_CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)


def _kuhn_reference_gradients() -> np.ndarray:
    """(6, 4, 3) gradients of the barycentric coordinates of the six Kuhn tets of the unit cube.

    Kuhn tet l has the vertices CUBE_CORNERS[KUHN_TETS[l]]; its edge matrix has entries 0 and 1
    and determinant 1 (it is positively oriented), so the gradients (rows of its inverse, and minus
    their sum) have entries -1, 0, 1 and are exact in floating point."""
    grads = np.empty((6, 4, 3))
    for l, tet in enumerate(KUHN_TETS):
        x = CUBE_CORNERS[tet].astype(float)
        inv = np.rint(np.linalg.inv((x[1:] - x[0]).T))
        grads[l, 1:] = inv
        grads[l, 0] = -inv.sum(axis=0)
    return grads


KUHN_GRADIENTS = _kuhn_reference_gradients()

KUHN_CORNER_COUNTS = ((np.arange(256)[:, None] >> np.arange(8)) & 1)[:, KUHN_TETS].sum(axis=2).astype(np.int8)
"""(256, 6) how many nodes of Kuhn tet l are among the cube corners of a set (bit c for corner c)."""


# Lattice numbering of the edges and faces of a structured box.  The nodes of a Kuhn tet form a
# chain for the componentwise order of their cube corners (a monotone path 000 -> 111), so an edge
# of the lattice is {v, v + e_S} and a face {v, v + e_A, v + e_A + e_B}: v its lowest node, S, A, B
# nonempty sets of axes (A and B disjoint), e_S the sum of their unit steps.  With the code
# c(S) = sum of 2**axis over S (1..7), the node above v along S has the id v + o(c(S)),
# o(c) = (c & 1) + (nx + 1) ((c >> 1) & 1) + (nx + 1)(ny + 1) (c >> 2), which increases with c
# (nx, ny >= 1).  So (v, c(S)) numbers the edges, (v, c(A), c(A u B)) the faces, and ordering them
# by these integers orders them by their sorted node ids: no sort of node triples is needed.
KUHN_EDGE_CODES = (KUHN_TETS[:, :, None] ^ KUHN_TETS[:, None, :]).astype(np.int8)
"""(6, 4, 4) c(S) of the edge between local nodes i and j of Kuhn tet l (0 on the diagonal)."""

# the 12 face types (c(A), c(A u B)), in increasing order
_FACE_TYPES = sorted((a, a | b) for a in range(1, 8) for b in range(1, 8) if a & b == 0)


def _kuhn_face_tables():
    """(6, 4) local node of the lowest corner of face k (opposite to node k) of Kuhn tet l, and
    (6, 4) the rank of the face's type (c(A), c(A u B)) in :data:`_FACE_TYPES`."""
    low = np.zeros((6, 4), dtype=np.int8)
    kind = np.zeros((6, 4), dtype=np.int8)
    for l, tet in enumerate(KUHN_TETS):
        for k, face in enumerate(TET_FACES):
            order = np.argsort(tet[face])
            c0, c1, c2 = tet[face][order]
            low[l, k] = face[order[0]]
            kind[l, k] = _FACE_TYPES.index((c1 ^ c0, c2 ^ c0))
    return low, kind


_KUHN_FACE_LOW, _KUHN_FACE_TYPE = _kuhn_face_tables()


@lru_cache(maxsize=1)
def kuhn_neighbour_offsets() -> np.ndarray:
    """(13, 3) the lattice vectors q - p between two nodes p != q of one Kuhn tet or of two Kuhn tets
    sharing a face, oriented with (dz, dy, dx) lexicographically positive (q after p in the node
    numbering of a box), in that order: the 7 edge directions of the Kuhn lattice and the 6 vectors
    between the opposite vertices of face-adjacent tets.  Enumerated from the tets of the 27 cells
    around the cell at the origin and each tet of that cell (every pair of face-adjacent tets is one
    of those up to translation)."""
    cells = np.array([(x, y, z) for z in (-1, 0, 1) for y in (-1, 0, 1) for x in (-1, 0, 1)])
    tets = (cells[:, None, None, :] + CUBE_CORNERS[KUHN_TETS][None]).reshape(-1, 4, 3)
    as_sets = [frozenset(map(tuple, t)) for t in tets]
    found = set()
    for a in as_sets[13 * 6 : 14 * 6]:  # the six tets of cell (0, 0, 0)
        for b in as_sets:
            if len(a & b) >= 3:  # the same tet or a shared face
                for p in a | b:
                    for q in a | b:
                        d = tuple(int(v) for v in np.subtract(q, p))
                        if d[::-1] > (0, 0, 0):
                            found.add(d)
    return np.array(sorted(found, key=lambda d: d[::-1]), dtype=np.int64)


def kuhn_face_keys(tets: np.ndarray, kuhn: np.ndarray) -> np.ndarray:
    """Keys of the faces of tets of a structured box: ``12 v + type`` (4m,), with v the node
    number (in ``tets``) of the face's lowest lattice node and type in 0..11 its (c(A), c(A u B))
    rank (see :data:`KUHN_EDGE_CODES`).  Row 4t + k is the face opposite to local vertex k of tet t.

    ``tets`` (m, 4) node numbers of Kuhn tets in their :data:`KUHN_TETS` vertex order (any node
    numbering of the box's nodes), ``kuhn`` (m,) their Kuhn type (background tet id % 6).  Equal
    faces have equal keys, and when the node numbers increase with the background ids the keys
    increase with the sorted node triples of :func:`tet_face_keys`: grouping them gives the same
    faces in the same order, with keys below 12 n (n nodes) instead of three columns.
    """

    tets = np.ascontiguousarray(tets)
    out = np.empty(4 * len(tets), dtype=np.int64)
    mesh_kernels.kuhn_face_keys(tets, np.ascontiguousarray(kuhn).reshape(-1), _KUHN_FACE_LOW, _KUHN_FACE_TYPE, out)
    return out


def kuhn_face_pairs(tets: np.ndarray, kuhn: np.ndarray, n_nodes: int):
    """The faces shared by two of the Kuhn tets ``tets`` (m, 4) (node numbers below ``n_nodes``,
    types ``kuhn``): ``(pairs (F, 2), opposite (F, 2) int8)`` as :func:`cutfem.geometry.markers.interior_facets`
    returns them, the keys of :func:`kuhn_face_keys` grouped without making them
    (:func:`cutfem.geometry.mesh_kernels.kuhn_face_pairs`)."""

    return mesh_kernels.kuhn_face_pairs(tets, np.asarray(kuhn).reshape(-1), _KUHN_FACE_LOW, _KUHN_FACE_TYPE, 12 * int(n_nodes))


def sorted_row_keys(rows: np.ndarray, n: int) -> np.ndarray:
    """Encode each row (a, b) of two non-negative integers below ``n`` as one int64, independent of
    the order of the two entries: ``min(a, b) * n + max(a, b)``, computed column-wise.

    ``rows`` (m, 2).  Fits in int64 for n below 3.0e9 (n**2 < 2**63); raises OverflowError above.
    Triples (faces) are not packed into one integer: :func:`tet_face_keys` keeps their three sorted
    columns, so that their size is not capped (n**3 < 2**63 would stop at n = 2**21).
    """
    rows = np.asarray(rows, dtype=np.int64)
    if rows.ndim != 2 or rows.shape[1] != 2:
        raise ValueError(f"rows must have shape (m, 2), got {rows.shape}; faces use tet_face_keys")
    if float(n) ** 2 >= 2.0**63:
        raise OverflowError(f"cannot encode pairs of indices below {n} in int64")
    a, b = np.ascontiguousarray(rows[:, 0]), np.ascontiguousarray(rows[:, 1])
    return np.minimum(a, b) * n + np.maximum(a, b)


def tet_face_keys(tets: np.ndarray, n: int) -> tuple:
    """Keys of the faces of tets (m, 4) with node ids below ``n``: three (4m,) columns
    ``(lo, mid, hi)``, the sorted node ids of each face.  The face opposite to local vertex k of
    tet t is row 4t + k; equal faces have equal rows.

    The columns are int32 when n <= 2**31 (int64 otherwise); :func:`pair_up` and
    :func:`stable_argsort` sort such column tuples lexicographically, packing the 3 * ceil(log2 n)
    bits of a row into as few radix passes as the key count allows, so there is no cap on n.
    """
    tets = np.asarray(tets, dtype=np.int64)
    dtype = index_dtype(n - 1)
    m = len(tets)
    cols = [np.empty((m, 4), dtype=dtype) for _ in range(3)]
    for k, face in enumerate(TET_FACES):  # the four local faces, each over all tets at once
        a, b, c = (np.ascontiguousarray(tets[:, j]) for j in face)
        lo = np.minimum(np.minimum(a, b), c)
        hi = np.maximum(np.maximum(a, b), c)
        cols[0][:, k] = lo
        cols[1][:, k] = a + b + c - lo - hi
        cols[2][:, k] = hi
    return tuple(col.reshape(-1) for col in cols)


def _as_columns(keys) -> list:
    """A key array or a tuple of key columns (most significant first) as a list of 1-d arrays of one length."""
    cols = [np.asarray(c).reshape(-1) for c in (keys if isinstance(keys, (tuple, list)) else (keys,))]
    if len({c.size for c in cols}) > 1:
        raise ValueError(f"key columns must have one length, got {[c.size for c in cols]}")
    return cols


def stable_argsort(keys) -> np.ndarray:
    """The stable sorting order of integer keys, by compiled radix passes over packed keys.

    ``keys``: a 1-d integer array, or a tuple of 1-d integer arrays of one length (columns, the most
    significant first), sorted lexicographically: the order of ``np.lexsort(keys[::-1])``.

    A row is the bit string of its columns, each shifted to start at 0 and given
    ``w_j = bit_length(max_j - min_j)`` bits, so a row has B = sum w_j bits.  These are cut into
    words of up to 63 bits, sorted word by word from the least significant one, each by the stable
    LSD radix sort :func:`cutfem.geometry.mesh_kernels.radix_argsort` (counting sorts of 8-bit digits), so the
    whole sort is stable and takes at most ceil(B / 8) linear passes, whatever the number or widths
    of the columns.  Same result as the stable argsort for every input; unsigned 64-bit and
    non-integer keys fall back to it.  numpy's sorts ran at about 60 ns a key on the 2-core machine
    (no SIMD sort dispatched there), and the packed keys needed one sort per 63 - log2(n) bits:
    1.77 million random keys of 37 bits took 109-134 ms that way and 87-94 ms by radix passes, 60
    bits 302 against 110 ms, and 3.5 million face-like keys of three 19-bit columns 655 against
    243 ms.
    """

    cols = _as_columns(keys)
    n = cols[0].size
    if n < 2 or any(c.dtype.kind not in "iu" or c.dtype == np.uint64 for c in cols):
        return np.lexsort(cols[::-1]) if len(cols) > 1 else np.argsort(cols[0], kind="stable")
    # (column, its offset (subtracted), its width, its first bit in the row), least significant first
    layout, first_bit = [], 0
    for col in reversed(cols):
        lo, hi = int(col.min()), int(col.max())
        offset = lo if lo < 0 else 0
        width = max(hi - offset, 1).bit_length()
        layout.append((col, offset, width, first_bit))
        first_bit += width
    total_bits = first_bit
    order = None
    for start in range(0, total_bits, 63):
        stop = min(start + 63, total_bits)
        d = None
        for col, offset, width, at in layout:
            lo, hi = max(start, at), min(stop, at + width)
            if lo >= hi:
                continue
            part = (col if order is None else col[order]).astype(np.int64, copy=False)
            if offset:
                part = part - offset
            if lo > at:
                part = part >> (lo - at)
            if hi < at + width:
                part = part & ((1 << (hi - lo)) - 1)
            if lo > start:
                part = part << (lo - start)
            d = part if d is None else d | part
        step = np.empty(n, dtype=np.int64)
        mesh_kernels.radix_argsort(np.ascontiguousarray(d, dtype=np.int64), stop - start, step)
        order = step if order is None else order[step]
    return order


def pair_up(keys):
    """Group equal keys by one stable sort (:func:`stable_argsort`).

    ``keys``: a 1-d integer array or a tuple of such columns (a key is then a row).
    Returns ``(order, starts, counts)``: the keys in the order ``order`` are sorted and the run of
    the g-th distinct key is ``order[starts[g] : starts[g] + counts[g]]``.
    """
    cols = _as_columns(keys)
    order = stable_argsort(tuple(cols))
    size = cols[0].size
    new = np.empty(size, bool)
    if size:
        new[0] = True
        sk = cols[0][order]
        np.not_equal(sk[1:], sk[:-1], out=new[1:])  # in place: no key-sized temporary (90 M keys in a face penalty)
        for col in cols[1:]:
            sk = col[order]
            new[1:] |= sk[1:] != sk[:-1]
        del sk
    starts = np.flatnonzero(new)
    counts = np.diff(np.append(starts, size))
    return order, starts, counts


def unique_keys(keys: np.ndarray, return_inverse: bool = False):
    """Sorted distinct values of an integer array (and the inverse map), by one stable sort.

    Same result as ``np.unique(keys, return_inverse=...)`` for 1-d integer arrays, but uses
    :func:`stable_argsort`, which is many times faster on tens of millions of keys; and numpy's own
    (numpy 2.4, a hash table) took 5.4 s for 8 million distinct keys, where a sort takes 0.13 s.
    The one distinct-values routine of the package's paths that grow with the mesh.
    """
    keys = np.asarray(keys).reshape(-1)
    order, starts, counts = pair_up(keys)
    uniq = keys[order[starts]]
    if not return_inverse:
        return uniq
    inverse = np.empty(keys.size, dtype=np.int64)
    inverse[order] = np.repeat(np.arange(uniq.size), counts)
    return uniq, inverse


def dense_unique(ids: np.ndarray, n: int, inverse_dtype=None):
    """Sorted distinct values of integer ids in [0, n) and the inverse map: ``(unique (u,),
    inverse)`` with ``unique[inverse] == ids`` (same shape as ids; of ``inverse_dtype`` when given).
    Costs O(n / 64 + ids.size), no sort, n / 4 bytes of bitmap and counts
    (:func:`cutfem.geometry.mesh_kernels.dense_unique`); meant for ids that are a sizeable part of a known range,
    or a band of a box's nodes."""

    return mesh_kernels.dense_unique(ids, n, inverse_dtype)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of (..., 3) arrays, written out (``np.cross`` costs several times more)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """|T| = |(x_1 - x_0) x (x_2 - x_0)| / 2 of triangles (m, 3) of ``points`` (p, 3), one compiled
    pass (:func:`cutfem.geometry.mesh_kernels.triangle_areas`; numpy's nine gathers and twenty array operations
    took 1.4 s for the 4.5 million triangles of the torus at spacing 0.00625)."""

    return mesh_kernels.triangle_areas(points, triangles)


def barycentric_gradients(vertices: np.ndarray):
    """Gradients of the barycentric coordinates of tetrahedra.

    ``vertices`` (m, 4, 3).  With the edges e_k = x_k - x_0 (k = 1, 2, 3) and
    ``det = e_1 . (e_2 x e_3)``, lambda_k has gradient ``(e_{k+1} x e_{k+2}) / det`` (indices
    1..3 cyclic: the rows of the inverse of the edge matrix by the adjugate) and
    ``grad lambda_0 = -sum_k grad lambda_k``.
    Returns ``(grads (m, 4, 3), volumes (m,))`` with signed volumes ``det/6``.
    """
    v = np.asarray(vertices, dtype=float)
    e1, e2, e3 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], v[:, 3] - v[:, 0]
    grads = np.empty((v.shape[0], 4, 3))
    grads[:, 1] = cross(e2, e3)
    grads[:, 2] = cross(e3, e1)
    grads[:, 3] = cross(e1, e2)
    det = np.einsum("ij,ij->i", e1, grads[:, 1])
    grads[:, 1:] /= det[:, None, None]
    grads[:, 0] = -(grads[:, 1] + grads[:, 2] + grads[:, 3])
    return grads, det / 6.0


def _used_mask(n: int, tets) -> np.ndarray:
    """(n,) bool: which of n points are nodes of the tets."""
    used = np.zeros(n, dtype=bool)
    used[np.asarray(tets).reshape(-1)] = True
    return used


#: Two nodes of the tets closer than COINCIDENT_TOLERANCE times the diagonal of the box of those
#: nodes are one point written twice (see :func:`_check_coincident`).
COINCIDENT_TOLERANCE = 1e-10

# a unit direction with no simple ratio between its components: the points of a lattice aligned
# with the axes (a structured mesh written to a file) have distinct projections on it
_PROJECTION = np.array([0.5390573056, 0.6293836337, 0.5597298126])
_PROJECTION = _PROJECTION / np.linalg.norm(_PROJECTION)


def close_pairs(points, r: float) -> np.ndarray:
    """(k, 2) the pairs ``i < j`` of rows of ``points`` (n, 3) at distance ``|p_i - p_j| <= r``, in
    O(n log n): one sort of the projections ``p . d`` on a fixed unit direction d, then a k-d tree
    (scipy's cKDTree) on the few points whose projection lies within r of a neighbour's (two points
    within r have projections within r, and so do all the projections sorted between them).  d has
    no simple ratio between its components, so the points of a mesh, structured or not, have well
    separated projections and almost none reach the tree.  On a million mesh nodes 40-90 ms,
    against 0.5-0.9 s for the k-d tree of all of them."""
    p = np.asarray(points, dtype=float)
    if len(p) < 2:
        return np.empty((0, 2), dtype=np.int64)
    s = p @ _PROJECTION
    order = np.argsort(s, kind="stable")
    # the projections' rounding: a few units in the last place of |p| (|d| = 1)
    slack = 8.0 * np.finfo(float).eps * float(np.abs(p).max())
    near = np.diff(s[order]) <= float(r) + slack
    if not near.any():
        return np.empty((0, 2), dtype=np.int64)
    from scipy.spatial import cKDTree  # imported only when some points are that close (about 40 ms)

    mark = np.zeros(len(p), dtype=bool)
    mark[:-1] |= near
    mark[1:] |= near
    ids = np.sort(order[mark])
    pairs = cKDTree(p[ids]).query_pairs(float(r), output_type="ndarray").astype(np.int64)
    pairs = ids[pairs]
    pairs.sort(axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _check_coincident(points, used) -> None:
    """Refuse nodes of the tets (``used``, a mask of the points) that lie at one point: closer than
    ``r = COINCIDENT_TOLERANCE * diam`` (1e-10 times the diagonal of the box of the nodes of the
    tets; :func:`close_pairs`).  Their tets do not share the faces there, so the mesh has a crack, a
    P1 field is discontinuous across it and the faces drop out of the face penalties.  A mesher that
    writes a node twice writes equal coordinates or coordinates that differ by its rounding, a few
    units in the last place (1e-16 |x|, so 1e-12 for coordinates of 1e4), far below r; the nodes of
    any usable mesh are far above it (r is 1e-6 of the spacing of a mesh with 1e4 cells a side).  The
    scale is that of the whole mesh, not of its shortest edge: the copies in a crack are not joined by
    an edge, and a collapsed edge is itself such a defect.  Copies further apart than r are two nodes
    (a crack wider than r that the surface crosses is named by the cut: a hole in the background).
    Points that no tet uses may coincide with anything."""
    ids = np.flatnonzero(used)
    if ids.size < 2:
        return
    p = points[ids]
    r = COINCIDENT_TOLERANCE * float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    pairs = close_pairs(p, r)
    if len(pairs):
        a, b = (int(v) for v in ids[pairs[0]])
        involved = np.unique(pairs).size
        raise ValueError(
            f"{involved} nodes coincide with other nodes of the tets (first: nodes {a} and {b} at "
            f"{points[a].tolist()}, {float(np.linalg.norm(points[a] - points[b])):.3g} apart, closer than "
            f"{r:.3g} = {COINCIDENT_TOLERANCE:g} times the mesh's diagonal): the mesh is split there, its tets do not "
            "share those faces; merge the duplicated nodes (one node per point; in gmsh 'Coherence Mesh') and "
            "renumber the tets"
        )


#: A point of the boundary of a tet mesh lies strictly inside a tet when its four barycentric
#: coordinates there exceed this (see :func:`_check_overlap`): far above their round-off (1e-16
#: times the tet's condition), far below any real overlap.
OVERLAP_TOLERANCE = 1e-8


def _face_parities(tets: np.ndarray) -> np.ndarray:
    """(4m,) int8: for each face row 4 t + k (the face opposite to local vertex k of tet t), the
    parity of the permutation that takes the tet's vertex order to (lo, mid, hi, apex), the face's
    sorted nodes followed by its opposite vertex.  For a positively oriented tet, orient(lo, mid,
    hi, apex) > 0 exactly when the parity is even, so two positively oriented tets sharing a face
    lie on opposite sides of it exactly when their parities on it differ.  The parity is the number
    of inversions of the tet's order plus the number of face nodes above the apex, mod 2."""
    cols = [np.ascontiguousarray(tets[:, j]) for j in range(4)]
    inversions = np.zeros(len(tets), dtype=np.int8)
    for i in range(4):
        for j in range(i + 1, 4):
            inversions += cols[i] > cols[j]
    out = np.empty((len(tets), 4), dtype=np.int8)
    for k, face in enumerate(TET_FACES):
        above = inversions.copy()
        for j in face:
            above += cols[j] > cols[k]
        out[:, k] = above & 1
    return out.reshape(-1)


def _check_folded(tets: np.ndarray, face_rows: np.ndarray, flipped) -> None:
    """Refuse positively oriented tets (m, 4) two of which share a face and lie on the same side of
    it (:func:`_face_parities`): they overlap, the mesh is folded there.  A valid mesh has every
    interior face between two tets on opposite sides.  ``flipped`` (m,) bool or None: the tets that
    were inverted in the input (reordered by ``orient=True``), named as the likely culprits."""
    interior = face_rows[:, 1] >= 0
    if not interior.any():
        return
    rows = face_rows[interior]
    parity = _face_parities(tets)
    bad = np.flatnonzero(parity[rows[:, 0]] == parity[rows[:, 1]])
    if not bad.size:
        return
    pairs = rows[bad] // 4
    folded = unique_keys(pairs.reshape(-1))
    pair_text = ", ".join(f"({a}, {b})" for a, b in pairs[:5].tolist())
    text = f"{bad.size} interior faces have their two tets on the same side (first tet pairs: {pair_text}; {folded.size} tets in all)"
    if flipped is not None and np.any(flipped[folded]):
        inverted = folded[flipped[folded]]
        text += (f"; {inverted.size} of them are inverted (negative volume) in the input, first tets "
                 f"{inverted[:5].tolist()}, and reordering them (orient=True) cannot make the mesh consistent")
    raise ValueError(
        f"the mesh is tangled: {text}. Such tets overlap their neighbours (a node moved through the opposite face of "
        "its tets), so volumes and integrals count the overlap twice; untangle the mesh (move the nodes back or "
        "re-mesh the region)"
    )


def _check_wound(points: np.ndarray, tets: np.ndarray, boundary: np.ndarray) -> None:
    """Refuse an interior node (one on no boundary face; ``boundary`` its sorted ids) whose tets wind
    around it more than once: the solid angles of its tets at it sum to 4 pi k, k the number of
    times they cover the directions around it (:func:`cutfem.geometry.mesh_kernels.vertex_solid_angles`), 4 pi
    for a mesh that covers its domain once.  With every interior face between tets on opposite
    sides (:func:`_check_folded`) k is a whole number, so the threshold 6 pi is far from round-off.
    Such a star passes the face test and has no boundary near it for :func:`_check_overlap`."""

    total = np.zeros(len(points))
    mesh_kernels.vertex_solid_angles(points, np.ascontiguousarray(tets), total)
    total[boundary] = 0.0
    wound = np.flatnonzero(total > 6.0 * np.pi)
    if not wound.size:
        return
    node = int(wound[0])
    star = np.flatnonzero(np.any(tets == node, axis=1))
    raise ValueError(
        f"the mesh winds around {wound.size} interior nodes more than once (first: node {node} at "
        f"{points[node].tolist()}, whose {star.size} tets {star[:5].tolist()}{', ...' if star.size > 5 else ''} cover "
        f"the directions around it {total[node] / (4 * np.pi):.3g} times: solid angles summing to "
        f"{total[node]:.4g} instead of 4 pi), so the domain is covered more than once there; re-mesh the region"
    )


def _check_overlap(points: np.ndarray, tets: np.ndarray, triangles: np.ndarray) -> None:
    """Refuse a mesh with a point of its boundary strictly inside one of its tets (all barycentric
    coordinates above :data:`OVERLAP_TOLERANCE`).  In a mesh that covers each point of its domain
    once, the boundary faces (``triangles``, (b, 3)) lie on the domain's boundary and meet no tet's
    interior; when two parts overlap (two meshes stacked, or a part wound over another), the
    boundary of one runs through the tets of the other.  The probes are the boundary nodes and the
    boundary faces' centroids, sorted into a uniform grid of cells about the median tet size; one
    compiled pass over the tets tests the probes in the cells their bounding box meets
    (:func:`cutfem.geometry.mesh_kernels.points_inside_tets`).  The interior face check (:func:`_check_folded`)
    sees folds; this sees overlap at a distance."""

    if not len(triangles):
        return
    nodes = unique_keys(triangles.reshape(-1))
    probes = np.concatenate([points[nodes], points[triangles].mean(axis=1)])
    lower = probes.min(axis=0)
    span = probes.max(axis=0) - lower
    # the cell: the median largest bounding-box side of a sample of the tets
    xs = points[tets[:: max(1, len(tets) // 65536)]]
    cell = float(np.median(np.max(xs.max(axis=1) - xs.min(axis=1), axis=1)))
    cell = max(cell, 1e-9 * float(span.max()), np.finfo(float).tiny)
    while True:
        dims = np.floor(span / cell).astype(np.int64) + 1
        if math.prod(int(d) for d in dims) <= max(len(tets) // 2, 1_000_000):  # Python ints: no wrap
            break
        cell *= 2.0
    pc = np.minimum(np.floor((probes - lower) / cell).astype(np.int64), dims - 1)
    pkey = pc[:, 0] + dims[0] * (pc[:, 1] + dims[1] * pc[:, 2])
    cell_probes = np.argsort(pkey, kind="stable")
    cell_start = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    np.cumsum(np.bincount(pkey, minlength=int(np.prod(dims))), out=cell_start[1:])
    # the cell of every point, clipped to [-1, dims] (outside the probes' box on that side)
    node_cells = np.empty(points.shape, dtype=np.int32)
    with np.errstate(invalid="ignore"):  # points no tet uses may be NaN; they are never read
        for a in range(3):
            node_cells[:, a] = np.clip(np.floor((points[:, a] - lower[a]) / cell), -1, dims[a])
    hits = np.empty((64, 2), dtype=np.int64)
    found = mesh_kernels.points_inside_tets(points, np.ascontiguousarray(tets), node_cells, probes, dims, cell_start,
                                       cell_probes, OVERLAP_TOLERANCE, hits)
    if not found:
        return
    hits = hits[: min(found, len(hits))]
    t, q = (int(v) for v in hits[0])
    where = (f"boundary node {int(nodes[q])}" if q < len(nodes)
             else f"the centroid of the boundary face {triangles[q - len(nodes)].tolist()}")
    raise ValueError(
        f"the mesh overlaps itself: {found} (point of its boundary, tet) pairs have the point strictly inside the tet "
        f"(first: {where} at {np.round(probes[q], 12).tolist()} inside tet {t}; overlapping tets "
        f"{unique_keys(hits[:, 0])[:5].tolist()}), so parts of the domain are covered twice and volumes and integrals "
        "count them twice (two meshes stacked, or a part wound over another). Give one conforming mesh of the domain: "
        "remove the duplicated part, or merge the parts with a mesher"
    )


class TetMesh:
    """A conforming tetrahedral mesh.

    Parameters
    ----------
    points : (N, 3) float
    tets : (M, 4) int, vertex indices of each tetrahedron
    orient : if True, tets with negative volume are reordered (two vertices swapped); if False
        (default), negative volumes are an error.
    check : validate finiteness, index range, non-degeneracy (volume > 1e-12 * mean |volume|),
        that no two nodes of the tets coincide (closer than :data:`COINCIDENT_TOLERANCE` = 1e-10
        times the diagonal of their box: a crack, see :func:`_check_coincident`), and that the
        tets cover each point of their domain once: no face in more than two tets, the two tets
        of every interior face on opposite sides of it (:func:`_check_folded`; reordering inverted
        tets with ``orient`` is accepted only where that makes them agree with their neighbours),
        no interior node wound round more than once (:func:`_check_wound`), and no boundary point
        strictly inside a tet (:func:`_check_overlap`).  At least one tet.  Not seen: tets wound
        twice around an edge whose two ends are both on the boundary when, by symmetry, every
        boundary point of one turn lies on a face of the other (a perturbed ring is seen by the
        overlap test; an edge test would need a sort of the 6 M edges).

    Cached topology: ``faces`` (F, 3) sorted node triples, ``face_tets`` (F, 2) with -1 for the
    missing neighbour of a boundary face (the first entry is always a tet), ``tet_faces`` (M, 4)
    (face opposite to local vertex k), ``edges`` (E, 2), ``boundary_faces`` (indices into faces),
    ``boundary_nodes``, ``interior_faces``.  Mesh size ``h = N**(-1/3)``, N the nodes of the tets.
    """

    def __init__(self, points, tets, *, orient: bool = False, check: bool = True):
        points = np.ascontiguousarray(points, dtype=float)
        tets = np.ascontiguousarray(tets, dtype=np.int64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {points.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ValueError(f"tets must have shape (M, 4), got {tets.shape}")
        if len(tets) == 0:
            raise ValueError(
                f"a TetMesh needs at least one tet; got 0 tets (on {len(points)} points): give the tets' vertex indices "
                "(M, 4), or read the mesh file with read_mesh"
            )
        if check:
            if tets.size and (tets.min() < 0 or tets.max() >= len(points)):
                raise ValueError(f"tet vertex indices must lie in [0, {len(points)}); got range [{tets.min()}, {tets.max()}]")
            used = self.__dict__["_used"] = _used_mask(len(points), tets)  # the cached _used
            if not np.all(np.isfinite(points)):  # only the nodes of the tets count (stray points of a file do not)
                bad = np.flatnonzero(used & ~np.all(np.isfinite(points), axis=1))
                if bad.size:
                    raise ValueError(f"{bad.size} nodes of the tets are NaN or infinite (first: point {bad[0]}); fix the input mesh")
            vol = self._signed_volumes(points, tets)
            scale = np.mean(np.abs(vol)) if vol.size else 0.0
            degenerate = np.abs(vol) <= 1e-12 * scale
            if np.any(degenerate):
                k = np.flatnonzero(degenerate)
                raise ValueError(
                    f"{k.size} degenerate (zero-volume) tetrahedra, first: tet {k[0]} with vertices {tets[k[0]].tolist()}; "
                    "remove them or re-mesh"
                )
            _check_coincident(points, used)
            inverted = vol < 0
            if np.any(inverted):
                tets = tets.copy()
                tets[inverted, 2], tets[inverted, 3] = tets[inverted, 3], tets[inverted, 2].copy()
        self.points = points
        self.tets = tets
        if check:
            # a valid mesh covers each point of its domain once: no fold, no overlap (the faces
            # found here are kept for the topology).  Folds first: a tangled mesh is named as such
            # even without orient, where reordering its inverted tets would not help
            face_rows = self._face_topology[3]
            _check_folded(tets, face_rows, inverted if np.any(inverted) else None)
            if np.any(inverted) and not orient:
                k = np.flatnonzero(inverted)
                raise ValueError(
                    f"{k.size} inverted (negatively oriented) tetrahedra, first: tet {k[0]}; "
                    "swap two vertices of each, or pass orient=True to reorder them"
                )
            boundary_faces = self._face_topology[0][face_rows[:, 1] < 0]
            _check_wound(points, tets, unique_keys(boundary_faces.reshape(-1)))
            _check_overlap(points, tets, boundary_faces)

    @staticmethod
    def _signed_volumes(points, tets):
        v = points[tets]
        return np.einsum("ij,ij->i", np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), v[:, 3] - v[:, 0]) / 6.0

    def tet_node_counts(self, node_mask) -> np.ndarray:
        """(M,) int8: how many of the four nodes of each tet have ``node_mask`` (N,) true."""
        return np.asarray(node_mask, dtype=bool)[self.tets].sum(axis=1, dtype=np.int8)

    # -- sizes ---------------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @cached_property
    def _used(self) -> np.ndarray:
        """(N,) bool: the points that are nodes of a tet."""
        return _used_mask(len(self.points), self.tets)

    @cached_property
    def n_used_points(self) -> int:
        """The number of nodes of the tets: ``n_points`` less the points that no tet uses."""
        return int(np.count_nonzero(self._used))

    @property
    def h(self) -> float:
        """Global mesh size N**(-1/3), N = the number of nodes of the tets (docs/math.md §2): points
        that no tet uses (stray points of a mesh file) are not nodes of the mesh and do not count."""
        return float(self.n_used_points) ** (-1.0 / 3.0)

    @cached_property
    def volumes(self) -> np.ndarray:
        """(M,) tet volumes (positive)."""
        return self._signed_volumes(self.points, self.tets)

    @cached_property
    def bounds(self):
        """(lower (3,), upper (3,)) bounding box of the nodes of the tets (points no tet uses left out)."""
        if self.n_used_points == self.n_points:
            return self.points.min(axis=0), self.points.max(axis=0)
        return self.points[self._used].min(axis=0), self.points[self._used].max(axis=0)

    # -- topology ------------------------------------------------------------------------
    @cached_property
    def _face_topology(self):
        """(faces, face_tets, tet_faces, face_rows): face_rows (F, 2) the rows 4 t + k (face
        opposite to local vertex k of tet t) of each face, -1 for the missing one."""
        m, n = self.n_tets, self.n_points
        keys = tet_face_keys(self.tets, n)
        order, starts, counts = pair_up(keys)
        if np.any(counts > 2):
            many = np.flatnonzero(counts > 2)
            g = many[0]
            tets = (order[starts[g] : starts[g] + counts[g]] // 4).tolist()
            raise ValueError(
                f"{many.size} faces are shared by more than two tets (first: face {[int(c[order[starts[g]]]) for c in keys]} "
                f"of tets {tets}): the mesh is not conforming, tets overlap there (a tet given twice, or two meshes "
                "stacked); give each tet once and one conforming mesh of the domain"
            )
        first = order[starts]
        faces = np.stack([col[first] for col in keys], axis=1).astype(np.int64)
        face_rows = np.full((len(starts), 2), -1, dtype=np.int64)
        face_rows[:, 0] = first
        two = counts == 2
        face_rows[two, 1] = order[starts[two] + 1]
        face_tets = np.where(face_rows >= 0, face_rows // 4, -1)
        face_of_row = np.empty(4 * m, dtype=np.int64)
        face_of_row[order] = np.repeat(np.arange(len(starts)), counts)
        return faces, face_tets, face_of_row.reshape(m, 4), face_rows

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) unique faces as sorted vertex triples."""
        return self._face_topology[0]

    @property
    def face_tets(self) -> np.ndarray:
        """(F, 2) the tets of each face; -1 in the second column for boundary faces."""
        return self._face_topology[1]

    @property
    def tet_faces(self) -> np.ndarray:
        """(M, 4) face index of the face opposite to each local vertex."""
        return self._face_topology[2]

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """Indices (into ``faces``) of faces with a single tet."""
        return np.flatnonzero(self.face_tets[:, 1] < 0)

    @cached_property
    def interior_faces(self) -> np.ndarray:
        """Indices (into ``faces``) of faces shared by two tets."""
        return np.flatnonzero(self.face_tets[:, 1] >= 0)

    @cached_property
    def boundary_nodes(self) -> np.ndarray:
        """Sorted indices of the nodes on boundary faces."""
        return unique_keys(self.faces[self.boundary_faces])

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) unique edges as sorted vertex pairs."""
        n = self.n_points
        keys = np.concatenate([sorted_row_keys(self.tets[:, e], n) for e in TET_EDGES])
        keys = unique_keys(keys)
        return np.stack([keys // n, keys % n], axis=1)

    @property
    def euler_characteristic(self) -> int:
        """V - E + F - T; equals 1 for a mesh of a ball (e.g. a box)."""
        return self.n_points - len(self.edges) + len(self.faces) - self.n_tets

    def to_pyvista(self):
        """The mesh as a ``pyvista.UnstructuredGrid``."""
        import pyvista as pv

        return pv.UnstructuredGrid({pv.CellType.TETRA: self.tets}, self.points)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n_points={self.n_points}, n_tets={self.n_tets})"


#: :func:`structured_box` keeps the box when (upper - lower) / spacing is within this relative
#: amount of a whole number, and :class:`StructuredBox` accepts a spacing that differs from
#: (upper - lower) / cells by this relative amount (plus the round-off of the corners): round-off
#: of a spacing written in decimal, never a different mesh.
SPACING_TOLERANCE = 1e-9

#: the largest node or tet id of a structured box: ids are int64
_LARGEST_ID = 2**63 - 1


def _readable_count(n) -> str:
    """An exact (Python) integer for a message: '3,000,000' below a billion, '2.70e+19' above, at
    any size (a float would overflow past 1.8e308 and int64 wraps past 9.2e18)."""
    n = int(n)
    if abs(n) < 10**9:
        return f"{n:,}"
    digits = str(abs(n))
    return f"{'-' if n < 0 else ''}{digits[0]}.{digits[1:3]}e+{len(digits) - 1}"


def _whole_cells(cells) -> tuple:
    """The three cell counts as Python ints (exact, whatever their size)."""
    a = np.asarray(cells)
    if a.dtype.kind == "f":
        return tuple(int(v) for v in np.broadcast_to(a, (3,)))
    return tuple(int(v) for v in np.broadcast_to(a, (3,)).tolist())


def _check_box_size(cells, what: str, fix: str) -> None:
    """Refuse a structured box whose node or tet ids do not fit in int64 (more than 9.2e18 nodes or
    tets) with :class:`cutfem.memory.InsufficientMemoryError`, stating the real counts (exact
    Python integers) and the memory of the band search's node bitmap (a quarter byte a node, the
    least any use of the box needs).  Such a box cannot be numbered, let alone held."""
    n_points = math.prod(c + 1 for c in cells)
    n_tets = 6 * math.prod(cells)
    if max(n_points, n_tets) <= _LARGEST_ID:
        return
    from ..memory import BYTES_PER_BOX_NODE, InsufficientMemoryError, available_memory, format_bytes

    available, source = available_memory()
    need = n_points * int(4 * BYTES_PER_BOX_NODE) // 4  # exact: BYTES_PER_BOX_NODE is a quarter byte
    raise InsufficientMemoryError(
        f"{what} has {_readable_count(n_points)} nodes and {_readable_count(n_tets)} tets: their ids do not fit in "
        f"64-bit integers (at most {_readable_count(_LARGEST_ID)}), and the band search's node bitmap alone needs about "
        f"{_readable_count(need)} bytes of memory, more than the {format_bytes(available)} available ({source}); {fix}"
    )


def _spacing_whose_ids_fit(extent) -> float:
    """The smallest spacing at which a box of the given side lengths has fewer than 2**63 / 6 cells
    (so that its tet ids fit in int64), from logarithms (the product of the sides may overflow)."""
    logs = sum(math.log(float(e)) for e in extent)
    return math.exp((logs + math.log(6.0) - math.log(_LARGEST_ID)) / 3.0)


class StructuredBox(TetMesh):
    """Tetrahedral mesh of the box ``[lower, upper]`` with ``cells = (nx, ny, nz)`` cuboids, six
    Kuhn tets per cuboid (all sharing the cuboid's main diagonal).

    Node (i, j, k) has id ``i + (nx+1) * (j + (ny+1) * k)`` and coordinates
    ``lower + (i, j, k) * spacing``; cell (i, j, k) has id ``i + nx * (j + ny * k)``; tet
    ``6 * cell + l`` is the l-th Kuhn tet of the cell (:data:`KUHN_TETS`).  The whole ``points`` and
    ``tets`` arrays are built only when asked for; :meth:`cell_tets` and :meth:`node_coordinates`
    serve any subset.
    """

    def __init__(self, lower, upper, cells, spacing=None):
        lower = np.asarray(lower, dtype=float).reshape(3)
        upper = np.asarray(upper, dtype=float).reshape(3)
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise ValueError("box corners must be finite")
        if np.any(upper <= lower):
            raise ValueError(f"box must have upper > lower in every axis, got lower={lower}, upper={upper}")
        cells = _whole_cells(cells)
        if min(cells) < 1:
            raise ValueError(f"need at least one cell per axis, got cells={list(cells)}")
        _check_box_size(cells, f"a structured box of {' x '.join(_readable_count(c) for c in cells)} cells",
                        "give fewer cells")
        cells = np.array(cells, dtype=np.int64)
        self.lower, self.upper, self.cells = lower, upper, cells
        # the spacing as requested when known (structured_box), not recomputed from the corners
        implied = (upper - lower) / cells
        if spacing is None:
            self.spacing = implied
        else:
            self.spacing = np.broadcast_to(np.asarray(spacing, float), (3,)).copy()
            # node (i, j, k) is at lower + (i, j, k) * spacing: the last one must be upper (to round-off)
            slack = SPACING_TOLERANCE * np.abs(self.spacing) + 8 * np.finfo(float).eps * np.maximum(np.abs(lower), np.abs(upper)) / cells
            if not (np.all(np.isfinite(self.spacing)) and np.all(np.abs(implied - self.spacing) <= slack)):
                raise ValueError(
                    f"spacing={self.spacing.tolist()} does not match the corners and cells: lower + cells * spacing = "
                    f"{(lower + cells * self.spacing).tolist()}, not upper = {upper.tolist()}. The consistent spacing "
                    f"is (upper - lower) / cells = {implied.tolist()}: pass that, or leave spacing out, or use "
                    "structured_box(lower, upper, spacing=...), which fits the cells to a spacing"
                )
        self.node_shape = cells + 1

    # sizes without building anything
    @property
    def n_points(self) -> int:
        return math.prod(int(n) for n in self.node_shape)  # Python ints: exact at any size

    @property
    def n_cells(self) -> int:
        return math.prod(int(c) for c in self.cells)

    @property
    def n_tets(self) -> int:
        return 6 * self.n_cells

    @property
    def n_used_points(self) -> int:  # type: ignore[override]
        return self.n_points  # every node of the lattice is a corner of a tet

    @property
    def bounds(self):
        return self.lower.copy(), self.upper.copy()

    # ids and coordinates of any subset
    def node_index(self, ids) -> np.ndarray:
        """(k, 3) integer (i, j, k) of node ids."""
        ids = np.asarray(ids, dtype=np.int64)
        nx1, ny1 = self.node_shape[0], self.node_shape[1]
        return np.stack([ids % nx1, (ids // nx1) % ny1, ids // (nx1 * ny1)], axis=-1)

    def node_id(self, ijk) -> np.ndarray:
        ijk = np.asarray(ijk, dtype=np.int64)
        return ijk[..., 0] + self.node_shape[0] * (ijk[..., 1] + self.node_shape[1] * ijk[..., 2])

    def coordinates(self, ijk) -> np.ndarray:
        """Coordinates of integer node indices ``ijk`` (..., 3): ``lower + ijk * spacing``."""
        return self.lower + np.asarray(ijk) * self.spacing

    @cached_property
    def neighbour_id_offsets(self) -> np.ndarray:
        """(13,) increasing node-id differences of :func:`kuhn_neighbour_offsets` on this box: two
        nodes of one tet or of two face-adjacent tets differ in id by one of them."""
        return np.sort(self.node_id(kuhn_neighbour_offsets()))

    def node_coordinates(self, ids) -> np.ndarray:
        """(..., 3) coordinates of node ids (...): :meth:`coordinates` of :meth:`node_index`, in one
        compiled pass (:func:`cutfem.geometry.mesh_kernels.box_node_coordinates`; numpy's integer divisions and
        stacks took 0.55 s for the 5.2 million nodes of the solid torus at spacing 0.01)."""

        ids = np.asarray(ids, dtype=np.int64)
        flat = np.ascontiguousarray(ids.reshape(-1))
        out = np.empty((len(flat), 3))
        mesh_kernels.box_node_coordinates(flat, int(self.node_shape[0]), int(self.node_shape[1]),
                                     np.asarray(self.lower, dtype=float), np.asarray(self.spacing, dtype=float), out)
        return out.reshape(ids.shape + (3,))

    def cell_index(self, cell_ids) -> np.ndarray:
        c = np.asarray(cell_ids, dtype=np.int64)
        nx, ny = self.cells[0], self.cells[1]
        return np.stack([c % nx, (c // nx) % ny, c // (nx * ny)], axis=-1)

    def cell_corner_ids(self, cell_ids) -> np.ndarray:
        """(k, 8) node ids of the cube corners (corner c has offset bits (c&1, c>>1&1, c>>2&1)), in
        one compiled pass (:func:`cutfem.geometry.mesh_kernels.box_cell_corner_ids`; numpy's divisions, stacks
        and sums took 0.14 s for the 4 million band cells at spacing 0.003125)."""

        c = np.ascontiguousarray(np.asarray(cell_ids, dtype=np.int64).reshape(-1))
        out = np.empty((len(c), 8), dtype=np.int64)
        mesh_kernels.box_cell_corner_ids(c, int(self.cells[0]), int(self.cells[1]), int(self.node_shape[0]),
                                    int(self.node_shape[1]), np.ascontiguousarray(self.node_id(CUBE_CORNERS)), out)
        return out

    @property
    def gradient_table(self) -> np.ndarray:
        """(6, 4, 3) the barycentric gradients of the six Kuhn tet types of this box, indexed by
        Kuhn type (tet id % 6).  A point of a cell is ``x = corner + xi * spacing``
        (componentwise), so they are those of the reference Kuhn tets (:data:`KUHN_GRADIENTS`,
        entries -1, 0, 1) divided by the spacing, axis by axis; no vertex coordinates are needed."""
        return KUHN_GRADIENTS / self.spacing

    @property
    def tet_volume(self) -> float:
        """Volume of every tet: the cell volume / 6."""
        return float(np.prod(self.spacing)) / 6.0

    def tet_node_counts(self, node_mask) -> np.ndarray:
        """(6 n_cells,) int8: how many of the four nodes of each tet have ``node_mask`` (N,) true.

        Each cell's eight corners give one byte (bit c for corner c, from eight shifted views of the
        mask on the node grid) and :data:`KUHN_CORNER_COUNTS` the counts of its six tets: no
        (6 n_cells, 4) array of nodes is made (the whole-box node gather took 0.85 s at 4 million tets)."""
        nx, ny, nz = (int(c) for c in self.cells)
        mask = np.asarray(node_mask, dtype=bool).reshape(nz + 1, ny + 1, nx + 1)  # node id i + (nx+1)(j + (ny+1)k)
        bits = np.zeros((nz, ny, nx), dtype=np.uint8)
        for c, (i, j, k) in enumerate(CUBE_CORNERS):
            bits |= mask[k : k + nz, j : j + ny, i : i + nx].view(np.uint8) << np.uint8(c)
        return KUHN_CORNER_COUNTS[bits.reshape(-1)].reshape(-1)  # cell id i + nx(j + ny k): tet 6 cell + l

    def kuhn_tet_nodes(self, tet_ids) -> np.ndarray:
        """(k, 4) node ids of tets ``tet_ids`` (in :data:`KUHN_TETS` order): the lowest corner of each
        cell plus a (6, 4) table of node offsets, in one compiled pass (:func:`cutfem.geometry.mesh_kernels.kuhn_tet_nodes`;
        the numpy passes took 3.9 s, this 0.4 s, for the 17 million tets of the solid torus at spacing 0.0125)."""

        tet_ids = np.ascontiguousarray(tet_ids, dtype=np.int64)
        offsets = np.ascontiguousarray(self.node_id(CUBE_CORNERS)[KUHN_TETS])  # (6, 4)
        out = np.empty((len(tet_ids), 4), dtype=np.int64)
        (cx, cy, _), (nx, ny, _) = (int(c) for c in self.cells), (int(n) for n in self.node_shape)
        mesh_kernels.kuhn_tet_nodes(tet_ids, cx, cy, nx, ny, offsets, out)
        return out

    def cell_tets(self, cell_ids) -> np.ndarray:
        """(6k, 4) node ids of the Kuhn tets of the given cells, tet ``6*c + l`` order."""
        return self.cell_corner_ids(cell_ids)[:, KUHN_TETS].reshape(-1, 4)

    @cached_property
    def points(self) -> np.ndarray:  # type: ignore[override]
        ijk = self.node_index(np.arange(self.n_points))
        return self.coordinates(ijk)

    @cached_property
    def tets(self) -> np.ndarray:  # type: ignore[override]
        return self.cell_tets(np.arange(self.n_cells))

    @cached_property
    def boundary_nodes(self) -> np.ndarray:
        """Node ids on the box boundary, from the six faces of the grid (no visit of the interior)."""
        ids = []
        for axis in range(3):
            a, b = [d for d in range(3) if d != axis]
            ga, gb = np.meshgrid(np.arange(self.node_shape[a]), np.arange(self.node_shape[b]), indexing="ij")
            for side in (0, self.node_shape[axis] - 1):
                ijk = np.empty(ga.shape + (3,), dtype=np.int64)
                ijk[..., axis], ijk[..., a], ijk[..., b] = side, ga, gb
                ids.append(self.node_id(ijk).reshape(-1))
        return unique_keys(np.concatenate(ids))

    def __repr__(self) -> str:
        return (
            f"StructuredBox(lower={self.lower.tolist()}, upper={self.upper.tolist()}, cells={self.cells.tolist()}, "
            f"n_points={self.n_points}, n_tets={self.n_tets})"
        )


def _per_axis(name: str, value, scalar: bool, integral: bool = False) -> np.ndarray:
    """``value`` as 3 numbers (x, y, z): a real array of shape (3,), or with ``scalar`` also one
    number for all axes; ``integral``: whole numbers, returned as int64.  A ValueError naming
    ``name`` for anything else (strings, booleans, 2-D corners, two values)."""
    a = np.asarray(value)
    what = "a number or 3 numbers (x, y, z)" if scalar else "3 numbers (x, y, z)"
    if integral:
        what = what.replace("number", "whole number")
    if a.dtype.kind not in "iuf" or a.shape not in (((), (3,)) if scalar else ((3,),)):
        raise ValueError(f"{name} must be {what}, got {value!r}")
    if integral:
        if not (np.all(np.isfinite(a)) and np.all(a == np.rint(a))):
            raise ValueError(f"{name} must be {what}, got {value!r}")
        if np.any(np.abs(a) >= 2.0**62):  # would wrap in int64: refuse with the exact counts
            exact = _whole_cells(a)
            if min(exact) >= 1:
                _check_box_size(exact, f"a structured box of {' x '.join(_readable_count(c) for c in exact)} cells",
                                "give fewer cells")
            raise ValueError(f"{name} must be {what} of at least 1, got {value!r}")
        return np.broadcast_to(a.astype(np.int64), (3,))
    return np.broadcast_to(a.astype(float), (3,))


def structured_box(lower, upper, spacing=None, cells=None) -> StructuredBox:
    """Structured tetrahedral mesh of the box ``[lower, upper]`` (6 Kuhn tets per cuboid).

    Give either ``cells`` (an int or 3 ints: the spacing is then ``(upper - lower) / cells``) or
    ``spacing`` (a positive finite number or 3 of them).  With ``spacing`` the mesh has exactly that
    spacing (``box.spacing`` is the number given, bit for bit) and a whole number of cells per axis:

    * when ``(upper - lower) / spacing`` is a whole number n (to within 1e-9 relative), the box is
      the one given, with n cells;
    * otherwise the box is *grown* symmetrically about its centre to the next whole number of cells,
      ``n = ceil((upper - lower) / spacing)``, so that it still contains the box asked for (and the
      surface inside it); ``box.lower``/``box.upper`` are the corners used.  It is never shrunk and
      the spacing is never changed to fit the box.

    ``lower`` and ``upper`` are 3 numbers each; ``cells`` whole numbers (2.5 is refused, not
    truncated).  Anything else is refused with a ValueError naming the argument.
    """
    lower = _per_axis("lower", lower, scalar=False)
    upper = _per_axis("upper", upper, scalar=False)
    if (spacing is None) == (cells is None):
        raise ValueError("give exactly one of spacing= or cells=")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))) or np.any(upper <= lower):
        raise ValueError(f"box must have finite corners with upper > lower in every axis, got lower={lower.tolist()}, upper={upper.tolist()}")
    if cells is not None:
        return StructuredBox(lower, upper, _per_axis("cells", cells, scalar=True, integral=True))
    spacing = _per_axis("spacing", spacing, scalar=True)
    if np.any(~np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ValueError(f"spacing must be a positive finite number, got {spacing.tolist()}; give e.g. spacing=0.1")
    with np.errstate(over="ignore"):
        ratio = (upper - lower) / spacing  # inf when the quotient (or the extent) overflows
    huge = not np.all(ratio < 2.0**62)  # then 6 n_x n_y n_z > 2**63: refused below
    if huge:  # count the cells exactly (rationals of the floats) for the message
        exact = tuple(max(math.ceil((Fraction(float(u)) - Fraction(float(l))) / Fraction(float(h))), 1)
                      for l, u, h in zip(lower, upper, spacing))
    else:
        whole = np.rint(ratio)
        fits = (np.abs(ratio - whole) <= SPACING_TOLERANCE * np.maximum(ratio, 1)) & (whole >= 1)
        cells = np.where(fits, whole, np.ceil(ratio)).astype(np.int64)
        exact = tuple(int(c) for c in cells)
    # a box too large to number is refused here, in words about the spacing
    text = f"{spacing[0]:.3g}" if np.all(spacing == spacing[0]) else str(spacing.tolist())
    extent = [Fraction(float(u)) - Fraction(float(l)) for l, u in zip(lower, upper)]
    _check_box_size(exact, f"the structured box [{lower.tolist()}, {upper.tolist()}] at spacing={text}",
                    f"use a coarser spacing: at least {_spacing_whose_ids_fit(extent):.3g} for the ids to fit, and in "
                    "practice a spacing whose cut fits the memory (the cut checks that and names one), or a smaller box")
    if not fits.all():
        centre = 0.5 * (lower + upper)
        grown = ~fits
        lower = np.where(grown, centre - 0.5 * cells * spacing, lower)
        upper = np.where(grown, lower + cells * spacing, upper)
    return StructuredBox(lower, upper, cells, spacing=spacing)


def _box_surface(lower, upper):
    """Closed triangulated surface of a box (8 vertices, 12 outward triangles)."""
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    v = lower + CUBE_CORNERS * (upper - lower)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    tris = []
    for a, b, c, d in quads:
        tris += [[a, b, c], [a, c, d]]
    return v, np.array(tris, dtype=np.int32)


def _tetwild(vertices, faces, edge_length, optimize=True) -> TetMesh:
    import pytetwild

    if not np.isfinite(edge_length) or edge_length <= 0:
        raise ValueError(f"edge_length must be positive, got {edge_length}")
    # fTetWild writes a debug file (__tracked_surface.stl) into the working directory: run it in a
    # scratch directory so that meshing never litters the user's folder
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="cutfem-tetwild-") as scratch:
        os.chdir(scratch)
        try:
            pts, tets = pytetwild.tetrahedralize(
                np.asarray(vertices, float), np.asarray(faces, np.int32), edge_length_abs=float(edge_length), optimize=optimize
            )
        finally:
            os.chdir(cwd)
    used, inv = unique_keys(np.asarray(tets, np.int64), return_inverse=True)
    return TetMesh(np.asarray(pts)[used], inv.reshape(-1, 4), orient=True)


def unstructured_box(lower, upper, edge_length: float, optimize: bool = True) -> TetMesh:
    """Unstructured tetrahedral mesh of the box ``[lower, upper]`` by pytetwild at a target edge length."""
    v, f = _box_surface(lower, upper)
    return _tetwild(v, f, edge_length, optimize)


def unstructured_around(surface, edge_length: float, padding: float = 0.2, optimize: bool = True) -> TetMesh:
    """Unstructured tetrahedral mesh (pytetwild) of the box around a closed surface.

    ``surface`` has ``points`` (N, 3) (a SurfaceMesh or pyvista.PolyData); the box is its bounding
    box grown by ``padding`` times its diagonal on every side, so the surface stays strictly inside.
    """
    p = np.asarray(surface.points, float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    pad = padding * np.linalg.norm(hi - lo)
    return unstructured_box(lo - pad, hi + pad, edge_length, optimize)


def _volume_cell_kind(cell_type: str):
    """'tet' for meshio's tetrahedra of any order (their first four nodes are the corners, in the
    vtk and gmsh orders alike), 'other' for the other volume cells, None for points, lines and faces."""
    name = cell_type.lower()
    if name.startswith("tetra") or name == "vtk_lagrange_tetrahedron":
        return "tet"
    if name.startswith(("hexahedron", "wedge", "pyramid", "polyhedron", "vtk_lagrange_hexahedron", "vtk_lagrange_wedge",
                        "vtk_lagrange_pyramid")):
        return "other"
    return None


def read_mesh(path) -> TetMesh:
    """Read a tetrahedral mesh with meshio (any format meshio reads: .vtu, .vtk, .msh, .mesh, .xdmf, ...).

    The tets are the file's tetra cells, of every block.  Higher-order tets (tetra10, ...) give
    their four corners: the straight-sided tets of the same vertices, the mid-edge nodes being
    points that no tet uses (they count nowhere, e.g. not in ``h``).  Points, lines and surface
    cells (the boundary triangles and physical groups of a gmsh file) are left out.  A file with
    other volume cells (hexahedra, wedges, pyramids) is refused: the tets alone would leave holes
    where those cells are.  So is a file without tets (a surface or 2-D mesh).  Tets written with
    negative volume are reordered, and the mesh is then checked as every :class:`TetMesh` is: a
    tangled mesh (a node moved through a face of its tets) or one that overlaps itself (two meshes
    in one file) is refused, naming the tets.
    """
    import meshio

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        m = meshio.read(path)
    except ModuleNotFoundError as exc:  # formats whose reader needs another package (.xdmf: h5py)
        raise ValueError(f"cannot read mesh file {path}: meshio needs the package {exc.name!r} for this format; install it "
                         f"(pip install {exc.name}) or convert the file to .vtu or .msh") from exc
    except (Exception, SystemExit) as exc:  # meshio raises several types (even SystemExit) for broken files
        raise ValueError(f"cannot read mesh file {path}: {exc}. Use a format meshio reads (.vtu, .vtk, .msh, .mesh, .xdmf)") from exc
    kinds = [(c, _volume_cell_kind(c.type)) for c in m.cells if len(c.data)]
    other = {}
    for c, kind in kinds:
        if kind == "other":
            other[c.type] = other.get(c.type, 0) + len(c.data)
    if other:
        raise ValueError(
            f"{path} holds volume cells other than tetrahedra ({', '.join(f'{n} {t}' for t, n in other.items())}): the "
            "tets alone would leave holes where they are. Mesh the domain with tetrahedra only, or split those cells "
            "into conforming tetrahedra before reading"
        )
    blocks = [np.asarray(c.data)[:, :4] for c, kind in kinds if kind == "tet"]
    if not blocks:
        dim = np.asarray(m.points).shape[1] if np.asarray(m.points).ndim == 2 else 0
        raise ValueError(
            f"{path} holds no tetrahedra (cell types: {sorted({c.type for c in m.cells}) or 'none'}, points with {dim} "
            "coordinates): the background must be a 3-D mesh of tetrahedra; a surface mesh is read by "
            "cutfem.geometry.surface.read_surface"
        )
    points = np.asarray(m.points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path} has tetrahedra on points of shape {points.shape}; a 3-D mesh needs (N, 3)")
    return TetMesh(points, np.concatenate(blocks), orient=True)


def write_mesh(mesh: TetMesh, path, point_data=None, cell_data=None) -> None:
    """Write a tetrahedral mesh (and optional point/cell data dicts of arrays) with meshio."""
    import meshio

    cd = {k: [np.asarray(v)] for k, v in (cell_data or {}).items()}
    meshio.write(Path(path), meshio.Mesh(mesh.points, [("tetra", mesh.tets)], point_data=point_data or {}, cell_data=cd))
