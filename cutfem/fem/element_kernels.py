"""Compiled element kernels: exact integrals on the pieces of a cut surface, traces of P1
functions at its vertices, jumps of normal derivatives across facets, tangential gradients, the
meshed surface's closed forms, and the quadrature sums of the error norms.

The piece kernels integrate the P1 basis exactly over each polygon of S_h in its cut tet (the
barycentric coordinates of the triangle's vertices, one pass a piece); the error sums keep one
accumulator a quadrature point and add the blocks in order (:func:`cutfem.jit._add_blocks`), so a
norm has the same bits on any number of threads.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..geometry.mesh_kernels import _area
from ..geometry.numbering import TET_EDGES
from ..jit import SUM_BLOCK, _add_blocks, _ordered_sum, parallel_kernel

@njit(cache=True, error_model="numpy", inline="always")
def _barycentric(x, points, tets, g, k, lam):
    """lam (4,) = the P1 basis values of tet k (vertices ``tets[k]`` into ``points``, basis gradients
    g (4, 3)) at x: delta_i0 + grad lambda_i . (x - x_0)."""
    o = tets[k, 0]
    d0, d1, d2 = x[0] - points[o, 0], x[1] - points[o, 1], x[2] - points[o, 2]
    for i in range(4):
        lam[i] = g[i, 0] * d0 + g[i, 1] * d1 + g[i, 2] * d2
    lam[0] += 1.0


@njit(cache=True, error_model="numpy")
def _piece_moments(vertices, triangles, tets_of, areas, points, tets, table, types, edges, diagonal, integrals):
    lam = np.empty((3, 4))
    for t in range(triangles.shape[0]):
        k = tets_of[t]
        g = table[types[k]]
        for v in range(3):
            _barycentric(vertices[triangles[t, v]], points, tets, g, k, lam[v])
        w = areas[t] / 12.0
        for i in range(4):
            si = lam[0, i] + lam[1, i] + lam[2, i]
            integrals[k, i] += areas[t] * si / 3.0
            diagonal[k, i] += w * (lam[0, i] * lam[0, i] + lam[1, i] * lam[1, i] + lam[2, i] * lam[2, i] + si * si)
        for e in range(6):
            i, j = TET_EDGES[e, 0], TET_EDGES[e, 1]
            si = lam[0, i] + lam[1, i] + lam[2, i]
            sj = lam[0, j] + lam[1, j] + lam[2, j]
            edges[k, e] += w * (lam[0, i] * lam[0, j] + lam[1, i] * lam[1, j] + lam[2, i] * lam[2, j] + si * sj)


def piece_moments(vertices, triangles, tets_of, areas, points, tets, table, types):
    """The exact P1 moments of the pieces of S_h over their m cut tets ``tets`` (m, 4) (vertex ids into
    ``points``): ``(edges (m, 6), diagonal (m, 4), integrals (m, 4))`` with
    M_K[i, j] = int_{S_K} lambda_i lambda_j for the local edges (i, j) of
    :data:`~cutfem.geometry.numbering.TET_EDGES` and on the diagonal, and int_{S_K} lambda_i.

    The piece S_K is the union of its triangles T (``triangles`` (T, 3) into ``vertices``, in tet
    ``tets_of`` (T,), area ``areas``); the basis functions are affine on T, so with their values
    lambda_v at the three vertices and s = lambda_1 + lambda_2 + lambda_3,

        int_T lambda_i lambda_j = |T| / 12 (sum_v lambda_{v,i} lambda_{v,j} + s_i s_j),
        int_T lambda_i = |T| s_i / 3.

    The values come from the tet's first vertex and its basis gradients ``table[types[k]]``
    (:meth:`~cutfem.geometry.markers.ElementSet.gradient_lookup`): lambda_i(x) = delta_i0 + grad lambda_i . (x - x_0)."""
    m = len(tets)
    edges, diagonal, integrals = np.zeros((m, 6)), np.zeros((m, 4)), np.zeros((m, 4))
    _piece_moments(np.ascontiguousarray(vertices, dtype=float), np.ascontiguousarray(triangles),
                   np.ascontiguousarray(tets_of), np.ascontiguousarray(areas, dtype=float),
                   np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(tets),
                   np.ascontiguousarray(table, dtype=float), np.ascontiguousarray(types), edges, diagonal, integrals)
    return edges, diagonal, integrals


@njit(cache=True, error_model="numpy")
def piece_integrals(vertices, triangles, tets_of, areas, points, tets, table, types, dofs, out):
    """out[dofs[k, i]] += int_T lambda_i = |T| lambda_i(centroid of T) for the triangles ``triangles``
    (T, 3) into ``vertices``, of areas ``areas``, lying in the tets ``tets_of`` (T,) (vertex ids
    ``tets`` (m, 4) into ``points``, basis gradients ``table[types[k]]``, dofs ``dofs`` (m, 4)):
    the integrals of the P1 basis functions over the pieces of S_h, exact (lambda_i is affine on T)."""
    lam = np.empty(4)
    x = np.empty(3)
    for t in range(triangles.shape[0]):
        k = tets_of[t]
        for d in range(3):
            x[d] = (vertices[triangles[t, 0], d] + vertices[triangles[t, 1], d] + vertices[triangles[t, 2], d]) / 3.0
        _barycentric(x, points, tets, table[types[k]], k, lam)
        for i in range(4):
            out[dofs[k, i]] += areas[t] * lam[i]


@njit(cache=True, error_model="numpy")
def _vertex_values(vertices, triangles, tets_of, points, tets, table, types, dofs, coeffs, out):
    done = np.zeros(vertices.shape[0], dtype=np.bool_)
    lam = np.empty(4)
    for t in range(triangles.shape[0] - 1, -1, -1):
        k = tets_of[t]
        for v in range(3):
            p = triangles[t, v]
            if done[p]:
                continue
            done[p] = True
            _barycentric(vertices[p], points, tets, table[types[k]], k, lam)
            for c in range(coeffs.shape[1]):
                s = 0.0
                for i in range(4):
                    s += lam[i] * coeffs[dofs[k, i], c]
                out[p, c] = s


def vertex_values(vertices, triangles, tets_of, points, tets, table, types, dofs, coeffs):
    """A P1 function on the tets ``tets`` (m, 4) (vertex ids into ``points``, basis gradients
    ``table[types[k]]``, dofs ``dofs`` (m, 4), coefficients ``coeffs`` (n, c)) at the vertices of the
    triangles ``triangles`` (T, 3) lying in the tets ``tets_of`` (T,): (V, c), each vertex valued in
    the tet of the last triangle that has it (the trace is continuous: any of them would do).  One
    pass over the triangles, last to first, each vertex once; no per-vertex basis arrays."""
    coeffs = np.ascontiguousarray(coeffs, dtype=float)
    out = np.zeros((len(vertices), coeffs.shape[1]))
    _vertex_values(np.ascontiguousarray(vertices, dtype=float), np.ascontiguousarray(triangles),
                   np.ascontiguousarray(tets_of), np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(tets),
                   np.ascontiguousarray(table, dtype=float), np.ascontiguousarray(types), np.ascontiguousarray(dofs),
                   coeffs, out)
    return out


@njit(cache=True, error_model="numpy")
def jump_rows(pairs, normals_a, normals_b, sign_b, weights, dofs, table, types, out_dofs, out_values):
    """Rows of the jumps c = sqrt(w) (t_a . G_{K_a}, t_b . G_{K_b}) for the pairs (K_a, K_b) =
    ``pairs`` (F, 2) of elements with k dofs, t_a = ``normals_a`` (F, 3), t_b = ``sign_b``
    ``normals_b``, w = ``weights`` (F,): ``out_dofs`` (F, 2k) the dofs of K_a then K_b (``dofs``
    (m, k)), ``out_values`` (F, 2k); the gradients are ``table[types[K]]`` (k, 3)
    (:meth:`~cutfem.fem.spaces.CutSpace.gradient_lookup`)."""
    k = dofs.shape[1]
    for f in range(pairs.shape[0]):
        w = np.sqrt(weights[f])
        for side in range(2):
            el = pairs[f, side]
            g = table[types[el]]
            t = normals_a[f] if side == 0 else normals_b[f]
            scale = w if side == 0 else w * sign_b
            for i in range(k):
                out_dofs[f, k * side + i] = dofs[el, i]
                out_values[f, k * side + i] = scale * (g[i, 0] * t[0] + g[i, 1] * t[1] + g[i, 2] * t[2])


@parallel_kernel
def triangle_points(points, triangles, bary, x, area):
    """The quadrature points x (b, q, 3) = sum_v bary[q, v] x_v and the areas ``area`` (b,) of the
    triangles ``triangles`` (b, 3) into ``points``."""
    for t in prange(triangles.shape[0]):
        p0, p1, p2 = points[triangles[t, 0]], points[triangles[t, 1]], points[triangles[t, 2]]
        for i in range(bary.shape[0]):
            for d in range(3):
                x[t, i, d] = bary[i, 0] * p0[d] + bary[i, 1] * p1[d] + bary[i, 2] * p2[d]
        area[t] = _area(p0, p1, p2)


@parallel_kernel
def squared_error(values, triangles, bary, weights, area, exact):
    """sum_T |T| sum_q w_q |u^e(x_q) - u_h(x_q)|^2 over the triangles (b, 3), u_h linear on each with
    ``values`` (V, c) at the vertices, u_h(x_q) = sum_v bary[q, v] u_v; ``exact`` (b, q, c), or an
    empty array for u^e = 0 (the norm of u_h itself).  Summed per block of :data:`SUM_BLOCK`
    triangles, the blocks in order (the same bits on any number of threads)."""
    c = values.shape[1]
    n = triangles.shape[0]
    with_exact = exact.shape[0] > 0
    nblocks = (n + SUM_BLOCK - 1) // SUM_BLOCK
    part = np.zeros((nblocks, 1))
    for b in prange(nblocks):
        for t in range(b * SUM_BLOCK, min((b + 1) * SUM_BLOCK, n)):
            v0, v1, v2 = values[triangles[t, 0]], values[triangles[t, 1]], values[triangles[t, 2]]
            s = 0.0
            for i in range(bary.shape[0]):
                for l in range(c):
                    d = (exact[t, i, l] if with_exact else 0.0) - (bary[i, 0] * v0[l] + bary[i, 1] * v1[l] + bary[i, 2] * v2[l])
                    s += weights[i] * d * d
            part[b, 0] += area[t] * s
    total = np.zeros(1)
    _add_blocks(part, total)
    return total[0]


@parallel_kernel
def barycentric_values(points, origin, grads, out):
    """out[e, i, a] = delta_a0 + grads[e, a] . (points[e, i] - origin[e]): the P1 basis values at
    ``points`` (m, q, 3) of elements with first vertex ``origin`` (m, 3) and basis gradients
    ``grads`` (m, k, 3)."""
    for e in prange(points.shape[0]):
        o0, o1, o2 = origin[e, 0], origin[e, 1], origin[e, 2]
        for i in range(points.shape[1]):
            y0, y1, y2 = points[e, i, 0] - o0, points[e, i, 1] - o1, points[e, i, 2] - o2
            for a in range(grads.shape[1]):
                out[e, i, a] = grads[e, a, 0] * y0 + grads[e, a, 1] * y1 + grads[e, a, 2] * y2
            out[e, i, 0] += 1.0


@parallel_kernel
def cell_value_error(phi, local, exact, weights):
    """sum_K sum_q w_Kq |u^e(x_Kq) - u_h(x_Kq)|^2 over the cells K of a block, u_h(x_Kq) =
    sum_a phi[K, q, a] local[K, a, :]: basis values ``phi`` (b, q, k), or (1, q, k) when every
    cell shares them (whole cells: the rule's barycentric coordinates), the cells' coefficients
    ``local`` (b, k, c), ``exact`` (b, q, c), ``weights`` (b, q).  The sums run per point q across
    the cells of each block of :data:`SUM_BLOCK` (independent accumulators, so the loops pipeline),
    the blocks on all cores and added in order at the end."""
    b, nq = weights.shape
    k, c = local.shape[1], local.shape[2]
    shared = phi.shape[0] == 1
    nblocks = (b + SUM_BLOCK - 1) // SUM_BLOCK
    acc = np.zeros((nblocks, nq))
    for blk in prange(nblocks):
        uh = np.empty(nq)
        for e in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, b)):
            p = phi[0] if shared else phi[e]
            for l in range(c):
                uh[:] = 0.0
                for a in range(k):
                    la = local[e, a, l]
                    for i in range(nq):
                        uh[i] += p[i, a] * la
                for i in range(nq):
                    d = exact[e, i, l] - uh[i]
                    acc[blk, i] += weights[e, i] * (d * d)
    total = np.zeros(nq)
    _add_blocks(acc, total)
    return _ordered_sum(total)


@parallel_kernel
def cell_gradient_error(table, types, local, exact, weights, normals):
    """sum_K sum_q w_Kq |P (grad u^e(x_Kq) - grad u_h|_K)|^2 over the cells K of a block, grad u_h
    = sum_a local[K, a] G_K[a] constant on K (gradients G_K = ``table[types[K]]`` (k, 3), read in
    place: a gathered (b, k, 3) copy took a third of this sum's time; ``local`` (b, k)),
    ``exact`` (b, q, 3), ``weights`` (b, q); P = I - n n^T with the cells' unit ``normals`` (b, 3)
    on a surface, P = I when ``normals`` is empty.  Summed per point q as :func:`cell_value_error`."""
    b, nq = weights.shape
    surface = normals.shape[0] > 0
    nblocks = (b + SUM_BLOCK - 1) // SUM_BLOCK
    acc = np.zeros((nblocks, nq))
    for blk in prange(nblocks):
        for e in range(blk * SUM_BLOCK, min((blk + 1) * SUM_BLOCK, b)):
            G = table[types[e]]
            g0 = g1 = g2 = 0.0
            for a in range(G.shape[0]):
                g0 += local[e, a] * G[a, 0]
                g1 += local[e, a] * G[a, 1]
                g2 += local[e, a] * G[a, 2]
            if surface:
                n0, n1, n2 = normals[e, 0], normals[e, 1], normals[e, 2]
                for i in range(nq):
                    d0, d1, d2 = exact[e, i, 0] - g0, exact[e, i, 1] - g1, exact[e, i, 2] - g2
                    dn = d0 * n0 + d1 * n1 + d2 * n2
                    d0, d1, d2 = d0 - dn * n0, d1 - dn * n1, d2 - dn * n2
                    acc[blk, i] += weights[e, i] * (d0 * d0 + d1 * d1 + d2 * d2)
            else:
                for i in range(nq):
                    d0, d1, d2 = exact[e, i, 0] - g0, exact[e, i, 1] - g1, exact[e, i, 2] - g2
                    acc[blk, i] += weights[e, i] * (d0 * d0 + d1 * d1 + d2 * d2)
    total = np.zeros(nq)
    _add_blocks(acc, total)
    return _ordered_sum(total)


@njit(cache=True, error_model="numpy")
def tangential_gradient_sums(dofs, table, types, normals, weights, out):
    """out[dofs[K, i]] += weights[K] (I - n_K n_K^T) grad lambda_i for the elements K: ``dofs`` (m, 4),
    gradients ``table[types[K]]``, unit ``normals`` (m, 3), ``out`` (n, 3)."""
    for t in range(dofs.shape[0]):
        g = table[types[t]]
        n0, n1, n2 = normals[t, 0], normals[t, 1], normals[t, 2]
        w = weights[t]
        for i in range(4):
            gn = g[i, 0] * n0 + g[i, 1] * n1 + g[i, 2] * n2
            a = dofs[t, i]
            out[a, 0] += w * (g[i, 0] - gn * n0)
            out[a, 1] += w * (g[i, 1] - gn * n1)
            out[a, 2] += w * (g[i, 2] - gn * n2)


@parallel_kernel
def triangle_gradients(v, grads, normals, areas):
    """Surface gradients of the barycentric coordinates of triangles ``v`` (m, 3, 3), for
    :func:`cutfem.fem.spaces.triangle_gradients` (which states them), into ``grads`` (m, 3, 3),
    ``normals`` (m, 3) and ``areas`` (m,): one pass, where numpy made four cross products of
    (m, 3) temporaries (0.13 s for the 590 thousand triangles of the torus 768 x 384)."""
    for t in prange(v.shape[0]):
        a0, a1, a2 = v[t, 1, 0] - v[t, 0, 0], v[t, 1, 1] - v[t, 0, 1], v[t, 1, 2] - v[t, 0, 2]
        b0, b1, b2 = v[t, 2, 0] - v[t, 0, 0], v[t, 2, 1] - v[t, 0, 1], v[t, 2, 2] - v[t, 0, 2]
        c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        twice = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        n0, n1, n2 = c0 / twice, c1 / twice, c2 / twice
        normals[t, 0], normals[t, 1], normals[t, 2] = n0, n1, n2
        areas[t] = 0.5 * twice
        for i in range(3):
            p, q = (i + 2) % 3, (i + 1) % 3
            e0, e1, e2 = v[t, p, 0] - v[t, q, 0], v[t, p, 1] - v[t, q, 1], v[t, p, 2] - v[t, q, 2]
            grads[t, i, 0] = (n1 * e2 - n2 * e1) / twice
            grads[t, i, 1] = (n2 * e0 - n0 * e2) / twice
            grads[t, i, 2] = (n0 * e1 - n1 * e0) / twice


@parallel_kernel
def tangential_entries(table, types, normals, areas, edges, diagonal):
    """The entries of |K| (P G)(P G)^T, P = I - n n^T, for tets whose gradients G (4, 3) are
    ``table[types[k]]``, with normal ``normals[k]`` and weight ``areas[k]``: on the local edges
    (:data:`~cutfem.geometry.numbering.TET_EDGES` order) into ``edges`` (m, 6) and on the diagonal into
    ``diagonal`` (m, 4), for :func:`cutfem.fem.closed_forms._kuhn_tangential_stiffness`:
    |K| (G_a . G_b - (G_a . n)(G_b . n)).  One pass (numpy's masks per type, gathers and products
    took 0.17 s for the 853 thousand cut tets at spacing 0.0125)."""
    for k in prange(types.shape[0]):
        G = table[types[k]]
        c = np.empty(4)
        for a in range(4):
            c[a] = G[a, 0] * normals[k, 0] + G[a, 1] * normals[k, 1] + G[a, 2] * normals[k, 2]
        w = areas[k]
        for a in range(4):
            diagonal[k, a] = (G[a, 0] * G[a, 0] + G[a, 1] * G[a, 1] + G[a, 2] * G[a, 2] - c[a] * c[a]) * w
        for e in range(6):
            a, b = TET_EDGES[e, 0], TET_EDGES[e, 1]
            edges[k, e] = (G[a, 0] * G[b, 0] + G[a, 1] * G[b, 1] + G[a, 2] * G[b, 2] - c[a] * c[b]) * w


@njit(cache=True, error_model="numpy")
def meshed_position_load(points, tri, out):
    """out[v] += |T| grad lambda_v over the triangles T of a triangulated surface, for
    :func:`cutfem.fem.terms.position_load`: with c = (x_1 - x_0) x (x_2 - x_0) = 2 |T| n_T,

        |T| grad lambda_k = (1/2) n_T x (x_{k+2} - x_{k+1}) = c x (x_{k+2} - x_{k+1}) / (2 |c|),

    the in-plane edge opposite vertex k turned a quarter towards it.  One pass over the triangles
    (no gradients stored, no stiffness matrix)."""
    for t in range(tri.shape[0]):
        a, b, d = tri[t, 0], tri[t, 1], tri[t, 2]
        u0, u1, u2 = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        w0, w1, w2 = points[d, 0] - points[a, 0], points[d, 1] - points[a, 1], points[d, 2] - points[a, 2]
        c0, c1, c2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
        s = 0.5 / np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        c0, c1, c2 = c0 * s, c1 * s, c2 * s
        for k in range(3):
            p, q = tri[t, (k + 1) % 3], tri[t, (k + 2) % 3]
            e0, e1, e2 = points[q, 0] - points[p, 0], points[q, 1] - points[p, 1], points[q, 2] - points[p, 2]
            v = tri[t, k]
            out[v, 0] += c1 * e2 - c2 * e1
            out[v, 1] += c2 * e0 - c0 * e2
            out[v, 2] += c0 * e1 - c1 * e0


@njit(cache=True, error_model="numpy")
def meshed_edge_penalty(tri, S, Q, areas, h, h1, h2, n):
    """The edge penalty J_E of a closed triangulated surface in closed form, for
    :func:`cutfem.fem.closed_forms._meshed_edge_penalty` (which derives it): per half-edge g = 3 t + k the
    scaled jump coefficients b_start, b_end, b_opp, then ``(diagonal (n,), on_edges (E,),
    opposite (E,))``: the values on the edges {i, j} and on the pairs {k, l} of vertices opposite
    them (:meth:`cutfem.fem.spaces.SurfaceP1Space.edge_stencil_pattern`).  ``S``, ``Q`` (M, 3) the edge-vector dot
    products, ``areas`` (M,), ``h1``, ``h2`` (E,) the half-edges of each edge.  Two passes over
    the half-edges and one over the edges, where numpy made a dozen (M, 3) temporaries."""
    M = tri.shape[0]
    E = h1.shape[0]
    twin = np.empty(3 * M, np.int64)
    for e in range(E):
        twin[h1[e]], twin[h2[e]] = h2[e], h1[e]
    c_end = np.empty(3 * M)  # sqrt(h |E|) c_end of each half-edge, then b_start
    b_opp = np.empty(3 * M)
    b_start = np.empty(3 * M)
    for t in range(M):
        for k in range(3):
            length = np.sqrt(S[t, k])
            cs = -0.5 * np.sqrt(length * h) / (length * areas[t])
            c_end[3 * t + k] = Q[t, (k + 2) % 3] * cs
            b_start[3 * t + k] = Q[t, k] * cs  # sqrt(h |E|) c_start, plus the twin's c_end below
            b_opp[3 * t + k] = S[t, k] * cs
    for g in range(3 * M):
        b_start[g] += c_end[twin[g]]
    received = c_end  # reused: what each half-edge receives from the two others of its triangle
    diagonal = np.zeros(n)
    for t in range(M):
        for k in range(3):
            g, nx, pv = 3 * t + k, 3 * t + (k + 1) % 3, 3 * t + (k + 2) % 3
            # the half-edge before g gives b_end b_opp, the one after it b_opp b_start
            received[g] = b_start[twin[pv]] * b_opp[pv] + b_opp[nx] * b_start[nx]
            diagonal[tri[t, k]] += b_start[g] * b_start[g] + b_opp[nx] * b_opp[nx]
    on_edges, opposite = np.empty(E), np.empty(E)
    for e in range(E):
        a, b = h1[e], h2[e]
        on_edges[e] = b_start[a] * b_start[b] + received[a] + received[b]
        opposite[e] = b_opp[a] * b_opp[b]
    return diagonal, on_edges, opposite
