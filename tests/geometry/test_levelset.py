"""Tests of cutfem.geometry.levelset against independent references.

References used: central finite differences written here, closed forms of the sphere, first and
second fundamental forms of explicit parametrizations (torus, ellipsoid), Gauss-Legendre x
trapezoid quadrature of parametric area elements, brute-force minimization over dense surface
samples, and the Hausdorff bound of an inscribed polyhedron.
"""

import numpy as np
import pytest

from cutfem.geometry.levelset import (
    Ellipsoid,
    FunctionLevelSet,
    LevelSet,
    SignedDistance,
    Sphere,
    Torus,
    interpolate,
)

RNG_SEED = 20240601


# ----------------------------------------------------------------------------------------------
# independent helpers
# ----------------------------------------------------------------------------------------------
def fd_gradient(f, x, h=1e-6):
    """Central differences of a scalar field f at x (n, 3) -> (n, 3)."""
    cols = [(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(3)]
    return np.stack(cols, axis=-1)


def fd_jacobian(g, x, h=1e-6):
    """Central differences of a vector field g at x (n, 3) -> J (n, 3, 3), J[:, i, j] = dg_i/dx_j."""
    cols = [(g(x + h * e) - g(x - h * e)) / (2 * h) for e in np.eye(3)]
    return np.stack(cols, axis=-1)


def parametric_geometry(r_u, r_v, r_uu, r_uv, r_vv, outward_hint):
    """Outward unit normal and k1 + k2 from the fundamental forms of a parametrization.

    k1 + k2 = -(e G - 2 f F + g E) / (E G - F^2) with the outward normal (2/R on a sphere).
    """
    n = np.cross(r_u, r_v)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n *= np.sign(np.sum(n * outward_hint, axis=-1))[:, None]
    E, F, G = (np.sum(a * b, axis=-1) for a, b in ((r_u, r_u), (r_u, r_v), (r_v, r_v)))
    e, f, g = (np.sum(a * n, axis=-1) for a in (r_uu, r_uv, r_vv))
    return n, -(e * G - 2 * f * F + g * E) / (E * G - F**2)


def torus_param(R, r, t, p):
    """Point, derivatives and outward hint of the torus of docs/math.md parametrization."""
    ct, st, cp, sp = np.cos(t), np.sin(t), np.cos(p), np.sin(p)
    rho = R + r * cp
    x = np.stack([rho * ct, rho * st, r * sp], axis=-1)
    r_t = np.stack([-rho * st, rho * ct, 0 * t], axis=-1)
    r_p = np.stack([-r * sp * ct, -r * sp * st, r * cp], axis=-1)
    r_tt = np.stack([-rho * ct, -rho * st, 0 * t], axis=-1)
    r_tp = np.stack([r * sp * st, -r * sp * ct, 0 * t], axis=-1)
    r_pp = np.stack([-r * cp * ct, -r * cp * st, -r * sp], axis=-1)
    core = np.stack([R * ct, R * st, 0 * t], axis=-1)
    return x, r_t, r_p, r_tt, r_tp, r_pp, x - core


def ellipsoid_param(a, b, c, th, ph):
    """Point, derivatives and outward hint of (a sin th cos ph, b sin th sin ph, c cos th)."""
    s, co, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
    x = np.stack([a * s * cp, b * s * sp, c * co], axis=-1)
    r_t = np.stack([a * co * cp, b * co * sp, -c * s], axis=-1)
    r_p = np.stack([-a * s * sp, b * s * cp, 0 * th], axis=-1)
    r_tt = np.stack([-a * s * cp, -b * s * sp, -c * co], axis=-1)
    r_tp = np.stack([-a * co * sp, b * co * cp, 0 * th], axis=-1)
    r_pp = np.stack([-a * s * cp, -b * s * sp, 0 * th], axis=-1)
    return x, r_t, r_p, r_tt, r_tp, r_pp, x


def tensor_quadrature(n_u, n_v, u_range, periodic_v=True):
    """Gauss-Legendre in u on u_range times the trapezoid rule in a periodic v on [0, 2 pi)."""
    xg, wg = np.polynomial.legendre.leggauss(n_u)
    lo, hi = u_range
    u = 0.5 * (hi - lo) * xg + 0.5 * (hi + lo)
    wu = 0.5 * (hi - lo) * wg
    v = 2 * np.pi * np.arange(n_v) / n_v
    wv = np.full(n_v, 2 * np.pi / n_v)
    U, V = np.meshgrid(u, v, indexing="ij")
    return U.ravel(), V.ravel(), np.outer(wu, wv).ravel()


def random_directions(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# derivatives against finite differences
# ----------------------------------------------------------------------------------------------
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


def _poly(x):
    return x[..., 0] ** 2 + 2 * x[..., 1] ** 2 + np.sin(x[..., 2]) + x[..., 0] * x[..., 1] * x[..., 2] - 1


def _poly_grad(x):
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([2 * x0 + x1 * x2, 4 * x1 + x0 * x2, np.cos(x2) + x0 * x1], axis=-1)


def _poly_hess(x):
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    two, four = np.full_like(x0, 2.0), np.full_like(x0, 4.0)
    return np.stack(
        [np.stack([two, x2, x1], -1), np.stack([x2, four, x0], -1), np.stack([x1, x0, -np.sin(x2)], -1)],
        axis=-2,
    )


def test_function_levelset_finite_differences_match_exact_derivatives():
    rng = np.random.default_rng(RNG_SEED)
    x = rng.uniform(-2, 2, size=(5, 6, 3))
    values_only = FunctionLevelSet(_poly)
    np.testing.assert_allclose(values_only.gradient(x), _poly_grad(x), atol=1e-8)
    np.testing.assert_allclose(values_only.hessian(x), _poly_hess(x), atol=2e-6)
    with_grad = FunctionLevelSet(_poly, gradient=_poly_grad)
    np.testing.assert_allclose(with_grad.hessian(x), _poly_hess(x), atol=1e-7)
    full = FunctionLevelSet(_poly, gradient=_poly_grad, hessian=_poly_hess)
    # the test's own central differences of the given callables
    flat = x.reshape(-1, 3)
    np.testing.assert_allclose(full.gradient(flat), fd_gradient(_poly, flat), atol=1e-7)
    np.testing.assert_allclose(full.hessian(flat), fd_jacobian(_poly_grad, flat), atol=1e-6)


def test_function_levelset_distance_closest_point_and_curvature():
    R = 0.8
    ls = FunctionLevelSet(lambda x: np.linalg.norm(x, axis=-1) - R, is_distance=True, lipschitz=1.0)
    rng = np.random.default_rng(RNG_SEED)
    x = random_directions(rng, 20) * rng.uniform(0.5, 1.5, size=(20, 1))
    np.testing.assert_allclose(ls.closest_point(x), R * x / np.linalg.norm(x, axis=1, keepdims=True), atol=1e-9)
    on = R * random_directions(rng, 20)
    np.testing.assert_allclose(ls.mean_curvature(on), 2 / R, rtol=1e-6)


def test_function_levelset_rejects_bad_shapes():
    bad = FunctionLevelSet(lambda x: np.linalg.norm(x, axis=-1, keepdims=True) - 1)
    with pytest.raises(ValueError, match="returned shape"):
        bad.value(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="returned shape"):
        FunctionLevelSet(_poly, gradient=lambda x: x[..., :2]).gradient(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="shape"):
        FunctionLevelSet(_poly).value(np.zeros((4, 2)))
    with pytest.raises(NotImplementedError, match="must implement value"):
        LevelSet().closest_point(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="lipschitz"):
        FunctionLevelSet(_poly, lipschitz=-1.0)


# ----------------------------------------------------------------------------------------------
# sphere
# ----------------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------------
# torus
# ----------------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------------
# ellipsoid
# ----------------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------------
# signed distance to a triangle mesh
# ----------------------------------------------------------------------------------------------
class _Mesh:
    def __init__(self, points, triangles):
        self.points, self.triangles = points, triangles


def _unit_icosphere(nsub=3):
    import pyvista as pv

    ico = pv.Icosphere(radius=1.0, nsub=nsub)
    pts = np.asarray(ico.points, dtype=float)
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)  # exactly on the unit sphere in float64
    return pts, np.asarray(ico.regular_faces)


def test_signed_distance_of_a_triangulated_sphere():
    pts, tris = _unit_icosphere()
    sd = SignedDistance(_Mesh(pts, tris))
    assert sd.is_distance and sd.lipschitz == 1.0
    # Hausdorff bound of an inscribed polyhedron: each face lies in a disk of radius rho_T
    # (circumradius) at distance sqrt(1 - rho_T^2) from the center
    e = [np.linalg.norm(pts[tris[:, i]] - pts[tris[:, (i + 1) % 3]], axis=1) for i in range(3)]
    area = 0.5 * np.linalg.norm(np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]]), axis=1)
    rho = e[0] * e[1] * e[2] / (4 * area)
    gap = np.max(1 - np.sqrt(1 - rho**2))
    rng = np.random.default_rng(RNG_SEED)
    radii = np.concatenate([rng.uniform(0.2, 0.95, 10), rng.uniform(1.05, 2.5, 10)])
    x = random_directions(rng, 20) * radii[:, None]
    v = sd.value(x)
    assert np.all(np.abs(v - (radii - 1)) <= gap + 1e-12)
    assert np.all(np.sign(v) == np.sign(radii - 1))
    g = sd.gradient(x)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-6)
    assert np.all(np.sum(g * x, axis=1) / radii > 0.99)
    p = sd.closest_point(x)
    assert np.max(np.abs(sd.value(p))) < 1e-8
    # polyhedron area/volume from the mesh, close to the sphere's
    assert sd.area == pytest.approx(area.sum(), rel=1e-14)
    assert 4 / 3 * np.pi * (1 - gap) ** 3 < sd.volume < 4 / 3 * np.pi
    with pytest.raises(NotImplementedError, match="Hessian"):
        sd.hessian(x)


def test_signed_distance_orientation_and_mesh_checks():
    import pyvista as pv

    pts, tris = _unit_icosphere(2)
    probe = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    reversed_sd = SignedDistance(_Mesh(pts, tris[:, ::-1]))  # inward-oriented input
    polydata_sd = SignedDistance(pv.Icosphere(radius=1.0, nsub=2))
    for sd in (reversed_sd, polydata_sd):
        v = sd.value(probe)
        assert v[0] < 0 < v[1]
        assert v[1] == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="closed"):
        SignedDistance(_Mesh(pts, tris[1:]))
    mixed = tris.copy()
    mixed[0] = mixed[0, ::-1]
    with pytest.raises(ValueError, match="oriented"):
        SignedDistance(_Mesh(pts, mixed))


# ----------------------------------------------------------------------------------------------
# interpolate
# ----------------------------------------------------------------------------------------------
def test_interpolate_values_and_nan_detection():
    rng = np.random.default_rng(RNG_SEED)
    x = rng.uniform(-1, 1, size=(12, 3))
    np.testing.assert_allclose(interpolate(Sphere(0.5), x), np.linalg.norm(x, axis=1) - 0.5, atol=1e-15)
    with np.errstate(invalid="ignore"):
        ls = FunctionLevelSet(lambda y: np.sqrt(y[..., 0]) - 0.5)  # NaN where x < 0
        with pytest.raises(ValueError, match=r"NaN or infinite at \d+ of 12 point"):
            interpolate(ls, x)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        interpolate(Sphere(), x[:, :2])


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
