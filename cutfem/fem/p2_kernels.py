"""Compiled kernels of the built-in terms on P2 fields: local matrices per cell, and their sum into
one symmetric CSR matrix.

Local matrices.  :func:`cell_matrices` integrates one of the cell terms (mass, stiffness, tangential
stiffness, normal-gradient penalty, Nitsche) over a block of cells, :func:`face_matrices` the
face-jump penalty over a block of faces (the 20 dofs of a face's two tets) and
:func:`interface_matrices` the interface Nitsche coupling of two fields (the 20 dofs of a cut tet in
the NEG and the POS field), :func:`cell_vectors` the loads and :func:`gradient_errors` the H1 error of a discrete function, point by
point from the
barycentric coordinates, the barycentric gradients G of each tet and, on a lifted geometry, the
Jacobians J = D Theta_h of the points: the P2 basis and its gradients are made at the point
(:mod:`cutfem.fem.lagrange`), the gradients mapped by J^-T (a closed-form 3 x 3 inverse) and the
point's weight times the products of the basis pairs added into the local matrix.  Nothing per
point and basis function outlives the point (the numpy route held (cells, points, 10, 3) gradient
arrays).  The local matrices are exactly symmetric: the entries a <= b are summed, then mirrored.

The sum.  :func:`symmetric_csr` adds local matrices (m, k, k) on dofs (m, k) into CSR arrays without
a sort of the triples: the cells that have each dof are listed by a counting sort (in cell order),
each row's columns are the sorted union of the dofs of its cells (made twice, to count and to fill:
kept, they would take half the local matrices' memory), and each row sums its entries right of the
diagonal over its cells in cell order, on any thread, then the entries left of it copy their mirror.  So the matrix is exactly symmetric and has the same bits on any number of
threads (every entry is one thread's ordered sum).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit, prange

from ..geometry.numbering import TET_EDGES, index_dtype
from ..jit import parallel_kernel

__all__ = ["MASS", "STIFFNESS", "TANGENTIAL", "NORMAL_GRADIENT", "NITSCHE", "cell_matrices", "face_matrices",
           "interface_matrices", "cell_vectors", "tangential_gradient_vectors", "gradient_errors", "symmetric_csr", "inverse_3x3"]

#: the cell terms of :func:`cell_matrices`
MASS, STIFFNESS, TANGENTIAL, NORMAL_GRADIENT, NITSCHE = range(5)

#: cells a thread takes at once (its scratch arrays are made once a chunk)
CHUNK = 256


@njit(cache=True, error_model="numpy", inline="always")
def _inverse(J, out):
    """out = J^-1 of a 3 x 3 J: the transposed cofactors over the determinant."""
    c00 = J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1]
    c01 = J[1, 2] * J[2, 0] - J[1, 0] * J[2, 2]
    c02 = J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]
    r = 1.0 / (J[0, 0] * c00 + J[0, 1] * c01 + J[0, 2] * c02)
    out[0, 0] = c00 * r
    out[1, 0] = c01 * r
    out[2, 0] = c02 * r
    out[0, 1] = (J[0, 2] * J[2, 1] - J[0, 1] * J[2, 2]) * r
    out[1, 1] = (J[0, 0] * J[2, 2] - J[0, 2] * J[2, 0]) * r
    out[2, 1] = (J[0, 1] * J[2, 0] - J[0, 0] * J[2, 1]) * r
    out[0, 2] = (J[0, 1] * J[1, 2] - J[0, 2] * J[1, 1]) * r
    out[1, 2] = (J[0, 2] * J[1, 0] - J[0, 0] * J[1, 2]) * r
    out[2, 2] = (J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]) * r


@parallel_kernel
def _inverses(J, out):
    n = J.shape[0]
    for c in prange((n + CHUNK - 1) // CHUNK):
        for t in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            _inverse(J[t], out[t])


def inverse_3x3(J: np.ndarray) -> np.ndarray:
    """J^-1 of 3 x 3 matrices J (..., 3, 3), each by its cofactors (no LU, no pivoting: the
    Jacobians of Theta_h are close to the identity)."""
    flat = np.ascontiguousarray(J, dtype=float).reshape(-1, 3, 3)
    out = np.empty_like(flat)
    _inverses(flat, out)
    return out.reshape(np.shape(J))


@njit(cache=True, error_model="numpy", inline="always")
def _basis(lam, G, phi, grad):
    """P2 values phi (10,) and gradients grad (10, 3) at barycentric coordinates lam (4,) of a tet
    with barycentric gradients G (4, 3) (:mod:`cutfem.fem.lagrange`)."""
    for i in range(4):
        phi[i] = lam[i] * (2.0 * lam[i] - 1.0)
        s = 4.0 * lam[i] - 1.0
        for d in range(3):
            grad[i, d] = s * G[i, d]
    for e in range(6):
        i, j = TET_EDGES[e, 0], TET_EDGES[e, 1]
        phi[4 + e] = 4.0 * lam[i] * lam[j]
        for d in range(3):
            grad[4 + e, d] = 4.0 * lam[j] * G[i, d] + 4.0 * lam[i] * G[j, d]


@njit(cache=True, error_model="numpy", inline="always")
def _map(grad, Jinv, out):
    """out[k] = grad[k] J^-1 (the gradients D Theta^-T grad^ as rows)."""
    for k in range(grad.shape[0]):
        for d in range(3):
            out[k, d] = grad[k, 0] * Jinv[0, d] + grad[k, 1] * Jinv[1, d] + grad[k, 2] * Jinv[2, d]


@njit(cache=True, error_model="numpy", inline="always")
def _mapped(jac, t, p, ref, Jinv, grad):
    """grad = the reference gradients ``ref`` mapped by J^-T of point p of cell t (J^-1 left in
    ``Jinv``), or ``ref`` itself when ``jac`` is empty (an undeformed cell)."""
    if jac.shape[0] > 0:
        _inverse(jac[t, p], Jinv)
        _map(ref, Jinv, grad)
    else:
        grad[:, :] = ref


@njit(cache=True, error_model="numpy", inline="always")
def _mirror(local):
    k = local.shape[0]
    for a in range(k):
        for b in range(a):
            local[a, b] = local[b, a]


@parallel_kernel
def cell_matrices(kind, lam, G, jac, weights, normals, sign, penalty, out):
    """out (m, 10, 10): the local matrices of term ``kind`` on cells with barycentric coordinates
    ``lam`` (m, q, 4) of their points in tets of barycentric gradients ``G`` (m, 4, 3); ``jac``
    (m, q, 3, 3) the Jacobians D Theta_h at the points, or empty (the identity); ``weights`` (m, q)
    the weights (times h^a where the term has it); ``normals`` (m, q, 3) the normals at the points
    (empty for the terms without one); Nitsche's outward ``sign`` and ``penalty`` (m,) gamma / h:

        MASS             sum_q w phi_a phi_b
        STIFFNESS        sum_q w grad phi_a . grad phi_b
        TANGENTIAL       sum_q w P grad phi_a . P grad phi_b,  P grad = grad - (n . grad) n
        NORMAL_GRADIENT  sum_q w (n . grad phi_a)(n . grad phi_b)
        NITSCHE          sum_q w (penalty phi_a phi_b - phi_a d_b - d_a phi_b),  d = sign n . grad phi."""
    m, q = weights.shape
    for c in prange((m + CHUNK - 1) // CHUNK):
        phi = np.empty(10)
        ref = np.empty((10, 3))
        grad = np.empty((10, 3))
        dn = np.empty(10)
        Jinv = np.empty((3, 3))
        for t in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            local = out[t]
            local[:, :] = 0.0
            for p in range(q):
                _basis(lam[t, p], G[t], phi, ref)
                _mapped(jac, t, p, ref, Jinv, grad)
                w = weights[t, p]
                if kind == MASS:
                    for a in range(10):
                        for b in range(a, 10):
                            local[a, b] += w * phi[a] * phi[b]
                elif kind == STIFFNESS:
                    for a in range(10):
                        for b in range(a, 10):
                            local[a, b] += w * (grad[a, 0] * grad[b, 0] + grad[a, 1] * grad[b, 1] + grad[a, 2] * grad[b, 2])
                elif kind == TANGENTIAL:
                    n = normals[t, p]
                    for a in range(10):
                        s = grad[a, 0] * n[0] + grad[a, 1] * n[1] + grad[a, 2] * n[2]
                        for d in range(3):
                            grad[a, d] -= s * n[d]
                    for a in range(10):
                        for b in range(a, 10):
                            local[a, b] += w * (grad[a, 0] * grad[b, 0] + grad[a, 1] * grad[b, 1] + grad[a, 2] * grad[b, 2])
                else:
                    n = normals[t, p]
                    for a in range(10):
                        dn[a] = grad[a, 0] * n[0] + grad[a, 1] * n[1] + grad[a, 2] * n[2]
                    if kind == NORMAL_GRADIENT:
                        for a in range(10):
                            for b in range(a, 10):
                                local[a, b] += w * dn[a] * dn[b]
                    else:
                        g = penalty[t]
                        for a in range(10):
                            for b in range(a, 10):
                                local[a, b] += w * (g * phi[a] * phi[b] - sign * (phi[a] * dn[b] + dn[a] * phi[b]))
            _mirror(local)


@parallel_kernel
def interface_matrices(lam, G, jac, weights, normals, flux_neg, flux_pos, penalty, out):
    """out (m, 20, 20): the interface Nitsche coupling's local matrices on the dofs of a cut tet in the
    NEG field, then in the POS field (one tet: one basis), arguments as :func:`cell_matrices`:
    sum_q w (penalty j_a j_b - j_a f_b - f_a j_b), the jump j = (phi, -phi) and the flux
    f = (flux_neg n . grad phi, flux_pos n . grad phi), ``flux_neg`` (m,) k_NEG a_NEG and ``flux_pos`` k_POS a_POS."""
    m, q = weights.shape
    for c in prange((m + CHUNK - 1) // CHUNK):
        phi = np.empty(10)
        ref = np.empty((10, 3))
        grad = np.empty((10, 3))
        Jinv = np.empty((3, 3))
        jump = np.empty(20)
        flux = np.empty(20)
        for t in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            local = out[t]
            local[:, :] = 0.0
            for p in range(q):
                _basis(lam[t, p], G[t], phi, ref)
                _mapped(jac, t, p, ref, Jinv, grad)
                n = normals[t, p]
                for a in range(10):
                    dn = grad[a, 0] * n[0] + grad[a, 1] * n[1] + grad[a, 2] * n[2]
                    jump[a], jump[10 + a] = phi[a], -phi[a]
                    flux[a], flux[10 + a] = flux_neg[t] * dn, flux_pos[t] * dn
                w, g = weights[t, p], penalty[t]
                for a in range(20):
                    for b in range(a, 20):
                        local[a, b] += w * (g * jump[a] * jump[b] - (jump[a] * flux[b] + flux[a] * jump[b]))
            _mirror(local)


@parallel_kernel
def cell_vectors(lam, G, jac, values, normals, sign, penalty, out):
    """out (m, 10, c): the local vectors sum_q values_c (penalty phi_a - sign n . grad phi_a) of loads
    ``values`` (m, q, c) (the data times the weights) on cells, arguments as :func:`cell_matrices`;
    ``normals`` empty: sum_q values_c phi_a (the gradients are not made)."""
    m, q = values.shape[0], values.shape[1]
    nc = values.shape[2]
    for ch in prange((m + CHUNK - 1) // CHUNK):
        phi = np.empty(10)
        ref = np.empty((10, 3))
        grad = np.empty((10, 3))
        Jinv = np.empty((3, 3))
        test = np.empty(10)
        for t in range(ch * CHUNK, min(m, (ch + 1) * CHUNK)):
            local = out[t]
            local[:, :] = 0.0
            for p in range(q):
                _basis(lam[t, p], G[t], phi, ref)
                if normals.shape[0] > 0:
                    _mapped(jac, t, p, ref, Jinv, grad)
                    n = normals[t, p]
                    for a in range(10):
                        test[a] = penalty[t] * phi[a] - sign * (grad[a, 0] * n[0] + grad[a, 1] * n[1] + grad[a, 2] * n[2])
                else:
                    test[:] = phi
                for a in range(10):
                    for c in range(nc):
                        local[a, c] += values[t, p, c] * test[a]


@parallel_kernel
def tangential_gradient_vectors(lam, G, jac, weights, normals, out):
    """out (m, 10, 3): sum_q w_q P grad phi_a, P = I - n n^T with the points' ``normals`` (m, q, 3),
    arguments as :func:`cell_matrices`: the load (P e_k, grad phi_a) of the coordinates x_k."""
    m, q = weights.shape
    for ch in prange((m + CHUNK - 1) // CHUNK):
        phi = np.empty(10)
        ref = np.empty((10, 3))
        grad = np.empty((10, 3))
        Jinv = np.empty((3, 3))
        for t in range(ch * CHUNK, min(m, (ch + 1) * CHUNK)):
            local = out[t]
            local[:, :] = 0.0
            for p in range(q):
                _basis(lam[t, p], G[t], phi, ref)
                _mapped(jac, t, p, ref, Jinv, grad)
                n, w = normals[t, p], weights[t, p]
                for a in range(10):
                    dn = grad[a, 0] * n[0] + grad[a, 1] * n[1] + grad[a, 2] * n[2]
                    for c in range(3):
                        local[a, c] += w * (grad[a, c] - dn * n[c])


@njit(cache=True, error_model="numpy", inline="always")
def _face_side(lam, G, jac, theta, n, t, p, phi, ref, grad, Jinv, hess, first, second, offset, sign):
    """The normal derivatives (``first``) and second normal derivatives (``second``) of one side's
    basis at point p of face t, times ``sign``, at ``offset`` in the face's 20 dofs: with
    v = J^-1 n and H^ the constant Hessians of the undeformed basis (``hess`` (10, 3, 3)),
    n^T H n = v^T (H^ - sum_c (grad phi)_c H(Theta_c)) v (:func:`cutfem.fem.lagrange.map_hessians`)."""
    _basis(lam[t, p], G[t], phi, ref)
    v0, v1, v2 = n[0], n[1], n[2]
    moved = jac.shape[0] > 0
    _mapped(jac, t, p, ref, Jinv, grad)
    if moved:
        v0 = Jinv[0, 0] * n[0] + Jinv[0, 1] * n[1] + Jinv[0, 2] * n[2]
        v1 = Jinv[1, 0] * n[0] + Jinv[1, 1] * n[1] + Jinv[1, 2] * n[2]
        v2 = Jinv[2, 0] * n[0] + Jinv[2, 1] * n[1] + Jinv[2, 2] * n[2]
    curve0 = curve1 = curve2 = 0.0
    if moved:
        for comp in range(3):
            H = theta[t, comp]
            s = (v0 * (H[0, 0] * v0 + H[0, 1] * v1 + H[0, 2] * v2) + v1 * (H[1, 0] * v0 + H[1, 1] * v1 + H[1, 2] * v2)
                 + v2 * (H[2, 0] * v0 + H[2, 1] * v1 + H[2, 2] * v2))
            if comp == 0:
                curve0 = s
            elif comp == 1:
                curve1 = s
            else:
                curve2 = s
    for k in range(10):
        H = hess[k]
        s = (v0 * (H[0, 0] * v0 + H[0, 1] * v1 + H[0, 2] * v2) + v1 * (H[1, 0] * v0 + H[1, 1] * v1 + H[1, 2] * v2)
             + v2 * (H[2, 0] * v0 + H[2, 1] * v1 + H[2, 2] * v2))
        s -= grad[k, 0] * curve0 + grad[k, 1] * curve1 + grad[k, 2] * curve2
        second[offset + k] = sign * s
        first[offset + k] = sign * (grad[k, 0] * n[0] + grad[k, 1] * n[1] + grad[k, 2] * n[2])


@njit(cache=True, error_model="numpy", inline="always")
def _hessians(G, hess):
    """hess (10, 3, 3) the constant P2 Hessians of a tet: 4 G_i G_i^T, 4 (G_i G_j^T + G_j G_i^T)."""
    for i in range(4):
        for a in range(3):
            for b in range(3):
                hess[i, a, b] = 4.0 * (G[i, a] * G[i, b])
    for e in range(6):
        i, j = TET_EDGES[e, 0], TET_EDGES[e, 1]
        for a in range(3):
            for b in range(3):
                hess[4 + e, a, b] = 4.0 * (G[i, a] * G[j, b] + G[j, a] * G[i, b])


@parallel_kernel
def face_matrices(lam0, lam1, G0, G1, jac0, jac1, theta0, theta1, normals, weights, first_scale, second_scale, out):
    """out (m, 20, 20): the face-jump penalty's local matrices on the dofs of the two tets of each face
    (minus, then plus): sum_q w (first_scale [n . grad phi_a][n . grad phi_b] + second_scale
    [n^T H phi_a n][n^T H phi_b n]).  Per side: ``lam`` (m, q, 4) the barycentric coordinates of the
    face's points in the tet, ``G`` (m, 4, 3) its barycentric gradients, ``jac`` (m, q, 3, 3) D Theta_h
    at the points and ``theta`` (m, 3, 3, 3) the Hessians of Theta_h's components (both empty on an
    undeformed cut); ``normals`` (m, 3), ``weights`` (m, q), the scales (m,) h^a and h^(a+2) / 4."""
    m, q = weights.shape
    for c in prange((m + CHUNK - 1) // CHUNK):
        phi = np.empty(10)
        ref = np.empty((10, 3))
        grad = np.empty((10, 3))
        Jinv = np.empty((3, 3))
        hess0 = np.empty((10, 3, 3))
        hess1 = np.empty((10, 3, 3))
        first = np.empty(20)
        second = np.empty(20)
        for t in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            local = out[t]
            local[:, :] = 0.0
            _hessians(G0[t], hess0)
            _hessians(G1[t], hess1)
            n = normals[t]
            for p in range(q):
                _face_side(lam0, G0, jac0, theta0, n, t, p, phi, ref, grad, Jinv, hess0, first, second, 0, 1.0)
                _face_side(lam1, G1, jac1, theta1, n, t, p, phi, ref, grad, Jinv, hess1, first, second, 10, -1.0)
                w1 = weights[t, p] * first_scale[t]
                w2 = weights[t, p] * second_scale[t]
                for a in range(20):
                    for b in range(a, 20):
                        local[a, b] += w1 * first[a] * first[b] + w2 * second[a] * second[b]
            _mirror(local)


@parallel_kernel
def gradient_errors(lam, G, jac, coeffs, exact, weights, normals, out):
    """out (m,): sum_q w |grad u^e - grad u_h|^2 over each cell (the tangential part where ``normals``
    (m, 1 or q, 3) is not empty), grad u_h = sum_k coeffs[t, k, c] grad phi_k of the P1 (k = 4) or P2
    (k = 10) basis at the points, mapped by ``jac`` (empty: the identity); ``exact`` (m, q, c, 3)
    the gradients of the c components of u^e, other arguments as :func:`cell_matrices`."""
    m, q = weights.shape
    k, nc = coeffs.shape[1], coeffs.shape[2]
    for ch in prange((m + CHUNK - 1) // CHUNK):
        phi = np.empty(10)
        ref = np.empty((10, 3))
        grad = np.empty((10, 3))
        Jinv = np.empty((3, 3))
        d = np.empty(3)
        for t in range(ch * CHUNK, min(m, (ch + 1) * CHUNK)):
            acc = 0.0
            for p in range(q):
                if k == 10:
                    _basis(lam[t, p], G[t], phi, ref)
                else:
                    ref[:4, :] = G[t]
                if jac.shape[0] > 0:
                    _inverse(jac[t, p], Jinv)
                    _map(ref[:k], Jinv, grad[:k])
                else:
                    grad[:k, :] = ref[:k]
                part = 0.0
                for c in range(nc):
                    for x in range(3):
                        d[x] = exact[t, p, c, x]
                        for a in range(k):
                            d[x] -= coeffs[t, a, c] * grad[a, x]
                    if normals.shape[0] > 0:
                        n = normals[t, p if normals.shape[1] > 1 else 0]
                        s = d[0] * n[0] + d[1] * n[1] + d[2] * n[2]
                        for x in range(3):
                            d[x] -= s * n[x]
                    part += d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                acc += weights[t, p] * part
            out[t] = acc


# -- the symmetric sum into CSR -------------------------------------------------------------------

@njit(cache=True, error_model="numpy")
def _incidence(dofs, n):
    """(start (n + 1,), slots (m k,)): the slots e k + a with dofs[e, a] = i at start[i]:start[i + 1],
    in increasing order (a counting sort)."""
    m, k = dofs.shape
    start = np.zeros(n + 1, dtype=np.int64)
    for e in range(m):
        for a in range(k):
            start[dofs[e, a] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    slots = np.empty(m * k, dtype=np.int64)
    for e in range(m):
        for a in range(k):
            i = dofs[e, a]
            slots[fill[i]] = e * k + a
            fill[i] += 1
    return start, slots


#: rows a thread takes at once in the CSR sum (its marks, one integer a dof, are made once a chunk)
ROW_CHUNK = 1 << 14


@njit(cache=True, error_model="numpy", inline="always")
def _columns(i, dofs, start, slots, mark, buf):
    """The number c of distinct dofs of the cells that have dof i, written sorted to ``buf[:c]`` (an
    insertion as each is met: a row has a few dozen); ``mark`` (n,) holds i at the dofs seen."""
    k = dofs.shape[1]
    c = 0
    for s in range(start[i], start[i + 1]):
        e = slots[s] // k
        for b in range(k):
            j = dofs[e, b]
            if mark[j] != i:
                mark[j] = i
                t = c
                while t > 0 and buf[t - 1] > j:
                    buf[t] = buf[t - 1]
                    t -= 1
                buf[t] = j
                c += 1
    return c


@parallel_kernel
def _row_counts(dofs, start, slots, width, counts):
    n = counts.shape[0]
    for ch in prange((n + ROW_CHUNK - 1) // ROW_CHUNK):
        mark = np.full(n, -1, dtype=np.int64)
        buf = np.empty(width, dtype=np.int64)
        for i in range(ch * ROW_CHUNK, min(n, (ch + 1) * ROW_CHUNK)):
            counts[i] = _columns(i, dofs, start, slots, mark, buf)


@parallel_kernel
def _row_sums(dofs, local, start, slots, width, indptr, indices, data):
    k = dofs.shape[1]
    n = indptr.shape[0] - 1
    for ch in prange((n + ROW_CHUNK - 1) // ROW_CHUNK):
        mark = np.full(n, -1, dtype=np.int64)
        buf = np.empty(width, dtype=np.int64)
        where = np.empty(n, dtype=np.int64)  # read only at the columns of the row at hand, written first
        for i in range(ch * ROW_CHUNK, min(n, (ch + 1) * ROW_CHUNK)):
            c = _columns(i, dofs, start, slots, mark, buf)
            p0 = indptr[i]
            for t in range(c):
                indices[p0 + t] = buf[t]
                where[buf[t]] = p0 + t
            for s in range(start[i], start[i + 1]):
                e, a = slots[s] // k, slots[s] % k
                for b in range(k):
                    j = dofs[e, b]
                    if j >= i:
                        data[where[j]] += local[e, a, b]


@parallel_kernel
def _mirror_rows(indptr, indices, data):
    for i in prange(indptr.shape[0] - 1):
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if j < i:
                row = indices[indptr[j] : indptr[j + 1]]
                data[p] = data[indptr[j] + np.searchsorted(row, i)]


def symmetric_csr(dofs: np.ndarray, local: np.ndarray, n: int) -> sp.csr_matrix:
    """The n x n CSR sum of the symmetric local matrices ``local`` (m, k, k) on the dofs ``dofs`` (m, k)
    (a dof may repeat within a cell: the two tets of a face share six): sorted, duplicate-free,
    exactly symmetric (module docstring)."""
    dofs = np.ascontiguousarray(dofs, dtype=np.int64)
    local = np.ascontiguousarray(local, dtype=float)
    start, slots = _incidence(dofs, int(n))
    counts = np.zeros(int(n), dtype=np.int64)
    width = int(np.diff(start).max(initial=0)) * dofs.shape[1]  # the most columns a row can have
    _row_counts(dofs, start, slots, width, counts)
    nnz = int(counts.sum())
    index = index_dtype(max(nnz, int(n)))
    indptr = np.zeros(int(n) + 1, dtype=index)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(nnz, dtype=index)
    data = np.zeros(nnz)
    _row_sums(dofs, local, start, slots, width, indptr, indices, data)
    _mirror_rows(indptr, indices, data)
    A = sp.csr_matrix((data, indices, indptr), shape=(int(n), int(n)))
    A.has_sorted_indices = True
    return A
