"""Compiled kernels of the cut by several level sets (:mod:`cutfem.geometry.csg_cut`): each tet
clipped by the planes of the P1 level sets that change sign in it, into sub-tetrahedra (each in the
domain or not) and the oriented pieces of the boundary parts, and the pieces of a boundary clipped
by further level sets (a part tagged by ``where``).

Clipping (docs/math.md §16).  A plane splits a tet into at most one tet and a prism (three tets) on
its two sides, or two prisms; a convex polygon into two convex polygons (Sutherland-Hodgman), its
cyclic order kept.  A point made on a segment from a (phi_k < 0) to b (phi_k >= 0) is
``a + t (b - a)``, ``t = phi_k(a) / (phi_k(a) - phi_k(b))``, always computed from the inside end,
with phi_k = 0 there and the other level sets interpolated linearly (exact for P1), an interpolated
value below 1e-12 of its ends set to 0 (the zero rule's snap); it is b itself, bit for bit, when
phi_k(b) = 0.  A value that is exactly 0 counts as outside.

Keys.  Each vertex of a boundary piece carries its key: the background nodes of the smallest face
of the tet it lies in (its support: a node, an edge, a face or the tet; the union of its segment's
ends', or b's when it is b) and the level sets that are zero there (the planes it lies on).  The
key names the point where it lies, not how it was made: two tets compute the same key for a point
of their common face, also when two planes meet on a face of the mesh (x = a and y = a on the
Kuhn faces x = y), so the pieces of neighbouring tets share their vertices by key.

The points of a tet live in one pool (coordinates, values, supports), its sub-tets and polygons as
rows of pool points.  Two passes over chunks of tets (:data:`~cutfem.geometry.cut_kernels.COUNT_FILL_CHUNK`)
on all cores: the first counts each tet's output rows (from its signs when one plane crosses it),
the second writes each tet from its first row: the same arrays as one pass in tet order.  The
scratch of a chunk grows when a tet needs more (a tet crossed by many planes).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..jit import parallel_kernel

#: relative size of an interpolated level-set value that counts as zero (the zero rule's snap)
SNAP = 1e-12
#: the columns of a vertex key: four background node ids (sorted, -1 padded) and the planes' bits
KEY_WIDTH = 5
#: sub-tets and polygons a chunk's scratch holds at first (four times more when a tet needs more)
SCRATCH = 64


@njit(cache=True, error_model="numpy", inline="always")
def _cross(px, pp, ps, a, b, k, m, o):
    """The point where plane k crosses the segment of the pool points a (phi_k < 0) and b
    (phi_k >= 0): b itself when phi_k(b) = 0 (returns b), else the new pool point o (returns o), its
    support the union of a's and b's.  See the module docstring."""
    if pp[b, k] == 0.0:
        return b
    t = pp[a, k] / (pp[a, k] - pp[b, k])
    for d in range(3):
        px[o, d] = px[a, d] + t * (px[b, d] - px[a, d])
    for j in range(m):
        if j == k:
            pp[o, j] = 0.0
        else:
            v = pp[a, j] + t * (pp[b, j] - pp[a, j])
            if abs(v) <= SNAP * max(abs(pp[a, j]), abs(pp[b, j])):
                v = 0.0
            pp[o, j] = v
    ps[o] = ps[a] | ps[b]
    return o


# the sub-tets of a split, as local points: 0..3 the tet's nodes (in the order a, b, c, d below),
# 4.. the crossing points; NEG pieces first.  One inside node a (points P_ab, P_ac, P_ad): one tet
# and a prism; three inside a, b, c (P_ad, P_bd, P_cd): a prism and one tet; two inside a, b
# (P_ac, P_ad, P_bc, P_bd): two prisms.  A prism (A0 A1 A2 | B0 B1 B2), lateral edges Ai Bi, is
# the tets (A0 A1 A2 B0), (A1 A2 B0 B1), (A2 B0 B1 B2).
_SPLIT_1 = np.array([[0, 4, 5, 6], [1, 2, 3, 4], [2, 3, 4, 5], [3, 4, 5, 6]], dtype=np.int64)
_SPLIT_3 = np.array([[0, 1, 2, 4], [1, 2, 4, 5], [2, 4, 5, 6], [3, 4, 5, 6]], dtype=np.int64)
_SPLIT_2 = np.array([[0, 4, 5, 1], [4, 5, 1, 6], [5, 1, 6, 7], [2, 4, 6, 3], [4, 6, 3, 5], [6, 3, 5, 7]], dtype=np.int64)


@njit(cache=True, error_model="numpy", inline="always")
def _split_tet(cv, cc, s, k, m, nv, nc, n, px, pp, ps, npool, local, split1, split2, split3):
    """Sub-tet ``s`` (pool points cv[s], code cc[s]) split by plane k into (nv, nc) from row ``n``:
    the NEG pieces get bit k.  Returns (rows, pool points) after it."""
    bit = np.int64(1) << k
    ni = 0
    for v in range(4):  # inside points first, then outside ones
        if pp[cv[s, v], k] < 0.0:
            local[ni] = cv[s, v]
            ni += 1
    no = ni
    for v in range(4):
        if not pp[cv[s, v], k] < 0.0:
            local[no] = cv[s, v]
            no += 1
    if ni == 0 or ni == 4:
        for v in range(4):
            nv[n, v] = cv[s, v]
        nc[n] = cc[s] | (bit if ni == 4 else 0)
        return n + 1, npool
    if ni == 1:
        for q in range(3):
            local[4 + q] = _cross(px, pp, ps, local[0], local[1 + q], k, m, npool)
            npool += local[4 + q] == npool
        table, negs = split1, 1
    elif ni == 3:
        for q in range(3):
            local[4 + q] = _cross(px, pp, ps, local[q], local[3], k, m, npool)
            npool += local[4 + q] == npool
        table, negs = split3, 3
    else:
        for q in range(4):
            local[4 + q] = _cross(px, pp, ps, local[q // 2], local[2 + q % 2], k, m, npool)
            npool += local[4 + q] == npool
        table, negs = split2, 3
    for r in range(table.shape[0]):
        for v in range(4):
            nv[n, v] = local[table[r, v]]
        nc[n] = cc[s] | (bit if r < negs else 0)
        n += 1
    return n, npool


@njit(cache=True, error_model="numpy", inline="always")
def _split_polygon(q, j, m, cv, cn, cc, nv, nn, nc, n, px, pp, ps, npool):
    """Polygon ``q`` (pool points cv[q, :cn[q]], code cc[q]) split by plane j into (nv, nn, nc) from
    row ``n``, each part in the polygon's cyclic order (Sutherland-Hodgman), the inside part (bit
    j in its code) first; a crossing point is one pool point of both parts.  Returns (rows, pool
    points) after it."""
    bit = np.int64(1) << j
    count = cn[q]
    ins = 0
    for v in range(count):
        if pp[cv[q, v], j] < 0.0:
            ins += 1
    if ins == 0 or ins == count:
        for v in range(count):
            nv[n, v] = cv[q, v]
        nn[n] = count
        nc[n] = cc[q] | (bit if ins == count else 0)
        return n + 1, npool
    a_row, b_row = n, n + 1
    na = 0
    nb = 0
    for v in range(count):
        p, w = cv[q, v], cv[q, (v + 1) % count]
        pin = pp[p, j] < 0.0
        if pin:
            nv[a_row, na] = p
            na += 1
        else:
            nv[b_row, nb] = p
            nb += 1
        if pin != (pp[w, j] < 0.0):
            o = _cross(px, pp, ps, p if pin else w, w if pin else p, j, m, npool)
            npool += o == npool
            nv[a_row, na] = o
            nv[b_row, nb] = o
            na += 1
            nb += 1
    nn[a_row], nc[a_row] = na, cc[q] | bit
    nn[b_row], nc[b_row] = nb, cc[q]
    return n + 2, npool


@njit(cache=True, error_model="numpy", inline="always")
def _clip_polygons(planes, m, pv, pn, pc, qv, qn, qc, px, pp, ps, npool):
    """The polygon in row 0 of (pv, pn, pc) clipped by each plane of the bits ``planes`` in
    increasing order, the pieces ending in (pv, pn, pc).  Returns (pieces, pool points), or
    (-1, npool) when the buffers are too small."""
    npoly = 1
    flipped = False
    for j in range(m):
        if not (planes >> j) & 1:
            continue
        if 2 * npoly > pv.shape[0] or npool + npoly * pv.shape[1] > px.shape[0]:
            return -1, npool
        nq = 0
        for q in range(npoly):
            if flipped:
                nq, npool = _split_polygon(q, j, m, qv, qn, qc, pv, pn, pc, nq, px, pp, ps, npool)
            else:
                nq, npool = _split_polygon(q, j, m, pv, pn, pc, qv, qn, qc, nq, px, pp, ps, npool)
        flipped = not flipped
        npoly = nq
    if flipped:
        for q in range(npoly):
            for v in range(qn[q]):
                pv[q, v] = qv[q, v]
            pn[q], pc[q] = qn[q], qc[q]
    return npoly, npool


@njit(cache=True, error_model="numpy", inline="always")
def _constant_over(table, fixed, free):
    """Whether the domain's ``table`` takes one value over the codes ``fixed | s``, s every subset
    of the bits ``free``."""
    first = table[fixed]
    s = free
    while True:
        if table[fixed | s] != first:
            return False
        if s == 0:
            return True
        s = (s - 1) & free


@njit(cache=True, error_model="numpy", inline="always")
def _bounds_part(table, fixed, free, bit):
    """Whether plane ``bit`` bounds the domain for some code ``fixed | s`` (s a subset of ``free``):
    the domain changes across it there."""
    s = free
    while True:
        if table[fixed | s | bit] != table[(fixed | s) & ~bit]:
            return True
        if s == 0:
            return False
        s = (s - 1) & free


@njit(cache=True, error_model="numpy", inline="always")
def _unit_gradient(x, phi, e, k, out):
    """grad phi_k / |grad phi_k| of the P1 interpolant on tet e (x[e] (4, 3), phi[e] (4, m)) into
    ``out`` (3,): g = sum_i d_i c_i / det, d_i = phi_k(x_i) - phi_k(x_0), c_i the cross product of
    the other two edges (Cramer's rule).  Returns whether the tet is negatively oriented."""
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    for i in range(3):
        a, b = (i + 1) % 3 + 1, (i + 2) % 3 + 1
        a0, a1, a2 = x[e, a, 0] - x[e, 0, 0], x[e, a, 1] - x[e, 0, 1], x[e, a, 2] - x[e, 0, 2]
        b0, b1, b2 = x[e, b, 0] - x[e, 0, 0], x[e, b, 1] - x[e, 0, 1], x[e, b, 2] - x[e, 0, 2]
        di = phi[e, i + 1, k] - phi[e, 0, k]
        g0 += di * (a1 * b2 - a2 * b1)
        g1 += di * (a2 * b0 - a0 * b2)
        g2 += di * (a0 * b1 - a1 * b0)
    e0, e1, e2 = x[e, 1, 0] - x[e, 0, 0], x[e, 1, 1] - x[e, 0, 1], x[e, 1, 2] - x[e, 0, 2]
    c0 = (x[e, 2, 1] - x[e, 0, 1]) * (x[e, 3, 2] - x[e, 0, 2]) - (x[e, 2, 2] - x[e, 0, 2]) * (x[e, 3, 1] - x[e, 0, 1])
    c1 = (x[e, 2, 2] - x[e, 0, 2]) * (x[e, 3, 0] - x[e, 0, 0]) - (x[e, 2, 0] - x[e, 0, 0]) * (x[e, 3, 2] - x[e, 0, 2])
    c2 = (x[e, 2, 0] - x[e, 0, 0]) * (x[e, 3, 1] - x[e, 0, 1]) - (x[e, 2, 1] - x[e, 0, 1]) * (x[e, 3, 0] - x[e, 0, 0])
    det = e0 * c0 + e1 * c1 + e2 * c2
    scale = (1.0 if det > 0 else -1.0) / np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    out[0], out[1], out[2] = g0 * scale, g1 * scale, g2 * scale
    return det < 0


@njit(cache=True, error_model="numpy", inline="always")
def _vertex_key(px, pp, ps, o, nodes, e, key):
    """The key of pool point o of tet e: the background ids of its support's nodes, sorted and
    padded with -1, then the bits of the level sets that are zero there (the planes it lies on)."""
    c = 0
    for v in range(4):
        if (ps[o] >> v) & 1:
            g = nodes[e, v]
            p = c
            while p > 0 and key[p - 1] > g:  # insertion sort of at most four ids
                key[p] = key[p - 1]
                p -= 1
            key[p] = g
            c += 1
    for p in range(c, 4):
        key[p] = -1
    planes = 0
    for k in range(pp.shape[1]):
        if pp[o, k] == 0.0:
            planes |= 1 << k
    key[4] = planes


@njit(cache=True, error_model="numpy")
def _buffers(cap, mv, m):
    """A tet's scratch: the pool of points (8 cap): coordinates, values, supports; the sub-tets
    (cap) as pool points and codes, twice; the polygons (cap) as pool points (mv each), sizes and
    codes, twice."""
    return (np.empty((8 * cap, 3)), np.empty((8 * cap, m)), np.empty(8 * cap, dtype=np.int64),
            np.empty((cap, 4), dtype=np.int64), np.empty(cap, dtype=np.int64), np.empty((cap, 4), dtype=np.int64),
            np.empty(cap, dtype=np.int64), np.empty((cap, mv), dtype=np.int64), np.empty(cap, dtype=np.int64),
            np.empty(cap, dtype=np.int64), np.empty((cap, mv), dtype=np.int64), np.empty(cap, dtype=np.int64),
            np.empty(cap, dtype=np.int64))


@njit(cache=True, error_model="numpy")
def _slots(e, phi, mixed, nvert):
    """The sub-tets and triangles of clipped tet ``e`` crossed by one plane, from its signs: one tet
    and a prism (4), or two prisms (6); the polygon's triangles.  (-1, -1) for a tet crossed by more
    planes (few: near the edges of the domain), which is counted by clipping it."""
    p = 0
    k = 0
    for j in range(phi.shape[2]):
        if (mixed[e] >> j) & 1:
            p += 1
            k = j
    if p > 1:
        return -1, -1
    code = 0
    ni = 0
    for v in range(4):
        if phi[e, v, k] < 0.0:
            code |= 1 << v
            ni += 1
    return (6 if ni == 2 else 4), nvert[code] - 2


@njit(cache=True, error_model="numpy")
def _clip_range(lo, hi, x, phi, nodes, fixed, mixed, table, edge_i, edge_j, nvert, flip, write, sub_at, tri_at, sub_n, tri_n,
                whole, sub_x, sub_in, sub_tet, tri_x, tri_key, tri_part, tri_normal, tri_tet, split1, split2, split3):
    """The tets lo..hi-1 of :func:`_clip_chunks`, each clipped here (see :func:`clip_tets`): its
    sub-tets by each plane that changes sign in it, in increasing order; for each plane i that
    bounds the domain in it, its polygon (the marching tables, counterclockwise about grad phi_i)
    clipped by the other planes, the pieces where the domain changes across plane i fanned into
    triangles, counterclockwise about the outward normal.  The points live in one pool per tet
    (coordinates, values, supports), the sub-tets and polygons as rows of pool points; a tet that
    overflows the scratch is clipped again with four times more.  (The steps are written out in the
    loop: a call per tet with forty arrays took a third of the time.)"""
    m = phi.shape[2]
    cap = SCRATCH
    px, pp, ps, tv, tc, uv, uc, pv, pn, pc, qv, qn, qc = _buffers(cap, 4 + m, m)
    local, normal, key = np.empty(8, dtype=np.int64), np.empty(3), np.empty(KEY_WIDTH, dtype=np.int64)
    for e in range(lo, hi):
        if not write:
            if _constant_over(table, fixed[e], mixed[e]):  # the domain does not depend on the planes here
                whole[e] = 1 if table[fixed[e]] else 0
                sub_at[e], tri_at[e] = 0, 0
                continue
            whole[e] = -1
            sub_at[e], tri_at[e] = _slots(e, phi, mixed, nvert)
            if sub_at[e] >= 0:
                continue
        elif whole[e] >= 0:
            continue
        so, to = sub_at[e], tri_at[e]
        while True:
            ok = True
            room = px.shape[0]
            for v in range(4):  # the pool starts with the tet's nodes
                for d in range(3):
                    px[v, d] = x[e, v, d]
                for j in range(m):
                    pp[v, j] = phi[e, v, j]
                ps[v] = 1 << v
                tv[0, v] = v
            npool = 4
            tc[0] = fixed[e]
            n = 1
            flipped = False
            for k in range(m):
                if not (mixed[e] >> k) & 1:
                    continue
                if 6 * n > tv.shape[0] or npool + 4 * n > room:
                    ok = False
                    break
                nn = 0
                for s in range(n):
                    if flipped:
                        nn, npool = _split_tet(uv, uc, s, k, m, tv, tc, nn, px, pp, ps, npool, local, split1, split2, split3)
                    else:
                        nn, npool = _split_tet(tv, tc, s, k, m, uv, uc, nn, px, pp, ps, npool, local, split1, split2, split3)
                flipped = not flipped
                n = nn
            n_sub, n_tri = n, 0
            if ok and write:
                for s in range(n):
                    for v in range(4):
                        o = uv[s, v] if flipped else tv[s, v]
                        for d in range(3):
                            sub_x[so + s, v, d] = px[o, d]
                    sub_in[so + s] = table[uc[s] if flipped else tc[s]]
                    sub_tet[so + s] = e
            for i in range(m if ok else 0):
                bit = np.int64(1) << i
                if not (mixed[e] >> i) & 1 or not _bounds_part(table, fixed[e], mixed[e] & ~bit, bit):
                    continue
                code = 0
                for v in range(4):
                    if phi[e, v, i] < 0.0:
                        code |= 1 << v
                negative = _unit_gradient(x, phi, e, i, normal)
                count = nvert[code]
                reverse = flip[code] != negative  # counterclockwise about grad phi_i after this
                if npool + 4 > room:
                    ok = False
                    break
                for s in range(count):
                    o = _cross(px, pp, ps, edge_i[code, s], edge_j[code, s], i, m, npool)
                    npool += o == npool
                    pv[0, count - 1 - s if reverse else s] = o
                pn[0], pc[0] = count, fixed[e]
                npoly, npool = _clip_polygons(mixed[e] & ~bit, m, pv, pn, pc, qv, qn, qc, px, pp, ps, npool)
                if npoly < 0:
                    ok = False
                    break
                for q in range(npoly):
                    inside = table[pc[q] | bit]
                    if inside == table[pc[q] & ~bit]:
                        continue
                    for f in range(1, pn[q] - 1):  # a fan from the polygon's first vertex
                        if write:
                            t = to + n_tri
                            for c in range(3):
                                o = pv[q, 0 if c == 0 else (f + c - 1 if inside else f + 2 - c)]
                                for d in range(3):
                                    tri_x[t, c, d] = px[o, d]
                                _vertex_key(px, pp, ps, o, nodes, e, key)
                                for w in range(KEY_WIDTH):
                                    tri_key[t, c, w] = key[w]
                            sign = 1.0 if inside else -1.0
                            for d in range(3):
                                tri_normal[t, d] = sign * normal[d]
                            tri_part[t] = i
                            tri_tet[t] = e
                        n_tri += 1
            if ok:
                break
            cap *= 4  # a tet crossed by many planes: larger buffers, and the tet again
            px, pp, ps, tv, tc, uv, uc, pv, pn, pc, qv, qn, qc = _buffers(cap, 4 + m, m)
        if write:
            sub_n[e], tri_n[e] = n_sub, n_tri
        else:
            sub_at[e], tri_at[e] = n_sub, n_tri


@parallel_kernel
def _clip_chunks(x, phi, nodes, fixed, mixed, table, edge_i, edge_j, nvert, flip, bounds, write, sub_at, tri_at, sub_n, tri_n,
                 whole, sub_x, sub_in, sub_tet, tri_x, tri_key, tri_part, tri_normal, tri_tet, split1, split2, split3):
    """Two passes over chunks of tets.  ``write`` False: each tet's rows into (sub_at, tri_at), 0
    for a tet that the domain holds or misses whole (``whole``); True: each clipped tet written from
    its rows (sub_at, tri_at) on, its counts into (sub_n, tri_n)."""
    for c in prange(bounds.shape[0] - 1):
        _clip_range(bounds[c], bounds[c + 1], x, phi, nodes, fixed, mixed, table, edge_i, edge_j, nvert, flip, write, sub_at, tri_at,
                    sub_n, tri_n, whole, sub_x, sub_in, sub_tet, tri_x, tri_key, tri_part, tri_normal, tri_tet, split1, split2, split3)


@parallel_kernel
def tet_codes(counts, table, fixed, mixed, state):
    """Per background tet t, from ``counts`` (m, M) (how many of its nodes each level set has
    negative): the bits ``fixed`` of the level sets negative at all four nodes, the bits ``mixed``
    of those that change sign in it, and ``state`` 1 (the domain ``table`` holds it whole), 0 (misses
    it) or -1 (some level set changes sign in it: to be clipped).  One pass over the tets."""
    for t in prange(counts.shape[1]):
        f = 0
        x = 0
        for k in range(counts.shape[0]):
            c = counts[k, t]
            if c == 4:
                f |= 1 << k
            elif c > 0:
                x |= 1 << k
        fixed[t] = f
        mixed[t] = x
        state[t] = -1 if x else (1 if table[f] else 0)


def clip_tets(x, phi, nodes, fixed, mixed, table, edge_i, edge_j, nvert, flip, chunk: int):
    """The candidate tets (c of them: coordinates ``x`` (c, 4, 3), the m level sets' snapped values
    ``phi`` (c, 4, m), background node ids ``nodes`` (c, 4)) clipped by the planes of the level sets
    in the bits ``mixed`` (c,) (those that change sign in the tet; the bits ``fixed`` (c,): the
    level sets negative at all four nodes), for the domain ``table`` (2^m,) (bit k of a code:
    phi_k < 0), with the marching tables of :mod:`cutfem.geometry.marching`.

    Returns ``whole`` (c,) int8 (1: the domain does not depend on the planes there and holds the
    whole tet, 0: holds none of it, -1: clipped), the sub-tets of the clipped tets ``(sub_x (s, 4, 3),
    sub_in (s,) bool, sub_tet (s,))`` and their boundary triangles ``(tri_x (t, 3, 3), tri_key
    (t, 3, 5), tri_part (t,), tri_normal (t, 3), tri_tet (t,))``: counterclockwise about the outward
    normal grad phi_k / |grad phi_k| (or its negative where the domain lies on the side phi_k > 0) of
    their part k, in tet order.

    One clipping pass for most tets: the first pass counts each tet's rows, from its signs for a tet
    crossed by one plane (:func:`_slots`), by clipping it for the few crossed by more; the second
    clips each tet into its rows."""
    c = len(x)
    bounds = np.append(np.arange(0, c, chunk, dtype=np.int64), np.int64(c))
    args = (np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(phi, dtype=float), np.ascontiguousarray(nodes, dtype=np.int64),
            np.ascontiguousarray(fixed, dtype=np.int64), np.ascontiguousarray(mixed, dtype=np.int64),
            np.ascontiguousarray(table, dtype=np.bool_), np.ascontiguousarray(edge_i, dtype=np.int64),
            np.ascontiguousarray(edge_j, dtype=np.int64), np.ascontiguousarray(nvert, dtype=np.int64),
            np.ascontiguousarray(flip, dtype=np.bool_), bounds)
    tables = (_SPLIT_1, _SPLIT_2, _SPLIT_3)
    sub_rows, tri_rows = np.empty(c, dtype=np.int64), np.empty(c, dtype=np.int64)
    sub_n, tri_n = np.zeros(c, dtype=np.int64), np.zeros(c, dtype=np.int64)
    whole = np.empty(c, dtype=np.int8)
    _clip_chunks(*args, False, sub_rows, tri_rows, sub_n, tri_n, whole, np.empty((0, 4, 3)), np.empty(0, dtype=np.bool_),
                 np.empty(0, dtype=np.int64), np.empty((0, 3, 3)), np.empty((0, 3, KEY_WIDTH), dtype=np.int64),
                 np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty(0, dtype=np.int64), *tables)
    S, T = int(sub_rows.sum()), int(tri_rows.sum())
    sub_at, tri_at = np.cumsum(sub_rows) - sub_rows, np.cumsum(tri_rows) - tri_rows
    out = (np.empty((S, 4, 3)), np.empty(S, dtype=np.bool_), np.empty(S, dtype=np.int64), np.empty((T, 3, 3)),
           np.empty((T, 3, KEY_WIDTH), dtype=np.int64), np.empty(T, dtype=np.int64), np.empty((T, 3)), np.empty(T, dtype=np.int64))
    if S or T:
        _clip_chunks(*args, True, sub_at, tri_at, sub_n, tri_n, whole, *out, *tables)
    if not (np.array_equal(sub_n[whole < 0], sub_rows[whole < 0]) and np.array_equal(tri_n[whole < 0], tri_rows[whole < 0])):
        raise RuntimeError("clip_tets: the clipping wrote other rows than it counted")  # a broken invariant, not bad input
    return (whole, *out)


@parallel_kernel
def _triangle_chunks(points, values, table, bounds, write, start, out_x, out_source):
    m = values.shape[2]
    all_planes = (np.int64(1) << m) - 1
    for c in prange(bounds.shape[0] - 1):
        cap = SCRATCH
        px, pp, ps, _, _, _, _, pv, pn, pc, qv, qn, qc = _buffers(cap, 3 + m, m)
        o = start[c] if write else 0
        for t in range(bounds[c], bounds[c + 1]):
            while True:
                for v in range(3):
                    for d in range(3):
                        px[v, d] = points[t, v, d]
                    for j in range(m):
                        pp[v, j] = values[t, v, j]
                    ps[v] = 0
                    pv[0, v] = v
                pn[0], pc[0] = 3, 0
                npoly, _ = _clip_polygons(all_planes, m, pv, pn, pc, qv, qn, qc, px, pp, ps, 3)
                if npoly >= 0:
                    break
                cap *= 4
                px, pp, ps, _, _, _, _, pv, pn, pc, qv, qn, qc = _buffers(cap, 3 + m, m)
            for q in range(npoly):
                if not table[pc[q]]:
                    continue
                for f in range(1, pn[q] - 1):  # a fan from the first vertex: the order kept
                    if write:
                        for c3 in range(3):
                            p = pv[q, 0 if c3 == 0 else f + c3 - 1]
                            for d in range(3):
                                out_x[o, c3, d] = px[p, d]
                        out_source[o] = t
                    o += 1
        if not write:
            start[c] = o


def clip_triangles(points, values, table, chunk: int):
    """The triangles ``points`` (T, 3, 3) clipped by the planes of m linear functions given by their
    values at the vertices ``values`` (T, 3, m), keeping the pieces whose sign pattern (bit k:
    value k < 0; 0 counts as outside) is in the domain ``table`` (2^m,): ``(triangles (T', 3, 3),
    source triangle (T',))``, in triangle order, each piece in its triangle's orientation."""
    T = len(points)
    bounds = np.append(np.arange(0, T, chunk, dtype=np.int64), np.int64(T))
    args = (np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(values, dtype=float),
            np.ascontiguousarray(table, dtype=np.bool_), bounds)
    counts = np.zeros(len(bounds) - 1, dtype=np.int64)
    _triangle_chunks(*args, False, counts, np.empty((0, 3, 3)), np.empty(0, dtype=np.int64))
    start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    n = int(counts.sum())
    out_x, out_source = np.empty((n, 3, 3)), np.empty(n, dtype=np.int64)
    if n:
        _triangle_chunks(*args, True, start, out_x, out_source)
    return out_x, out_source
