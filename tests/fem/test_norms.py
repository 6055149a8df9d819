"""Tests for cutfem.fem.norms: error functionals and convergence rates.

References: exact areas summed from the triangles, exact rates of synthetic data, the known O(h^2)
interpolation error, the mass matrix's quadratic form computed in the test.
"""

import numpy as np
import pytest

from cutfem.fem.norms import discrete_error, fitted_rate, h1_error, l2_error, l2_h1_errors, rates, surface_integral
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import NEG
from cutfem.geometry.box import structured_box
from cutfem.geometry.surface_meshes import sphere_mesh
from surface_matrices import mass_matrix


@pytest.fixture(scope="module")
def small_cut_sphere():
    return CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02])))


def smooth(x):
    return np.sin(2 * x[..., 0]) * x[..., 1] + np.exp(x[..., 2])


def smooth_gradient(x):
    g = np.zeros(x.shape)
    g[..., 0] = 2 * np.cos(2 * x[..., 0]) * x[..., 1]
    g[..., 1] = np.sin(2 * x[..., 0])
    g[..., 2] = np.exp(x[..., 2])
    return g


def test_interpolation_error_rates_meshed_sphere():
    h, e0, e1 = [], [], []
    for level in (2, 3, 4):
        V = SurfaceP1Space(sphere_mesh(level))
        u = V.interpolate(smooth)
        h.append(V.h)
        e0.append(l2_error(V, u, smooth))
        e1.append(h1_error(V, u, smooth_gradient))
    assert V.h == pytest.approx((10 * 4**4 + 2) ** -0.5)
    assert np.all((rates(h, e0) > 1.85) & (rates(h, e0) < 2.15))
    assert np.all((rates(h, e1) > 0.9) & (rates(h, e1) < 1.15))
    assert fitted_rate(h, e0) == pytest.approx(2.0, abs=0.1)


def test_interpolation_error_rate_cut_sphere():
    h, e = [], []
    for cells in (8, 16, 32):
        V = CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=cells), Sphere(0.7, [0.03, -0.01, 0.02])))
        h.append(V.h)
        e.append(l2_error(V, V.interpolate(smooth), smooth))
    assert h[0] == pytest.approx(9**-1.0)
    assert np.all((rates(h, e) > 1.8) & (rates(h, e) < 2.3))


def test_linear_functions_have_zero_error(small_cut_sphere):
    V = small_cut_sphere
    g = np.array([0.5, -1.0, 2.0])
    u = V.interpolate(lambda x: x @ g + 1.0)
    assert l2_error(V, u, lambda x: x @ g + 1.0) < 1e-13
    assert h1_error(V, u, lambda x: np.broadcast_to(g, x.shape)) < 1e-12
    X = V.interpolate(lambda x: x)
    assert l2_error(V, X, lambda x: x) < 1e-13  # vector valued
    assert l2_error(V, u, lambda x: x @ g) == pytest.approx(np.sqrt(V.cut.area), rel=1e-12)  # off by 1
    with pytest.raises(ValueError, match="degree >= 4"):
        l2_error(V, u, lambda x: x @ g, degree=2)


def test_one_pass_errors_equal_the_separate_ones():
    """l2_h1_errors against l2_error and h1_error: on a bulk field over the cut volume of a side
    (whole and cut tets, several blocks), and on a trace over S_h; zero for a linear function."""
    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=10), Sphere(0.7, [0.03, -0.01, 0.02]))
    V = CutSpace(cut, NEG)
    dx = cut.dx(NEG)
    u = V.interpolate(lambda x: np.cos(x[..., 0]) * x[..., 2])
    pair = l2_h1_errors(V, u, lambda x: (smooth(x), smooth_gradient(x)), dx, chunk=500)
    assert pair[0] == pytest.approx(l2_error(V, u, smooth, dx), rel=1e-13)
    assert pair[1] == pytest.approx(h1_error(V, u, smooth_gradient, dx), rel=1e-13)
    assert pair[0] > 0.1 and pair[1] > 0.1
    T = CutSpace(cut)
    w = T.interpolate(smooth)
    l2, h1 = l2_h1_errors(T, w, lambda x: (smooth(x), smooth_gradient(x)))
    assert l2 == pytest.approx(l2_error(T, w, smooth), rel=1e-12)
    assert h1 == pytest.approx(h1_error(T, w, smooth_gradient), rel=1e-13)
    g = np.array([0.5, -1.0, 2.0])
    lin = V.interpolate(lambda x: x @ g + 1.0)
    zero = l2_h1_errors(V, lin, lambda x: (x @ g + 1.0, np.broadcast_to(g, x.shape)), dx)
    assert zero[0] < 1e-13 and zero[1] < 1e-12
    # two columns: a gradient per column (rows), the errors the root of the columns' squared sums
    two = l2_h1_errors(V, np.stack([u, u], axis=1), lambda x: (np.stack([smooth(x)] * 2, axis=-1),
                                                                np.stack([smooth_gradient(x)] * 2, axis=-2)), dx)
    one = l2_h1_errors(V, u, lambda x: (smooth(x), smooth_gradient(x)), dx)
    np.testing.assert_allclose(two, np.sqrt(2.0) * np.array(one), rtol=1e-13)
    with pytest.raises(ValueError, match=r"exact gradient must have shape \(\d+, \d+, 2, 3\)"):
        l2_h1_errors(V, np.stack([u, u], axis=1), lambda x: (np.stack([smooth(x)] * 2, axis=-1), smooth_gradient(x)), dx)


@pytest.mark.parametrize("c", [1, 3])
def test_cell_error_kernels_are_the_weighted_sums(c):
    """element_kernels.cell_value_error and cell_gradient_error against the sums written out in numpy:
    per-cell basis values and one shared table, scalar and vector fields, with and without the
    tangential projection."""
    from cutfem.fem.element_kernels import cell_gradient_error, cell_value_error

    rng = np.random.default_rng(c)
    b, q, k = 37, 14, 4
    phi, local, exact, w = rng.random((b, q, k)), rng.normal(size=(b, k, c)), rng.normal(size=(b, q, c)), rng.random((b, q))
    ref = np.sum(w[..., None] * (exact - np.einsum("bqk,bkc->bqc", phi, local)) ** 2)
    assert cell_value_error(phi, local, exact, w) == pytest.approx(ref, rel=1e-13)
    table = phi[:1]
    ref = np.sum(w[..., None] * (exact - np.einsum("qk,bkc->bqc", table[0], local)) ** 2)
    assert cell_value_error(table, local, exact, w) == pytest.approx(ref, rel=1e-13)
    # the gradients read from a table by type (here 5 types), as the Kuhn table of a structured box
    gtable, types = rng.normal(size=(5, k, 3)), rng.integers(0, 5, b)
    grads, u, ge = gtable[types], rng.normal(size=(b, k)), rng.normal(size=(b, q, 3))
    d = ge - np.einsum("bk,bkd->bd", u, grads)[:, None, :]
    assert cell_gradient_error(gtable, types, u, ge, w, np.zeros((0, 3))) == pytest.approx(np.sum(w * np.sum(d * d, axis=2)), rel=1e-13)
    n = rng.normal(size=(b, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dt = d - np.sum(d * n[:, None, :], axis=2, keepdims=True) * n[:, None, :]
    assert cell_gradient_error(gtable, types, u, ge, w, n) == pytest.approx(np.sum(w * np.sum(dt * dt, axis=2)), rel=1e-13)
    # one table row per element (a generic mesh's stored gradients): the same sum as the gathered rows
    assert cell_gradient_error(grads, np.arange(b), u, ge, w, n) == cell_gradient_error(gtable, types, u, ge, w, n)


def test_discrete_error_and_surface_integral():
    V = SurfaceP1Space(sphere_mesh(2))
    P = np.asarray(V.dof_points)[V.element_dofs]
    area = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1).sum()
    M = mass_matrix(V)
    assert discrete_error(V, np.full(V.n_dofs, 3.0)) == pytest.approx(3.0 * np.sqrt(area), rel=1e-12)
    E = np.column_stack([np.ones(V.n_dofs), 2 * np.ones(V.n_dofs), np.zeros(V.n_dofs)])
    assert discrete_error(V, E) == pytest.approx(np.sqrt(5 * area), rel=1e-12)  # components summed
    rng = np.random.default_rng(3)
    e = rng.normal(size=V.n_dofs)
    assert discrete_error(V, e) == pytest.approx(np.sqrt(e @ (M @ e)), rel=1e-13)  # the mass matrix's quadratic form
    # a cut space: the traces at the vertices of S_h give the cut mass matrix's form
    W = CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02])))
    Mw = mass_matrix(W)
    Ew = rng.normal(size=(W.n_dofs, 2))
    assert discrete_error(W, Ew) == pytest.approx(np.sqrt(np.sum(Ew * (Mw @ Ew))), rel=1e-12)
    with pytest.raises(ValueError):
        discrete_error(CutSpace(W.cut, NEG), np.ones(CutSpace(W.cut, NEG).n_dofs))  # a bulk field has no S_h
    assert surface_integral(V, np.full(V.n_dofs, 2.0)) == pytest.approx(2 * area, rel=1e-12)
    np.testing.assert_allclose(surface_integral(V, E), [area, 2 * area, 0.0], rtol=1e-12, atol=1e-14)


def test_rates_on_synthetic_data():
    h = np.array([0.4, 0.2, 0.1, 0.025])
    np.testing.assert_allclose(rates(h, 3.0 * h**2), [2.0, 2.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(rates(h, 0.5 * h**1.3), [1.3, 1.3, 1.3], rtol=1e-12)
    e = np.array([1.0, 0.5, 0.125, 0.1])
    np.testing.assert_allclose(rates(h, e), [1.0, 2.0, np.log(1.25) / np.log(4.0)], rtol=1e-12)
    assert fitted_rate(h, 7.0 * h**1.5) == pytest.approx(1.5, rel=1e-12)
    assert len(rates([1.0], [1.0])) == 0
