"""The built-in bilinear terms on P2 fields: the quadrature of their integrands by compiled
per-cell kernels.

On a P2 field (:class:`~cutfem.fem.spaces.CutSpace` of order 2) a built-in term is its integrand
(:mod:`cutfem.fem.terms`) integrated by quadrature of the field's degree
(:meth:`~cutfem.fem.forms.Integrand.degree_for`).  The form language evaluates an integrand one
pair of basis functions at a time (55 to 210 passes over a block's points); each function here
hands a block's barycentric coordinates, barycentric gradients, weights and (on a lifted cut) the
Jacobians D Theta_h of the points to a kernel of :mod:`cutfem.fem.p2_kernels`, which makes the
basis, its mapped gradients and the local matrix point by point, never a (cells, points, 10, 3)
array.  The reference is the form language itself (:meth:`~cutfem.fem.forms.Form.by_quadrature`:
the same matrices to round-off, tested).  Each function takes the term and the scalar field and
yields ``(dofs (m, k), local matrices (m, k, k))`` block by block of cells (the interface coupling
of two fields: in the numbering of the product space, :func:`interface_blocks`), which
:func:`~cutfem.fem.forms.assemble` sums by :func:`~cutfem.fem.p2_kernels.symmetric_csr`; a vector
field goes by the form language.

Linear terms alike: :func:`load_vectors`, :func:`nitsche_load_vectors` and :func:`position_load_vectors`
yield ``(dofs (m, k), local vectors (m, k) or (m, k, c))`` (:func:`~cutfem.fem.p2_kernels.cell_vectors`,
:func:`~cutfem.fem.p2_kernels.tangential_gradient_vectors`).

Also here: the second normal derivative n^T H n of a basis function (:func:`second_normal`), the
order-2 part of the face-jump penalty's integrand.
"""

from __future__ import annotations

import numpy as np

from . import p2_kernels
from .p2_kernels import MASS, NITSCHE, NORMAL_GRADIENT, STIFFNESS, TANGENTIAL
from .pointwise import _point_values, _Zero

__all__ = ["second_normal", "mass_blocks", "stiffness_blocks", "tangential_blocks", "normal_gradient_blocks", "face_jump_blocks",
           "nitsche_blocks", "interface_blocks", "load_vectors", "nitsche_load_vectors",
           "position_load_vectors"]


#: cells per block on P2 fields: a block's points and Jacobians at degree 4 (14 points) take 10 MB
BLOCK_CELLS = 1 << 13

_NONE = np.empty((0, 1, 3, 3))  # no Jacobians: the identity
_NO_NORMALS = np.empty((0, 1, 3))


def second_normal(hessian, n):
    """n^T H n of Hessians H (m, q, 3, 3) (of a vector field (m, q, 3, 3, 3), per component) and
    normals n (m, 1, 3); ZERO (and the probe) pass through."""
    if isinstance(hessian, _Zero) or isinstance(n, _Zero):
        return hessian
    if hessian.ndim == 5:
        n = n[:, :, None]
    return np.einsum("...ij,...i,...j->...", hessian, n, n)


def _cell_terms(term, space, kind, scale=None, normals=None, sign=0.0, penalty=None):
    """Per block of the term's measure at the field's degree: (dofs, local matrices) of ``kind``
    (:func:`~cutfem.fem.p2_kernels.cell_matrices`), the weights times ``scale(quad)`` (m,) when
    given, the normals ``normals(quad)`` (m, 1 or q, 3) and Nitsche's ``penalty(quad)`` (m,)."""
    measure = term.measure
    for _, quad in measure.blocks(term.integrand.degree_for(space.order), BLOCK_CELLS):
        el = space.local_elements(measure, quad.parent)
        m, q = quad.weights.shape
        lam = np.ascontiguousarray(space._barycentric_on(measure, quad, el))
        weights = quad.weights if scale is None else quad.weights * scale(quad)[:, None]
        n = _NO_NORMALS if normals is None else np.ascontiguousarray(np.broadcast_to(normals(quad), (m, q, 3)))
        jac = _NONE if quad.jacobians is None else quad.jacobians
        g = np.zeros(m) if penalty is None else penalty(quad)
        local = np.empty((m, 10, 10))
        p2_kernels.cell_matrices(kind, lam, np.ascontiguousarray(space.gradients_of(el)), np.ascontiguousarray(jac),
                                 np.ascontiguousarray(weights), n, float(sign), np.ascontiguousarray(g, dtype=float), local)
        yield space.element_dofs[el], local


def mass_blocks(term, space):
    """(u, v)."""
    return _cell_terms(term, space, MASS)


def stiffness_blocks(term, space):
    """h_T^a (grad u, grad v) over a volume (a = ``h_power``, 0 by default)."""
    a = term.params.get("h_power", 0)
    return _cell_terms(term, space, STIFFNESS, None if a == 0 else lambda quad: term.measure.h[quad.parent] ** a)


def tangential_blocks(term, space):
    """(P_h grad u, P_h grad v) over a surface, P_h = I - n n^T with the normals of the cells (of the
    points on a deformed surface)."""
    return _cell_terms(term, space, TANGENTIAL, normals=lambda quad: quad.point_normals)


def normal_gradient_blocks(term, space):
    """h_T^a (n_h . grad u, n_h . grad v) over whole tets with a normal (lifted: the normal per point)."""
    measure, a = term.measure, term.params["h_power"]
    return _cell_terms(term, space, NORMAL_GRADIENT, lambda quad: measure.h[quad.parent] ** a,
                       lambda quad: measure.normals[quad.parent][:, None] if quad.normal is None else quad.point_normals)


def nitsche_blocks(term, space, outward):
    """-(n . grad u, v) - (u, n . grad v) + (gamma / h_T)(u, v) over Gamma_h, n = ``outward`` n_h."""
    measure, gamma = term.measure, term.params["gamma"]
    return _cell_terms(term, space, NITSCHE, normals=lambda quad: quad.point_normals, sign=outward,
                       penalty=lambda quad: gamma / measure.h[quad.parent])


def face_jump_blocks(term, space):
    """sum_F h^a ([n . grad u], [n . grad v])_F + h^(a+2) / 4 ([n^T H u n], [n^T H v n])_F: the local
    matrices on the dofs of the two tets of each face (minus, then plus).  On the planar faces of a
    lifted cut each trace takes its own tet's D Theta_h at the face's points and Theta_h's Hessians
    (:meth:`~cutfem.fem.spaces.CutSpace.derivatives`)."""
    measure, a = term.measure, term.params["h_power"]
    deformation = getattr(getattr(measure.elements, "cut", None), "deformation", None)
    for _, quad in measure.blocks(term.integrand.degree_for(space.order), BLOCK_CELLS):
        m, q = quad.weights.shape
        pairs = measure.facets.pairs[quad.parent]
        points = quad.points if quad.reference_points is None else quad.reference_points
        h = measure.h[quad.parent]
        sides, dofs = [], []
        for s in range(2):
            el = space.local_elements(measure, pairs[:, s])
            lam = np.ascontiguousarray(space.barycentric_at(points, el))
            jac, theta = _NONE, np.empty((0, 3, 3, 3))
            if deformation is not None:
                jac = np.ascontiguousarray(deformation.map(measure.elements, pairs[:, s], points)[1])
                theta = np.ascontiguousarray(deformation.hessians(measure.elements, pairs[:, s]))
            sides.append((lam, np.ascontiguousarray(space.gradients_of(el)), jac, theta))
            dofs.append(space.element_dofs[el])
        (l0, g0, j0, t0), (l1, g1, j1, t1) = sides
        local = np.empty((m, 20, 20))
        p2_kernels.face_matrices(l0, l1, g0, g1, j0, j1, t0, t1, np.ascontiguousarray(quad.normal, dtype=float),
                                 np.ascontiguousarray(quad.weights), h**a, 0.25 * h ** (a + 2.0), local)
        yield np.concatenate(dofs, axis=1), local


def interface_blocks(term, space, offsets, fields, k_neg, a_neg, a_pos, two_s):
    """-({a n . grad u}, [v]) - ([u], {a n . grad v}) + (gamma 2 s / h_T)([u], [v]) over Gamma_h
    (:func:`~cutfem.fem.terms.interface_nitsche`, ``two_s`` (cut tets,) its 2 s = lambda / gamma):
    the local matrices on a cut tet's dofs in the NEG field, then the POS field (``fields``: their
    positions in the product ``space``), in the product's numbering (``offsets``), or None when a
    field is not P2 (the form language then integrates it)."""
    i, j = fields["neg_field"], fields["pos_field"]
    V, P = space.fields[i], space.fields[j]
    if getattr(V, "order", 1) < 2 or getattr(P, "order", 1) < 2:
        return None
    return _interface(term, V, P, offsets[i], offsets[j], k_neg, a_neg, a_pos, two_s)


def _interface(term, V, P, off_v, off_p, k_neg, a_neg, a_pos, two_s):
    measure, gamma = term.measure, term.params["gamma"]
    for _, quad in measure.blocks(term.integrand.degree_for(2), BLOCK_CELLS):
        el, parent = V.local_elements(measure, quad.parent), quad.parent
        m, q = quad.weights.shape
        lam = np.ascontiguousarray(V._barycentric_on(measure, quad, el))
        jac = _NONE if quad.jacobians is None else quad.jacobians
        local = np.empty((m, 20, 20))
        p2_kernels.interface_matrices(lam, np.ascontiguousarray(V.gradients_of(el)), np.ascontiguousarray(jac),
                                      np.ascontiguousarray(quad.weights), np.ascontiguousarray(np.broadcast_to(quad.point_normals, (m, q, 3))),
                                      k_neg[parent] * a_neg, (1.0 - k_neg[parent]) * a_pos, gamma * two_s[parent] / measure.h[parent], local)
        yield np.concatenate([V.element_dofs[el] + off_v, P.element_dofs[P.local_elements(measure, parent)] + off_p], axis=1), local


def _load_terms(term, space, data, what, normals=None, sign=0.0, penalty=None):
    """Per block of the term's measure at the field's degree: (dofs, local vectors) of the load
    ``data(x)`` (checked as ``what``), tested with phi, or with penalty(quad) phi - sign n . grad phi."""
    measure = term.measure
    for _, quad in measure.blocks(term.integrand.degree_for(space.order), BLOCK_CELLS):
        el = space.local_elements(measure, quad.parent)
        m, q = quad.weights.shape
        fx = _point_values(data, quad.points, what)
        fw = np.ascontiguousarray((fx * (quad.weights if fx.ndim == 2 else quad.weights[..., None])).reshape(m, q, -1))
        n = _NO_NORMALS if normals is None else np.ascontiguousarray(np.broadcast_to(normals(quad), (m, q, 3)))
        jac = _NONE if quad.jacobians is None or normals is None else quad.jacobians
        g = np.zeros(m) if penalty is None else penalty(quad)
        local = np.empty((m, 10, fw.shape[2]))
        p2_kernels.cell_vectors(np.ascontiguousarray(space._barycentric_on(measure, quad, el)),
                                np.ascontiguousarray(space.gradients_of(el)), np.ascontiguousarray(jac), fw, n, float(sign),
                                np.ascontiguousarray(g, dtype=float), local)
        yield space.element_dofs[el], local.reshape(local.shape[:2] + fx.shape[2:])


def load_vectors(term, space):
    """(f, v) over a cell measure."""
    return _load_terms(term, space, term.params["f"], "the load f(x)")


def nitsche_load_vectors(term, space, outward):
    """-(g, n . grad v) + (gamma / h_T)(g, v) over Gamma_h, n = ``outward`` n_h."""
    measure, gamma = term.measure, term.params["gamma"]
    return _load_terms(term, space, term.params["g"], "nitsche: g(x)", lambda quad: quad.point_normals, outward,
                       lambda quad: gamma / measure.h[quad.parent])


def position_load_vectors(term, space):
    """(P_h e_k, grad v), k = 1, 2, 3, over a surface: the tangential gradients of the basis with the
    points' normals (lifted: D Theta_h^-T grad and the deformed normal), one column per coordinate."""
    measure = term.measure
    for _, quad in measure.blocks(term.integrand.degree_for(space.order), BLOCK_CELLS):
        el = space.local_elements(measure, quad.parent)
        m, q = quad.weights.shape
        jac = _NONE if quad.jacobians is None else quad.jacobians
        local = np.empty((m, 10, 3))
        p2_kernels.tangential_gradient_vectors(np.ascontiguousarray(space._barycentric_on(measure, quad, el)),
                                               np.ascontiguousarray(space.gradients_of(el)), np.ascontiguousarray(jac),
                                               np.ascontiguousarray(quad.weights),
                                               np.ascontiguousarray(np.broadcast_to(quad.point_normals, (m, q, 3))), local)
        yield space.element_dofs[el], local
