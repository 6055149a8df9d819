"""Compiled kernels of the meshes: structured boxes (Kuhn tets, their faces and node ids),
mesh checks (orientation, tangling, solid angles), quadrature points, triangle geometry, and the
sort and unique primitives of the geometry (radix sort, dense unique by bitmaps).

Each replaces a numpy chain of (n, k) temporaries over every element by one pass: the face pairs
of a box's active mesh come from lattice face keys made on the fly and two marker arrays, the
distinct ids in [0, n) from a bitmap of n bits and per-word popcounts (100 MB instead of 2 GB at
400 million nodes), the half-edge table of a closed surface from one counting sort.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..jit import parallel_kernel
from .numbering import index_dtype

@njit(cache=True, error_model="numpy", inline="always")
def _area(p0, p1, p2):
    """|(p1 - p0) x (p2 - p0)| / 2."""
    e0, e1, e2 = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
    f0, f1, f2 = p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]
    c0, c1, c2 = e1 * f2 - e2 * f1, e2 * f0 - e0 * f2, e0 * f1 - e1 * f0
    return 0.5 * np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)


@njit(cache=True, error_model="numpy")
def _triangle_areas(points, triangles, area):
    for t in range(triangles.shape[0]):
        area[t] = _area(points[triangles[t, 0]], points[triangles[t, 1]], points[triangles[t, 2]])


def triangle_areas(points, triangles):
    """(m,) |T| = |(x_1 - x_0) x (x_2 - x_0)| / 2 of the triangles (m, 3) of ``points`` (p, 3)."""
    points = np.ascontiguousarray(points, dtype=float)
    triangles = np.ascontiguousarray(triangles)
    area = np.empty(len(triangles))
    _triangle_areas(points, triangles, area)
    return area


RADIX_BITS = 8


@njit(cache=True, error_model="numpy")
def radix_argsort(keys, bits, order):
    """The stable sorting order of the non-negative int64 ``keys`` (n,) below 2**bits, by LSD radix
    passes of :data:`RADIX_BITS` bits (a counting sort each, stable; the digit counts of all the
    passes from one read of the keys, and a pass whose digit is the same for every key skipped);
    ``order`` (n,) int64 is overwritten with the result.  O(n) a pass: no comparisons."""
    n = keys.shape[0]
    nb = 1 << RADIX_BITS
    mask = np.int64(nb - 1)
    passes = max((bits + RADIX_BITS - 1) // RADIX_BITS, 1)
    count = np.zeros((passes, nb), dtype=np.int64)
    for i in range(n):
        x = keys[i]
        for q in range(passes):
            count[q, (x >> (q * RADIX_BITS)) & mask] += 1
    k, k2 = keys, np.empty(n, dtype=np.int64)
    idx, idx2 = np.arange(n), np.empty(n, dtype=np.int64)
    first = True
    for q in range(passes):
        c = count[q]
        constant = False
        for b in range(nb):
            if c[b] == n:
                constant = True
        if constant:
            continue
        total = 0
        for b in range(nb):  # exclusive prefix sums: the first slot of each digit
            t = c[b]
            c[b] = total
            total += t
        shift = q * RADIX_BITS
        for i in range(n):
            d = (k[i] >> shift) & mask
            p = c[d]
            c[d] = p + 1
            k2[p] = k[i]
            idx2[p] = idx[i]
        if first:  # the input keys are never written
            k, k2 = k2, np.empty(n, dtype=np.int64)
            first = False
        else:
            k, k2 = k2, k
        idx, idx2 = idx2, idx
    order[:] = idx


@parallel_kernel
def kuhn_tet_nodes(tet_ids, cells_x, cells_y, nodes_x, nodes_y, offsets, out):
    """out[t] = the node ids of the Kuhn tet ``tet_ids[t]`` of a structured box: cell c = id // 6
    with indices (i, j, k) on a grid of ``cells_x`` x ``cells_y`` cells, lowest corner node id
    i + nodes_x (j + nodes_y k), plus the row id % 6 of the node offsets ``offsets`` (6, 4)."""
    for t in prange(tet_ids.shape[0]):
        c = tet_ids[t] // 6
        l = tet_ids[t] - 6 * c
        i = c % cells_x
        r = c // cells_x
        j = r % cells_y
        k = r // cells_y
        base = i + nodes_x * (j + nodes_y * k)
        for v in range(4):
            out[t, v] = base + offsets[l, v]


@parallel_kernel
def signed_volumes(v, out):
    """out[e] = (x_1 - x_0) x (x_2 - x_0) . (x_3 - x_0) / 6 for the tets ``v`` (m, 4, 3), in the
    order of :func:`cutfem.geometry.quadrature.signed_volumes`' terms (the same bits)."""
    for e in prange(v.shape[0]):
        a0, a1, a2 = v[e, 1, 0] - v[e, 0, 0], v[e, 1, 1] - v[e, 0, 1], v[e, 1, 2] - v[e, 0, 2]
        b0, b1, b2 = v[e, 2, 0] - v[e, 0, 0], v[e, 2, 1] - v[e, 0, 1], v[e, 2, 2] - v[e, 0, 2]
        c0, c1, c2 = v[e, 3, 0] - v[e, 0, 0], v[e, 3, 1] - v[e, 0, 1], v[e, 3, 2] - v[e, 0, 2]
        out[e] = (a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0)) / 6.0


@parallel_kernel
def box_node_coordinates(ids, nodes_x, nodes_y, lower, spacing, out):
    """out[t] = lower + (i, j, k) spacing for the node id ``ids[t]`` = i + nodes_x (j + nodes_y k) of
    a structured box (componentwise; the bits of numpy's ``lower + ijk * spacing``)."""
    for t in prange(ids.shape[0]):
        n = ids[t]
        r = n // nodes_x
        k = r // nodes_y
        out[t, 0] = lower[0] + np.float64(n - nodes_x * r) * spacing[0]
        out[t, 1] = lower[1] + np.float64(r - nodes_y * k) * spacing[1]
        out[t, 2] = lower[2] + np.float64(k) * spacing[2]


@parallel_kernel
def box_cell_corner_ids(cell_ids, cells_x, cells_y, nodes_x, nodes_y, offsets, out):
    """out[t, b] = the node id of corner b of the cell ``cell_ids[t]`` = i + cells_x (j + cells_y k)
    of a structured box: i + nodes_x (j + nodes_y k) + ``offsets[b]`` (the corners' id offsets)."""
    for t in prange(cell_ids.shape[0]):
        c = cell_ids[t]
        r = c // cells_x
        k = r // cells_y
        base = (c - cells_x * r) + nodes_x * ((r - cells_y * k) + nodes_y * k)
        for b in range(offsets.shape[0]):
            out[t, b] = base + offsets[b]


@njit(cache=True, error_model="numpy")
def box_ids_on_faces(ids, nodes_x, nodes_y, nodes_z):
    """Whether any node id ``ids[t]`` = i + nodes_x (j + nodes_y k) of a structured box lies on one
    of its faces (i, j or k first or last); stops at the first."""
    for t in range(ids.shape[0]):
        n = ids[t]
        r = n // nodes_x
        k = r // nodes_y
        i, j = n - nodes_x * r, r - nodes_y * k
        if i == 0 or i == nodes_x - 1 or j == 0 or j == nodes_y - 1 or k == 0 or k == nodes_z - 1:
            return True
    return False


@parallel_kernel
def _kuhn_types(tet_ids, out):
    for t in prange(tet_ids.shape[0]):
        out[t] = tet_ids[t] % 6


def kuhn_types(tet_ids):
    """(m,) int8: the Kuhn type (tet id % 6) of tets of a structured box, in one pass on all cores
    (numpy's remainder and cast: 64 ms for 13.7 million tets)."""
    tet_ids = np.ascontiguousarray(tet_ids, dtype=np.int64)
    out = np.empty(len(tet_ids), dtype=np.int8)
    _kuhn_types(tet_ids, out)
    return out


@parallel_kernel
def longest_edges(points, simplices, out):
    """out[e] = the longest edge of simplex e, the nodes ``simplices`` (m, k) of ``points`` (N, 3),
    k = 3 or 4 (:func:`cutfem.geometry.markers.longest_edges`): the coordinates gathered in the same pass,
    each edge's length as numpy's norm computes it."""
    k = simplices.shape[1]
    for e in prange(simplices.shape[0]):
        top = 0.0
        for a in range(k):
            for b in range(a + 1, k):
                p, q = simplices[e, a], simplices[e, b]
                d0 = points[q, 0] - points[p, 0]
                d1 = points[q, 1] - points[p, 1]
                d2 = points[q, 2] - points[p, 2]
                top = max(top, np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
        out[e] = top


@parallel_kernel
def rule_points(bary, nodes, simplices, out):
    """out[e, i] = sum_v bary[i, v] x_ev, the points of a reference rule (q, k) on b simplices: x_ev
    = nodes[simplices[e, v]] (node coordinates (N, 3) and node numbers (b, k), gathered in the same
    pass), or x_ev = nodes[k e + v] when ``simplices`` is empty (the vertices (b, k, 3) as (b k, 3)).
    The vertices of a simplex (k = 2, 3 or 4) are held in scalars and the sums over v unrolled
    (the same sums in the same order): 1.24 against 1.62 ns a point on both cores with the
    14-point rule on the tets of a structured box."""
    q, k = bary.shape
    gather = simplices.shape[0] > 0
    m = out.shape[0]
    for e in prange(m):
        x = np.zeros((4, 3))  # hoisted out of the point loop; the unused rows stay zero
        for v in range(k):
            n = simplices[e, v] if gather else k * e + v
            x[v, 0], x[v, 1], x[v, 2] = nodes[n, 0], nodes[n, 1], nodes[n, 2]
        x0, y0, z0, x1, y1, z1 = x[0, 0], x[0, 1], x[0, 2], x[1, 0], x[1, 1], x[1, 2]
        x2, y2, z2, x3, y3, z3 = x[2, 0], x[2, 1], x[2, 2], x[3, 0], x[3, 1], x[3, 2]
        for i in range(q):
            b0, b1 = bary[i, 0], bary[i, 1]
            p0, p1, p2 = b0 * x0 + b1 * x1, b0 * y0 + b1 * y1, b0 * z0 + b1 * z1
            if k > 2:
                b2 = bary[i, 2]
                p0, p1, p2 = p0 + b2 * x2, p1 + b2 * y2, p2 + b2 * z2
            if k > 3:
                b3 = bary[i, 3]
                p0, p1, p2 = p0 + b3 * x3, p1 + b3 * y3, p2 + b3 * z3
            out[e, i, 0], out[e, i, 1], out[e, i, 2] = p0, p1, p2


@parallel_kernel
def rule_weights(sizes, w, out):
    """out[e, i] = sizes[e] w[i]: a reference rule's weights (q,) scaled by the cells' measures (m,)
    (numpy's broadcast product of (m, 1) and (1, q) runs an inner loop of q per row: 0.57 against
    0.07 ms for 65536 cells and q = 4)."""
    for e in prange(out.shape[0]):
        s = sizes[e]
        for i in range(out.shape[1]):
            out[e, i] = s * w[i]


@njit(cache=True, error_model="numpy", inline="always")
def _face_normal_area(table, l, k, volume):
    """(n_x, n_y, n_z, |F|) of the face opposite to vertex k of a tet of gradient type l and volume
    ``volume``: n = -g / |g| out of the tet and |F| = 3 |T| |g|, g = grad lambda_k = ``table[l, k]``
    (|T| = |F| height / 3, |g| = 1 / height)."""
    gx, gy, gz = table[l, k, 0], table[l, k, 1], table[l, k, 2]
    gn = gx * gx
    gn += gy * gy
    gn += gz * gz
    gn = np.sqrt(gn)
    return gx / -gn, gy / -gn, gz / -gn, 3.0 * volume * gn


@njit(cache=True, error_model="numpy")
def face_normals_areas(pairs, opposite, table, types, volumes, normals, areas):
    """For each face f between tets ``pairs[f]``: ``normals[f]`` = -g / |g| and ``areas[f]`` =
    3 |T| |g|, with g = grad lambda_k of the first tet T for the vertex k = ``opposite[f, 0]``
    opposite to the face (``table[types[T], k]``, volumes ``volumes``): the unit normal out of T and
    the face area (|T| = |F| height / 3, |g| = 1 / height)."""
    for f in range(pairs.shape[0]):
        t = pairs[f, 0]
        normals[f, 0], normals[f, 1], normals[f, 2], areas[f] = _face_normal_area(table, types[t], opposite[f, 0], volumes[t])


@njit(cache=True, error_model="numpy", inline="always")
def _kuhn_face_key(tets, kinds, low, ftype, r):
    """The lattice key 12 v + type of face row r = 4 t + k (the face opposite to local vertex k of
    tet t), see :func:`cutfem.geometry.box.kuhn_face_keys`."""
    t, k = r >> 2, r & 3
    l = kinds[t]
    return 12 * np.int64(tets[t, low[l, k]]) + ftype[l, k]


@njit(cache=True, error_model="numpy")
def kuhn_face_keys(tets, kinds, low, ftype, out):
    """out[4 t + k] = the lattice key of the face opposite to local vertex k of Kuhn tet t."""
    for r in range(out.shape[0]):
        out[r] = _kuhn_face_key(tets, kinds, low, ftype, r)


@njit(cache=True, error_model="numpy")
def _mark_kuhn_faces(tets, kinds, low, ftype, first, second):
    for r in range(4 * tets.shape[0]):
        key = _kuhn_face_key(tets, kinds, low, ftype, r)
        if first[key] < 0:
            first[key] = r
        elif second[key] == -1:
            second[key] = r
        else:
            second[key] = -2  # a third row: not a pair
    n = 0
    for key in range(first.shape[0]):
        if second[key] >= 0:
            n += 1
    return n


@njit(cache=True, error_model="numpy")
def _collect_pairs(first, second, pairs, opposite):
    n = 0
    for key in range(first.shape[0]):
        if second[key] >= 0:
            a, b = first[key], second[key]
            pairs[n, 0], pairs[n, 1] = a >> 2, b >> 2
            opposite[n, 0], opposite[n, 1] = a & 3, b & 3
            n += 1


def kuhn_face_pairs(tets, kinds, low, ftype, n_keys: int):
    """The interior faces of Kuhn tets ``tets`` (m, 4) (node numbers below n_keys / 12, types
    ``kinds`` (m,), key tables ``low``, ``ftype`` (6, 4) of :func:`cutfem.geometry.box.kuhn_face_keys`):
    ``(pairs (F, 2), opposite (F, 2) int8)``, the two tets of each face whose key occurs exactly
    twice (first the earlier row) and the local vertex opposite to it in each, in increasing key
    order.  The keys are computed on the fly and paired by two marker arrays of length n_keys: no
    (4m,) key array and no sort.  ``pairs`` is int32 when m < 2**31."""
    tets = np.ascontiguousarray(tets)
    kinds = np.ascontiguousarray(kinds)
    rows = 4 * len(tets)
    dtype = index_dtype(rows)
    first, second = np.full(n_keys, -1, dtype=dtype), np.full(n_keys, -1, dtype=dtype)
    n = _mark_kuhn_faces(tets, kinds, low, ftype, first, second)
    pairs, opposite = np.empty((n, 2), dtype=dtype), np.empty((n, 2), dtype=np.int8)
    _collect_pairs(first, second, pairs, opposite)
    return pairs, opposite


@njit(cache=True, error_model="numpy", inline="always")
def _orientation(a0, a1, a2, b, c, d, points):
    """(b - a) . ((c - a) x (d - a)) for a = (a0, a1, a2) and the points rows b, c, d."""
    u0, u1, u2 = points[b, 0] - a0, points[b, 1] - a1, points[b, 2] - a2
    v0, v1, v2 = points[c, 0] - a0, points[c, 1] - a1, points[c, 2] - a2
    w0, w1, w2 = points[d, 0] - a0, points[d, 1] - a1, points[d, 2] - a2
    return u0 * (v1 * w2 - v2 * w1) + u1 * (v2 * w0 - v0 * w2) + u2 * (v0 * w1 - v1 * w0)


@njit(cache=True, error_model="numpy")
def points_inside_tets(points, tets, node_cells, probes, dims, cell_start, cell_probes, tolerance, hits):
    """The pairs (tet, probe) with the probe strictly inside the positively oriented tet: its four
    barycentric coordinates above ``tolerance`` (each the signed volume of the tet with one vertex
    replaced by the probe, over the tet's).  Candidates: the probes in the grid cells (``dims`` (3,)
    cells, cell c = i + dims[0] (j + dims[1] k)) met by the tet's bounding box, listed by cell as
    ``cell_probes[cell_start[c]:cell_start[c + 1]]``, and inside that box.  The box's cells come
    from ``node_cells`` (N, 3) int32, the cell of each node clipped to [-1, dims] (floor is
    monotone, so the cells of the box are those between its nodes'); the coordinates are read only
    for the tets that meet a probe's cell, and the probes of a row of cells are one run.
    Writes the first ``len(hits)`` pairs into ``hits`` (k, 2); returns how many there are.  One
    pass over the tets, no per-tet arrays (:func:`cutfem.geometry.mesh._check_overlap`)."""
    found = 0
    c0 = np.empty(3, dtype=np.int64)
    c1 = np.empty(3, dtype=np.int64)
    lo = np.empty(3)
    hi = np.empty(3)
    for t in range(tets.shape[0]):
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        empty = False
        for x in range(3):
            c0[x] = max(min(min(node_cells[a, x], node_cells[b, x]), min(node_cells[c, x], node_cells[d, x])), 0)
            c1[x] = min(max(max(node_cells[a, x], node_cells[b, x]), max(node_cells[c, x], node_cells[d, x])), dims[x] - 1)
            if c1[x] < c0[x]:
                empty = True
        if empty:
            continue
        volume = -1.0
        for k in range(c0[2], c1[2] + 1):
            for j in range(c0[1], c1[1] + 1):
                g = c0[0] + dims[0] * (j + dims[1] * k)
                for q in range(cell_start[g], cell_start[g + c1[0] - c0[0] + 1]):
                    p = cell_probes[q]
                    if volume < 0.0:  # the tet's box and volume, once
                        for x in range(3):
                            lo[x] = min(min(points[a, x], points[b, x]), min(points[c, x], points[d, x]))
                            hi[x] = max(max(points[a, x], points[b, x]), max(points[c, x], points[d, x]))
                        volume = _orientation(points[a, 0], points[a, 1], points[a, 2], b, c, d, points)
                    p0, p1, p2 = probes[p, 0], probes[p, 1], probes[p, 2]
                    if not (lo[0] < p0 < hi[0] and lo[1] < p1 < hi[1] and lo[2] < p2 < hi[2]):
                        continue
                    limit = tolerance * volume
                    if (_orientation(p0, p1, p2, b, c, d, points) > limit
                            and _orientation(p0, p1, p2, c, a, d, points) > limit
                            and _orientation(p0, p1, p2, a, b, d, points) > limit
                            and _orientation(p0, p1, p2, b, a, c, points) > limit):
                        if found < hits.shape[0]:
                            hits[found, 0], hits[found, 1] = t, p
                        found += 1
    return found


@njit(cache=True, error_model="numpy")
def vertex_solid_angles(points, tets, out):
    """Adds to ``out`` (N,) the solid angle of each tet (m, 4) at each of its vertices: with a, b, c
    the other three vertices minus the vertex, tan(Omega / 2) = |det[a b c]| / (|a||b||c| +
    (a.b)|c| + (b.c)|a| + (c.a)|b|) (Van Oosterom and Strackee), summed tet by tet in order
    (:func:`cutfem.geometry.mesh._check_wound`)."""
    for t in range(tets.shape[0]):
        for k in range(4):
            v = tets[t, k]
            i, j, l = tets[t, (k + 1) % 4], tets[t, (k + 2) % 4], tets[t, (k + 3) % 4]
            a0, a1, a2 = points[i, 0] - points[v, 0], points[i, 1] - points[v, 1], points[i, 2] - points[v, 2]
            b0, b1, b2 = points[j, 0] - points[v, 0], points[j, 1] - points[v, 1], points[j, 2] - points[v, 2]
            c0, c1, c2 = points[l, 0] - points[v, 0], points[l, 1] - points[v, 1], points[l, 2] - points[v, 2]
            det = abs(a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0))
            la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            lb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
            lc = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            den = (la * lb * lc + (a0 * b0 + a1 * b1 + a2 * b2) * lc + (b0 * c0 + b1 * c1 + b2 * c2) * la
                   + (c0 * a0 + c1 * a1 + c2 * a2) * lb)
            out[v] += 2.0 * np.arctan2(det, den)


@njit(cache=True, error_model="numpy", inline="always")
def _popcount(x):
    """Set bits of a 64-bit word (SWAR)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@njit(cache=True, error_model="numpy")
def _mark_bits(ids, words):
    for r in range(ids.shape[0]):
        i = np.uint64(ids[r])
        words[i >> np.uint64(6)] |= np.uint64(1) << (i & np.uint64(63))


@njit(cache=True, error_model="numpy")
def _rank_bits(words, prefix, unique):
    total = 0
    for w in range(words.shape[0]):
        prefix[w] = total
        x = words[w]
        while x:
            b = _trailing_bit(x)
            unique[total] = 64 * w + b
            total += 1
            x &= x - np.uint64(1)
    return total


@njit(cache=True, error_model="numpy", inline="always")
def _trailing_bit(x):
    """Position of the lowest set bit of a nonzero 64-bit word."""
    return _popcount((x & (~x + np.uint64(1))) - np.uint64(1))


@parallel_kernel
def _bit_ranks(ids, words, prefix, inverse):
    for r in prange(ids.shape[0]):
        i = np.uint64(ids[r])
        w = i >> np.uint64(6)
        below = words[w] & ((np.uint64(1) << (i & np.uint64(63))) - np.uint64(1))
        inverse[r] = prefix[w] + _popcount(below)


def dense_unique(ids, n: int, inverse_dtype=None):
    """Sorted distinct values of integer ids in [0, n) and the inverse map: ``(unique (u,) int64,
    inverse)`` with ``unique[inverse] == ids`` (inverse of the shape of ids, of ``inverse_dtype`` when
    given (it must hold u - 1), else int32 when u < 2**31: a caller that keeps int64 numbers gets
    them written directly, not converted from an int32 copy).
    A bitmap of n bits and a running count of its set bits per 64-bit word (n / 4 bytes in all)
    instead of a marker and a lookup array of length n (5 n bytes: 2 GB for the 404 million nodes of
    the box at spacing 0.003125, of which the band touches a few), and no sort."""
    ids = np.asarray(ids)
    flat = np.ascontiguousarray(ids.reshape(-1))
    words = np.zeros((int(n) + 63) // 64, dtype=np.uint64)
    _mark_bits(flat, words)
    prefix = np.empty(len(words), dtype=np.int64)
    unique = np.empty(min(int(n), flat.size), dtype=np.int64)
    u = _rank_bits(words, prefix, unique)
    dtype = np.dtype(inverse_dtype) if inverse_dtype is not None else np.dtype(index_dtype(u))
    if u > 0 and np.iinfo(dtype).max < u - 1:
        raise ValueError(f"inverse_dtype {dtype} cannot hold {u} distinct values")
    inverse = np.empty(flat.size, dtype=dtype)
    _bit_ranks(flat, words, prefix, inverse)
    return unique[:u].copy(), inverse.reshape(ids.shape)


@parallel_kernel
def triangle_geometry(points, tri):
    """Cross products, their lengths and edge-vector dot products of triangles, for
    :func:`cutfem.geometry.surface_checks._triangle_geometry` (which states them): ``(cross (M, 3), twice_area (M,),
    dots (2, M, 3), longest (M,))``.  One pass over the triangles, where numpy gathered coordinate
    columns and made two dozen temporaries a block."""
    M = tri.shape[0]
    cross, twice, dots, longest = np.empty((M, 3)), np.empty(M), np.empty((2, M, 3)), np.empty(M)
    for t in prange(M):
        e = np.empty((3, 3))
        for k in range(3):
            a, b = tri[t, k], tri[t, (k + 1) % 3]
            for d in range(3):
                e[k, d] = points[b, d] - points[a, d]
        # (x_1 - x_0) x (x_2 - x_0), with x_2 - x_0 = -e_2
        cross[t, 0] = e[0, 2] * e[2, 1] - e[0, 1] * e[2, 2]
        cross[t, 1] = e[0, 0] * e[2, 2] - e[0, 2] * e[2, 0]
        cross[t, 2] = e[0, 1] * e[2, 0] - e[0, 0] * e[2, 1]
        twice[t] = np.sqrt(cross[t, 0] * cross[t, 0] + cross[t, 1] * cross[t, 1] + cross[t, 2] * cross[t, 2])
        top = 0.0
        for k in range(3):
            nx = (k + 1) % 3
            sq = e[k, 0] * e[k, 0] + e[k, 1] * e[k, 1] + e[k, 2] * e[k, 2]
            dots[0, t, k] = sq
            dots[1, t, k] = e[k, 0] * e[nx, 0] + e[k, 1] * e[nx, 1] + e[k, 2] * e[nx, 2]
            top = max(top, sq)
        longest[t] = top
    return cross, twice, dots, longest


@njit(cache=True, error_model="numpy")
def _rows_sorted(lo, key, n, order):
    """Writes into ``order`` (m,) the indices k in the order of (lo[k], key[k]), stable (equal
    entries in index order), and returns the row starts (n + 1,) of lo = 0..n-1 in it (``order``'s
    integer type): a counting sort on lo, then an insertion sort on key within each row (the rows
    of a surface mesh hold a handful of entries)."""
    start = np.zeros(n + 1, order.dtype)
    for k in range(lo.shape[0]):
        start[lo[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    for k in range(lo.shape[0]):
        order[fill[lo[k]]] = k
        fill[lo[k]] += 1
    for i in range(n):
        s, e = start[i], start[i + 1]
        for t in range(s + 1, e):
            k = order[t]
            u = t
            while u > s and key[order[u - 1]] > key[k]:
                order[u] = order[u - 1]
                u -= 1
            order[u] = k
    return start


@njit(cache=True, error_model="numpy")
def closed_halfedges(tri, n):
    """The half-edges of a triangle mesh with n nodes in the order of the key
    2 (min(a, b) n + max(a, b)) + [a > b] of half-edge a -> b, for
    :func:`cutfem.geometry.surface_checks._closed_halfedge_table` (which states what it is for): a stable counting
    sort on min(a, b), then an insertion sort on the rest of the key within each node's few
    half-edges (numpy: an argsort of the keys).  Returns ``(closed, order (3 M,), edges (3 M / 2,
    2), halfedge_edge (3 M,))``: ``closed`` is whether the sorted keys come in pairs
    (2 k, 2 k + 1), i.e. every edge has one forward and one backward half-edge and nothing else;
    the other arrays are meaningful only then."""
    H = 3 * tri.shape[0]
    lo, rest = np.empty(H, np.int64), np.empty(H, np.int64)
    for t in range(tri.shape[0]):
        for k in range(3):
            a, b = tri[t, k], tri[t, (k + 1) % 3]
            lo[3 * t + k] = min(a, b)
            rest[3 * t + k] = 2 * max(a, b) + (1 if a > b else 0)
    order = np.empty(H, np.int64)
    _rows_sorted(lo, rest, n, order)
    edges = np.empty((H // 2, 2), np.int64)
    halfedge_edge = np.empty(H, np.int64)
    if H % 2:
        return False, order, edges, halfedge_edge
    for p in range(H // 2):
        f, b = order[2 * p], order[2 * p + 1]
        if lo[f] != lo[b] or rest[f] & 1 or rest[b] != rest[f] + 1:
            return False, order, edges, halfedge_edge
        edges[p, 0], edges[p, 1] = lo[f], rest[f] >> 1
        halfedge_edge[f], halfedge_edge[b] = p, p
    return True, order, edges, halfedge_edge
