"""The compiled pieces of the P2 terms (cutfem.fem.p2_kernels): the symmetric sum of local matrices
into CSR against scipy's sum of the triples, its bits on one thread and on all, the closed-form
3 x 3 inverses, the H1 error kernel against the basis gradients, and a P2 matrix's bits on one thread."""

import numba
import numpy as np
import scipy.sparse as sp

from cutfem.fem.forms import assemble
from cutfem.fem.norms import _varying_gradient_error
from cutfem.fem.p2_kernels import inverse_3x3, symmetric_csr
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, nitsche, stiffness
from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT, NEG
from cutfem.geometry.shapes import Sphere


def _blocks(rng, m=3000, k=20, n=900):
    dofs = rng.integers(0, n, size=(m, k))
    dofs[:, k // 2 : k // 2 + 3] = dofs[:, :3]  # dofs repeated within a cell, as on a face's two tets
    local = rng.standard_normal((m, k, k))
    return dofs, local + np.swapaxes(local, 1, 2), n


def test_symmetric_csr_is_the_sum_of_the_triples_exactly_symmetric_on_any_thread_count():
    dofs, local, n = _blocks(np.random.default_rng(3))
    A = symmetric_csr(dofs, local, n)
    k = dofs.shape[1]
    rows, cols = np.repeat(dofs, k, axis=1).reshape(-1), np.tile(dofs, (1, k)).reshape(-1)
    B = sp.coo_matrix((local.reshape(-1), (rows, cols)), shape=(n, n)).tocsr()
    assert abs(A - B).max() <= 1e-13 * abs(B).max()
    assert abs(A - A.T).max() == 0.0 and A.has_sorted_indices
    assert np.array_equal(np.diff(A.indptr), np.diff(B.indptr))  # the pattern: every pair of a cell, once
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        C = symmetric_csr(dofs, local, n)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(A.data, C.data) and np.array_equal(A.indices, C.indices)


def test_symmetric_csr_of_no_cells():
    A = symmetric_csr(np.zeros((0, 10), dtype=np.int64), np.zeros((0, 10, 10)), 5)
    assert A.shape == (5, 5) and A.nnz == 0


def test_inverse_3x3_by_cofactors():
    J = np.eye(3) + 0.3 * np.random.default_rng(1).standard_normal((7, 5, 3, 3))
    assert np.allclose(inverse_3x3(J), np.linalg.inv(J), rtol=1e-12, atol=1e-12)
    assert np.array_equal(inverse_3x3(np.broadcast_to(np.eye(3), (4, 3, 3))), np.broadcast_to(np.eye(3), (4, 3, 3)))


def test_gradient_errors_match_the_gradients_of_the_basis_on_a_lifted_cut():
    """The H1 error kernel against the mapped basis gradients of CutSpace.derivatives (P2 on a volume
    and on the surface, P1 on the lifted surface)."""
    c = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=6), Sphere(0.7, [0.03, -0.01, 0.02]), order=2)
    rng = np.random.default_rng(0)
    for V, measure in ((CutSpace(c, NEG, order=2), c.dx(NEG)), (CutSpace(c, CUT, order=2), c.ds()), (CutSpace(c, CUT), c.ds())):
        coeffs = rng.standard_normal(V.n_dofs)
        quad = measure.quadrature(6)
        e = V.local_elements(measure, quad.parent)
        ge = rng.standard_normal(quad.points.shape)
        _, G, _ = V.derivatives(measure, quad, e, hessians=False)
        diff = ge - np.einsum("mk,mqkd->mqd", coeffs[V.element_dofs[e]], np.broadcast_to(G, ge.shape[:2] + G.shape[2:]))
        if measure.surface:
            diff -= np.sum(diff * quad.point_normals, axis=-1, keepdims=True) * quad.point_normals
        reference = float(np.sum(np.sum(diff**2, axis=-1) * quad.weights))
        assert abs(_varying_gradient_error(V, measure, quad, e, coeffs[V.element_dofs[e]], ge, coeffs) - reference) <= 1e-13 * reference


def test_p2_assembly_has_the_same_bits_on_one_thread():
    c = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=6), Sphere(0.7, [0.03, -0.01, 0.02]), order=2)
    V = CutSpace(c, NEG, order=2)
    form = stiffness(c.dx(NEG)) + nitsche(c.ds(), 40.0) + 0.1 * face_jump_penalty(c.dF(c.ghost_facets(NEG)), h_power=1)
    A = assemble(form, V)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        B = assemble(form, V)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(A.data, B.data) and np.array_equal(A.indices, B.indices) and np.array_equal(A.indptr, B.indptr)
