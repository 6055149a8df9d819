"""Tests of cutfem.studies.baselines: the cotangent formula and pyvista's curvature, with their conventions.

Reference values are closed-form: a sphere of radius R has H = (2/R) n (docs/math.md §1) and VTK's mean
curvature (k1 + k2)/2 = 1/R; a regular tetrahedron has equilateral faces (Voronoi = barycentric
areas); a triangle with a 120 degree angle is obtuse (mixed areas A/2, A/4, A/4).
"""

import numpy as np
import pytest

from cutfem.studies.baselines import (
    corner_cotangents,
    cotangent_laplacian,
    cotangent_mean_curvature,
    lumped_mass,
    pyvista_mean_curvature,
    pyvista_mean_curvature_vector,
    vertex_normals,
)
from cutfem.fem.forms import assemble
from cutfem.fem.terms import tangential_stiffness
from cutfem.geometry.shapes import Torus
from cutfem.fem.spaces import SurfaceP1Space
from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh

R = 2.0


@pytest.fixture(scope="module")
def sphere():
    return sphere_mesh(5, radius=R)


def test_cotangent_laplacian_is_the_p1_stiffness_matrix(sphere):
    L = cotangent_laplacian(sphere.points, sphere.triangles)
    A = assemble(tangential_stiffness(sphere.ds()), SurfaceP1Space(sphere))
    assert abs(L - A).max() < 1e-12 * abs(A).max()
    assert np.abs(L @ np.ones(sphere.n_points)).max() < 1e-12
    assert abs(L - L.T).max() == 0.0


def test_cotangents_of_a_right_isosceles_triangle():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    cot = corner_cotangents(pts, [[0, 1, 2]])
    assert np.allclose(cot, [[0.0, 1.0, 1.0]])  # 90, 45, 45 degrees


def test_cotangent_formula_on_a_fine_sphere(sphere):
    n = sphere.points / R
    H = cotangent_mean_curvature(sphere.points, sphere.triangles, mass="voronoi")
    assert np.abs(H - (2 / R) * n).max() < 3e-3 * (2 / R)  # measured 1.9e-3 (relative) at level 5
    # barycentric areas: exact on average, worse at the 12 valence-5 nodes
    Hb = cotangent_mean_curvature(sphere.points, sphere.triangles, mass="barycentric")
    err = np.linalg.norm(Hb - (2 / R) * n, axis=1)
    assert np.median(err) < 2e-3 * (2 / R)
    assert np.einsum("ij,ij->i", Hb, n).min() > 0  # outward


def test_weighted_sum_of_nodal_curvatures_vanishes(sphere):
    for kind in ("voronoi", "barycentric"):
        m = lumped_mass(sphere.points, sphere.triangles, kind)
        H = cotangent_mean_curvature(sphere.points, sphere.triangles, mass=kind)
        total = (m[:, None] * H).sum(axis=0)  # = 1^T L X = 0
        assert np.abs(total).max() < 1e-12 * np.abs(m[:, None] * H).sum()
        assert m.sum() == pytest.approx(sphere.area, rel=1e-13)


def test_voronoi_equals_barycentric_on_equilateral_faces():
    pts = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])  # regular tetrahedron
    tri = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    mv = lumped_mass(pts, tri, "voronoi")
    mb = lumped_mass(pts, tri, "barycentric")
    face = np.sqrt(3) / 4 * 8  # equilateral triangle with side 2 sqrt 2
    assert np.allclose(mv, mb) and np.allclose(mb, face)  # 3 faces x face/3 per vertex


def test_mixed_area_of_an_obtuse_triangle():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [np.cos(2 * np.pi / 3), np.sin(2 * np.pi / 3), 0]])  # 120 deg at node 0
    A = 0.5 * np.sin(2 * np.pi / 3)
    m = lumped_mass(pts, [[0, 1, 2]], "voronoi")
    assert np.allclose(m, [A / 2, A / 4, A / 4])


def test_vertex_normals_point_outward_on_the_sphere(sphere):
    n = vertex_normals(sphere.points, sphere.triangles)
    assert np.einsum("ij,ij->i", n, sphere.points / R).min() > 0.9999


def test_pyvista_mean_curvature_convention(sphere):
    """VTK's 'mean' curvature is (k1 + k2)/2 = 1/R on an outward sphere, so H = 2 c n."""
    c = pyvista_mean_curvature(sphere.points, sphere.triangles)
    assert np.median(c) == pytest.approx(1 / R, rel=1e-3)
    assert np.percentile(c, 99) < 1.01 / R and c.min() > 0.99 / R
    H = pyvista_mean_curvature_vector(sphere.points, sphere.triangles)
    err = np.linalg.norm(H - (2 / R) * sphere.points / R, axis=1)
    assert np.median(err) < 1e-3 * (2 / R)


def test_cotangent_formula_converges_on_structured_not_on_perturbed_torus():
    """Nodal max error: about h^2 on the structured torus grid, no convergence on perturbed nodes."""
    torus = Torus()

    def err(n, family):
        m = torus_mesh(n, family=family, seed=0)
        H = cotangent_mean_curvature(m.points, m.triangles, mass="voronoi")
        return np.linalg.norm(H - torus.exact_mean_curvature_vector(m.points), axis=1).max()

    e32, e64 = err(32, "structured"), err(64, "structured")
    assert np.log2(e32 / e64) > 1.8  # measured 1.96
    assert e64 < 0.02
    assert err(64, "perturbed") > 1.0 and err(128, "perturbed") > 1.0  # measured 2.8, 2.2


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="barycentric"):
        lumped_mass(np.eye(3), [[0, 1, 2]], "lumped")
    with pytest.raises(ValueError, match="degenerate"):
        corner_cotangents(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), [[0, 1, 2]])
    with pytest.raises(ValueError, match="outside"):
        cotangent_laplacian(np.eye(3), [[0, 1, 3]])
