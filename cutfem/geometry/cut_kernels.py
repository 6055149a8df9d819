"""Compiled kernels of the cut: the zero rule on the band of a structured box, the sides of
each tet (whole or split into sub-tetrahedra at the zero crossings of the P1 level set), marching
tetrahedra for the surface S_h (sign codes, polygon slots, vertices once each, oriented triangles),
the level set's normals, and the band search's block refinement.

Kernels whose output size is not known count it chunk by chunk (:data:`COUNT_FILL_CHUNK`), then
fill from each chunk's offset on all cores: the same arrays as one pass in row order.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..jit import parallel_kernel
from .numbering import index_dtype

@njit(cache=True, error_model="numpy")
def side_split(tets, values, neg, whole, partial, counts):
    """Split the tets (m, 4) by the sign of the nodal ``values`` on one side (``neg``: phi < 0, else
    phi > 0): writes the tets wholly on the side (NEG: all values < 0; POS: all >= 0) into ``whole``
    and those with 1-3 nodes on it (and not whole) into ``partial``, with those counts into
    ``counts``, both in increasing order; returns (number whole, number partial)."""
    nw = 0
    npart = 0
    for e in range(tets.shape[0]):
        k = 0
        ge = 0
        for v in range(4):
            x = values[tets[e, v]]
            if (x < 0.0) if neg else (x > 0.0):
                k += 1
            if x >= 0.0:
                ge += 1
        if k == 4 or (not neg and ge == 4):
            whole[nw] = e
            nw += 1
        elif k > 0:
            partial[npart] = e
            counts[npart] = k
            npart += 1
    return nw, npart


@njit(cache=True, error_model="numpy", inline="always")
def _cut_point(x, w, i, j, out, row):
    t = w[i] / (w[i] - w[j])
    for d in range(3):
        out[row, d] = x[i, d] + t * (x[j, d] - x[i, d])


@parallel_kernel
def side_pieces(points, tets, values, neg, partial, counts, rank, base, sizes, sub, parent):
    """The sub-tetrahedra of :func:`cutfem.geometry.markers.side_subtetrahedra` (which states them) for the
    ``partial`` tets with ``counts`` nodes on the side: tet q of the group of count c, of rank
    ``rank[q]`` in it, writes its sub-tet s at ``base[c] + s sizes[c] + rank[q]`` of ``sub`` (s, 4, 3)
    and ``parent``, the order of the numpy expression (a group at a time, sub-tet by sub-tet), the
    same points operation for operation."""
    for q in prange(partial.shape[0]):
        e = partial[q]
        c = counts[q]
        x = np.empty((4, 3))
        w = np.empty(4)
        n = 0
        for pas in range(2):  # the side's nodes first, each part in the tet's order
            for v in range(4):
                val = values[tets[e, v]]
                on = (val < 0.0) if neg else (val > 0.0)
                if on == (pas == 0):
                    for d in range(3):
                        x[n, d] = points[tets[e, v], d]
                    w[n] = val
                    n += 1
        pts = np.empty((6, 3))  # the prism a, b, c, a2, b2, c2 (or the one tet in its first four)
        if c == 1:
            pts[0] = x[0]
            _cut_point(x, w, 0, 1, pts, 1)
            _cut_point(x, w, 0, 2, pts, 2)
            _cut_point(x, w, 0, 3, pts, 3)
            nsub = 1
        elif c == 2:
            pts[0] = x[0]
            _cut_point(x, w, 0, 2, pts, 1)
            _cut_point(x, w, 0, 3, pts, 2)
            pts[3] = x[1]
            _cut_point(x, w, 1, 2, pts, 4)
            _cut_point(x, w, 1, 3, pts, 5)
            nsub = 3
        else:
            pts[0], pts[1], pts[2] = x[0], x[1], x[2]
            _cut_point(x, w, 0, 3, pts, 3)
            _cut_point(x, w, 1, 3, pts, 4)
            _cut_point(x, w, 2, 3, pts, 5)
            nsub = 3
        for s in range(nsub):
            row = base[c] + s * sizes[c] + rank[q]
            parent[row] = e
            for v in range(4):
                src = v + s  # the prism's tets: (a, b, c, a2), (b, c, a2, b2), (c, a2, b2, c2)
                for d in range(3):
                    sub[row, v, d] = pts[src, d]


@parallel_kernel
def tets_near(tets, marked, n_nodes, out):
    """out[t] = whether tet t shares a node with a tet of ``marked`` (m,) (itself included): the
    marked tets' nodes flagged in one pass (the marked tets are few: a serial pass), then every tet
    tested on all cores.  ``tets`` (m, 4) node numbers below ``n_nodes``."""
    near = np.zeros(n_nodes, np.bool_)
    for t in range(tets.shape[0]):
        if marked[t]:
            for k in range(4):
                near[tets[t, k]] = True
    for t in prange(tets.shape[0]):
        out[t] = near[tets[t, 0]] or near[tets[t, 1]] or near[tets[t, 2]] or near[tets[t, 3]]


@parallel_kernel
def level_set_normals(values, table, types, out):
    """out[t] = g / |g|, g = sum_k values[t, k] grad lambda_k with the gradients ``table[types[t]]``
    (4, 3): the unit normals n_h of the zero level set of the P1 interpolant in each tet.  Where
    |g|^2 overflows or underflows (a level set of values near 1e300 or 1e-300), g is first divided
    by its largest component; elsewhere the plain formula (the same bits as before).  A tet with
    g = 0, or g not finite, gets NaN (the caller checks)."""
    for t in prange(values.shape[0]):
        G = table[types[t]]
        g0 = g1 = g2 = 0.0
        for k in range(4):
            v = values[t, k]
            g0 += v * G[k, 0]
            g1 += v * G[k, 1]
            g2 += v * G[k, 2]
        square = g0 * g0 + g1 * g1 + g2 * g2
        if not (1e-290 < square < 1e300):
            a = max(abs(g0), abs(g1), abs(g2))
            if 0.0 < a < np.inf:
                g0, g1, g2 = g0 / a, g1 / a, g2 / a
                square = g0 * g0 + g1 * g1 + g2 * g2
        norm = np.sqrt(square)
        out[t, 0] = g0 / norm
        out[t, 1] = g1 / norm
        out[t, 2] = g2 / norm


@njit(cache=True, error_model="numpy")
def _marching(tet_ids, labels, vals, edge_i_table, edge_j_table, code):
    n = 0
    for t in range(vals.shape[0]):
        c = 0
        for k in range(4):
            if vals[t, k] < 0:
                c |= 1 << k
        keep = True
        for s in range(4):
            if vals[t, edge_j_table[c, s]] == 0.0:
                keep = _distinct_slots(vals, t, c, edge_i_table, edge_j_table) >= 3
                break
        if keep:
            if n != t:
                tet_ids[n] = tet_ids[t]
                for k in range(4):
                    labels[n, k] = labels[t, k]
                    vals[n, k] = vals[t, k]
            code[n] = c
            n += 1
    return n


@njit(cache=True, error_model="numpy")
def _distinct_slots(vals, t, c, edge_i_table, edge_j_table):
    """How many distinct vertices the four slots of tet t (sign code c) have: a slot is the node j
    when phi_j == 0, else its edge (i, j)."""
    k4 = np.empty(4, dtype=np.int64)
    distinct = 0
    for s in range(4):
        i, j = edge_i_table[c, s], edge_j_table[c, s]
        k4[s] = j if vals[t, j] == 0.0 else 4 + 4 * i + j
        new = True
        for r in range(s):
            if k4[s] == k4[r]:
                new = False
        if new:
            distinct += 1
    return distinct


def marching(tet_ids, labels, vals, edge_i_table, edge_j_table):
    """Marching tetrahedra on the candidate tets ``tet_ids`` (m,) with node labels ``labels``
    (m, 4) and nodal values ``vals`` (m, 4): the sign code of each tet (bit k: vals[k] < 0), and
    the tets whose piece has fewer than three distinct vertices dropped.  The polygon slots of the
    sign code are the edges (i, j) of the case tables; a slot is the node j when phi_j == 0, else
    its edge (see :func:`cutfem.geometry.cut._marching`).

    The three arrays are compacted **in place**; returns ``(n, code)``: the kept tets are their
    first n rows, ``code`` (n,) uint8 their sign codes."""
    code = np.empty(len(vals), dtype=np.uint8)
    n = _marching(tet_ids, labels, vals, np.ascontiguousarray(edge_i_table), np.ascontiguousarray(edge_j_table), code)
    return n, code[:n]


@parallel_kernel
def _slot_keys(tets, types, code, vals, edge_i_table, edge_j_table, edge_codes, p, lattice, key):
    for t in prange(tets.shape[0]):
        c = code[t]
        for s in range(4):
            i, j = edge_i_table[c, s], edge_j_table[c, s]
            a, b = tets[t, i], tets[t, j]
            lo, hi = min(a, b), max(a, b)
            if vals[t, j] == 0.0:
                key[t, s] = b
            elif lattice:
                key[t, s] = p - 1 + 7 * lo + edge_codes[types[t], i, j]
            else:
                key[t, s] = p + lo * p + hi


def slot_keys(tets, code, vals, edge_i_table, edge_j_table, p, lattice=None):
    """(m, 4) int64 keys of the polygon slots of the pieces: the active node j (``< p``) for a slot
    at a node (phi_j == 0), else a key of its edge {a, b} = the active nodes of (i, j), lo = min:
    ``p + lo p + hi`` in general, or with ``lattice = (edge_codes (6, 4, 4), types (m,))`` on a
    structured box ``p - 1 + 7 lo + c(S)``, c(S) in 1..7 the lattice code of the edge
    (:data:`~cutfem.geometry.box.KUHN_EDGE_CODES` of the Kuhn type), keys below 8p when the active nodes
    increase with the background ids."""
    m = len(tets)
    key = np.empty((m, 4), dtype=np.int64)
    if lattice is None:
        edge_codes, types, flag = np.zeros((1, 4, 4), dtype=np.int8), np.zeros(m, dtype=np.int8), False
    else:
        (edge_codes, types), flag = lattice, True
    _slot_keys(tets, types, code, vals, edge_i_table, edge_j_table, np.ascontiguousarray(edge_codes), np.int64(p), flag, key)
    return key


@njit(cache=True, error_model="numpy")
def _surface(vinv, tets, code, vals, points, edge_i_table, edge_j_table, nvert, flip, negative, tri_slots,
             vertices, tri, tri_tet, fill):
    seen = np.zeros(vertices.shape[0], dtype=np.bool_)
    n = 0
    for t in range(vinv.shape[0]):
        c = code[t]
        if fill:
            for s in range(4):
                v = vinv[t, s]
                if seen[v]:
                    continue
                seen[v] = True
                i, j = edge_i_table[c, s], edge_j_table[c, s]
                a, b = tets[t, i], tets[t, j]
                pa, pb = vals[t, i], vals[t, j]
                if pb == 0.0:
                    for d in range(3):
                        vertices[v, d] = points[b, d]
                else:
                    u = pa / (pa - pb)
                    for d in range(3):
                        vertices[v, d] = points[a, d] + u * (points[b, d] - points[a, d])
        f = 1 if flip[c] else 0
        if negative.shape[0] > 0 and negative[t]:
            f = 1 - f
        for q in range(2 if nvert[c] == 4 else 1):
            v0 = vinv[t, tri_slots[f, 3 * q]]
            v1 = vinv[t, tri_slots[f, 3 * q + 1]]
            v2 = vinv[t, tri_slots[f, 3 * q + 2]]
            if v0 != v1 and v1 != v2 and v0 != v2:
                if fill:
                    tri[n, 0], tri[n, 1], tri[n, 2] = v0, v1, v2
                    tri_tet[n] = t
                n += 1
    return n


def surface(vinv, n_vertices, tets, code, vals, points, edge_i_table, edge_j_table, nvert, flip, tri_slots, negative=None):
    """The vertices and triangles of S_h from the vertex numbers ``vinv`` (m, 4) of the polygon
    slots of the pieces.  Each vertex is computed once, from its first slot in the order of
    ``vinv``: ``x_a + u (x_b - x_a)``, u = phi_a / (phi_a - phi_b), for the slot's edge (a, b), or
    the node b itself when phi_b == 0.  The triangles of a piece are the slots ``tri_slots[f]``
    (f = flip[code], turned over where ``negative``), (0, 1, 2) and for quads (0, 2, 3); those with
    a repeated vertex are dropped.  Returns ``(vertices (V, 3), triangles (T, 3) of vinv's dtype,
    triangle_tets (T,) int32 while the tets' count fits, else int64)``, in tet order; two passes
    (count, then fill)."""
    vinv = np.ascontiguousarray(vinv)
    neg = np.zeros(0, dtype=np.bool_) if negative is None else np.ascontiguousarray(negative, dtype=np.bool_)
    tables = (np.ascontiguousarray(edge_i_table), np.ascontiguousarray(edge_j_table), np.ascontiguousarray(nvert),
              np.ascontiguousarray(flip, dtype=np.bool_), neg, np.ascontiguousarray(tri_slots, dtype=np.int64))
    vertices = np.empty((n_vertices, 3))
    args = (vinv, tets, code, vals, points) + tables[:4]
    tet_dtype = index_dtype(len(vinv))  # the counting pass gets empty arrays of the same types: one compiled signature
    n = _surface(*args, tables[4], tables[5], vertices, np.empty((0, 3), dtype=vinv.dtype), np.empty(0, dtype=tet_dtype), False)
    tri, tri_tet = np.empty((n, 3), dtype=vinv.dtype), np.empty(n, dtype=tet_dtype)
    _surface(*args, tables[4], tables[5], vertices, tri, tri_tet, True)
    return vertices, tri, tri_tet


@parallel_kernel
def _mixed_kuhn_tets(values, corner, cell_ids, mixed_table, kuhn_tets, tol, centre, bound, dist, bounds, starts,
                     broken, ratio, tet_ids, nodes, vals):
    fill = tet_ids.shape[0] > 0
    check = centre.shape[0] > 0 and not fill
    for ch in prange(bounds.shape[0] - 1):
        n = starts[ch] if fill else 0
        bad, top = 0, 0.0
        cv = np.empty(8)
        for c in range(bounds[ch], bounds[ch + 1]):
            signs = 0
            for b in range(8):
                v = values[corner[c, b]]
                if check:
                    d = abs(v - centre[c])
                    top = max(top, d / dist)
                    if d > bound:
                        bad += 1
                if abs(v) <= tol[corner[c, b]]:  # the zero rule's snap, the node's own tolerance
                    v = 0.0
                cv[b] = v
                if v < 0:
                    signs |= 1 << b
            for l in range(6):
                if mixed_table[signs, l]:
                    if fill:
                        tet_ids[n] = 6 * cell_ids[c] + l
                        for k in range(4):
                            nodes[n, k] = corner[c, kuhn_tets[l, k]]
                            vals[n, k] = cv[kuhn_tets[l, k]]
                    n += 1
        if not fill:
            starts[ch] = n
            broken[ch] = bad
            ratio[ch] = top


@njit(cache=True, error_model="numpy")
def label_scales(values, corner, cap):
    """(L,): for each label l with |values[l]| <= ``cap``, the largest |values[m]| over the labels m
    of the cells ``corner`` (k, 8) that have l as a corner: the scale of the level set's values
    around a node, from its own cells (the local scale of the zero rule,
    :func:`cutfem.geometry.nodal_values._zero_tolerance`); 0 for the other labels.  With cap >= 1e-12 max |values|
    no other label can be snapped (its value exceeds 1e-12 times any maximum around it), so only
    the cells with such a corner are reduced: one read-mostly serial pass, 0.04 s for the torus's
    0.9 million band cells at spacing 0.00625 (0.08-0.16 s scattering to every label); the (k, 8)
    corner values are never made."""
    out = np.zeros(values.shape[0])
    for c in range(corner.shape[0]):
        small = False
        for b in range(8):
            if abs(values[corner[c, b]]) <= cap:
                small = True
        if not small:
            continue
        top = 0.0
        for b in range(8):
            top = max(top, abs(values[corner[c, b]]))
        for b in range(8):
            label = corner[c, b]
            if abs(values[label]) <= cap and top > out[label]:
                out[label] = top
    return out


#: rows per chunk of the kernels that count their output chunk by chunk, then fill it from each
#: chunk's offset, on all cores (:func:`mixed_kuhn_tets`, :func:`refine_blocks`): the same arrays
#: as one pass in row order
COUNT_FILL_CHUNK = 1 << 14


def _count_fill_bounds(k: int):
    """The chunk bounds (c + 1,) of k rows for the count-then-fill kernels."""
    return np.append(np.arange(0, k, COUNT_FILL_CHUNK, dtype=np.int64), np.int64(k))


def _offsets(counts):
    """(each chunk's first output row (c,), the output's length) from the chunks' counts."""
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64), int(counts.sum())


def mixed_kuhn_tets(values, corner, cell_ids, mixed_table, kuhn_tets, tol=0.0, centre=None, bound: float = 0.0,
                    dist: float = 1.0):
    """The Kuhn tets of the cells ``cell_ids`` (k,) whose corner values have both signs by
    ``mixed_table`` (256, 6) (bit c of the row: corner c has phi < 0).  Corner c of cell i has the
    label ``corner[i, c]`` and the value ``values[corner[i, c]]``, set to 0 where its modulus is at
    most ``tol`` (the zero rule's snap: one number, or one per label, (L,), see
    :func:`label_scales`).  Returns ``(tet_ids (n,), nodes (n, 4), vals (n, 4), broken,
    ratio)``: the tets in cell order, then Kuhn type, the nodes (labels) and snapped values in
    :data:`~cutfem.geometry.box.KUHN_TETS` order; with ``centre`` (k,), the value at each cell's centre,
    also the count ``broken`` of corners whose unsnapped value differs from their cell's centre
    value by more than ``bound``, and the largest |value - centre| / ``dist`` (a Lipschitz bound
    checked where the band search relies on it; 0 and 0.0 without ``centre``).  Two passes over
    chunks of :data:`COUNT_FILL_CHUNK` cells, each on any core: count (and check) per chunk, then fill
    from the chunk's offset (the same arrays as one pass in cell order); the (k, 8) corner values
    are never made."""
    values, corner = np.ascontiguousarray(values, dtype=float), np.ascontiguousarray(corner)
    cell_ids = np.ascontiguousarray(cell_ids, dtype=np.int64)
    centre = np.zeros(0) if centre is None else np.ascontiguousarray(centre, dtype=float)
    table = np.ascontiguousarray(mixed_table, dtype=np.bool_)
    kt = np.ascontiguousarray(kuhn_tets, dtype=np.int64)
    bounds = _count_fill_bounds(len(cell_ids))
    nch = len(bounds) - 1
    counts, broken, ratio = np.zeros(nch, dtype=np.int64), np.zeros(nch, dtype=np.int64), np.zeros(nch)
    tol = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=float), values.shape))
    args = (values, corner, cell_ids, table, kt, tol, centre, float(bound), float(dist), bounds)
    empty = np.empty(0, dtype=np.int64)
    _mixed_kuhn_tets(*args, counts, broken, ratio, empty, np.empty((0, 4), dtype=corner.dtype), np.empty((0, 4)))
    starts, n = _offsets(counts)
    tet_ids, nodes, vals = np.empty(n, dtype=np.int64), np.empty((n, 4), dtype=corner.dtype), np.empty((n, 4))
    if n:
        _mixed_kuhn_tets(*args, starts, broken, ratio, tet_ids, nodes, vals)
    return tet_ids, nodes, vals, int(broken.sum()), float(ratio.max()) if nch else 0.0


@njit(cache=True, error_model="numpy")
def _edge_census(triangles, n_vertices, start, upper):
    T = triangles.shape[0]
    for t in range(T):  # half-edges bucketed by their lower end: how many in each bucket
        for k in range(3):
            a, b = triangles[t, k], triangles[t, (k + 1) % 3]
            start[min(a, b) + 1] += 1
    for v in range(n_vertices):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    for t in range(T):
        for k in range(3):
            a, b = triangles[t, k], triangles[t, (k + 1) % 3]
            lo = min(a, b)
            upper[fill[lo]] = max(a, b)
            fill[lo] += 1


@parallel_kernel
def _sorted_runs(start, upper, n_vertices):
    n = not_two = 0
    for v in prange(n_vertices):  # each bucket (a few entries) sorted in place, its runs counted
        s, e = start[v], start[v + 1]
        for i in range(s + 1, e):
            x = upper[i]
            j = i - 1
            while j >= s and upper[j] > x:
                upper[j + 1] = upper[j]
                j -= 1
            upper[j + 1] = x
        i = s
        while i < e:
            j = i + 1
            while j < e and upper[j] == upper[i]:
                j += 1
            n += 1
            if j - i != 2:
                not_two += 1
            i = j
    return n, not_two


def edge_census(triangles, n_vertices: int):
    """``(E, B)`` of the ``triangles`` (T, 3) (vertex numbers below ``n_vertices``): how many distinct
    edges they have, and how many of those are not held by exactly two triangles (B = 0: closed and
    edge-manifold).  The 3T half-edges are bucketed by their lower end (a counting pass and a
    scatter) and each bucket, a few entries, is sorted in place: no sort of 3T keys (numpy's sort of
    the int64 keys min V + max took 1.3 s of 2.5 s at 27 million half-edges, the surface of the
    torus at spacing 0.003125), and no array of counts is made (108 MB there)."""
    triangles = np.ascontiguousarray(triangles)
    start = np.zeros(n_vertices + 1, dtype=np.int64)
    upper = np.empty(3 * len(triangles), dtype=triangles.dtype)
    _edge_census(triangles, n_vertices, start, upper)
    n, not_two = _sorted_runs(start, upper, n_vertices)
    return int(n), int(not_two)


@parallel_kernel
def _refine_blocks(blocks, phi, keep, size, cells, lower, spacing, corners, bounds, starts, children, centres, parent_phi):
    fill = children.shape[0] > 0
    for ch in prange(bounds.shape[0] - 1):
        n = starts[ch] if fill else 0
        for b in range(bounds[ch], bounds[ch + 1]):
            if not keep[b]:
                continue
            for c in range(8):
                i0 = blocks[b, 0] + size * corners[c, 0]
                i1 = blocks[b, 1] + size * corners[c, 1]
                i2 = blocks[b, 2] + size * corners[c, 2]
                if i0 < cells[0] and i1 < cells[1] and i2 < cells[2]:
                    if fill:
                        children[n, 0], children[n, 1], children[n, 2] = i0, i1, i2
                        centres[n, 0] = lower[0] + (i0 + 0.5 * size) * spacing[0]
                        centres[n, 1] = lower[1] + (i1 + 0.5 * size) * spacing[1]
                        centres[n, 2] = lower[2] + (i2 + 0.5 * size) * spacing[2]
                        parent_phi[n] = phi[b]
                    n += 1
        if not fill:
            starts[ch] = n


@njit(cache=True, error_model="numpy")
def _prune_blocks(phi, parent_phi, slack, dist, keep):
    nonfinite = broken = kept = 0
    top = 0.0
    check = parent_phi.shape[0] > 0
    for t in range(phi.shape[0]):
        v = phi[t]
        if not np.isfinite(v):
            nonfinite += 1
            keep[t] = False
            continue
        if check:
            d = abs(v - parent_phi[t])
            top = max(top, d / dist)
            if d > slack:
                broken += 1
        keep[t] = abs(v) <= slack
        if keep[t]:
            kept += 1
    return nonfinite, broken, top, kept


def prune_blocks(phi, parent_phi, slack: float, dist: float):
    """One level of the band search over the values ``phi`` (k,) at the centres of blocks of
    half-diagonal ``dist``: ``(keep (k,) bool, kept, nonfinite, broken, ratio)``, keep = |phi| <=
    ``slack`` (L dist and its rounding slack; finite values only), the counts of kept blocks and of
    non-finite values, and with the parents' values ``parent_phi`` (k,) (None on the first level;
    each centre lies ``dist`` from its parent's) the count of blocks whose |phi - parent| exceeds
    ``slack`` and the largest |phi - parent| / ``dist`` (0 and 0.0 without parents).  One pass,
    where numpy made five (k,) temporaries."""
    phi = np.ascontiguousarray(phi, dtype=float)
    parent = np.zeros(0) if parent_phi is None else np.ascontiguousarray(parent_phi, dtype=float)
    keep = np.empty(len(phi), dtype=np.bool_)
    nonfinite, broken, ratio, kept = _prune_blocks(phi, parent, float(slack), float(dist), keep)
    return keep, int(kept), int(nonfinite), int(broken), float(ratio)


@njit(cache=True, error_model="numpy")
def kept_cells(blocks, phi, keep, cells_x, cells_y, ids, kept_phi):
    """The cell ids i + cells_x (j + cells_y k) of the blocks (k, 3) of one cell with ``keep``, and
    their values, in block order, into ``ids`` and ``kept_phi``."""
    n = 0
    for t in range(blocks.shape[0]):
        if keep[t]:
            ids[n] = blocks[t, 0] + cells_x * (blocks[t, 1] + cells_y * blocks[t, 2])
            kept_phi[n] = phi[t]
            n += 1


def refine_blocks(blocks, phi, keep, size: int, cells, lower, spacing, corners):
    """The children of the kept blocks of the band search: for each block ``blocks`` (k, 3) (lower
    cell index) with ``keep``, its 8 sub-blocks of ``size`` cells at ``corners`` (8, 3) that start
    inside the box of ``cells`` (3,), in block order then corner order: ``(children (k', 3), their
    centres lower + (child + size / 2) spacing (k', 3), the parent's phi (k',))``.  Two passes
    (count, fill) over chunks of :data:`COUNT_FILL_CHUNK` blocks on all cores; no (k, 8, 3) arrays."""
    bounds = _count_fill_bounds(len(blocks))
    args = (np.ascontiguousarray(blocks, dtype=np.int64), np.ascontiguousarray(phi, dtype=float),
            np.ascontiguousarray(keep, dtype=np.bool_), np.int64(size), np.ascontiguousarray(cells, dtype=np.int64),
            np.ascontiguousarray(lower, dtype=float), np.ascontiguousarray(spacing, dtype=float),
            np.ascontiguousarray(corners, dtype=np.int64), bounds)
    counts = np.zeros(len(bounds) - 1, dtype=np.int64)
    _refine_blocks(*args, counts, np.empty((0, 3), dtype=np.int64), np.empty((0, 3)), np.empty(0))
    starts, n = _offsets(counts)
    children, centres, parent_phi = np.empty((n, 3), dtype=np.int64), np.empty((n, 3)), np.empty(n)
    if n:
        _refine_blocks(*args, starts, children, centres, parent_phi)
    return children, centres, parent_phi
