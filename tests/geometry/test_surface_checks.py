"""Tests for cutfem.geometry.surface_checks: what a SurfaceMesh refuses (open, non-manifold,
inconsistently oriented, bad input) and how it orients each component outward."""

import numpy as np
import pytest

from cutfem.geometry.surface import SurfaceMesh
from cutfem.geometry.surface_meshes import sphere_mesh


def tet_surface(ids):
    """Outward faces of a positively oriented tetrahedron (a, b, c, d)."""
    a, b, c, d = ids
    return np.array([[b, c, d], [a, d, c], [a, b, d], [a, c, b]])


UNIT_TET = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
SPHERE = sphere_mesh(1)


def test_open_surface_rejected():
    with pytest.raises(ValueError, match=r"the surface is open: 3 boundary edge"):
        SurfaceMesh(SPHERE.points, SPHERE.triangles[1:])


def test_non_manifold_edge_rejected():
    # two tetrahedra sharing the edge (0, 1): that edge lies in four triangles
    points = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=float)
    triangles = np.concatenate([tet_surface([0, 2, 3, 1]), tet_surface([0, 4, 5, 1])])
    with pytest.raises(ValueError, match=r"non-manifold: 1 edge.*\(0, 1\)"):
        SurfaceMesh(points, triangles)


def test_non_manifold_vertex_rejected():
    # two tetrahedra touching at the single node 0
    points = np.concatenate([UNIT_TET, -UNIT_TET[1:]])
    triangles = np.concatenate([tet_surface([0, 1, 2, 3]), tet_surface([0, 5, 4, 6])])
    with pytest.raises(ValueError, match=r"non-manifold at 1 vertex.*nodes 0"):
        SurfaceMesh(points, triangles)


def test_inconsistent_orientation_rejected():
    triangles = SPHERE.triangles.copy()
    triangles[5] = triangles[5, [0, 2, 1]]
    with pytest.raises(ValueError, match=r"not consistently oriented: on 3 edge"):
        SurfaceMesh(SPHERE.points, triangles)


def test_inward_orientation_is_flipped_outward():
    inward = SPHERE.triangles[:, [0, 2, 1]]
    mesh = SurfaceMesh(SPHERE.points, inward)
    assert mesh.flipped_components == 1
    assert np.array_equal(mesh.triangles, SPHERE.triangles)
    assert mesh.enclosed_volume == pytest.approx(SPHERE.enclosed_volume, rel=1e-14)
    assert mesh.enclosed_volume > 0


def test_each_component_oriented_outward():
    # two disjoint unit tetrahedra, the second one given inward
    points = np.concatenate([UNIT_TET, UNIT_TET + 5.0])
    triangles = np.concatenate([tet_surface([0, 1, 2, 3]), tet_surface([4, 5, 6, 7])[:, [0, 2, 1]]])
    mesh = SurfaceMesh(points, triangles)
    assert mesh.flipped_components == 1
    assert mesh.enclosed_volume == pytest.approx(2 / 6, rel=1e-14)
    assert mesh.euler_characteristic == 4
    assert np.all(np.einsum("ij,ij->i", mesh.normals, mesh.centroids - np.repeat([[0.25] * 3, [5.25] * 3], 4, 0)) > 0)


def test_check_false_skips_validation_but_not_topology():
    mesh = SurfaceMesh(SPHERE.points, SPHERE.triangles[:, [0, 2, 1]], check=False)
    assert mesh.enclosed_volume < 0  # kept as given
    open_mesh = SurfaceMesh(SPHERE.points, SPHERE.triangles[1:], check=False)
    with pytest.raises(ValueError, match="exactly two triangles"):
        open_mesh.edge_triangles
    # the geometry is a compiled pass: an index out of range is an error, not a read past the points
    bad = SPHERE.triangles.copy()
    bad[3, 1] = len(SPHERE.points)
    with pytest.raises(ValueError, match=r"outside \[0, "):
        SurfaceMesh(SPHERE.points, bad, check=False).areas


def _with_nan():
    p = SPHERE.points.copy()
    p[4, 1] = np.nan
    return p, SPHERE.triangles


def _collinear():
    p = UNIT_TET.copy()
    p[3] = 0.5 * (p[0] + p[1])  # faces through 0, 1, 3 become segments
    return p, tet_surface([0, 1, 2, 3])


@pytest.mark.parametrize(
    "make, match",
    [
        (_with_nan, r"1 point\(s\) have non-finite.*rows 4"),
        (_collinear, r"zero area"),
        (lambda: (UNIT_TET, np.array([[0, 1, 1], [0, 1, 2], [0, 2, 3], [1, 2, 3]])), r"repeat a vertex"),
        (lambda: (UNIT_TET, tet_surface([0, 1, 2, 4])), r"outside \[0, 4\)"),
        (lambda: (UNIT_TET, tet_surface([0, 1, 2, -1])), r"outside \[0, 4\)"),
        (lambda: (UNIT_TET, tet_surface([0, 1, 2, 3]).astype(float)), r"integer"),
        (lambda: (UNIT_TET[:, :2], tet_surface([0, 1, 2, 3])), r"shape \(N, 3\)"),
        (lambda: (UNIT_TET, np.arange(12).reshape(3, 4)), r"shape \(M, 3\)"),
        (lambda: (UNIT_TET, np.zeros((0, 3), int)), r"no triangles"),
        (lambda: (np.concatenate([UNIT_TET, [[9.0, 9, 9]]]), tet_surface([0, 1, 2, 3])), r"1 point\(s\) belong to no"),
        (lambda: (UNIT_TET, np.concatenate([tet_surface([0, 1, 2, 3]), [[1, 2, 3]]])), r"duplicate"),
    ],
    ids=["nan", "collinear", "repeated", "index-high", "index-negative", "float-indices", "2d-points",
         "4-columns", "empty", "unused-point", "duplicate"],
)
def test_bad_input_rejected(make, match):
    points, triangles = make()
    with pytest.raises(ValueError, match=match):
        SurfaceMesh(points, triangles)
