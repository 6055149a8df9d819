"""P2 fields (CutSpace(..., order=2)): interpolation, the reference element matrices, the affine-map
identity of a deformed quadrature, definiteness, and the ghost penalty of order 2 (docs/math.md §18)."""

import itertools
import math

import numpy as np
import pytest
import sympy

from cutfem.fem.forms import assemble, bilinear_form
from cutfem.fem.norms import l2_h1_errors
from cutfem.fem.pointwise import dot, inner
from cutfem.fem.spaces import CutSpace, ProductSpace, VectorSpace
from cutfem.fem.terms import (face_jump_penalty, interface_nitsche, load, mass, nitsche, normal_gradient_penalty, position_load, stiffness,
                              tangential_stiffness)
from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT, NEG, POS, ElementSet
from cutfem.geometry.measures import Measure
from cutfem.geometry.mesh import TetMesh
from cutfem.geometry.numbering import TET_EDGES
from cutfem.geometry.quadrature import Quadrature
from cutfem.geometry.shapes import Sphere


def quadratic(x):
    return 1.0 - 2.0 * x[..., 0] + 0.5 * x[..., 1] + 3.0 * x[..., 0] ** 2 - x[..., 1] * x[..., 2] + 0.7 * x[..., 2] ** 2


def quadratic_gradient(x):
    return np.stack([-2.0 + 6.0 * x[..., 0], 0.5 - x[..., 2], -x[..., 1] + 1.4 * x[..., 2]], axis=-1)


@pytest.fixture(scope="module")
def perturbed():
    """A cut of a 4^3 Kuhn box whose interior nodes are moved at random (general tets), by a sphere."""
    b = structured_box([-1, -1, -1], [1, 1, 1], cells=4)
    points = np.array(b.points, dtype=float)
    inner_nodes = np.all(np.abs(points) < 0.99, axis=1)
    points[inner_nodes] += np.random.default_rng(0).uniform(-0.12, 0.12, (inner_nodes.sum(), 3))
    mesh = TetMesh(points, np.array(b.tets), orient=True)
    values = np.linalg.norm(points, axis=1) - 0.8
    cut = cut_mesh(mesh, values)
    whole = np.setdiff1d(cut.elements(NEG).tet_ids, cut.elements(CUT).tet_ids)
    return mesh, values, cut, int(whole[0])


@pytest.fixture(scope="module")
def sphere_cut():
    return cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=6), Sphere(0.7, [0.03, -0.01, 0.02]))


def test_order_is_checked(sphere_cut):
    with pytest.raises(ValueError, match="order must be 1"):
        CutSpace(sphere_cut, NEG, order=3)


def test_p1_dofs_are_a_prefix_and_edges_follow_in_background_order(sphere_cut):
    V1, V2 = CutSpace(sphere_cut, NEG), CutSpace(sphere_cut, NEG, order=2)
    n = V1.n_dofs
    assert np.array_equal(V2.element_dofs[:, :4], V1.element_dofs)
    assert np.array_equal(V2.dof_points[:n], V1.dof_points)
    pairs = V2.node_ids[V2.edge_nodes]  # background node pairs, sorted and increasing
    assert np.all(pairs[:, 0] < pairs[:, 1])
    keys = pairs[:, 0] * (pairs.max() + 1) + pairs[:, 1]
    assert np.all(np.diff(keys) > 0)
    assert V2.n_dofs == n + len(V2.edge_nodes)
    # local dof 4 + e is the midpoint of the element's edge TET_EDGES[e]
    X = V2.dof_points
    mid = 0.5 * (X[V2.element_dofs[:, TET_EDGES[:, 0]]] + X[V2.element_dofs[:, TET_EDGES[:, 1]]])
    assert np.allclose(X[V2.element_dofs[:, 4:]], mid, atol=1e-15)


@pytest.mark.parametrize("on", [NEG, CUT])
def test_quadratics_are_reproduced(sphere_cut, on):
    V = CutSpace(sphere_cut, on, order=2)
    u = V.interpolate(quadratic)
    measure = sphere_cut.dx(NEG) if on == NEG else sphere_cut.ds()
    x = measure.quadrature(6).points
    assert np.abs(V.evaluate(u, measure, 6) - quadratic(x)).max() < 1e-13
    l2, h1 = l2_h1_errors(V, u, lambda x: (quadratic(x), quadratic_gradient(x)), measure)
    assert l2 < 1e-13 and h1 < 1e-12
    if on == CUT:
        assert np.abs(V.surface_vertex_values(u) - quadratic(sphere_cut.vertices)).max() < 1e-13


def _reference_matrices(X):
    """(stiffness, mass) of the P2 basis on the tet X (4, 3), in the local order (vertices, then the
    edges of TET_EDGES), from the basis polynomials in the barycentric coordinates and the exact
    integrals int_T lambda^a = |T| a! 3! / (|a| + 3)!."""
    lam = sympy.symbols("l0:4")
    phi = [lam[i] * (2 * lam[i] - 1) for i in range(4)] + [4 * lam[i] * lam[j] for i, j in TET_EDGES]
    M = np.hstack([np.ones((4, 1)), X])
    G = np.linalg.inv(M)[1:].T  # (4, 3): row i the gradient of lambda_i
    volume = abs(np.linalg.det(M)) / 6.0

    def integral(p):
        total = 0.0
        for exps, c in sympy.Poly(sympy.expand(p), *lam).terms():
            total += float(c) * math.prod(math.factorial(a) for a in exps) * 6.0 / math.factorial(sum(exps) + 3)
        return volume * total

    dphi = [[sympy.diff(p, lam[i]) for i in range(4)] for p in phi]
    GG = G @ G.T
    K, Mm = np.zeros((10, 10)), np.zeros((10, 10))
    for a, b in itertools.product(range(10), repeat=2):
        K[a, b] = integral(sum(sympy.Float(GG[i, j]) * dphi[a][i] * dphi[b][j] for i in range(4) for j in range(4)))
        Mm[a, b] = integral(phi[a] * phi[b])
    return K, Mm


def test_reference_stiffness_and_mass(perturbed):
    mesh, _, cut, tet = perturbed
    es = ElementSet(mesh, [tet], name="one", cut=cut)
    V = CutSpace(cut, es, order=2)
    dx = cut.dx(es)
    d = V.element_dofs[0]
    K_ref, M_ref = _reference_matrices(V.dof_points[d[:4]])
    K = assemble(stiffness(dx), V).toarray()[np.ix_(d, d)]
    M = assemble(mass(dx), V).toarray()[np.ix_(d, d)]
    assert np.abs(K - K_ref).max() < 1e-12 * np.abs(K_ref).max()
    assert np.abs(M - M_ref).max() < 1e-12 * np.abs(M_ref).max()
    # the closed form of the P2 mass matrix, |T| / 420 times: 6 and 1 (vertices), -4 and -6 (a vertex and
    # an edge through it or not), 32, 16 and 8 (an edge, two edges with a vertex in common or none)
    assert np.allclose(M_ref[0] * 420 / dx.size, [6, 1, 1, 1, -4, -4, -4, -6, -6, -6])
    assert np.allclose(M_ref[4, 4:] * 420 / dx.size, [32, 16, 16, 16, 16, 8])


class _Deformed(Measure):
    """The whole tets of ``base`` mapped by x -> A x + b: points and weights of the image, with the
    undeformed points as reference points and D Theta = A as jacobians."""

    def __init__(self, base, A, b):
        super().__init__(base.elements, "deformed")
        self.base, self.A, self.b = base, A, b

    def _build(self, degree):
        q = self.base.quadrature(degree)
        m, n = q.weights.shape
        return Quadrature(q.points @ self.A.T + self.b, q.weights * abs(np.linalg.det(self.A)), q.parent, None, q.bary, q.whole,
                          reference_points=q.points, jacobians=np.broadcast_to(self.A, (m, n, 3, 3)))


@pytest.mark.parametrize("order", [1, 2])
def test_affine_map_identity(perturbed, order):
    """A quadrature mapped by x -> A x + b (jacobians A, reference points the undeformed ones) gives
    the matrices and loads of the same assembly on the mapped tets."""
    mesh, values, cut, _ = perturbed
    A = np.array([[1.3, 0.2, -0.1], [0.1, 0.8, 0.3], [-0.2, 0.1, 1.1]])
    b = np.array([0.3, -0.2, 0.5])
    image = TetMesh(mesh.points @ A.T + b, mesh.tets)
    image_cut = cut_mesh(image, values)
    V = CutSpace(cut, NEG, order=order)
    W = CutSpace(image_cut, NEG, order=order)
    deformed = _Deformed(cut.dx(cut.elements(NEG)), A, b)
    physical = image_cut.dx(image_cut.elements(NEG))

    @bilinear_form(symmetric=True)
    def form(u, v, w):
        a = dot(u.grad, v.grad) + (1.0 + w.x[..., 0] ** 2) * u * v
        return a + inner(u.hess, v.hess) if order == 2 else a

    f = lambda x: np.sin(x[..., 0]) + x[..., 1] * x[..., 2]  # noqa: E731
    K1, K2 = assemble(form * deformed, V).toarray(), assemble(form * physical, W).toarray()
    assert np.abs(K1 - K2).max() < 1e-12 * np.abs(K2).max()
    b1, b2 = assemble(load(f, deformed), V), assemble(load(f, physical), W)
    assert np.abs(b1 - b2).max() < 1e-13 * np.abs(b2).max()
    u = V.interpolate(lambda x: quadratic(x @ A.T + b))  # the same discrete function on both
    assert np.allclose(u, W.interpolate(quadratic), atol=1e-13)


def test_matrices_are_symmetric_and_definite(sphere_cut):
    V = CutSpace(sphere_cut, NEG, order=2)
    dx, ds = sphere_cut.dx(NEG), sphere_cut.ds()
    ghost = sphere_cut.dF(sphere_cut.ghost_facets(NEG))
    a = stiffness(dx) + nitsche(ds, 40.0) + 0.1 * face_jump_penalty(ghost, h_power=1)
    # the mass of the cut parts alone is near singular on small parts: with the ghost penalty it is not
    gp = 0.1 * face_jump_penalty(ghost, h_power=1)
    for form, definite in ((a, True), (mass(dx) + gp, True), (stiffness(dx) + gp, False)):
        K = assemble(form, V).toarray()
        assert np.abs(K - K.T).max() <= 1e-14 * np.abs(K).max()
        ev = np.linalg.eigvalsh(K)
        if definite:
            assert ev[0] > 1e-10 * ev[-1]
        else:  # the constants are its kernel, nothing below
            assert ev[0] > -1e-12 * ev[-1] and abs(ev[0]) < 1e-12 * ev[-1] and ev[1] > 1e-10 * ev[-1]
    W = CutSpace(sphere_cut, CUT, order=2)
    K = assemble(tangential_stiffness(ds) + mass(ds) + normal_gradient_penalty(sphere_cut.dx(sphere_cut.elements(CUT)), 1.0), W)
    ev = np.linalg.eigvalsh(K.toarray())
    assert ev[0] > 1e-10 * ev[-1]


def test_ghost_penalty_of_order_two(sphere_cut):
    V1, V2 = CutSpace(sphere_cut, NEG), CutSpace(sphere_cut, NEG, order=2)
    ghost = sphere_cut.dF(sphere_cut.ghost_facets(NEG))
    G1, G2 = assemble(face_jump_penalty(ghost, h_power=1), V1), assemble(face_jump_penalty(ghost, h_power=1), V2)
    u = V2.interpolate(quadratic)
    assert np.abs(G2 @ u).max() < 1e-12 * abs(G2).max() * np.abs(u).max()  # a global quadratic has no jumps
    cubic = V2.interpolate(lambda x: x[..., 0] ** 3)
    assert cubic @ G2 @ cubic > 1e-3 * abs(G2).max()  # its second derivatives jump
    # a P1 function in P2 (linear on each tet: no Hessian) sees the P1 ghost penalty
    p1 = V1.interpolate(lambda x: np.sin(2 * x[..., 0]) * x[..., 1])
    p2 = V2.interpolate_nodal(p1)
    assert np.isclose(p2 @ G2 @ p2, p1 @ G1 @ p1, rtol=1e-11)


def test_vector_space_of_p2(sphere_cut):
    V = VectorSpace(CutSpace(sphere_cut, NEG, order=2))
    assert V.order == 2 and V.n_dofs == 3 * V.scalar.n_dofs
    K = assemble(stiffness(sphere_cut.dx(NEG)), V)
    Ks = assemble(stiffness(sphere_cut.dx(NEG)), V.scalar)
    assert abs(K[: V.scalar.n_dofs, : V.scalar.n_dofs] - Ks).max() < 1e-13 * abs(Ks).max()


def test_vectorised_terms_match_the_form_language(sphere_cut):
    """The built-in terms on P2 (:mod:`cutfem.fem.high_order`, all basis pairs at once) are the
    quadrature of their integrands by the form language, to round-off."""
    c = sphere_cut
    V, P, W = (CutSpace(c, on, order=2) for on in (NEG, POS, CUT))
    band = c.dx(c.elements(CUT))
    cases = [(V, stiffness(c.dx(NEG))), (V, mass(c.dx(NEG))), (V, face_jump_penalty(c.dF(c.ghost_facets(NEG)), h_power=1)),
             (V, nitsche(c.ds(), 20.0)), (P, nitsche(c.ds(), 20.0)), (W, tangential_stiffness(c.ds())), (W, mass(c.ds())),
             (W, normal_gradient_penalty(band, 1.0)), (W, face_jump_penalty(c.dF(c.interior_facets(CUT)))), (W, stiffness(band)),
             (ProductSpace(V, P), interface_nitsche(c.ds(), 1.0, 0.1, 20.0))]
    for space, form in cases:
        A, B = assemble(form, space), assemble(form.by_quadrature(), space)
        assert abs(A - B).max() <= 1e-14 * abs(B).max(), form.terms[0][1].integrand.__name__


def test_vectorised_terms_match_the_form_language_on_a_lifted_cut():
    """As above on a cut lifted by Theta_h (cut_mesh(..., order=2)): the gradients and Hessians
    mapped only on the cells Theta_h moves (identity elsewhere), the Hessians of the form language's
    route computed when its integrand reads them."""
    c = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=6), Sphere(0.7, [0.03, -0.01, 0.02]), order=2)
    assert c.deformation.max_shift > 1e-4
    V, P, W = (CutSpace(c, on, order=2) for on in (NEG, POS, CUT))
    cases = [(V, stiffness(c.dx(NEG))), (V, mass(c.dx(NEG))), (V, face_jump_penalty(c.dF(c.ghost_facets(NEG)), h_power=1)),
             (P, nitsche(c.ds(), 20.0)), (W, tangential_stiffness(c.ds())), (W, mass(c.ds())),
             (W, face_jump_penalty(c.dF(c.interior_facets(CUT)))), (ProductSpace(V, P), interface_nitsche(c.ds(), 1.0, 0.1, 20.0)),
             (ProductSpace(V, P), interface_nitsche(c.ds(), 2.0, 1.0, 5.0, "volume") + stiffness(c.dx(NEG), field=0))]
    for space, form in cases:
        A, B = assemble(form, space), assemble(form.by_quadrature(), space)
        assert abs(A - B).max() <= 1e-13 * abs(B).max(), form.terms[0][1].integrand.__name__
        assert abs(A - A.T).max() == 0.0


def test_compiled_loads_match_the_form_language(sphere_cut):
    """The loads on P2 (load, the Nitsche load, the position load; one and two right-hand sides) by their compiled
    kernels are the form language's quadrature of their integrands, on a planar and a lifted cut."""
    lifted = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=6), Sphere(0.7, [0.03, -0.01, 0.02]), order=2)
    f = lambda x: np.sin(x[..., 0]) + x[..., 1] * x[..., 2]  # noqa: E731
    pair = lambda x: np.stack([f(x), x[..., 0] ** 2], axis=-1)  # noqa: E731
    for c in (sphere_cut, lifted):
        V, W = CutSpace(c, NEG, order=2), CutSpace(c, CUT, order=2)
        for space, form in ((V, load(f, c.dx(NEG))), (V, load(pair, c.dx(NEG), degree=2)), (V, nitsche(c.ds(), 20.0, g=f).load),
                            (W, load(f, c.ds())), (ProductSpace(V, CutSpace(c, POS, order=2)), load(f, c.dx(POS), field=1)),
                            (V, nitsche(c.ds(), 20.0, g=pair).load), (W, position_load(c.ds()))):
            a, b = assemble(form, space), assemble(form.by_quadrature(), space)
            assert a.shape == b.shape and np.abs(a - b).max() <= 1e-13 * np.abs(b).max()


def test_surface_norms_of_p2(sphere_cut):
    """On S_h the errors, the discrete norm and the integral of a P2 trace field use its quadratic
    values, not its vertex values: a quadratic's error is zero, its integral the rule's."""
    from cutfem.fem.norms import discrete_error, h1_error, l2_error, surface_integral

    W = CutSpace(sphere_cut, CUT, order=2)
    u = W.interpolate(quadratic)
    ds = sphere_cut.ds()
    assert l2_error(W, u, quadratic) < 1e-13
    assert h1_error(W, u, quadratic_gradient) < 1e-12
    assert np.isclose(surface_integral(W, u), ds.integrate(quadratic, 2), rtol=1e-13)
    assert np.isclose(discrete_error(W, u), np.sqrt(ds.integrate(lambda x: quadratic(x) ** 2, 4)), rtol=1e-13)


def test_boundary_dofs_of_p2():
    cut = cut_mesh(structured_box([0, 0, 0], [1, 1, 1], cells=4), Sphere(0.45, [0.5, 0.5, 0.5]))
    for side in (NEG, POS):
        V = CutSpace(cut, side, order=2)
        x = V.dof_points
        on = np.any((np.abs(x) < 1e-12) | (np.abs(x - 1) < 1e-12), axis=1)  # the nodes and edge midpoints on the box
        assert np.array_equal(np.sort(V.boundary_dofs), np.flatnonzero(on)) and on.any()


def test_lifted_linear_functions_are_exact_on_an_isoparametric_cut():
    """On a cut lifted by the P2 map Theta_h (cut_mesh(..., order=2)) a linear q, composed with
    Theta_h, is a P2 function of the undeformed tets: its lifted gradient is grad q, its lifted
    Hessian zero (Theta_h's own second derivatives taken into account), on the deformed cells and on
    the faces, where its ghost penalty then vanishes."""
    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=6), Sphere(0.7, [0.03, -0.01, 0.02]), order=2)
    V = CutSpace(cut, NEG, order=2)
    a = np.array([0.3, -1.2, 0.7])
    es = V.elements
    nodes = V.dof_points[V.element_dofs][:, None]  # (m, 1, 10, 3)
    theta = cut.deformation.map(es, np.arange(es.n_elements), nodes[:, 0])[0]  # (m, 10, 3)
    u = np.zeros(V.n_dofs)
    u[V.element_dofs] = theta @ a + 0.5
    assert cut.deformation.max_shift > 1e-4

    dx = cut.dx(NEG)
    quad = dx.quadrature(4)
    el = V.local_elements(dx, quad.parent)
    values, G, H = V.derivatives(dx, quad, el)
    local = u[V.element_dofs[el]]
    assert np.abs(np.einsum("mqk,mk->mq", values, local) - (quad.points @ a + 0.5)).max() < 1e-12
    assert np.abs(np.einsum("mqkd,mk->mqd", G, local) - a).max() < 1e-11
    assert np.abs(np.einsum("mqkij,mk->mqij", H, local)).max() < 1e-9
    ghost = cut.dF(cut.ghost_facets(NEG))
    Gp = assemble(face_jump_penalty(ghost, h_power=1), V)
    assert abs(u @ Gp @ u) < 1e-14 * abs(Gp).max() * (u @ u)
