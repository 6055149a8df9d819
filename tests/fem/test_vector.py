"""Vector fields (VectorSpace): what an integrand sees, the built-in terms on them, elasticity, errors, multigrid.

Expected numbers are exact identities written here: the divergence, symmetric gradient and curl of
a linear field are its matrix's trace, symmetric part and axial vector on every cell; the
componentwise terms are kron(I_3, the scalar matrix) bit for bit; the rigid motions a + b x x are
in the kernel of elasticity (and of its ghost penalty); the fast paths equal the quadrature of the
terms' integrands to round-off; the vector errors are the root of the components' squared errors.
Rates of manufactured solutions (cf.Exact) within 0.25 of 2 (L2) and 1 (H1), measured at the
levels given beside them.
"""

import numpy as np
import pytest
import scipy.sparse as sp

import cutfem as cf
from cutfem.fem.assembly import block_diagonal
from cutfem.fem.forms import assemble, bilinear_form
from cutfem.fem.pointwise import dot, inner
from cutfem.fem.spaces import CutSpace, ProductSpace, SurfaceP1Space, VectorSpace
from cutfem.fem.terms import (edge_jump_penalty, face_jump_penalty, load, mass, nitsche, normal_gradient_penalty,
                              position_load, stiffness, tangential_stiffness)
from cutfem.fem.elasticity import elasticity, elasticity_nitsche
from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT, NEG, POS
from cutfem.geometry.mesh import TetMesh
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.surface_meshes import torus_mesh
from cutfem.solvers.multigrid import multigrid_hierarchy

SPHERE = Sphere(0.62, center=(0.031, -0.017, 0.023))  # general position: no nodal value zero
A = np.array([[0.3, -1.1, 0.7], [2.0, 0.4, -0.5], [0.9, 1.3, -0.2]])
B = np.array([0.5, -0.25, 1.0])
MU, LAM = 1.3, 2.1


def vector_data(x):
    return np.stack([np.sin(x[..., 0]) * np.exp(x[..., 1] / 2), x[..., 1] * x[..., 2], np.cos(x[..., 2])], axis=-1)


@pytest.fixture(scope="module")
def ball():
    return cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), SPHERE)


@pytest.fixture(scope="module")
def plain_ball():
    """The same cut on the box's tets given as a plain TetMesh: no lattice, the general paths."""
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=8)
    return cut_mesh(TetMesh(np.array(box.points), np.array(box.tets)), SPHERE)


# ---------------------------------------------------------------------------------------------
# the language: dot, inner, and what a vector basis function is
# ---------------------------------------------------------------------------------------------


def test_dot_contracts_vectors_and_matrices():
    rng = np.random.default_rng(0)
    M, N = rng.normal(size=(5, 1, 3, 3)), rng.normal(size=(5, 4, 3, 3))
    u, v = rng.normal(size=(5, 4, 3)), rng.normal(size=(5, 1, 3))
    np.testing.assert_array_equal(dot(M, v), np.einsum("mqij,mqj->mqi", M, v))
    np.testing.assert_array_equal(dot(v, M), np.einsum("mqi,mqij->mqj", v, M))
    np.testing.assert_array_equal(dot(M, N), np.einsum("mqij,mqjk->mqik", np.broadcast_to(M, N.shape), N))
    np.testing.assert_array_equal(dot(u, v), np.einsum("...d,...d->...", u, v))  # vectors: as before, bit for bit
    np.testing.assert_array_equal(inner(M, N), np.einsum("mqij,mqij->mq", np.broadcast_to(M, N.shape), N))
    np.testing.assert_array_equal(inner(u, v), dot(u, v))
    assert dot(M, np.array([0.0, 0.0, 1.0])).shape == (5, 1, 3)  # a constant vector (3,)
    with pytest.raises(TypeError, match="ranks 2 and 1"):
        inner(M, v)
    assert inner(cf.ZERO, M) is cf.ZERO and dot(M, cf.ZERO) is cf.ZERO


def test_vector_basis_functions_of_a_linear_field(ball):
    """For u = A x + b: div u_h = tr A, eps(u_h) = (A + A^T) / 2, curl u_h = the axial vector of
    A - A^T, on every cell, read through the integrands of a mixed form (trial u, test a scalar q):
    (div u_h, q) = tr A (1, q) and so on, to round-off."""
    V = CutSpace(ball, NEG)
    W = ProductSpace(u=VectorSpace(V), q=V)
    x = W.join([W[0].interpolate(lambda p: p @ A.T + B), np.zeros(V.n_dofs)])
    ones = assemble(cf.basis_integrals(ball.dx(NEG)), V)
    e = np.eye(3)
    checks = {"div": (lambda u: u.div, np.trace(A)),
              "sym_grad 01": (lambda u: u.sym_grad[..., 0, 1], 0.5 * (A[0, 1] + A[1, 0])),
              "grad 21": (lambda u: u.grad[..., 2, 1], A[2, 1]),
              "curl": (lambda u: dot(u.curl, e[1]), A[0, 2] - A[2, 0]),
              "component": (lambda u: u[2] - dot(u, e[2]), 0.0)}
    for name, (of, value) in checks.items():
        mixed = bilinear_form(lambda u, v, w, of=of: of(u[0]) * v[1])
        b = W.split(assemble(mixed * ball.dx(NEG), W) @ x)[1]
        np.testing.assert_allclose(b, value * ones, rtol=0, atol=1e-13 * np.abs(ones).max() * (1 + abs(value))), name


def test_two_vector_fields_in_a_product_space(ball):
    """The jump of two vector fields across Gamma, (u_N - u_P, v_N - v_P): its first block is the
    vector mass on Gamma, and it vanishes on one field given to both sides."""
    WN, WP = VectorSpace(CutSpace(ball, NEG)), VectorSpace(CutSpace(ball, POS))
    W = ProductSpace(WN, WP)
    K = assemble(bilinear_form(lambda u, v, w: inner(u[0] - u[1], v[0] - v[1]), symmetric=True) * ball.ds(), W)
    n = WN.n_dofs
    M = assemble(mass(ball.ds()), WN)
    assert abs(K[:n, :n] - M).max() <= 1e-14 * abs(M).max()
    x = W.join([WN.interpolate(lambda p: p @ A.T + B), WP.interpolate(lambda p: p @ A.T + B)])
    assert np.abs(K @ x).max() <= 1e-13 * abs(K).max() * np.abs(x).max()


def test_a_vector_is_not_multiplied_into_a_scalar(ball):
    W = VectorSpace(CutSpace(ball, NEG))
    with pytest.raises(TypeError, match="dot"):
        assemble(bilinear_form(lambda u, v, w: u * v) * ball.dx(NEG), W)
    with pytest.raises(ValueError, match="one value per cell"):  # a vector integrand, not a number per point
        assemble(bilinear_form(lambda u, v, w: u.value * v.value) * ball.dx(NEG), W)
    with pytest.raises(ValueError, match=r"vector data.*\(m, q, 3\)"):
        assemble(load(lambda x: x[..., 0], ball.dx(NEG)), W)
    with pytest.raises(TypeError, match="scalar P1 space"):
        VectorSpace(W)
    with pytest.raises(TypeError, match="vector field"):
        assemble(elasticity(ball.dx(NEG), MU, LAM), W.scalar)
    with pytest.raises(ValueError, match="lam"):
        elasticity(ball.dx(NEG), MU, -1.0)


# ---------------------------------------------------------------------------------------------
# built-in terms on vector fields: kron(I_3, A), and every fast path against the quadrature
# ---------------------------------------------------------------------------------------------


def test_vector_terms_are_kron_of_the_scalar_ones(ball):
    """The vector Laplacian (and mass, ghost penalty, Nitsche) is kron(I_3, the scalar matrix)
    exactly, and its load is the scalar loads of the components, stacked."""
    V = CutSpace(ball, NEG)
    W = VectorSpace(V)
    dx, ds, dg = ball.dx(NEG), ball.ds(), ball.dF(ball.ghost_facets(NEG))
    form = stiffness(dx) + 0.5 * mass(dx) + 0.1 * face_jump_penalty(dg, h_power=1) + nitsche(ds, 10.0)
    K, k = assemble(form, W), assemble(form, V)
    assert (K != sp.kron(sp.identity(3), k)).nnz == 0
    assert (assemble(stiffness(dx), W) != block_diagonal(assemble(stiffness(dx), V), 3)).nnz == 0
    b = assemble(load(vector_data, dx) + nitsche(ds, 10.0, g=vector_data).load, W)
    columns = [assemble(load(lambda x, c=c: vector_data(x)[..., c], dx) + nitsche(ds, 10.0, g=lambda x, c=c: vector_data(x)[..., c]).load, V)
               for c in range(3)]
    np.testing.assert_allclose(b, np.concatenate(columns), rtol=0, atol=1e-15 * np.abs(b).max())


def _vector_cases(ball, plain_ball):
    out = {}
    for name, cut in (("lattice", ball), ("plain", plain_ball)):
        for side in (NEG, POS):
            W = VectorSpace(CutSpace(cut, side))
            dx, ds, dg = cut.dx(side), cut.ds(), cut.dF(cut.ghost_facets(side))
            N = elasticity_nitsche(ds, MU, LAM, 8.0, g=vector_data)
            out[f"elasticity {side} {name}"] = (elasticity(dx, MU, LAM), W)
            out[f"elasticity nitsche {side} {name}"] = (N, W)
            out[f"elasticity nitsche load {side} {name}"] = (N.load, W)
            out[f"elasticity system {side} {name}"] = (elasticity(dx, MU, LAM) + N + (2 * MU + LAM) * 0.1 * face_jump_penalty(dg, h_power=1)
                                                       + 0.3 * mass(dx), W)
            out[f"vector laplacian system {side} {name}"] = (stiffness(dx) + nitsche(ds, 8.0) + 0.1 * face_jump_penalty(dg, h_power=1), W)
            out[f"nitsche load {side} {name}"] = (nitsche(ds, 8.0, g=vector_data).load, W)
            out[f"load {side} {name}"] = (load(vector_data, dx), W)
        out[f"elasticity whole cut tets {name}"] = (elasticity(cut.dx(CUT), MU, 0.0), VectorSpace(CutSpace(cut, NEG)))
    T = VectorSpace(CutSpace(ball, CUT))
    out["trace terms"] = (mass(ball.ds()) + tangential_stiffness(ball.ds()) + 0.1 * face_jump_penalty(ball.dF(ball.interior_facets(CUT)))
                          + normal_gradient_penalty(ball.dx(CUT)), T)
    out["position load"] = (position_load(ball.ds()), T)
    mesh = VectorSpace(SurfaceP1Space(torus_mesh(12, "perturbed-flipped", seed=3)))
    out["meshed surface terms"] = (mass(mesh.scalar.mesh.ds()) + tangential_stiffness(mesh.scalar.mesh.ds()), mesh)
    out["meshed position load"] = (position_load(mesh.scalar.mesh.ds()), mesh)
    return out


@pytest.fixture(scope="module")
def vector_cases(ball, plain_ball):
    return _vector_cases(ball, plain_ball)


CASES = [f"{t} {s} {b}" for b in ("lattice", "plain") for s in (NEG, POS) for t in
         ("elasticity", "elasticity nitsche", "elasticity nitsche load", "elasticity system", "vector laplacian system",
          "nitsche load", "load")] + ["elasticity whole cut tets lattice", "elasticity whole cut tets plain", "trace terms",
                                      "position load", "meshed surface terms", "meshed position load"]


@pytest.mark.parametrize("case", CASES)
def test_fast_paths_are_the_quadrature_of_the_integrands(vector_cases, case):
    form, W = vector_cases[case]
    exact, quadrature = assemble(form, W), assemble(form.by_quadrature(), W)
    if form.linear:
        assert exact.shape == (W.n_dofs,)
        assert np.abs(exact - quadrature).max() <= 1e-12 * np.abs(quadrature).max()
    else:
        assert abs(exact - quadrature).max() <= 1e-12 * abs(quadrature).max()
        assert (exact != exact.T).nnz == 0  # exactly symmetric


def test_edge_penalty_on_a_vector_surface_field():
    W = VectorSpace(SurfaceP1Space(torus_mesh(12, "perturbed-flipped", seed=3)))
    ds = W.scalar.mesh.ds()
    assert (assemble(edge_jump_penalty(ds), W) != block_diagonal(assemble(edge_jump_penalty(ds), W.scalar), 3)).nnz == 0


def test_rigid_motions_are_the_kernel_of_elasticity(ball, plain_ball):
    """K r = 0 for the six rigid motions a + b x x (no boundary condition), with the ghost penalty,
    on the lattice and the general path, to round-off; a non-rigid linear field is not in it."""
    for cut in (ball, plain_ball):
        W = VectorSpace(CutSpace(cut, NEG))
        K = assemble(elasticity(cut.dx(NEG), MU, LAM) + 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1), W)
        e = np.eye(3)
        motions = [lambda x, a=a: np.broadcast_to(a, x.shape) for a in e] + [lambda x, b=b: np.cross(b, x) for b in e]
        for r in motions:
            x = W.interpolate(r)
            assert np.abs(K @ x).max() <= 1e-13 * abs(K).max() * np.abs(x).max()
        stretch = W.interpolate(lambda x: x @ A.T)
        assert np.abs(K @ stretch).max() > 1e-3 * abs(K).max()


def test_elasticity_on_its_rows_is_2_mu_eps_eps_plus_lam_div_div(ball):
    """elasticity(mu, lam) = 2 mu E + lam D with E, D the matrices of the user integrands
    eps(u) : eps(v) and div u div v (the linearity in the parameters, through the fast path)."""
    W = VectorSpace(CutSpace(ball, NEG))
    dx = ball.dx(NEG)
    E = assemble(bilinear_form(lambda u, v, w: inner(u.sym_grad, v.sym_grad), symmetric=True) * dx, W)
    D = assemble(bilinear_form(lambda u, v, w: u.div * v.div, symmetric=True) * dx, W)
    K = assemble(elasticity(dx, MU, LAM), W)
    assert abs(K - (2 * MU * E + LAM * D)).max() <= 1e-13 * abs(K).max()


# ---------------------------------------------------------------------------------------------
# errors and the multigrid hierarchy
# ---------------------------------------------------------------------------------------------


def test_vector_errors_are_the_components_errors(ball):
    V = CutSpace(ball, NEG)
    W = VectorSpace(V)
    u = cf.Exact(["sin(x) * exp(y / 2)", "y * z", "cos(z)"])
    grad = u.grad
    x = W.interpolate(lambda p: u(p) + 0.01 * np.sin(7 * p))
    dx = ball.dx(NEG)
    l2, h1 = cf.l2_h1_errors(W, x, lambda p: (u(p), grad(p)), dx)
    parts = [cf.l2_h1_errors(V, W.nodal(x)[:, c], lambda p, c=c: (u(p)[..., c], grad(p)[..., c, :]), dx) for c in range(3)]
    assert l2 == pytest.approx(np.sqrt(sum(p[0] ** 2 for p in parts)), rel=1e-13)
    assert h1 == pytest.approx(np.sqrt(sum(p[1] ** 2 for p in parts)), rel=1e-13)
    assert cf.l2_error(W, x, u, dx) == pytest.approx(l2, rel=1e-13)
    assert cf.h1_error(W, x, grad, dx) == pytest.approx(h1, rel=1e-13)
    linear = W.interpolate(lambda p: p @ A.T + B)
    zero = cf.l2_h1_errors(W, linear, lambda p: (p @ A.T + B, np.broadcast_to(A, p.shape[:2] + (3, 3))), dx)
    assert zero[0] < 1e-13 and zero[1] < 1e-12


def test_multigrid_sees_three_copies_of_the_scalar_hierarchy(ball):
    V = CutSpace(ball, NEG)
    scalar, vector = multigrid_hierarchy(V), multigrid_hierarchy(VectorSpace(V))
    for _ in range(2):
        P, P3 = next(scalar), next(vector)
        assert (P3 != sp.block_diag([P] * 3)).nnz == 0


# ---------------------------------------------------------------------------------------------
# convergence: vector Poisson and elasticity on a cut ball (Nitsche + ghost penalty)
# ---------------------------------------------------------------------------------------------

U = cf.Exact(["sin(x) * exp(y / 2)", "cos(y) * z", "x * y * z + sin(z)"])


def _vector_poisson(spacing):
    cut = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), Sphere(1.0, [0.03, -0.02, 0.01]))
    W = VectorSpace(CutSpace(cut, NEG))
    dx, ds = cut.dx(NEG), cut.ds()
    N = nitsche(ds, 10.0, g=U)
    form = stiffness(dx) + N + 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
    f = -U.laplacian
    x, _ = cf.solve(assemble(form, W), assemble(load(f, dx) + N.load, W), space=W)
    grad = U.grad
    return W.h, *cf.l2_h1_errors(W, x, lambda p: (U(p), grad(p)), dx)


def _elasticity(spacing, mu=1.0, lam=2.0):
    cut = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), Sphere(1.0, [0.03, -0.02, 0.01]))
    W = VectorSpace(CutSpace(cut, NEG))
    dx, ds = cut.dx(NEG), cut.ds()
    N = elasticity_nitsche(ds, mu, lam, 10.0, g=U)
    form = elasticity(dx, mu, lam) + N + (2 * mu + lam) * 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
    f = -(2 * mu * U.sym_grad + lam * U.div * cf.Exact.identity()).div
    x, info = cf.solve(assemble(form, W), assemble(load(f, dx) + N.load, W), space=W, indefinite_hint=form.indefinite_hint)
    grad = U.grad
    return W.h, *cf.l2_h1_errors(W, x, lambda p: (U(p), grad(p)), dx), info


def _rates(runs):
    h = [r[0] for r in runs]
    return cf.rates(h, [r[1] for r in runs])[-1], cf.rates(h, [r[2] for r in runs])[-1]


def test_vector_poisson_converges():
    runs = [_vector_poisson(s) for s in (0.4, 0.2)]
    # measured: L2 4.15e-2, 1.27e-2 (rate 1.91); H1 0.468, 0.264 (0.92)
    l2, h1 = _rates(runs)
    assert abs(l2 - 2) < 0.25 and abs(h1 - 1) < 0.25
    assert runs[-1][1] < 1.1 * 1.27e-2 and runs[-1][2] < 1.1 * 0.264


def test_elasticity_on_a_cut_ball_converges_with_multigrid():
    runs = [_elasticity(s) for s in (0.2, 0.1)]
    # measured: L2 2.14e-2, 6.10e-3 (rate 1.92); H1 0.280, 0.136 (1.11); 17475 unknowns, cg-mg in 14 iterations
    l2, h1 = _rates(runs)
    assert abs(l2 - 2) < 0.25 and abs(h1 - 1) < 0.25
    assert runs[-1][1] < 1.1 * 6.10e-3 and runs[-1][2] < 1.1 * 0.136
    info = runs[-1][3]
    assert info.method == "cg-mg" and info.iterations <= 20


@pytest.mark.slow
def test_vector_poisson_and_elasticity_converge_on_finer_levels():
    # measured at spacings 0.1, 0.05 (17475 and 118713 unknowns): vector Poisson L2 3.40e-3, 7.94e-4 (2.16),
    # H1 0.131, 0.0638 (1.06); elasticity L2 6.10e-3, 1.43e-3 (2.15), H1 0.136, 0.0650 (1.09), cg-mg 14 and 15 iterations
    for solve in (_vector_poisson, _elasticity):
        runs = [solve(s) for s in (0.1, 0.05)]
        l2, h1 = _rates(runs)
        assert abs(l2 - 2) < 0.2 and abs(h1 - 1) < 0.2, (solve.__name__, l2, h1)
