"""Tests of cutfem.geometry.shapes (Sphere, Torus, Ellipsoid, Plane) against independent references.

References used (tests/levelset_references.py): central finite differences, closed forms of the
sphere, first and second fundamental forms of explicit parametrizations (torus, ellipsoid),
Gauss-Legendre x trapezoid quadrature of parametric area elements, and brute-force minimization
over dense surface samples.
"""

import numpy as np
import pytest

from cutfem.geometry.shapes import Ellipsoid, Plane, Sphere, Torus
from levelset_references import (
    ellipsoid_param,
    fd_gradient,
    fd_jacobian,
    parametric_geometry,
    random_directions,
    tensor_quadrature,
    torus_param,
)

RNG_SEED = 20240601


def _sample_points(rng):
    """Random points in a box, away from the singular sets of the shapes used below."""
    return rng.uniform(-1.4, 1.4, size=(40, 3)) + np.array([0.1, -0.2, 0.3])


@pytest.mark.parametrize(
    "levelset",
    [
        Sphere(0.7, center=(0.1, -0.2, 0.3)),
        Torus(1.0, 0.5, center=(0.1, -0.2, 0.3)),
        Torus(1.3, 0.2),
        Ellipsoid(1.0, 0.8, 0.6, center=(0.1, -0.2, 0.3)),
    ],
    ids=["sphere", "torus", "thin-torus", "ellipsoid"],
)
def test_gradient_and_hessian_match_finite_differences(levelset):
    rng = np.random.default_rng(RNG_SEED)
    x = _sample_points(rng)
    g = levelset.gradient(x)
    hess = levelset.hessian(x)
    assert g.shape == (40, 3) and hess.shape == (40, 3, 3)
    np.testing.assert_allclose(g, fd_gradient(levelset.value, x), atol=1e-7)
    np.testing.assert_allclose(hess, fd_jacobian(levelset.gradient, x), atol=1e-6)
    np.testing.assert_allclose(hess, np.swapaxes(hess, 1, 2), atol=1e-14)
    # leading shapes are preserved
    assert levelset.value(x.reshape(4, 10, 3)).shape == (4, 10)
    assert levelset.hessian(x[0]).shape == (3, 3)


def test_sphere_curvature_and_mean_curvature_vector():
    R, c = 1.7, np.array([0.3, -0.1, 0.2])
    s = Sphere(R, center=c)
    rng = np.random.default_rng(RNG_SEED)
    u = random_directions(rng, 30)
    on = c + R * u
    np.testing.assert_allclose(s.value(on), 0.0, atol=1e-14)
    np.testing.assert_allclose(s.mean_curvature(on), 2 / R, rtol=1e-13)
    x = c + u * rng.uniform(0.3, 3.0, size=(30, 1))
    np.testing.assert_allclose(s.exact_mean_curvature_vector(x), (2 / R) * u, atol=1e-13)
    np.testing.assert_allclose(s.exact_normal(x), u, atol=1e-14)
    np.testing.assert_allclose(s.closest_point(x), on, atol=1e-14)
    assert s.area == pytest.approx(4 * np.pi * R**2, rel=1e-15)
    assert s.volume == pytest.approx(4 / 3 * np.pi * R**3, rel=1e-15)
    assert s.is_distance and s.lipschitz == 1.0
    with pytest.raises(ValueError, match="center"):
        s.gradient(c)
    with pytest.raises(ValueError, match="radius"):
        Sphere(-1.0)


def test_torus_curvature_identities_on_the_surface():
    R, r = 1.0, 0.5
    tor = Torus(R, r)
    rng = np.random.default_rng(RNG_SEED)
    t, p = rng.uniform(0, 2 * np.pi, size=(2, 50))
    x, r_t, r_p, r_tt, r_tp, r_pp, hint = torus_param(R, r, t, p)
    n_param, k_param = parametric_geometry(r_t, r_p, r_tt, r_tp, r_pp, hint)
    np.testing.assert_allclose(tor.value(x), 0.0, atol=1e-14)
    k_closed = tor.exact_mean_curvature(x)
    # closed form (docs/math.md §1) vs trace(P Hess)/|grad| vs the fundamental forms
    np.testing.assert_allclose(k_closed, (R + 2 * r * np.cos(p)) / (r * (R + r * np.cos(p))), atol=1e-12)
    np.testing.assert_allclose(k_closed, tor.mean_curvature(x), atol=1e-12)
    np.testing.assert_allclose(k_closed, k_param, atol=1e-10)
    # |grad rho| = 1, Lap rho = k1 + k2, grad rho = n
    np.testing.assert_allclose(np.linalg.norm(tor.gradient(x), axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.trace(tor.hessian(x), axis1=1, axis2=2), k_param, atol=1e-10)
    np.testing.assert_allclose(tor.normal(x), n_param, atol=1e-12)


def test_torus_exact_fields_off_the_surface():
    R, r, c = 1.2, 0.4, np.array([0.2, 0.1, -0.3])
    tor = Torus(R, r, center=c)
    rng = np.random.default_rng(RNG_SEED + 1)
    t, p = rng.uniform(0, 2 * np.pi, size=(2, 50))
    x, r_t, r_p, r_tt, r_tp, r_pp, hint = torus_param(R, r, t, p)
    n, k = parametric_geometry(r_t, r_p, r_tt, r_tp, r_pp, hint)
    delta = rng.uniform(-0.3, 0.3, size=50)
    y = c + x + delta[:, None] * n
    np.testing.assert_allclose(tor.value(y), delta, atol=1e-13)
    np.testing.assert_allclose(tor.closest_point(y), c + x, atol=1e-13)
    np.testing.assert_allclose(tor.exact_normal(y), n, atol=1e-12)
    np.testing.assert_allclose(tor.exact_mean_curvature(y), k, atol=1e-10)
    np.testing.assert_allclose(tor.exact_mean_curvature_vector(y), k[:, None] * n, atol=1e-10)


def test_torus_mean_curvature_vector_pass_against_the_numpy_expression():
    """Torus.exact_mean_curvature_vector (one compiled pass, in blocks) against its formula written
    in numpy, operation for operation: equal bitwise, for any shape (..., 3) and a count of points
    that is not a multiple of the block; a point on the axis or the core circle, or a NaN, still
    goes through the careful evaluation."""
    R, r, c = 1.2, 0.4, np.array([0.2, 0.1, -0.3])
    tor = Torus(R, r, center=c)
    y = np.random.default_rng(RNG_SEED + 7).uniform(-2.0, 2.0, size=(3, 601, 3))
    z = y - c
    s = np.sqrt(z[..., 0] * z[..., 0] + z[..., 1] * z[..., 1])
    d = np.sqrt((s - R) * (s - R) + z[..., 2] * z[..., 2])
    cos_p = (s - R) / d
    scale = (R + 2.0 * r * cos_p) / (r * d * (R + r * cos_p))
    expected = np.stack([scale * ((s - R) / s) * z[..., 0], scale * ((s - R) / s) * z[..., 1], scale * z[..., 2]], axis=-1)
    got = tor.exact_mean_curvature_vector(y)
    assert got.shape == y.shape
    np.testing.assert_array_equal(got, expected)
    with pytest.raises(ValueError, match="axis"):
        tor.exact_mean_curvature_vector(np.array([[1.0, 0.0, 0.0], [0.2, 0.1, 0.5]]))
    with pytest.raises(ValueError, match="core circle"):
        tor.exact_mean_curvature_vector(c + np.array([[R, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="NaN"):
        tor.exact_mean_curvature_vector(np.array([[1.0, np.nan, 0.0]]))


def test_torus_area_volume_bounds_and_bad_input():
    R, r = 1.0, 0.5
    tor = Torus(R, r)
    assert tor.area == pytest.approx(4 * np.pi**2 * R * r, rel=1e-15)
    assert tor.volume == pytest.approx(2 * np.pi**2 * R * r**2, rel=1e-15)
    # independent: integrate |x_t x x_p| and (1/3) x . n over the parametrization (periodic -> trapezoid)
    n_grid = 64
    tt, pp = np.meshgrid(*(2 * np.pi * np.arange(n_grid) / n_grid,) * 2, indexing="ij")
    x, r_t, r_p, _, _, _, hint = torus_param(R, r, tt.ravel(), pp.ravel())
    cross = np.cross(r_t, r_p)
    dA = np.linalg.norm(cross, axis=1) * (2 * np.pi / n_grid) ** 2
    normal = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    normal *= np.sign(np.sum(normal * hint, axis=1))[:, None]
    assert dA.sum() == pytest.approx(tor.area, rel=1e-12)
    assert (np.sum(x * normal, axis=1) * dA).sum() / 3 == pytest.approx(tor.volume, rel=1e-12)
    lo, hi = tor.bounds()
    np.testing.assert_allclose(lo, x.min(axis=0), atol=1e-2)
    np.testing.assert_allclose(hi, x.max(axis=0), atol=1e-2)
    assert np.all(lo <= x.min(axis=0)) and np.all(hi >= x.max(axis=0))
    with pytest.raises(ValueError, match="r < R"):
        Torus(1.0, 1.0)
    with pytest.raises(ValueError, match="axis"):
        tor.gradient(np.array([[0.0, 0.0, 0.3]]))
    with pytest.raises(ValueError, match="core circle"):
        tor.closest_point(np.array([[1.0, 0.0, 0.0]]))


def test_ellipsoid_exact_fields_against_parametrization():
    a, b, c = 1.0, 0.8, 0.6
    center = np.array([0.1, 0.2, -0.1])
    ell = Ellipsoid(a, b, c, center=center)
    assert ell.lipschitz is None and not ell.is_distance
    rng = np.random.default_rng(RNG_SEED)
    th = np.arccos(rng.uniform(-0.98, 0.98, size=60))
    ph = rng.uniform(0, 2 * np.pi, size=60)
    x, r_t, r_p, r_tt, r_tp, r_pp, hint = ellipsoid_param(a, b, c, th, ph)
    n, k = parametric_geometry(r_t, r_p, r_tt, r_tp, r_pp, hint)
    np.testing.assert_allclose(ell.mean_curvature(center + x), k, rtol=1e-12)
    # off the surface, within the reach c^2/a = 0.36
    delta = rng.uniform(-0.15, 0.3, size=60)
    y = center + x + delta[:, None] * n
    np.testing.assert_allclose(ell.closest_point(y), center + x, atol=1e-12)
    np.testing.assert_allclose(ell.exact_normal(y), n, atol=1e-12)
    np.testing.assert_allclose(ell.exact_mean_curvature(y), k, rtol=1e-10)
    np.testing.assert_allclose(ell.exact_mean_curvature_vector(y), k[:, None] * n, atol=1e-10)


def test_ellipsoid_closest_point_is_the_global_minimizer():
    a, b, c = 1.0, 0.8, 0.6
    ell = Ellipsoid(a, b, c)
    # dense surface samples for a brute-force minimum
    th, ph = np.meshgrid(np.linspace(0, np.pi, 301), np.linspace(0, 2 * np.pi, 600), indexing="ij")
    samples = ellipsoid_param(a, b, c, th.ravel(), ph.ravel())[0]
    rng = np.random.default_rng(RNG_SEED)
    queries = np.concatenate(
        [
            rng.uniform(-0.5, 0.5, size=(15, 3)),  # deep inside (far from the surface)
            rng.uniform(-2.0, 2.0, size=(10, 3)),
            [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.1, 0.05, 0.0], [0.0, 0.3, 0.0], [3.0, 0.0, 0.0]],
            # next to the medial set (tiny components) and far away
            [[0.3, 0.1, 1e-9], [0.1, 1e-12, -1e-12], [0.6, -0.4, -1e-7], [1e3, -2e2, 5e2]],
        ]
    )
    p = ell.closest_point(queries)
    np.testing.assert_allclose(ell.value(p), 0.0, atol=1e-12)
    dist = np.linalg.norm(queries - p, axis=1)
    brute = np.min(np.linalg.norm(queries[:, None, :] - samples[None, :, :], axis=2), axis=1)
    spacing = np.pi / 300 * a  # max parameter-to-arc factor is the largest semi-axis
    assert np.all(dist <= brute + 1e-12)
    assert np.all(dist >= brute - spacing**2)
    # the center: closest points are (0, 0, +-c)
    np.testing.assert_allclose(np.abs(p[25]), [0.0, 0.0, c], atol=1e-15)


def test_closest_points_lie_on_the_surface_along_the_normal():
    rng = np.random.default_rng(RNG_SEED)
    shapes = [Sphere(0.9, center=(0.1, 0, 0)), Torus(1.0, 0.5), Ellipsoid(1.0, 0.8, 0.6)]
    for ls in shapes:
        lo, hi = ls.bounds()
        x = rng.uniform(lo - 0.3, hi + 0.3, size=(200, 3))
        p = ls.closest_point(x)
        assert np.max(np.abs(ls.value(p))) < 1e-12
        n = ls.exact_normal(x)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-14)
        np.testing.assert_allclose(np.cross(x - p, n), 0.0, atol=1e-12)


def test_ellipsoid_with_equal_axes_is_a_sphere():
    R = 1.3
    ell, sph = Ellipsoid(R, R, R), Sphere(R)
    rng = np.random.default_rng(RNG_SEED)
    x = random_directions(rng, 30) * rng.uniform(0.2, 2.5, size=(30, 1))
    np.testing.assert_allclose(ell.mean_curvature(R * random_directions(rng, 30)), 2 / R, rtol=1e-13)
    np.testing.assert_allclose(ell.exact_mean_curvature(x), 2 / R, rtol=1e-12)
    np.testing.assert_allclose(ell.closest_point(x), sph.closest_point(x), atol=1e-13)
    assert ell.area == pytest.approx(4 * np.pi * R**2, rel=1e-15)


@pytest.mark.parametrize(
    "axes", [(1.0, 0.8, 0.6), (0.6, 1.0, 0.8), (2.0, 1.0, 1.0), (1.0, 1.0, 0.5), (1.0, 0.99, 0.98), (3.0, 0.5, 0.2)]
)
def test_ellipsoid_area_and_volume_against_quadrature(axes):
    a, b, c = axes
    ell = Ellipsoid(a, b, c)
    th, ph, w = tensor_quadrature(200, 256, (0.0, np.pi))
    x, r_t, r_p, _, _, _, hint = ellipsoid_param(a, b, c, th, ph)
    cross = np.cross(r_t, r_p)
    dA = np.linalg.norm(cross, axis=1)
    assert ell.area == pytest.approx(np.sum(w * dA), rel=1e-8)
    # volume by the divergence theorem: V = (1/3) int x . n dA
    assert ell.volume == pytest.approx(np.sum(w * np.sum(x * cross, axis=1)) / 3, rel=1e-8)
    lo, hi = ell.bounds()
    np.testing.assert_allclose(hi, axes)
    np.testing.assert_allclose(lo, -np.asarray(axes))


def test_torus_value_is_numpys_hypot_bit_for_bit():
    """The compiled torus level set gives the bits of the numpy expression (libm's hypot both
    ways), keeps the shape of its input, and names points that are not finite."""
    tor = Torus(1.1, 0.4, center=(0.1, -0.2, 0.05))
    x = np.random.default_rng(2).uniform(-2, 2, (7, 11, 3))
    y = x - tor.center
    ref = np.hypot(y[..., 2], np.hypot(y[..., 0], y[..., 1]) - tor.R) - tor.r
    np.testing.assert_array_equal(tor.value(x), ref)
    assert tor.value(x[0, 0]).shape == () and tor.value(x[0]).shape == (11,)
    x[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        tor.value(x)
    with pytest.raises(ValueError, match="shape"):
        tor.value(np.zeros((4, 2)))


def test_plane_is_the_signed_distance_to_its_plane():
    """Plane(n, p): phi = n.(x - p) / |n|, grad the unit normal, Hessian 0, the closest point on the
    plane along the normal, curvature 0; a zero normal or a bad point is refused."""
    rng = np.random.default_rng(RNG_SEED)
    x = rng.uniform(-1, 1, size=(20, 3))
    plane = Plane((0.0, 3.0, 4.0), (0.1, 0.2, 0.3))
    n = np.array([0.0, 0.6, 0.8])
    np.testing.assert_allclose(plane.value(x), (x - [0.1, 0.2, 0.3]) @ n, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(plane.gradient(x), np.broadcast_to(n, x.shape))
    np.testing.assert_array_equal(plane.hessian(x), np.zeros((20, 3, 3)))
    p = plane.closest_point(x)
    np.testing.assert_allclose(plane.value(p), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.cross(x - p, n), 0.0, atol=1e-15)
    assert np.all(plane.exact_mean_curvature(x) == 0) and plane.bounds() is None
    with pytest.raises(ValueError, match="normal must be a nonzero vector"):
        Plane((0, 0, 0))
    with pytest.raises(ValueError, match="the point must be 3 finite coordinates"):
        Plane((0, 0, 1), (0, np.nan, 0))
