"""Exact fields from sympy (cutfem.fem.exact): derivatives against central differences of the
field's own values, vector-calculus identities that hold exactly, closed forms derived by hand, the
shapes of evaluation, and the refusals."""

import numpy as np
import pytest

import cutfem as cf
from cutfem.fem.exact import Exact

RNG = np.random.default_rng(7)
POINTS = RNG.uniform(-1.0, 1.0, (40, 3))
H = 1e-5


def differences(f, x):
    """Central differences of a callable field: shape (..., *shape, 3)."""
    return np.stack([(f(x + H * e) - f(x - H * e)) / (2 * H) for e in np.eye(3)], axis=-1)


U = Exact(["sin(pi*x)*y + z**2", "exp(x*z)", "x*y*cos(z)"])
P = Exact("x*y*z + sin(y)")


def test_gradients_and_hessian_against_differences():
    for field in (U, P):
        np.testing.assert_allclose(field.grad(POINTS), differences(field, POINTS), atol=1e-8)
    np.testing.assert_allclose(P.hessian(POINTS), differences(P.grad, POINTS), atol=1e-8)
    np.testing.assert_allclose(U.div.grad(POINTS), differences(U.div, POINTS), atol=1e-8)


def test_div_laplacian_curl_against_differences():
    G = differences(U, POINTS)  # (n, 3, 3), rows the components
    np.testing.assert_allclose(U.div(POINTS), np.trace(G, axis1=1, axis2=2), atol=1e-8)
    np.testing.assert_allclose(U.curl(POINTS), np.stack([G[:, 2, 1] - G[:, 1, 2], G[:, 0, 2] - G[:, 2, 0],
                                                         G[:, 1, 0] - G[:, 0, 1]], axis=-1), atol=1e-8)
    np.testing.assert_allclose(U.sym_grad(POINTS), (G + G.transpose(0, 2, 1)) / 2, atol=1e-8)
    lap = np.einsum("nijj->ni", differences(U.grad, POINTS))
    np.testing.assert_allclose(U.laplacian(POINTS), lap, atol=1e-6)
    np.testing.assert_allclose(P.laplacian(POINTS), np.trace(differences(P.grad, POINTS), axis1=1, axis2=2), atol=1e-6)


def test_exact_identities():
    for x in (POINTS, POINTS[:3]):
        np.testing.assert_allclose(U.curl.div(x), 0.0, atol=1e-12)  # div curl = 0
        np.testing.assert_allclose(P.grad.curl(x), 0.0, atol=1e-12)  # curl grad = 0
        np.testing.assert_allclose(U.grad.div(x), U.laplacian(x), atol=1e-12)  # div of grad u row-wise
        np.testing.assert_allclose(U.sym_grad.trace(x), U.div(x), atol=1e-12)


def test_closed_forms_by_hand():
    x, y, z = POINTS.T
    # a rigid motion: eps(u) = 0, div u = 0
    rigid = Exact(["1 - y + 2*z", "x + 3 - z", "-2*x + y"])
    np.testing.assert_array_equal(rigid.sym_grad(POINTS), 0.0)
    np.testing.assert_array_equal(rigid.div(POINTS), 0.0)
    # the Stokes load -nu Lap u + grad p for u = (y^2, 0, 0), p = x z, nu = 0.5: (-1 + z, 0, x)
    f = -0.5 * Exact(["y**2", 0, 0]).laplacian + Exact("x*z").grad
    np.testing.assert_allclose(f(POINTS), np.stack([-1 + z, 0 * x, x], axis=-1), rtol=1e-15)
    # the elastic stress of u = (x, 0, 0): sigma = 2 mu eps + lam div I = diag(2 mu + lam, lam, lam)
    u = Exact(["x", "0", "0"])
    sigma = 2 * 1.5 * u.sym_grad + 4.0 * u.div * Exact.identity()
    np.testing.assert_allclose(sigma(POINTS[:1])[0], np.diag([7.0, 4.0, 4.0]))
    np.testing.assert_allclose(sigma.dot(Exact(["0", "1", "0"]))(POINTS[:1])[0], [0.0, 4.0, 0.0])
    # the unit normal of the sphere phi = |x|^2 - 1 and its divergence, the mean curvature 2 / |x|
    phi = Exact("x**2 + y**2 + z**2 - 1")
    r = np.linalg.norm(POINTS, axis=-1)
    np.testing.assert_allclose(phi.normal(POINTS), POINTS / r[:, None], rtol=1e-14)
    np.testing.assert_allclose(phi.normal.div(POINTS), 2 / r, rtol=1e-13)


def test_shapes_constants_and_leading_axes():
    block = RNG.random((4, 5, 3))
    assert U(block).shape == (4, 5, 3) and U.grad(block).shape == (4, 5, 3, 3) and P(block).shape == (4, 5)
    np.testing.assert_array_equal(Exact(2.5)(block), np.full((4, 5), 2.5))
    np.testing.assert_array_equal(Exact([0, "x", 1])(POINTS)[:, 2], 1.0)
    np.testing.assert_allclose(Exact("a*x + b", a=2.0, b=-1.0)(POINTS), 2 * POINTS[:, 0] - 1)
    import sympy

    xs = sympy.symbols("x y z")
    np.testing.assert_allclose(Exact(sympy.sin(xs[0]) * xs[2])(POINTS), np.sin(POINTS[:, 0]) * POINTS[:, 2])


def test_a_level_set_with_exact_derivatives():
    phi = Exact("x**2/4 + y**2 + z**2 - 1")
    L = phi.level_set()
    assert isinstance(L, cf.FunctionLevelSet)
    np.testing.assert_allclose(L.value(POINTS), phi(POINTS))
    np.testing.assert_allclose(L.gradient(POINTS), np.stack([POINTS[:, 0] / 2, 2 * POINTS[:, 1], 2 * POINTS[:, 2]], -1))
    cut = cf.cut_mesh(cf.structured_box([-2.2, -1.2, -1.2], [2.2, 1.2, 1.2], spacing=0.2), L)
    # the ellipsoid with semi-axes 2, 1, 1 has volume 8 pi / 3; the P1 cut at h = 0.2 is within 3 %
    assert abs(cut.dx(cf.NEG).size - 8 * np.pi / 3) < 0.03 * 8 * np.pi / 3


@pytest.mark.parametrize("expr, kwargs, match", [
    ("a*x", {}, r"symbol\(s\) a have no value"),
    ("x +* y", {}, "cannot read"),
    ([["x", "y"], ["z", "x"]], {}, "not of shape"),
    ("x", {"a": float("nan")}, "finite real"),
    (object(), {}, "not an expression"),
])
def test_bad_input_is_refused_naming_it(expr, kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        Exact(expr, **kwargs)


def test_operators_refuse_the_wrong_kind_of_field():
    with pytest.raises(ValueError, match="scalar field has no divergence"):
        P.div
    with pytest.raises(ValueError, match="defined for a vector field"):
        P.curl
    with pytest.raises(ValueError, match="cannot \\+ fields of shapes"):
        U + P.hessian
    with pytest.raises(ValueError, match="points must have shape"):
        U(np.zeros((4, 2)))
