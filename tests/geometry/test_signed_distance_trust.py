"""Signed distance to meshes, the generators' size checks and the analytic surfaces at extreme
sizes: each test asserts numbers or the words of the error."""

from __future__ import annotations

import re

import numpy as np
import pytest

from cutfem.geometry.shapes import Ellipsoid, Sphere, Torus
from cutfem.geometry.signed_distance import SignedDistance
from cutfem.memory import InsufficientMemoryError
from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh


# ----------------------------------------------------------------------------------------------
# generators: sizes checked before anything is computed or allocated
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("level, shown", [(10**20, "1e+20"), (100000, "100000"), (11, "11")])
def test_sphere_mesh_refuses_a_level_above_the_finest_at_once(level, shown):
    with pytest.raises(ValueError, match=re.escape(f"level must be an integer <= 10; got {shown} (level 10 has 20,971,520")):
        sphere_mesh(level)


@pytest.mark.parametrize("call, message", [
    (lambda: sphere_mesh(-1), "level must be an integer >= 0; got -1."),
    (lambda: sphere_mesh(-10**5000), "level must be an integer >= 0; got -2**16609 or more."),
    (lambda: torus_mesh(4), "n must be an integer >= 6; got 4."),
    (lambda: torus_mesh(-2), "n must be an integer >= 6; got -2."),
])
def test_generators_refuse_small_and_negative_sizes(call, message):
    with pytest.raises(ValueError) as err:
        call()
    assert str(err.value) == message


def test_torus_mesh_checks_its_memory_before_allocating(monkeypatch):
    monkeypatch.setenv("CUTFEM_MEMORY_LIMIT", "100MiB")
    with pytest.raises(InsufficientMemoryError) as err:
        torus_mesh(10**6)
    assert str(err.value).startswith(
        "torus_mesh(n=1000000) (500000000000 nodes, 1000000000000 triangles) needs about 364 TiB of memory, "
        "more than the 100 MiB available (CUTFEM_MEMORY_LIMIT); use a smaller n (the memory grows like n**2; n = 362 fits)"
    )
    assert torus_mesh(362).n_points == 362 * 181  # the size named fits
    with pytest.raises(InsufficientMemoryError, match=r"sphere_mesh\(level=8\) \(655,362 nodes.*level 6 fits"):
        sphere_mesh(8)


# ----------------------------------------------------------------------------------------------
# extreme sizes: lengths checked at construction, points evaluated without overflow
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("call, message", [
    (lambda: sphere_mesh(1, radius=1e-160), "sphere_mesh: radius = 1e-160 is outside [1e-50, 1e+50], where the areas, "
     "volumes and curvatures of the surface underflow in float64; rescale the unit of length."),
    (lambda: torus_mesh(8, R=1e200, r=1e199), "torus_mesh: R = 1e+200 is outside [1e-50, 1e+50], where the areas, "
     "volumes and curvatures of the surface overflow in float64; rescale the unit of length."),
    (lambda: Sphere(1e200), "Sphere: radius = 1e+200 is outside"),
    (lambda: Torus(1e200, 1e199), "Torus: R = 1e+200 is outside"),
    (lambda: Ellipsoid(1e-200, 1, 1), "Ellipsoid: a = 1e-200 is outside [1e-50, 1e+50], where the areas, volumes and "
     "curvatures of the surface underflow"),
    (lambda: Ellipsoid(1e-13, 1, 1), "Ellipsoid: the semi-axes a = 1e-13, b = 1, c = 1 have smallest / largest = 1e-13, "
     "below 1e-12"),
    (lambda: torus_mesh(8, R=1.0, r=1e-13), "torus_mesh(n=8, R=1, r=1e-13) makes degenerate triangles: the ratio "
     "r / R = 1e-13 is too small for the grid"),
])
def test_lengths_outside_the_representable_range_are_named(call, message):
    with pytest.raises(ValueError) as err:
        call()
    assert str(err.value).startswith(message)


def test_surfaces_at_the_ends_of_the_length_range_have_finite_measures():
    for scale in (1e-50, 1e50):
        assert Sphere(scale).area == pytest.approx(4 * np.pi * scale**2, rel=1e-15)
        assert sphere_mesh(2, radius=scale).area == pytest.approx(sphere_mesh(2).area * scale**2, rel=1e-13)
    for R, r in ((2e-50, 1e-50), (1e50, 0.5e50)):
        assert Torus(R, r).volume == pytest.approx(2 * np.pi**2 * R * r**2, rel=1e-15)
    flat = Ellipsoid(1.0, 0.5, 1e-12)
    assert flat.area == pytest.approx(np.pi, rel=1e-12)  # both faces of the ellipse
    # the centre of a face of (1, 1, 1e-10): k1 + k2 = 2 c / a^2 (was 0 from trace - n.H.n)
    assert Ellipsoid(1.0, 1.0, 1e-10).exact_mean_curvature([[0.0, 0.0, 1.1e-10]])[0] == pytest.approx(2e-10, rel=1e-12)


def test_sphere_projects_points_whose_squares_overflow_or_underflow():
    s = Sphere()
    np.testing.assert_allclose(s.closest_point([[1e300, 1e300, 0.0]]), [[2**-0.5, 2**-0.5, 0.0]], rtol=1e-15)  # was [0, 0, 0]
    assert s.value([[1e300, 1e300, 0.0]])[0] == pytest.approx(np.sqrt(2.0) * 1e300, rel=1e-15)  # was inf
    np.testing.assert_array_equal(s.closest_point([[1e-320, 0.0, 0.0]]), [[1.0, 0.0, 0.0]])  # was "at the center"
    np.testing.assert_allclose(Torus().closest_point([[1e300, 0.0, 1e300]]), [[1 + 0.5**1.5, 0.0, 0.5**1.5]], rtol=1e-14)


def test_torus_mean_curvature_vector_next_to_the_axis_and_the_core_circle():
    t = Torus()  # R = 1, r = 0.5: k1 + k2 = 0 on the inner equator, 1/r = 2 on the top circle
    np.testing.assert_array_equal(t.exact_mean_curvature_vector([[1e-310, 0.0, 0.0]]), [[0.0, 0.0, 0.0]])  # was nan
    np.testing.assert_array_equal(t.exact_mean_curvature_vector([[1.0, 0.0, 1e-320]]), [[0.0, 0.0, 2.0]])  # was nan, inf
    thin = Torus(1.0, 0.3)  # inner equator: -(R - 2r) / (r (R - r)) along -e_s
    np.testing.assert_allclose(thin.exact_mean_curvature_vector([[1e-310, 0.0, 0.0]]), [[-0.4 / 0.21, 0.0, 0.0]], rtol=1e-14)
    with pytest.raises(ValueError, match="on the torus axis"):
        t.exact_mean_curvature_vector([[0.0, 0.0, 1e-320]])
    with pytest.raises(ValueError, match="on the core circle"):
        t.exact_mean_curvature_vector([[1.0, 0.0, 0.0]])


# ----------------------------------------------------------------------------------------------
# SignedDistance: validated and oriented as a SurfaceMesh, closest points on the mesh
# ----------------------------------------------------------------------------------------------
class _Soup:
    def __init__(self, points, triangles):
        self.points, self.triangles = points, triangles


def _two_spheres(flip_second=True, gap=0.6):
    a, b = sphere_mesh(3, 0.5, (gap, 0.0, 0.0)), sphere_mesh(3, 0.5, (-gap, 0.0, 0.0))
    second = b.triangles[:, ::-1] if flip_second else b.triangles
    return np.concatenate([a.points, b.points]), np.concatenate([a.triangles, second + a.n_points])


def test_each_component_is_oriented_outward_on_its_own():
    import pyvista as pv

    sag = 0.5 * (1.0 - sphere_mesh(3).enclosed_volume / (4 / 3 * np.pi)) + 1e-3  # discretization, about 0.003
    probes = [[0.6, 0.0, 0.0], [-0.6, 0.0, 0.0], [0.0, 0.0, 0.0]]
    soup = SignedDistance(_Soup(*_two_spheres()))  # was +0.5 at the centre of the inverted sphere, -0.1 between
    np.testing.assert_allclose(soup.value(probes), [-0.5, -0.5, 0.1], atol=sag)
    assert soup.mesh.flipped_components == 1
    merged = pv.Sphere(radius=0.5, center=(0.6, 0, 0)).merge(pv.Sphere(radius=0.5, center=(-0.6, 0, 0)).flip_faces())
    np.testing.assert_allclose(SignedDistance(merged).value(probes), [-0.5, -0.5, 0.1], atol=0.01)  # was +0.497


def test_signed_distance_refuses_what_surface_mesh_refuses():
    nested = sphere_mesh(2), sphere_mesh(2, radius=0.5)
    points = np.concatenate([nested[0].points, nested[1].points])
    triangles = np.concatenate([nested[0].triangles, nested[1].triangles + nested[0].n_points])
    with pytest.raises(ValueError, match=r"closed components of the surface are nested: 1 component\(s\)"):
        SignedDistance(_Soup(points, triangles))  # was accepted
    with pytest.raises(ValueError, match="closed components of the surface intersect"):
        SignedDistance(_Soup(*_two_spheres(gap=0.3)))
    points, triangles = _two_spheres()
    with pytest.raises(ValueError, match="the surface is open: 3 boundary edge"):
        SignedDistance(_Soup(points, triangles[1:]))


def test_closest_point_lies_on_the_mesh_at_the_distance():
    mesh = sphere_mesh(3)
    sd = SignedDistance(mesh)
    rng = np.random.default_rng(7)
    u = rng.normal(size=(40, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    x = np.concatenate([u * rng.uniform(0.97, 1.03, (40, 1)), [[0.0, 0.0, 0.0], [1e6, 0.0, 0.0], [0.3, -2e5, 4e5]]])
    p = sd.closest_point(x)
    # was [0, 0, 0] at the centre (zero difference gradient) and (14.65, 0, 0) at (1e6, 0, 0)
    assert np.max(mesh.closest_points(p)[2]) < 1e-15  # on the mesh
    np.testing.assert_allclose(np.linalg.norm(x - p, axis=1), np.abs(sd.value(x)), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(p[-2], [1.0, 0.0, 0.0], atol=1e-15)
    # against all the triangles at once
    corners = mesh.points[mesh.triangles]
    from cutfem.geometry.closest import _closest_on_triangles

    every = _closest_on_triangles(x[:, None, :], corners[None, :, 0], corners[None, :, 1], corners[None, :, 2])
    # to rounding of the unit-size coordinates (the compiled pass sums the dot products in its own order)
    np.testing.assert_allclose(np.linalg.norm(x - p, axis=1), np.linalg.norm(x[:, None] - every, axis=2).min(axis=1), rtol=1e-14, atol=1e-15)
    with pytest.raises(ValueError, match=r"1 point\(s\) farther than 1e150 from the mesh"):
        sd.closest_point([[1e300, 0.0, 0.0]])


def test_value_far_from_the_mesh_is_the_distance():
    """VTK's value lost its digits far away (-2e8 at (1e8, 0, 0) from a unit sphere mesh, NaN off
    the axes); the compiled search gives the nearest-point distance at every range, with no step
    where VTK's value used to be replaced (100 bounding-box diagonals out)."""
    mesh = sphere_mesh(3)
    sd = SignedDistance(mesh)
    d = np.array([10.0, 1e3, 1e8, 1e12])[:, None]
    x = np.concatenate([d * [1.0, 0.0, 0.0], d * [0.6, 0.8, 0.0], d * [0.0, -0.28, 0.96], -d * [0.48, 0.6, 0.64]])
    value = sd.value(x)
    np.testing.assert_allclose(value, np.linalg.norm(x - sd.closest_point(x), axis=1), rtol=1e-14)
    assert np.all(value > 0) and value[2] == pytest.approx(1e8 - 1.0, rel=1e-15)
    diag = np.linalg.norm(mesh.points.max(axis=0) - mesh.points.min(axis=0))
    edge = mesh.points[:, 0].max() + 100.0 * diag
    inside, beyond = sd.value([[edge * (1 - 1e-12), 0.0, 0.0], [edge * (1 + 1e-12), 0.0, 0.0]])
    assert beyond - inside == pytest.approx(2e-12 * edge, rel=1e-3)

