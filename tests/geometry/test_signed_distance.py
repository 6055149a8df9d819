"""Tests of cutfem.geometry.signed_distance: the signed distance to a triangulated sphere against
the Hausdorff bound of an inscribed polyhedron, its orientation and its mesh checks."""

import numpy as np
import pytest

from cutfem.geometry.signed_distance import SignedDistance
from levelset_references import random_directions

RNG_SEED = 20240601


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
