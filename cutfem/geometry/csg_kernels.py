"""Compiled kernels of the cut by several level sets (:mod:`cutfem.geometry.csg_cut`): each tet
clipped by the planes of the P1 level sets that change sign in it, into sub-tetrahedra (each in the
domain or not) and the oriented pieces of the boundary parts, and the pieces of a boundary clipped
by further level sets (a part tagged by ``where``).

Clipping (docs/math.md §13).  A plane splits a tet into at most one tet and a prism (three tets) on
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

Kernels whose output size is not known count it chunk by chunk, then fill from each chunk's offset
on all cores (:data:`~cutfem.geometry.cut_kernels.COUNT_FILL_CHUNK`): the same arrays as one pass in
tet order.  The scratch of a chunk grows when a tet needs more (a tet crossed by many planes).
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
def _crossing(xa, pa, xb, pb, k, m, xo, po):
    """The point where plane k crosses the segment from a (phi_k < 0) to b (phi_k >= 0): its
    coordinates into ``xo`` (3,), the m level sets' values into ``po`` (m,).  Returns whether it is
    b itself (phi_k(b) = 0: then b is copied, bit for bit)."""
    if pb[k] == 0.0:
        xo[:] = xb
        po[:] = pb
        return True
    t = pa[k] / (pa[k] - pb[k])
    for d in range(3):
        xo[d] = xa[d] + t * (xb[d] - xa[d])
    for j in range(m):
        if j == k:
            po[j] = 0.0
        else:
            v = pa[j] + t * (pb[j] - pa[j])
            if abs(v) <= SNAP * max(abs(pa[j]), abs(pb[j])):
                v = 0.0
            po[j] = v
    return False


# the sub-tets of a split, as local points: 0..3 the tet's nodes (in the order a, b, c, d below),
# 4.. the crossing points; NEG pieces first.  One inside node a (points P_ab, P_ac, P_ad): one tet
# and a prism; three inside a, b, c (P_ad, P_bd, P_cd): a prism and one tet; two inside a, b
# (P_ac, P_ad, P_bc, P_bd): two prisms.  A prism (A0 A1 A2 | B0 B1 B2), lateral edges Ai Bi, is
# the tets (A0 A1 A2 B0), (A1 A2 B0 B1), (A2 B0 B1 B2).
_SPLIT_1 = np.array([[0, 4, 5, 6], [1, 2, 3, 4], [2, 3, 4, 5], [3, 4, 5, 6]], dtype=np.int64)
_SPLIT_3 = np.array([[0, 1, 2, 4], [1, 2, 4, 5], [2, 4, 5, 6], [3, 4, 5, 6]], dtype=np.int64)
_SPLIT_2 = np.array([[0, 4, 5, 1], [4, 5, 1, 6], [5, 1, 6, 7], [2, 4, 6, 3], [4, 6, 3, 5], [6, 3, 5, 7]], dtype=np.int64)


@njit(cache=True, error_model="numpy")
def _split_tet(cx, cp, cc, s, k, m, nx, np_, nc, n, lx, lp, order, split1, split2, split3):
    """Sub-tet ``s`` of the buffers (cx, cp, cc) split by plane k into the buffers (nx, np_, nc)
    from row ``n``: NEG pieces get bit k in their code.  Returns the new row count."""
    bit = np.int64(1) << k
    ni = 0
    for v in range(4):  # inside nodes first, then outside ones, each in local order
        if cp[s, v, k] < 0.0:
            order[ni] = v
            ni += 1
    no = ni
    for v in range(4):
        if not cp[s, v, k] < 0.0:
            order[no] = v
            no += 1
    if ni == 0 or ni == 4:
        nx[n] = cx[s]
        np_[n] = cp[s]
        nc[n] = cc[s] | (bit if ni == 4 else 0)
        return n + 1
    for v in range(4):
        lx[v] = cx[s, order[v]]
        lp[v] = cp[s, order[v]]
    if ni == 1:
        for q in range(3):
            _crossing(lx[0], lp[0], lx[1 + q], lp[1 + q], k, m, lx[4 + q], lp[4 + q])
        table, negs = split1, 1
    elif ni == 3:
        for q in range(3):
            _crossing(lx[q], lp[q], lx[3], lp[3], k, m, lx[4 + q], lp[4 + q])
        table, negs = split3, 3
    else:
        _crossing(lx[0], lp[0], lx[2], lp[2], k, m, lx[4], lp[4])
        _crossing(lx[0], lp[0], lx[3], lp[3], k, m, lx[5], lp[5])
        _crossing(lx[1], lp[1], lx[2], lp[2], k, m, lx[6], lp[6])
        _crossing(lx[1], lp[1], lx[3], lp[3], k, m, lx[7], lp[7])
        table, negs = split2, 3
    for r in range(table.shape[0]):
        for v in range(4):
            nx[n, v] = lx[table[r, v]]
            np_[n, v] = lp[table[r, v]]
        nc[n] = cc[s] | (bit if r < negs else 0)
        n += 1
    return n


@njit(cache=True, error_model="numpy")
def _split_polygon(q, j, m, cx, cp, cs, cn, cc, nx, np_, ns, nn, nc, n):
    """Polygon ``q`` of the buffers (c*) split by plane j into the buffers (n*) from row ``n``,
    each part in the polygon's cyclic order (Sutherland-Hodgman): the inside part (bit j in its
    code) first.  A crossing point's support is the union of its ends' (or the outside end's, when
    it is that end).  Returns the new row count."""
    bit = np.int64(1) << j
    nv = cn[q]
    ins = 0
    for v in range(nv):
        if cp[q, v, j] < 0.0:
            ins += 1
    if ins == 0 or ins == nv:
        nx[n] = cx[q]
        np_[n] = cp[q]
        ns[n] = cs[q]
        nn[n] = nv
        nc[n] = cc[q] | (bit if ins == nv else 0)
        return n + 1
    a_row, b_row = n, n + 1
    na = 0
    nb = 0
    for v in range(nv):
        w = (v + 1) % nv
        vin = cp[q, v, j] < 0.0
        win = cp[q, w, j] < 0.0
        row, at = (a_row, na) if vin else (b_row, nb)
        nx[row, at] = cx[q, v]
        np_[row, at] = cp[q, v]
        ns[row, at] = cs[q, v]
        if vin:
            na += 1
        else:
            nb += 1
        if vin != win:
            i, o = (v, w) if vin else (w, v)
            at_end = _crossing(cx[q, i], cp[q, i], cx[q, o], cp[q, o], j, m, nx[a_row, na], np_[a_row, na])
            ns[a_row, na] = cs[q, o] if at_end else cs[q, i] | cs[q, o]
            nx[b_row, nb] = nx[a_row, na]
            np_[b_row, nb] = np_[a_row, na]
            ns[b_row, nb] = ns[a_row, na]
            na += 1
            nb += 1
    nn[a_row], nc[a_row] = na, cc[q] | bit
    nn[b_row], nc[b_row] = nb, cc[q]
    return n + 2


@njit(cache=True, error_model="numpy")
def _polygon_buffers(cap, mv, m):
    """Two sets of polygon buffers: coordinates (cap, mv, 3), values (cap, mv, m), supports
    (cap, mv), vertex counts (cap,), codes (cap,)."""
    return (np.empty((cap, mv, 3)), np.empty((cap, mv, m)), np.zeros((cap, mv), dtype=np.int64), np.empty(cap, dtype=np.int64),
            np.empty(cap, dtype=np.int64), np.empty((cap, mv, 3)), np.empty((cap, mv, m)), np.zeros((cap, mv), dtype=np.int64),
            np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64))


@njit(cache=True, error_model="numpy")
def _clip_polygons(planes, m, px, pp, ps, pn, pc, qx, qp, qs, qn, qc):
    """The polygon in row 0 of (px, pp, ps, pn, pc) clipped by each plane of the bits ``planes``
    in increasing order; the pieces end in the first buffers (swapped back when needed).  Returns
    their number, or -1 when the buffers are too small."""
    npoly = 1
    flipped = False
    for j in range(m):
        if not (planes >> j) & 1:
            continue
        if 2 * npoly > px.shape[0]:
            return -1
        nq = 0
        for q in range(npoly):
            if flipped:
                nq = _split_polygon(q, j, m, qx, qp, qs, qn, qc, px, pp, ps, pn, pc, nq)
            else:
                nq = _split_polygon(q, j, m, px, pp, ps, pn, pc, qx, qp, qs, qn, qc, nq)
        flipped = not flipped
        npoly = nq
    if flipped:
        for q in range(npoly):
            px[q] = qx[q]
            pp[q] = qp[q]
            ps[q] = qs[q]
            pn[q] = qn[q]
            pc[q] = qc[q]
    return npoly


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _unit_gradient(x, phi, k, out):
    """grad phi_k / |grad phi_k| of the P1 interpolant on the tet x (4, 3) with values phi (4, m):
    g = sum_i d_i c_i / det, d_i = phi_k(x_i) - phi_k(x_0), c_i the cross products of the other two
    edges (Cramer's rule)."""
    e = np.empty((3, 3))
    for i in range(3):
        for d in range(3):
            e[i, d] = x[i + 1, d] - x[0, d]
    g = np.zeros(3)
    for i in range(3):
        a, b = e[(i + 1) % 3], e[(i + 2) % 3]
        c0, c1, c2 = a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]
        di = phi[i + 1, k] - phi[0, k]
        g[0] += di * c0
        g[1] += di * c1
        g[2] += di * c2
    det = e[0, 0] * (e[1, 1] * e[2, 2] - e[1, 2] * e[2, 1]) - e[0, 1] * (e[1, 0] * e[2, 2] - e[1, 2] * e[2, 0]) \
        + e[0, 2] * (e[1, 0] * e[2, 1] - e[1, 1] * e[2, 0])
    norm = np.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2)
    for d in range(3):
        out[d] = g[d] / norm * (1.0 if det > 0 else -1.0)
    return det < 0


@njit(cache=True, error_model="numpy")
def _volume(e, x, phi, fixed, mixed, m, table, write, so, sub_x, sub_in, sub_tet, tx, tp, tc, ux, up, uc, lx, lp, order,
            split1, split2, split3):
    """The sub-tets of tet ``e`` by each plane that changes sign in it, in increasing order, written
    (or counted) from row ``so``; -1 when the buffers are too small."""
    cap = tx.shape[0]
    tx[0] = x[e]
    tp[0] = phi[e]
    tc[0] = fixed[e]
    n = 1
    flipped = False
    for k in range(m):
        if not (mixed[e] >> k) & 1:
            continue
        if 6 * n > cap:
            return -1
        nn = 0
        for s in range(n):
            if flipped:
                nn = _split_tet(ux, up, uc, s, k, m, tx, tp, tc, nn, lx, lp, order, split1, split2, split3)
            else:
                nn = _split_tet(tx, tp, tc, s, k, m, ux, up, uc, nn, lx, lp, order, split1, split2, split3)
        flipped = not flipped
        n = nn
    if write:
        for s in range(n):
            sub_x[so + s] = ux[s] if flipped else tx[s]
            sub_in[so + s] = table[uc[s] if flipped else tc[s]]
            sub_tet[so + s] = e
    return n


@njit(cache=True, error_model="numpy")
def _boundary(e, x, phi, nodes, fixed, mixed, m, table, edge_i, edge_j, nvert, flip, write, to,
              tri_x, tri_key, tri_part, tri_normal, tri_tet, px, pp, ps, pn, pc, qx, qp, qs, qn, qc):
    """The boundary pieces of tet ``e``: for each plane i that bounds the domain here, its polygon
    (the marching tables; counterclockwise about grad phi_i) clipped by the other planes that change
    sign in the tet, the pieces where the domain changes across plane i fanned into triangles,
    counterclockwise about the outward normal.  Written (or counted) from row ``to``; -1 when the
    buffers are too small."""
    normal = np.empty(3)
    key = np.empty(KEY_WIDTH, dtype=np.int64)
    n_tri = 0
    for i in range(m):
        bit = np.int64(1) << i
        if not (mixed[e] >> i) & 1 or not _bounds_part(table, fixed[e], mixed[e] & ~bit, bit):
            continue
        code = 0
        for v in range(4):
            if phi[e, v, i] < 0.0:
                code |= 1 << v
        negative = _unit_gradient(x[e], phi[e], i, normal)
        nv = nvert[code]
        reverse = flip[code] != negative
        for s in range(nv):
            a, b = edge_i[code, s], edge_j[code, s]
            r = nv - 1 - s if reverse else s
            at_end = _crossing(x[e, a], phi[e, a], x[e, b], phi[e, b], i, m, px[0, r], pp[0, r])
            ps[0, r] = (1 << b) if at_end else (1 << a) | (1 << b)
        pn[0], pc[0] = nv, fixed[e]
        npoly = _clip_polygons(mixed[e] & ~bit, m, px, pp, ps, pn, pc, qx, qp, qs, qn, qc)
        if npoly < 0:
            return -1
        for q in range(npoly):
            inside = table[pc[q] | bit]
            if inside == table[pc[q] & ~bit]:
                continue
            for f in range(1, pn[q] - 1):  # a fan from the polygon's first vertex
                if write:
                    t = to + n_tri
                    for c in range(3):
                        v = 0 if c == 0 else (f + c - 1 if inside else f + 2 - c)
                        tri_x[t, c] = px[q, v]
                        _vertex_key(ps[q, v], pp[q, v], nodes[e], key)
                        tri_key[t, c] = key
                    sign = 1.0 if inside else -1.0
                    for d in range(3):
                        tri_normal[t, d] = sign * normal[d]
                    tri_part[t] = i
                    tri_tet[t] = e
                n_tri += 1
    return n_tri


@njit(cache=True, error_model="numpy", inline="always")
def _vertex_key(support, values, nodes, key):
    """The key of a vertex: the background ids of its support's nodes, sorted and padded with -1,
    then the bits of the level sets that are zero there (the planes it lies on)."""
    c = 0
    for v in range(4):
        if (support >> v) & 1:
            g = nodes[v]
            p = c
            while p > 0 and key[p - 1] > g:  # insertion sort of at most four ids
                key[p] = key[p - 1]
                p -= 1
            key[p] = g
            c += 1
    for p in range(c, 4):
        key[p] = -1
    planes = 0
    for k in range(values.shape[0]):
        if values[k] == 0.0:
            planes |= 1 << k
    key[4] = planes


@parallel_kernel
def _clip_chunks(x, phi, nodes, fixed, mixed, table, edge_i, edge_j, nvert, flip, bounds, write, sub_start, tri_start,
                 whole, sub_x, sub_in, sub_tet, tri_x, tri_key, tri_part, tri_normal, tri_tet, split1, split2, split3):
    m = phi.shape[2]
    for c in prange(bounds.shape[0] - 1):
        cap = SCRATCH
        so = sub_start[c] if write else 0
        to = tri_start[c] if write else 0
        tx, ux = np.empty((cap, 4, 3)), np.empty((cap, 4, 3))
        tp, up = np.empty((cap, 4, m)), np.empty((cap, 4, m))
        tc, uc = np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64)
        px, pp, ps, pn, pc, qx, qp, qs, qn, qc = _polygon_buffers(cap, 4 + m, m)
        lx, lp, order = np.empty((8, 3)), np.empty((8, m)), np.empty(4, dtype=np.int64)
        for e in range(bounds[c], bounds[c + 1]):
            if _constant_over(table, fixed[e], mixed[e]):  # the domain does not depend on the planes here
                whole[e] = 1 if table[fixed[e]] else 0
                continue
            whole[e] = -1
            while True:
                ns = _volume(e, x, phi, fixed, mixed, m, table, write, so, sub_x, sub_in, sub_tet, tx, tp, tc, ux, up, uc,
                             lx, lp, order, split1, split2, split3)
                nt = -1 if ns < 0 else _boundary(e, x, phi, nodes, fixed, mixed, m, table, edge_i, edge_j, nvert, flip, write,
                                                 to, tri_x, tri_key, tri_part, tri_normal, tri_tet, px, pp, ps, pn, pc, qx, qp,
                                                 qs, qn, qc)
                if nt >= 0:
                    break
                cap *= 4  # a tet crossed by many planes: larger buffers, and the tet again
                tx, ux = np.empty((cap, 4, 3)), np.empty((cap, 4, 3))
                tp, up = np.empty((cap, 4, m)), np.empty((cap, 4, m))
                tc, uc = np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64)
                px, pp, ps, pn, pc, qx, qp, qs, qn, qc = _polygon_buffers(cap, 4 + m, m)
            so += ns
            to += nt
        if not write:
            sub_start[c] = so
            tri_start[c] = to


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
    their part k, in tet order."""
    c = len(x)
    bounds = np.append(np.arange(0, c, chunk, dtype=np.int64), np.int64(c))
    nch = len(bounds) - 1
    args = (np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(phi, dtype=float), np.ascontiguousarray(nodes, dtype=np.int64),
            np.ascontiguousarray(fixed, dtype=np.int64), np.ascontiguousarray(mixed, dtype=np.int64),
            np.ascontiguousarray(table, dtype=np.bool_), np.ascontiguousarray(edge_i, dtype=np.int64),
            np.ascontiguousarray(edge_j, dtype=np.int64), np.ascontiguousarray(nvert, dtype=np.int64),
            np.ascontiguousarray(flip, dtype=np.bool_), bounds)
    tables = (_SPLIT_1, _SPLIT_2, _SPLIT_3)
    sub_count, tri_count = np.zeros(nch, dtype=np.int64), np.zeros(nch, dtype=np.int64)
    whole = np.empty(c, dtype=np.int8)
    _clip_chunks(*args, False, sub_count, tri_count, whole, np.empty((0, 4, 3)), np.empty(0, dtype=np.bool_),
                 np.empty(0, dtype=np.int64), np.empty((0, 3, 3)), np.empty((0, 3, KEY_WIDTH), dtype=np.int64),
                 np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty(0, dtype=np.int64), *tables)
    sub_start = np.concatenate([[0], np.cumsum(sub_count)[:-1]]).astype(np.int64)
    tri_start = np.concatenate([[0], np.cumsum(tri_count)[:-1]]).astype(np.int64)
    S, T = int(sub_count.sum()), int(tri_count.sum())
    out = (np.empty((S, 4, 3)), np.empty(S, dtype=np.bool_), np.empty(S, dtype=np.int64), np.empty((T, 3, 3)),
           np.empty((T, 3, KEY_WIDTH), dtype=np.int64), np.empty(T, dtype=np.int64), np.empty((T, 3)), np.empty(T, dtype=np.int64))
    if S or T:
        _clip_chunks(*args, True, sub_start, tri_start, whole, *out, *tables)
    return (whole, *out)


@parallel_kernel
def _triangle_chunks(points, values, table, bounds, write, start, out_x, out_source):
    m = values.shape[2]
    all_planes = (np.int64(1) << m) - 1
    for c in prange(bounds.shape[0] - 1):
        cap = SCRATCH
        o = start[c] if write else 0
        px, pp, ps, pn, pc, qx, qp, qs, qn, qc = _polygon_buffers(cap, 3 + m, m)
        for t in range(bounds[c], bounds[c + 1]):
            while True:
                for v in range(3):
                    px[0, v] = points[t, v]
                    pp[0, v] = values[t, v]
                pn[0], pc[0] = 3, 0
                npoly = _clip_polygons(all_planes, m, px, pp, ps, pn, pc, qx, qp, qs, qn, qc)
                if npoly >= 0:
                    break
                cap *= 4
                px, pp, ps, pn, pc, qx, qp, qs, qn, qc = _polygon_buffers(cap, 3 + m, m)
            for q in range(npoly):
                if not table[pc[q]]:
                    continue
                for f in range(1, pn[q] - 1):  # a fan from the first vertex: the order kept
                    if write:
                        out_x[o, 0] = px[q, 0]
                        out_x[o, 1] = px[q, f]
                        out_x[o, 2] = px[q, f + 1]
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
