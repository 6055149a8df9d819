"""The built-in bilinear terms on P2 fields: the quadrature of their integrands, vectorised over the local basis pairs.

On a P2 field (:class:`~cutfem.fem.spaces.CutSpace` of order 2) a built-in term is its integrand
(:mod:`cutfem.fem.terms`) integrated by quadrature of the field's degree
(:meth:`~cutfem.fem.forms.Integrand.degree_for`).  The form language evaluates an integrand one
pair of basis functions at a time (55 to 210 passes over a block's points); each function here
evaluates the same integrand for all pairs at once, as a product of the scaled basis values or
derivatives at the points, B^T B per cell (one pass, the local matrices built in cache).  The
reference is the form language itself (:meth:`~cutfem.fem.forms.Form.by_quadrature`: the same
matrices to round-off, tested).  Each function takes the term and the scalar field and yields
``(dofs (m, k), local matrices (m, k, k))`` block by block of cells; a vector field goes by the form
language.

Also here: the second normal derivative n^T H n of a basis function (:func:`second_normal`), the
order-2 part of the face-jump penalty's integrand.
"""

from __future__ import annotations

import numpy as np

from .pointwise import _Zero

__all__ = ["second_normal", "mass_blocks", "stiffness_blocks", "tangential_blocks", "normal_gradient_blocks", "face_jump_blocks",
           "nitsche_blocks"]


#: cells per block on P2 fields: their gradients are (cells, points, 10, 3), 18 MB a block at degree 4
#: (the P1 blocks' 65536 cells would make 220 MB arrays, several at once)
BLOCK_CELLS = 1 << 13


def second_normal(hessian, n):
    """n^T H n of Hessians H (m, q, 3, 3) (of a vector field (m, q, 3, 3, 3), per component) and
    normals n (m, 1, 3); ZERO (and the probe) pass through."""
    if isinstance(hessian, _Zero) or isinstance(n, _Zero):
        return hessian
    if hessian.ndim == 5:
        n = n[:, :, None]
    return np.einsum("...ij,...i,...j->...", hessian, n, n)


def _gram(B):
    """(m, k, k) B^T B of rows B (m, r, k): sum over r of B_ra B_rb."""
    return np.matmul(np.swapaxes(B, 1, 2), B)


def _cells(term, space):
    """Per block of the term's measure at the field's degree: (quad, elements, values, gradients, None)."""
    measure = term.measure
    for _, quad in measure.blocks(term.integrand.degree_for(space.order), BLOCK_CELLS):
        el = space.local_elements(measure, quad.parent)
        yield (quad, el) + space.derivatives(measure, quad, el, hessians=False)


def _along(G, n):
    """(m, q, k) n . grad phi_k of gradients G (m, q, k, 3) and directions n (m, 3) or (m, q, 3), by matmul."""
    n = n[:, None, :, None] if n.ndim == 2 else n[..., None]
    return np.matmul(G, n)[..., 0]


def _full(G, q):
    """Gradients (m, 1 or q, k, 3) with their point axis spelled out to q."""
    return np.broadcast_to(G, (G.shape[0], q) + G.shape[2:])


def mass_blocks(term, space):
    """(u, v): the Gram matrix of the values sqrt(w_q) phi_a(x_q)."""
    for quad, el, phi, _, _ in _cells(term, space):
        yield space.element_dofs[el], _gram(phi * np.sqrt(quad.weights)[..., None])


def _gradient_gram(G, weights):
    """(m, k, k) sum_q w_q grad phi_a . grad phi_b of gradients G (m, q or 1, k, 3)."""
    m, q = weights.shape
    B = _full(G, q) * np.sqrt(weights)[..., None, None]  # (m, q, k, 3)
    B = np.swapaxes(B, 2, 3).reshape(m, 3 * q, G.shape[2])
    return _gram(B)


def stiffness_blocks(term, space):
    """h_T^a (grad u, grad v) over a volume (a = ``h_power``, 0 by default)."""
    a = term.params.get("h_power", 0)
    for quad, el, _, G, _ in _cells(term, space):
        weights = quad.weights if a == 0 else quad.weights * (term.measure.h[quad.parent] ** a)[:, None]
        yield space.element_dofs[el], _gradient_gram(G, weights)


def tangential_blocks(term, space):
    """(P_h grad u, P_h grad v) over a surface, P_h = I - n n^T with the normals of the cells (of the
    points on a deformed surface)."""
    for quad, el, _, G, _ in _cells(term, space):
        G = _full(G, quad.weights.shape[1])
        n = np.broadcast_to(quad.point_normals, G.shape[:2] + (3,))  # the cell's normal, or the point's (deformed)
        tG = G - _along(G, n)[..., None] * n[:, :, None, :]
        yield space.element_dofs[el], _gradient_gram(tG, quad.weights)


def normal_gradient_blocks(term, space):
    """h_T^a (n_h . grad u, n_h . grad v) over whole tets with a normal."""
    measure, a = term.measure, term.params["h_power"]
    for quad, el, _, G, _ in _cells(term, space):
        m, q = quad.weights.shape
        n = measure.normals[quad.parent] if quad.normal is None else np.broadcast_to(quad.point_normals, (m, q, 3))  # lifted: per point
        dn = _along(_full(G, q), n)
        scale = np.sqrt(quad.weights * (measure.h[quad.parent] ** a)[:, None])
        yield space.element_dofs[el], _gram(dn * scale[..., None])


def face_jump_blocks(term, space):
    """sum_F h^a ([n . grad u], [n . grad v])_F + h^(a+2) / 4 ([n^T H u n], [n^T H v n])_F: the local
    matrices on the dofs of the two tets of each face (minus, then plus)."""
    measure, a = term.measure, term.params["h_power"]
    for _, quad in measure.blocks(term.integrand.degree_for(space.order), BLOCK_CELLS):
        m, q = quad.weights.shape
        pairs = measure.facets.pairs[quad.parent]
        points = quad.points if quad.reference_points is None else quad.reference_points
        n, h = quad.normal, measure.h[quad.parent]
        first, second, dofs = [], [], []
        for s, sign in ((0, 1.0), (1, -1.0)):
            el = space.local_elements(measure, pairs[:, s])
            _, G, H = space.derivatives(measure, quad, el, points=points, cells=pairs[:, s])
            first.append(sign * _along(_full(G, q), n))
            second.append(None if H is None else sign * _along(np.matmul(H, n[:, None, None, :, None])[..., 0], n))
            dofs.append(space.element_dofs[el])
        jumps = np.concatenate(first, axis=2) * np.sqrt(quad.weights * (h**a)[:, None])[..., None]
        local = _gram(jumps)
        if second[0] is not None:
            hess = np.concatenate(second, axis=2)  # (m, 1, 2k) constant on the face, or (m, q, 2k) on a deformed one
            w = quad.weights.sum(axis=1, keepdims=True) if hess.shape[1] == 1 else quad.weights
            local += _gram(hess * np.sqrt(0.25 * (h ** (a + 2.0))[:, None] * w)[..., None])
        yield np.concatenate(dofs, axis=1), local


def nitsche_blocks(term, space, outward):
    """-(n . grad u, v) - (u, n . grad v) + (gamma / h_T)(u, v) over Gamma_h, n = ``outward`` n_h."""
    measure, gamma = term.measure, term.params["gamma"]
    for quad, el, phi, G, _ in _cells(term, space):
        m, q = quad.weights.shape
        dn = outward * _along(_full(G, q), np.broadcast_to(quad.point_normals, (m, q, 3)))
        pw = phi * quad.weights[..., None]
        cross = np.matmul(np.swapaxes(pw, 1, 2), dn)  # (m, k, k): sum_q w phi_a (n . grad phi_b)
        penalty = (gamma / measure.h[quad.parent])[:, None, None]
        yield space.element_dofs[el], penalty * _gram(phi * np.sqrt(quad.weights)[..., None]) - cross - np.swapaxes(cross, 1, 2)
