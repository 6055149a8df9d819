"""A real field (RealSpace): one unknown, the constant 1 on every measure, for constraints.

Expected numbers: the coupling of a P1 field with the constant is the vector of the integrals of
its basis functions (basis_integrals, to round-off); the bordered Poisson-Neumann system is
nonsingular where the plain one has the constants as its kernel, and its solution has mean zero
over Omega_h (to round-off) and approximates u minus its mean (L2 rate about 2: 2.46 at the coarse levels tested, 2.25 at spacings 0.1 to 0.05).
"""

import numpy as np
import pytest
import scipy.sparse as sp

import cutfem as cf
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.spaces import CutSpace, ProductSpace, RealSpace, VectorSpace
from cutfem.fem.terms import basis_integrals, face_jump_penalty, load, mass, stiffness
from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.geometry.shapes import Sphere
from cutfem.solvers.direct import DirectSolver

U = cf.Exact("sin(x) * exp(y / 2)")


@bilinear_form(symmetric=True)
def constraint(u, v, w):
    """(u, mu) + (lam, v): the mean value of the field u[0] against the multiplier u[1]."""
    return u[0] * v[1] + u[1] * v[0]


def _neumann(spacing):
    """-Lap u = f in the ball, n . grad u = g on Gamma_h (the sphere's exact normal), (u, 1) = 0 by a multiplier."""
    cut = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), Sphere(1.0, [0.03, -0.02, 0.01]))
    V = CutSpace(cut, NEG)
    W = ProductSpace(u=V, lam=RealSpace())
    dx, ds = cut.dx(NEG), cut.ds()
    a = stiffness(dx, field="u") + 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1, field="u") + constraint * dx
    grad = U.grad
    center = np.array([0.03, -0.02, 0.01])

    @linear_form
    def flux(v, w):
        n = (w.x - center) / np.linalg.norm(w.x - center, axis=-1, keepdims=True)
        return np.einsum("mqd,mqd->mq", grad(w.x), n) * v

    K = assemble(a, W)
    b = assemble(load(-U.laplacian, dx, field="u") + flux.on(ds, field="u"), W)
    return cut, V, W, K, b


@pytest.fixture(scope="module")
def coarse():
    return _neumann(0.2)


def test_the_multiplier_row_is_the_integrals_of_the_basis_functions(coarse):
    cut, V, W, K, b = coarse
    assert K.shape == (V.n_dofs + 1, V.n_dofs + 1) and W.offsets.tolist() == [0, V.n_dofs, V.n_dofs + 1]
    ones = assemble(basis_integrals(cut.dx(NEG)), V)
    row = K[V.n_dofs].toarray().ravel()
    np.testing.assert_allclose(row[:-1], ones, rtol=0, atol=1e-14 * ones.max())
    assert row[-1] == 0.0 and (K != K.T).nnz == 0
    assert K[V.n_dofs].nnz == np.count_nonzero(ones)  # the row holds the field's dofs, nothing more
    assert b[-1] == 0.0
    # a linear form on the real field: (c, mu) = c |Omega_h|
    c = assemble(linear_form(lambda v, w: 2.5 * v[1]) * cut.dx(NEG), W)
    assert c[-1] == pytest.approx(2.5 * ones.sum(), rel=1e-13) and not c[:-1].any()


def test_bordered_neumann_problem_is_nonsingular_with_the_mean_zero_solution(coarse):
    cut, V, W, K, b = coarse
    plain = K[: V.n_dofs, : V.n_dofs]
    assert np.abs(plain @ np.ones(V.n_dofs)).max() < 1e-12 * abs(plain).max()  # the constants: singular without it
    solver = DirectSolver(K, spd=False)
    x = solver.solve(b)
    assert np.abs(K @ x - b).max() < 1e-10 * np.abs(b).max()
    u, lam = W.split(x)
    ones = assemble(basis_integrals(cut.dx(NEG)), V)
    assert abs(ones @ u) < 1e-12 * np.abs(ones).sum() * np.abs(u).max()  # mean zero over Omega_h
    assert abs(lam[0]) < 1e-2  # compatible data up to the geometry error: a small multiplier
    s = sp.linalg.svds(K.tocsc(), k=1, which="SM", return_singular_vectors=False, tol=1e-8, random_state=0)
    assert s[0] > 1e-4 * abs(K).max()


def test_bordered_neumann_problem_converges():
    errors, hs = [], []
    for s in (0.4, 0.2):
        cut, V, W, K, b = _neumann(s)
        u = W.split(DirectSolver(K, spd=False).solve(b))[0]
        dx = cut.dx(NEG)
        mean = assemble(load(U, dx), V).sum() / assemble(basis_integrals(dx), V).sum()
        errors.append(cf.l2_error(V, u, lambda x: U(x) - mean, dx))
        hs.append(V.h)
    # measured: 3.77e-2, 8.19e-3 (rate 2.46, pre-asymptotic: 2.46 and 2.25 on to spacings 0.1 and 0.05)
    assert abs(cf.rates(hs, errors)[0] - 2) < 0.5 and errors[-1] < 1.1 * 8.19e-3


def test_built_in_terms_refuse_a_real_field(coarse):
    cut, V, W, K, b = coarse
    with pytest.raises(TypeError, match="RealSpace"):
        assemble(mass(cut.dx(NEG), field="lam"), W)


def test_a_real_field_beside_a_vector_field(coarse):
    """ProductSpace(u=VectorSpace(V), p=V, lam=RealSpace()): the Stokes layout; the pressure's mean
    row and the divergence block (-div u, q) assemble like any fields."""
    cut, V, _, _, _ = coarse
    W = ProductSpace(u=VectorSpace(V), p=V, lam=RealSpace())
    form = bilinear_form(lambda u, v, w: -u[0].div * v[1] - v[0].div * u[1] + u[1] * v[2] + u[2] * v[1], symmetric=True)
    K = assemble(form * cut.dx(NEG), W)
    assert K.shape == (4 * V.n_dofs + 1,) * 2 and (K != K.T).nnz == 0
    x = W.join([W[0].interpolate(lambda p: p * [1.0, 2.0, -0.5]), np.zeros(V.n_dofs), [0.0]])
    ones = assemble(basis_integrals(cut.dx(NEG)), V)
    np.testing.assert_allclose(W.split(K @ x)[1], -2.5 * ones, rtol=0, atol=1e-13 * ones.max())  # div = 1 + 2 - 0.5
