"""Compiled kernels of the assembly: lattice sums and the symmetric patterns.

On a structured box the nodes of two tets that share a face differ by one of 13 lattice vectors, so
a symmetric matrix from tets and faces has at most 13 entries right of the diagonal in a row.  The
``lattice_add_*`` kernels add element matrices, Gram rows, surface pieces and face jumps, each times
a scale, into 13 slots a node (the pair (a, b), a < b, goes to slot 13 a + the rank of b - a), and
:func:`lattice_csr` writes CSR arrays from the slots on all cores at positions the slots fix: no
sort, no sparse product, exactly symmetric (:class:`cutfem.fem.assembly.LatticeSum`).  A vector
field's coupled terms (elasticity) add 3 x 3 blocks per slot (:func:`lattice_add_blocks`), written
with the scalar slots by :func:`vector_lattice_csr` (:class:`cutfem.fem.assembly.VectorSum`).  A meshed
surface's matrices share one :func:`symmetric_pattern`, built by a counting sort of the node pairs.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..geometry.mesh_kernels import _face_normal_area, _popcount, _rows_sorted
from ..geometry.numbering import TET_EDGES, index_dtype
from ..jit import SWEEP_CHUNKS, parallel_kernel
from .element_kernels import _barycentric

@njit(cache=True, error_model="numpy")
def _slot(ids, code, a, b):
    """The slot of the pair a < b, or -1 when their node ids differ by no lattice offset
    (``code`` (d_max + 1,) int8: the rank of each node-id difference d among the offsets, or -1)."""
    d = ids[b] - ids[a]
    if d >= code.shape[0]:
        return -1
    c = code[d]
    return -1 if c < 0 else a * 13 + c


@njit(cache=True, error_model="numpy", inline="always")
def _add_pair(ids, code, a, b, value, sums, partner):
    """Add ``value`` at the slot of the pair {a, b}; returns 1 when the pair is outside the lattice
    offsets (nothing added), else 0."""
    if a > b:
        a, b = b, a
    s = _slot(ids, code, a, b)
    if s < 0:
        return 1
    sums[s] += value
    partner[s] = b
    return 0


@parallel_kernel
def lattice_add_elements(ids, code, dofs, elements, edges, diagonal, types, weights, scale, sums, partner, diag, bounds):
    """Add ``scale`` times symmetric 4 x 4 element matrices into the slots: for each element k
    (``elements`` (n,), or every row of ``dofs`` (m, 4) when empty) the matrix with entries
    ``weights[k] edges[r]`` on the local edges and ``weights[k] diagonal[r]`` on the diagonal
    (tables ``edges`` (L, 6), ``diagonal`` (L, 4)), r = ``types[k]``, or r = 0 for a one-row table
    and r = k otherwise when ``types`` is empty; ``weights`` empty: 1.  Returns the number of pairs
    outside the lattice offsets (then the caller must not use the sums).  The elements in the
    chunks ``bounds`` of :func:`scatter_chunks`: the even chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            outside += _add_elements(ids, code, dofs, elements, edges, diagonal, types, weights, scale, sums, partner,
                                     diag, bounds[ch], bounds[ch + 1])
    return outside


@njit(cache=True, error_model="numpy")
def _add_elements(ids, code, dofs, elements, edges, diagonal, types, weights, scale, sums, partner, diag, start, stop):
    outside = 0
    for t in range(start, stop):
        k = elements[t] if elements.shape[0] > 0 else t
        r = types[k] if types.shape[0] > 0 else (0 if edges.shape[0] == 1 else k)
        w = scale * weights[k] if weights.shape[0] > 0 else scale
        for e in range(6):
            outside += _add_pair(ids, code, dofs[k, TET_EDGES[e, 0]], dofs[k, TET_EDGES[e, 1]], w * edges[r, e], sums,
                                 partner)
        for i in range(4):
            diag[dofs[k, i]] += w * diagonal[r, i]
    return outside


@parallel_kernel
def lattice_add_pieces(ids, code, vertices, triangles, tets_of, areas, points, tets, table, types, dofs, scale, sums,
                       partner, diag, bounds):
    """Add ``scale`` times the exact P1 mass matrices of the triangles ``triangles`` (T, 3) into
    ``vertices``, of areas ``areas``, lying in the tets ``tets_of`` (T,) (vertex ids ``tets`` into
    ``points``, basis gradients ``table[types[k]]``, dofs ``dofs`` (m, 4)) into the slots, triangle
    by triangle: int_T lambda_i lambda_j = |T| / 12 (sum_v lambda_vi lambda_vj + s_i s_j) as in
    :func:`piece_moments`, without its per-tet arrays; returns the number of pairs outside the
    lattice offsets.  The triangles in the chunks ``bounds`` of :func:`scatter_chunks`: the even
    chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            outside += _add_pieces(ids, code, vertices, triangles, tets_of, areas, points, tets, table, types, dofs, scale,
                                   sums, partner, diag, bounds[ch], bounds[ch + 1])
    return outside


@njit(cache=True, error_model="numpy")
def _add_pieces(ids, code, vertices, triangles, tets_of, areas, points, tets, table, types, dofs, scale, sums, partner,
                diag, start, stop):
    lam = np.empty((3, 4))
    outside = 0
    for t in range(start, stop):
        k = tets_of[t]
        g = table[types[k]]
        for v in range(3):
            _barycentric(vertices[triangles[t, v]], points, tets, g, k, lam[v])
        w = scale * areas[t] / 12.0
        for i in range(4):
            si = lam[0, i] + lam[1, i] + lam[2, i]
            diag[dofs[k, i]] += w * (lam[0, i] * lam[0, i] + lam[1, i] * lam[1, i] + lam[2, i] * lam[2, i] + si * si)
        for e in range(6):
            i, j = TET_EDGES[e, 0], TET_EDGES[e, 1]
            si = lam[0, i] + lam[1, i] + lam[2, i]
            sj = lam[0, j] + lam[1, j] + lam[2, j]
            value = w * (lam[0, i] * lam[0, j] + lam[1, i] * lam[1, j] + lam[2, i] * lam[2, j] + si * sj)
            outside += _add_pair(ids, code, dofs[k, i], dofs[k, j], value, sums, partner)
    return outside


@njit(cache=True, error_model="numpy")
def _add_gram_row(ids, code, row_dofs, row_values, u, v, scale, sums, partner, diag):
    """Add scale c c^T for one row c (``row_values`` on ``row_dofs``), its repeated dofs merged first (a
    face row has 8 entries on 5 nodes: 10 pairs instead of 28), ``u``, ``v`` scratch of the row's
    length; returns the number of pairs outside the lattice offsets."""
    nu = 0
    for p in range(row_dofs.shape[0]):
        a = row_dofs[p]
        for q in range(nu + 1):
            if q == nu:
                u[nu] = a
                v[nu] = row_values[p]
                nu += 1
            elif u[q] == a:
                v[q] += row_values[p]
                break
    outside = 0
    for p in range(nu):
        a, vp = u[p], v[p]
        diag[a] += scale * (vp * vp)
        for q in range(p + 1, nu):
            outside += _add_pair(ids, code, a, u[q], scale * (vp * v[q]), sums, partner)
    return outside


@parallel_kernel
def lattice_add_rows(ids, code, dofs, values, scale, sums, partner, diag, bounds):
    """Add ``scale`` times the Gram matrix sum_r c_r c_r^T of rows c_r (``values`` (r, k) on ``dofs`` (r, k); a dof
    repeated in a row counts with the sum of its values) into the slots; returns the number of
    pairs outside the lattice offsets.  The rows in the chunks ``bounds`` of
    :func:`scatter_chunks`: the even chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            u = np.empty(dofs.shape[1], dtype=dofs.dtype)
            v = np.empty(dofs.shape[1])
            for r in range(bounds[ch], bounds[ch + 1]):
                outside += _add_gram_row(ids, code, dofs[r], values[r], u, v, scale, sums, partner, diag)
    return outside


@parallel_kernel
def lattice_add_face_jumps(ids, code, pairs, opposite, factors, volumes, dofs, table, types, scale, sums, partner, diag,
                           bounds):
    """Add ``scale`` times sum_F c_F c_F^T into the slots, c_F the jump row of the face F between the
    tets ``pairs[F]`` (K_a, K_b) (dofs ``dofs`` (m, 4), gradients ``table[types[K]]``):
    c_F = sqrt(w_F) (n . G_{K_a}, -n . G_{K_b}), n the unit normal out of K_a, w_F = |F| times
    ``factors[F]`` (or ``factors[0]`` for all faces when it has one entry), on the five nodes of the
    two tets: those of K_a, then the vertex ``opposite[F, 1]`` of K_b, each shared node with the sum
    of its two values (as :func:`lattice_add_rows` merges them).  n and |F| come from the vertex
    k = ``opposite[F, 0]`` of K_a: n = -g / |g| and |F| = 3 |K_a| |g|, g = grad lambda_k
    (|K| = |F| height / 3, |g| = 1 / height; volumes ``volumes``).

    One face at a time in scalars: no normals, areas or rows stored (the normals and areas alone
    took 32 bytes a face, 0.7 GB for the 22 million interior faces of the cut torus at spacing
    0.003125), and the five nodes known from the opposite vertices instead of merged by search:
    5.7 million faces at spacing 0.00625 in 0.78-0.81 s against 1.29-1.40 s for the generic rows of
    :func:`jump_rows` merged and added by :func:`lattice_add_rows`'s loop (the same sums, bitwise).
    Returns the number of pairs outside the lattice offsets.  The faces in the chunks ``bounds``
    of :func:`scatter_chunks`: the even chunks at once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            outside += _add_face_jumps(ids, code, pairs, opposite, factors, volumes, dofs, table, types, scale, sums,
                                       partner, diag, bounds[ch], bounds[ch + 1])
    return outside


@njit(cache=True, error_model="numpy")
def _add_face_jumps(ids, code, pairs, opposite, factors, volumes, dofs, table, types, scale, sums, partner, diag, start,
                    stop):
    u = np.empty(5, dtype=dofs.dtype)
    v = np.empty(5)
    one = factors.shape[0] == 1
    outside = 0
    for f in range(start, stop):
        ea, eb = pairs[f, 0], pairs[f, 1]
        oa, ob = opposite[f, 0], opposite[f, 1]
        ta, tb = types[ea], types[eb]
        nx, ny, nz, area = _face_normal_area(table, ta, oa, volumes[ea])
        w = np.sqrt(area * factors[0 if one else f])
        for i in range(4):
            u[i] = dofs[ea, i]
            v[i] = w * (table[ta, i, 0] * nx + table[ta, i, 1] * ny + table[ta, i, 2] * nz)
        for j in range(4):
            d = dofs[eb, j]
            vb = -w * (table[tb, j, 0] * nx + table[tb, j, 1] * ny + table[tb, j, 2] * nz)
            if j == ob:
                u[4], v[4] = d, vb
            else:
                for i in range(4):
                    if u[i] == d:
                        v[i] += vb
                        break
        for p in range(5):
            a, vp = u[p], v[p]
            diag[a] += scale * (vp * vp)
            for q in range(p + 1, 5):
                outside += _add_pair(ids, code, a, u[q], scale * (vp * v[q]), sums, partner)
    return outside


@parallel_kernel
def _incoming_offsets(sums, partner, bounds, parity, incoming):
    """incoming[b] |= 1 << c for every nonzero slot (a, c) of the rows a of the chunks of ``bounds``
    with the given ``parity`` (their targets b lie in their own chunk or the next)."""
    S = 13
    for k in prange((bounds.shape[0] - parity) // 2):
        ch = 2 * k + parity
        for a in range(bounds[ch], bounds[ch + 1]):
            for c in range(S):
                if sums[a * S + c] != 0.0:
                    b = partner[a * S + c]
                    incoming[b] |= np.uint16(1 << c)


@parallel_kernel
def _lattice_fill(sums, partner, diag, incoming, indptr, indices, data):
    """Row a of the CSR arrays of :func:`lattice_csr` (diagonal and upper slots) and the mirrors of
    its slots, each at its own position: in row b the mirror of slot (a, c) comes after those of
    the slots with a larger offset rank c' (a smaller a'), the bits of ``incoming[b]`` above c."""
    n = diag.shape[0]
    S = 13
    for a in prange(n):
        pos = indptr[a] + _popcount(np.uint64(incoming[a]))
        indices[pos] = a
        data[pos] = diag[a]
        pos += 1
        for c in range(S):
            v = sums[a * S + c]
            if v != 0.0:
                b = partner[a * S + c]
                indices[pos] = b
                data[pos] = v
                pos += 1
                m = indptr[b] + _popcount(np.uint64(incoming[b]) >> np.uint64(c + 1))
                indices[m] = a
                data[m] = v


def lattice_csr(sums, partner, diag, indptr, indices, data):
    """The CSR arrays of the symmetric matrix held by the slots (``indptr`` (n + 1,) filled here,
    ``indices`` and ``data`` of length ``indptr[n]``, see :func:`lattice_nnz`): in row a the
    mirrors (a, c) of the slots (c, a), c < a, in increasing c, the diagonal, then the slots of a
    in increasing partner.  Slots whose sum is exactly zero are left out.

    On the available cores: a 13-bit mask per row of the slots that point at it
    (:func:`_lattice_pattern`), the row pointers from the masks' bit counts, then every row and the
    mirrors of its slots, each entry at a position fixed by the masks: the same arrays as one pass
    in row order, which took 1.2 s at spacing 0.003125 (4.7 million rows)."""
    incoming, lengths = _lattice_pattern(sums, partner, diag.shape[0])
    indptr[0] = 0
    np.cumsum(lengths, out=indptr[1:])
    _lattice_fill(sums, partner, diag, incoming, indptr, indices, data)


def _lattice_pattern(present, partner, n):
    """(incoming masks (n,), row lengths (n,)) of the slots with ``present`` != 0: the bits of the
    slots that point at each row, found by chunks of rows whose targets stay in the chunk or the
    next (even chunks at once, then odd; else one chunk), and each row's mirrors, diagonal and
    slots."""
    incoming = np.zeros(n, dtype=np.uint16)
    bounds = np.array([0, n], dtype=np.int64)
    for k in SWEEP_CHUNKS:
        if n < 64 * k:
            break
        cand = (np.arange(k + 1, dtype=np.int64) * n) // k
        last = _chunk_reach(partner, present, cand)
        if np.all(last[:-2] < cand[2:-1]):  # targets of chunk i stay below chunk i + 2
            bounds = cand
            break
    for parity in (0, 1):
        _incoming_offsets(present, partner, bounds, parity, incoming)
    return incoming, _row_lengths(present, incoming)


def vector_lattice_csr(sums, bsums, partner, diag, bdiag, n, index):
    """(indptr, indices, data) of the symmetric 3 n x 3 n matrix of a vector field, numbered
    component-major, held by scalar slots (``sums``, ``diag``: the terms acting component by
    component, I_3 times them) and 3 x 3 blocks per slot (``bsums`` (13 n * 9,), ``bdiag``
    (9 n,): block (l, k) of the pair (a, b) of slot s at 9 s + 3 l + k, K[(l, a), (k, b)]).  Row
    (l, a) holds, for k = 0, 1, 2, the columns k n + those of scalar row a (mirrors, diagonal,
    slots, as :func:`lattice_csr`); a slot is present when its scalar sum or any of its block
    entries is nonzero (its other entries are then stored, zeros included).  ``index``: the dtype
    of the index arrays."""
    present = _present_slots(sums, bsums)
    incoming, lengths = _lattice_pattern(present, partner, n)
    indptr = np.zeros(3 * n + 1, dtype=index)
    np.cumsum(np.tile(3 * lengths, 3), out=indptr[1:])
    nnz = int(indptr[-1])
    indices, data = np.empty(nnz, dtype=index), np.empty(nnz)
    _vector_lattice_fill(present, sums, bsums, partner, diag, bdiag, incoming, lengths, indptr, indices, data)
    return indptr, indices, data


@parallel_kernel
def _present_slots(sums, bsums):
    """1.0 for the slots with a nonzero scalar sum or block entry, else 0.0."""
    out = np.empty(sums.shape[0])
    for s in prange(sums.shape[0]):
        v = sums[s] != 0.0
        for e in range(9):
            v = v or bsums[9 * s + e] != 0.0
        out[s] = 1.0 if v else 0.0
    return out


@parallel_kernel
def _vector_lattice_fill(present, sums, bsums, partner, diag, bdiag, incoming, lengths, indptr, indices, data):
    """The rows (l, a) of :func:`vector_lattice_csr` and the mirrors of their slots, each entry at
    the position the masks fix (as :func:`_lattice_fill`, in each of the three column segments)."""
    n = diag.shape[0]
    S = 13
    for a in prange(n):
        L = lengths[a]
        p0 = _popcount(np.uint64(incoming[a]))
        for l in range(3):
            for k in range(3):
                pos = indptr[l * n + a] + k * L + p0
                indices[pos] = k * n + a
                data[pos] = (diag[a] if l == k else 0.0) + bdiag[9 * a + 3 * l + k]
                pos += 1
                for c in range(S):
                    s = a * S + c
                    if present[s] != 0.0:
                        b = partner[s]
                        v = (sums[s] if l == k else 0.0) + bsums[9 * s + 3 * l + k]
                        indices[pos] = k * n + b
                        data[pos] = v
                        pos += 1
                        m = indptr[k * n + b] + l * lengths[b] + _popcount(np.uint64(incoming[b]) >> np.uint64(c + 1))
                        indices[m] = l * n + a
                        data[m] = v


@parallel_kernel
def lattice_add_blocks(ids, code, dofs, blocks, types, weights, scale, partner, bsums, bdiag, bounds):
    """Add ``scale`` times symmetric 12 x 12 element matrices of a vector field into 3 x 3 blocks of
    the slots: element t (a row of ``dofs`` (m, 4)) adds ``weights[t] blocks[r]`` (``blocks``
    (L, 4, 4, 3, 3): K[(l, node i), (k, node j)] at [r, i, j, l, k]), r = ``types[t]``, or r = t when
    ``types`` is empty; ``weights`` empty: 1.  Returns the number of pairs outside the lattice
    offsets.  The elements in the chunks ``bounds`` of :func:`scatter_chunks`: the even chunks at
    once, then the odd ones."""
    outside = 0
    nch = bounds.shape[0] - 1
    for color in range(2):
        for h in prange((nch - color + 1) // 2):
            ch = 2 * h + color
            outside += _add_block_elements(ids, code, dofs, blocks, types, weights, scale, partner, bsums, bdiag, bounds[ch],
                                   bounds[ch + 1])
    return outside


@njit(cache=True, error_model="numpy")
def _add_block_elements(ids, code, dofs, blocks, types, weights, scale, partner, bsums, bdiag, start, stop):
    outside = 0
    for t in range(start, stop):
        r = types[t] if types.shape[0] > 0 else t
        w = scale * weights[t] if weights.shape[0] > 0 else scale
        for e in range(6):
            i, j = TET_EDGES[e, 0], TET_EDGES[e, 1]
            a, b = dofs[t, i], dofs[t, j]
            if a > b:
                a, b, i, j = b, a, j, i
            s = _slot(ids, code, a, b)
            if s < 0:
                outside += 1
                continue
            partner[s] = b
            for l in range(3):
                for k in range(3):
                    bsums[9 * s + 3 * l + k] += w * blocks[r, i, j, l, k]
        for i in range(4):
            a = dofs[t, i]
            for l in range(3):
                for k in range(3):
                    bdiag[9 * a + 3 * l + k] += w * blocks[r, i, i, l, k]
    return outside


@parallel_kernel
def _chunk_reach(partner, sums, bounds):
    """The largest target of a nonzero slot of each chunk of rows (its first row if none)."""
    S = 13
    out = np.empty(bounds.shape[0] - 1, dtype=np.int64)
    for ch in prange(bounds.shape[0] - 1):
        top = bounds[ch]
        for a in range(bounds[ch], bounds[ch + 1]):
            for c in range(S):
                if sums[a * S + c] != 0.0 and partner[a * S + c] > top:
                    top = partner[a * S + c]
        out[ch] = top
    return out


@parallel_kernel
def _row_lengths(sums, incoming):
    """Entries of each row of :func:`lattice_csr`: the mirrors (bits of ``incoming``), the
    diagonal and the nonzero slots."""
    S = 13
    out = np.empty(incoming.shape[0], dtype=np.int64)
    for b in prange(incoming.shape[0]):
        k = _popcount(np.uint64(incoming[b])) + 1
        for c in range(S):
            if sums[b * S + c] != 0.0:
                k += 1
        out[b] = k
    return out


@njit(cache=True, error_model="numpy")
def lattice_nnz(sums, n):
    """Stored entries of the matrix of :func:`lattice_csr`: n + 2 (nonzero slots)."""
    nz = 0
    for s in range(sums.shape[0]):
        if sums[s] != 0.0:
            nz += 1
    return n + 2 * nz


@njit(cache=True, error_model="numpy")
def scatter_add(dofs, local, out):
    """out[dofs[e, a], l] += local[e, a, l] for the elements e (m, k), in element order."""
    for e in range(dofs.shape[0]):
        for a in range(dofs.shape[1]):
            i = dofs[e, a]
            for l in range(out.shape[1]):
                out[i, l] += local[e, a, l]


@njit(cache=True, error_model="numpy")
def symmetric_data(diagonal_position, upper, lower, slot, diagonal, values, nnz):
    """The CSR values of :meth:`cutfem.fem.assembly.SymmetricPattern.matrix`: ``diagonal`` at
    ``diagonal_position``, and the value of each given pair k added at the positions of its
    distinct pair ``slot[k]`` (k itself when ``slot`` is empty), in the upper triangle and its
    mirror (repeated pairs summed in the order given).  One pass, where numpy summed the repeats by
    ``bincount`` and scattered three times."""
    data = np.zeros(nnz)
    for i in range(diagonal.shape[0]):
        data[diagonal_position[i]] = diagonal[i]
    for k in range(values.shape[0]):
        u = slot[k] if slot.shape[0] else k
        data[upper[u]] += values[k]
    for u in range(upper.shape[0]):
        data[lower[u]] = data[upper[u]]
    return data


@njit(cache=True, error_model="numpy")
def symmetric_pattern(pairs, n, presorted, like):
    """The CSR structure of a symmetric n x n matrix with its full diagonal and the undirected pairs
    {a_k, b_k} = ``pairs[k]`` (a_k != b_k, both in [0, n)), for :class:`cutfem.fem.assembly.SymmetricPattern`.

    The pairs (lo, hi) = (min, max) are put in lexicographic order by a stable counting sort on lo
    and an insertion sort on hi within each lo (rows of a surface mesh hold a handful of pairs), and
    repeated pairs become one; ``presorted`` promises they are unique and in that order already
    (then nothing is sorted).  Row i holds, in increasing column order, the mirrors (i, lo) of the
    pairs (lo, i), the diagonal, then the pairs (i, hi).  Returns (indptr (n + 1,), indices,
    diagonal (n,), upper (p,), lower (p,), slot (m,)): the positions in ``indices`` of the diagonal,
    of each distinct pair (lo, hi) and of its mirror (hi, lo), the pairs in lexicographic order; and
    the distinct pair of each given pair (empty when ``presorted``), so that the values of repeated
    pairs sum in the order given; and first ``(k, why)``: -1 when the pairs are valid, else the
    first invalid pair k and why (0: a_k == b_k, 1: outside [0, n)), with empty arrays.  Every
    array has the integer type of the empty array ``like``, which must hold n + 2 m (a fresh array
    is a first touch of its pages: int32 halves them); the pairs are checked before they are
    narrowed to it."""
    m = pairs.shape[0]
    dt = like.dtype
    lo, hi = np.empty(m, dt), np.empty(m, dt)
    for k in range(m):
        a, b = pairs[k, 0], pairs[k, 1]
        if a == b or min(a, b) < 0 or max(a, b) >= n:
            e = np.empty(0, dt)
            return k, 0 if a == b else 1, e, e, e, e, e, e
        lo[k], hi[k] = min(a, b), max(a, b)
    if presorted:
        slot = np.empty(0, dt)
        ulo, uhi, p = lo, hi, m
    else:
        order = np.empty(m, dt)
        start = _rows_sorted(lo, hi, n, order)  # stable: equal pairs in the order given
        slot = np.empty(m, dt)
        ulo = np.empty(m, dt)
        uhi = np.empty(m, dt)
        p = 0
        for i in range(n):
            s, e = start[i], start[i + 1]
            for t in range(s, e):
                k = order[t]
                if t == s or hi[k] != uhi[p - 1]:
                    ulo[p], uhi[p] = i, hi[k]
                    p += 1
                slot[k] = p - 1
    n_upper = np.zeros(n, dt)
    n_lower = np.zeros(n, dt)
    for u in range(p):
        n_upper[ulo[u]] += 1
        n_lower[uhi[u]] += 1
    indptr = np.empty(n + 1, dt)
    diagonal = np.empty(n, dt)
    indices = np.empty(n + 2 * p, dt)
    indptr[0] = 0
    for i in range(n):
        diagonal[i] = indptr[i] + n_lower[i]
        indices[diagonal[i]] = i
        indptr[i + 1] = diagonal[i] + 1 + n_upper[i]
    upper = np.empty(p, dt)
    lower = np.empty(p, dt)
    next_upper = n_upper  # reused as the next free position of each row's pairs
    next_lower = n_lower  # and of its mirrors
    for i in range(n):
        next_upper[i] = diagonal[i] + 1
        next_lower[i] = indptr[i]
    for u in range(p):  # lexicographic order: each row's columns come in increasing order
        r, c = ulo[u], uhi[u]
        upper[u] = next_upper[r]
        next_upper[r] += 1
        indices[upper[u]] = c
        lower[u] = next_lower[c]
        next_lower[c] += 1
        indices[lower[u]] = r
    return -1, -1, indptr, indices, diagonal, upper, lower, slot


@parallel_kernel
def _chunk_spans(dofs, owners, bounds, lo, hi):
    """lo[ch], hi[ch]: the least and largest dof the elements of chunk ch read (``owners`` (E, r), or
    (0, 1) when element e reads row e of ``dofs``)."""
    own = owners.shape[0] > 0
    for ch in prange(bounds.shape[0] - 1):
        a, b = np.int64(2**62), np.int64(-1)
        for e in range(bounds[ch], bounds[ch + 1]):
            for o in range(owners.shape[1]):
                row = owners[e, o] if own else e
                for i in range(dofs.shape[1]):
                    d = np.int64(dofs[row, i])
                    a = min(a, d)
                    b = max(b, d)
        lo[ch], hi[ch] = a, b


def scatter_chunks(dofs, owners, counts=SWEEP_CHUNKS):
    """Chunk bounds (k + 1,) of the elements of a lattice sum (:func:`lattice_add_elements`,
    :func:`lattice_add_pieces`, :func:`lattice_add_rows`, :func:`lattice_add_face_jumps`): element e
    adds into the nodes ``dofs[owners[e]]`` (``owners`` (E, r): the rows of ``dofs`` that element e
    reads, e.g. its tet, the two tets of a face, or its own row of Gram dofs).  The first k of
    ``counts`` for which k contiguous chunks of about equal elements give chunks of one parity
    disjoint ranges of nodes (so the even chunks can add at the same time, then the odd ones);
    [0, E] when none does.  Elements listed along the lattice pass: the whole tets of a side, the
    interior faces of a cut, and the cut's tets and the triangles of S_h, since the band search
    returns its cells in id order (in the order of its blocks, the cut's chunks spanned most node
    numbers and got one chunk: the piece mass and the cut rows ran on one core).
    The chunk order changes the order of the sums at nodes shared by two chunks: the same bits on
    any number of threads, not those of one pass in element order.  ``owners`` None: element e reads
    row e (no (E, 1) array of 0..E-1: 0.24 s for the 29 million tets of a side at spacing 0.01)."""
    if owners is None:  # the empty placeholder has the type the callers' owners have at this size: one signature
        owners, E = np.zeros((0, 1), index_dtype(len(dofs))), len(dofs)
    else:
        owners = np.ascontiguousarray(owners).reshape(len(owners), -1)
        E = owners.shape[0]
    for k in counts:
        if k < 2 or k % 2 or E < 64 * k:
            continue
        bounds = (np.arange(k + 1, dtype=np.int64) * E) // k
        lo, hi = np.empty(k, dtype=np.int64), np.empty(k, dtype=np.int64)
        _chunk_spans(dofs, owners, bounds, lo, hi)
        ok = True
        for parity in (0, 1):
            order = np.argsort(lo[parity::2])
            a, b = lo[parity::2][order], hi[parity::2][order]
            ok &= bool(np.all(a[1:] > b[:-1]))
        if ok:
            return bounds
    return np.array([0, E], dtype=np.int64)
