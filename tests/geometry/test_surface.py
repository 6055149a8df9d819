"""Tests for cutfem.geometry.surface: closed triangle surface meshes (docs/math.md §2, §6.1).

Expected numbers come from closed-form geometry (torus trapezoid areas, icosahedron formulas,
cube), never from the code under test.
"""

import numpy as np
import pytest

from cutfem.geometry.surface import (
    TORUS_FAMILIES,
    SurfaceMesh,
    read_surface,
    sphere_mesh,
    torus_mesh,
    write_surface,
)

# ----------------------------------------------------------------------------------------------
# exact reference values and small hand-made meshes
# ----------------------------------------------------------------------------------------------


def torus_rho(x, R, r):
    """Exact signed distance to the torus (docs/math.md §1)."""
    return np.sqrt(x[:, 2] ** 2 + (np.hypot(x[:, 0], x[:, 1]) - R) ** 2) - r


def structured_torus_area(n, R, r):
    """Exact area of the structured n x n/2 torus mesh, summed over its planar trapezoid cells.

    Cell (i, j): parallel sides 2 rho_j sin(pi/n) and 2 rho_{j+1} sin(pi/n) (rho = R + r cos p),
    perpendicular to the cell's mirror plane t = t_i + pi/n; the height is the distance between
    their midpoints (rho cos(pi/n), r sin p) in that plane.
    """
    m = n // 2
    p = 2 * np.pi * np.arange(m + 1) / m
    rho = R + r * np.cos(p)
    s, c = np.sin(np.pi / n), np.cos(np.pi / n)
    sides = 2 * rho * s
    height = np.hypot(np.diff(rho) * c, r * np.diff(np.sin(p)))
    return n * np.sum(0.5 * (sides[:-1] + sides[1:]) * height)


# unit cube, vertex index x + 2y + 4z; each face quad listed counter-clockwise seen from outside
CUBE_POINTS = np.array([[(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], dtype=float)
CUBE_QUADS = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
CUBE_TRIANGLES = np.concatenate([CUBE_QUADS[:, [0, 1, 2]], CUBE_QUADS[:, [0, 2, 3]]])


def tet_surface(ids):
    """Outward faces of a positively oriented tetrahedron (a, b, c, d)."""
    a, b, c, d = ids
    return np.array([[b, c, d], [a, d, c], [a, b, d], [a, c, b]])


UNIT_TET = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)


def rate(h, e):
    """Least-squares slope of log e against log h."""
    return np.polyfit(np.log(h), np.log(e), 1)[0]


# ----------------------------------------------------------------------------------------------
# torus
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("family", TORUS_FAMILIES)
@pytest.mark.parametrize("n", [6, 12])
def test_torus_topology(family, n):
    mesh = torus_mesh(n, family)
    nodes = n * (n // 2)
    assert mesh.n_points == nodes
    assert mesh.n_triangles == 2 * nodes
    assert mesh.n_edges == 3 * nodes
    assert mesh.euler_characteristic == 0
    assert mesh.h == pytest.approx(nodes**-0.5, rel=1e-15)
    assert mesh.flipped_components == 0  # generated outward


@pytest.mark.parametrize("family", TORUS_FAMILIES)
@pytest.mark.parametrize("R, r", [(1.0, 0.5), (2.0, 0.7)])
def test_torus_nodes_on_torus(family, R, r):
    mesh = torus_mesh(16, family, R=R, r=r, seed=3)
    assert np.max(np.abs(torus_rho(mesh.points, R, r))) < 1e-14


@pytest.mark.parametrize("n, R, r", [(8, 1.0, 0.5), (20, 2.0, 0.3)])
def test_structured_and_flipped_area_exact(n, R, r):
    expected = structured_torus_area(n, R, r)
    assert torus_mesh(n, "structured", R=R, r=r).area == pytest.approx(expected, rel=1e-13)
    # cells are planar trapezoids: the diagonal does not change the area
    assert torus_mesh(n, "flipped", R=R, r=r, seed=5).area == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("family", TORUS_FAMILIES)
def test_torus_area_converges_at_rate_two(family):
    R, r = 1.0, 0.5
    exact = 4 * np.pi**2 * R * r
    meshes = [torus_mesh(n, family, R=R, r=r, seed=1) for n in (16, 32, 64, 128)]
    h = [m.h for m in meshes]
    err = [abs(m.area - exact) for m in meshes]
    assert rate(h, err) == pytest.approx(2.0, abs=0.1)
    assert err[-1] / exact < 1e-3


def test_torus_normals_outward():
    R, r = 1.0, 0.5
    mesh = torus_mesh(32, "perturbed-flipped", seed=2)
    x = mesh.centroids
    axis_point = R * x * np.array([1, 1, 0]) / np.hypot(x[:, 0], x[:, 1])[:, None]
    exact = (x - axis_point) / np.linalg.norm(x - axis_point, axis=1)[:, None]
    assert np.allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-14)
    assert np.min(np.einsum("ij,ij->i", mesh.normals, exact)) > 0.9
    assert mesh.enclosed_volume == pytest.approx(2 * np.pi**2 * R * r**2, rel=0.05)


def test_flipped_differs_from_structured_with_same_points():
    structured = torus_mesh(12, "structured")
    flipped = torus_mesh(12, "flipped", seed=0)
    assert np.array_equal(structured.points, flipped.points)
    assert not np.array_equal(structured.triangles, flipped.triangles)
    assert not np.array_equal(structured.edges, flipped.edges)


def test_torus_seeding():
    for family in ("flipped", "perturbed", "perturbed-flipped"):
        a, b, c = (torus_mesh(10, family, seed=s) for s in (7, 7, 8))
        assert np.array_equal(a.points, b.points) and np.array_equal(a.triangles, b.triangles)
        assert not (np.array_equal(a.points, c.points) and np.array_equal(a.triangles, c.triangles))
    # the structured family ignores the seed
    assert np.array_equal(torus_mesh(10, seed=1).triangles, torus_mesh(10, seed=2).triangles)
    # documented: one stream, perturbed-flipped = nodes of perturbed + diagonals of flipped
    both = torus_mesh(10, "perturbed-flipped", seed=4)
    assert np.array_equal(both.points, torus_mesh(10, "perturbed", seed=4).points)
    assert np.array_equal(both.triangles, torus_mesh(10, "flipped", seed=4).triangles)


def test_torus_perturbation_bounded():
    n, m = 12, 6
    mesh = torus_mesh(n, "perturbed", seed=9)
    x = mesh.points
    t = np.arctan2(x[:, 1], x[:, 0])
    p = np.arctan2(x[:, 2], np.hypot(x[:, 0], x[:, 1]) - 1.0)
    i, j = np.divmod(np.arange(n * m), m)
    dt = np.angle(np.exp(1j * (t - 2 * np.pi * i / n))) / (2 * np.pi / n)
    dp = np.angle(np.exp(1j * (p - 2 * np.pi * j / m))) / (2 * np.pi / m)
    assert np.max(np.abs(dt)) <= 0.25 + 1e-12 and np.max(np.abs(dp)) <= 0.25 + 1e-12
    assert np.max(np.abs(dt)) > 0.1 and np.max(np.abs(dp)) > 0.1  # really perturbed


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n=7), "even"),
        (dict(n=4), ">= 6"),
        (dict(n=8.0), "integer"),
        (dict(n=8, family="random"), "structured, flipped, perturbed, perturbed-flipped"),
        (dict(n=8, R=0.5, r=0.5), "r < R"),
        (dict(n=8, r=-0.1), "positive"),
    ],
)
def test_torus_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        torus_mesh(**kwargs)


# ----------------------------------------------------------------------------------------------
# sphere
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("level", [0, 1, 3])
def test_sphere_counts_and_nodes(level):
    radius, center = 2.5, np.array([0.3, -1.0, 2.0])
    mesh = sphere_mesh(level, radius, center)
    assert mesh.n_points == 10 * 4**level + 2
    assert mesh.n_edges == 30 * 4**level
    assert mesh.n_triangles == 20 * 4**level
    assert mesh.euler_characteristic == 2
    assert np.max(np.abs(np.linalg.norm(mesh.points - center, axis=1) - radius)) < 1e-14 * radius * 4
    outward = np.einsum("ij,ij->i", mesh.normals, mesh.centroids - center)
    assert np.all(outward > 0)


def test_icosahedron_exact_area_and_volume():
    radius = 1.7
    a = 4 * radius / np.sqrt(10 + 2 * np.sqrt(5))  # edge of the inscribed regular icosahedron
    mesh = sphere_mesh(0, radius)
    assert np.allclose(mesh.edge_lengths, a, rtol=1e-14)
    assert mesh.area == pytest.approx(5 * np.sqrt(3) * a**2, rel=1e-14)
    assert mesh.enclosed_volume == pytest.approx(5 / 12 * (3 + np.sqrt(5)) * a**3, rel=1e-14)


def test_sphere_area_and_volume_converge():
    radius = 1.3
    meshes = [sphere_mesh(level, radius, (1.0, 2.0, 3.0)) for level in (1, 2, 3, 4)]
    h = [m.h for m in meshes]
    area_err = [abs(m.area - 4 * np.pi * radius**2) for m in meshes]
    vol_err = [abs(m.enclosed_volume - 4 / 3 * np.pi * radius**3) for m in meshes]
    assert rate(h, area_err) == pytest.approx(2.0, abs=0.15)
    assert rate(h, vol_err) == pytest.approx(2.0, abs=0.15)
    assert area_err[-1] / (4 * np.pi * radius**2) < 2e-3


@pytest.mark.parametrize(
    "kwargs, match", [(dict(level=-1), ">= 0"), (dict(radius=0.0), "positive"), (dict(center=(0, 0)), "center")]
)
def test_sphere_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sphere_mesh(**kwargs)


# ----------------------------------------------------------------------------------------------
# topology and conormals
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mesh", [torus_mesh(10, "perturbed-flipped", seed=1), sphere_mesh(2)], ids=["torus", "sphere"])
def test_edge_tables_consistent(mesh):
    E, M = mesh.n_edges, mesh.n_triangles
    edges = mesh.edges
    assert edges.shape == (E, 2) and np.all(edges[:, 0] < edges[:, 1])
    assert len(np.unique(edges, axis=0)) == E
    assert np.all(np.diff(edges[:, 0] * mesh.n_points + edges[:, 1]) > 0)  # lexicographic
    tri = mesh.triangles
    # local edge k of triangle t is (v_k, v_{k+1}) and is edges[triangle_edges[t, k]]
    local = np.stack([tri, np.roll(tri, -1, axis=1)], axis=2)  # (M, 3, 2)
    assert np.array_equal(np.sort(local, axis=2), edges[mesh.triangle_edges])
    assert np.array_equal(np.bincount(mesh.triangle_edges.ravel(), minlength=E), np.full(E, 2))
    # the two triangles of each edge contain it, and they are distinct
    et = mesh.edge_triangles
    assert et.shape == (E, 2) and np.all(et[:, 0] != et[:, 1])
    for k in range(2):
        assert np.all((mesh.triangle_edges[et[:, k]] == np.arange(E)[:, None]).any(axis=1))
    # column 0 traverses the edge upwards (i -> j), column 1 downwards (outward orientation)
    k0, k1 = mesh.edge_local_index.T
    assert np.array_equal(tri[et[:, 0], k0], edges[:, 0]) and np.array_equal(tri[et[:, 0], (k0 + 1) % 3], edges[:, 1])
    assert np.array_equal(tri[et[:, 1], k1], edges[:, 1]) and np.array_equal(tri[et[:, 1], (k1 + 1) % 3], edges[:, 0])
    # every triangle appears three times in edge_triangles
    assert np.array_equal(np.bincount(et.ravel(), minlength=M), np.full(M, 3))


@pytest.mark.parametrize("mesh", [torus_mesh(8, "perturbed-flipped", seed=4), sphere_mesh(1)], ids=["torus", "sphere"])
def test_edge_conormals_geometry(mesh):
    t = mesh.edge_conormals
    assert t.shape == (mesh.n_edges, 2, 3)
    a, b = mesh.points[mesh.edges[:, 0]], mesh.points[mesh.edges[:, 1]]
    et = mesh.edge_triangles
    # opposite vertex: the triangle's vertex sum minus the edge's two vertices
    opposite = mesh.triangles[et].sum(axis=2) - mesh.edges.sum(axis=1)[:, None]
    assert np.allclose(np.linalg.norm(t, axis=2), 1.0, atol=1e-14)
    assert np.max(np.abs(np.einsum("ekj,ej->ek", t, b - a))) < 1e-14
    assert np.max(np.abs(np.einsum("ekj,ekj->ek", t, mesh.normals[et]))) < 1e-14
    towards_opposite = np.einsum("ekj,ekj->ek", t, mesh.points[opposite] - a[:, None, :])
    assert np.all(towards_opposite < 0)


def test_cube_geometry_and_conormals():
    s = 2.0
    mesh = SurfaceMesh(s * CUBE_POINTS, CUBE_TRIANGLES)
    assert mesh.flipped_components == 0
    assert (mesh.n_points, mesh.n_edges, mesh.n_triangles, mesh.euler_characteristic) == (8, 18, 12, 2)
    assert mesh.area == pytest.approx(6 * s**2, rel=1e-15)
    assert mesh.enclosed_volume == pytest.approx(s**3, rel=1e-15)
    assert np.allclose(mesh.areas, s**2 / 2, rtol=1e-15)
    lengths = np.sort(mesh.edge_lengths)
    assert np.allclose(lengths[:12], s, rtol=1e-15) and np.allclose(lengths[12:], s * np.sqrt(2), rtol=1e-15)
    t = mesh.edge_conormals
    n = mesh.normals[mesh.edge_triangles]  # (E, 2, 3)
    diagonal = mesh.edge_lengths > 1.2 * s
    # coplanar triangles (face diagonals): opposite conormals
    assert np.allclose(t[diagonal, 0], -t[diagonal, 1], atol=1e-15)
    # 90-degree convex folds: each conormal equals the outward normal of the other face
    assert np.allclose(t[~diagonal, 0], n[~diagonal, 1], atol=1e-15)
    assert np.allclose(t[~diagonal, 1], n[~diagonal, 0], atol=1e-15)
    # outward normals are the six axis directions
    assert np.allclose(np.abs(mesh.normals).max(axis=1), 1.0) and np.allclose(mesh.normals.sum(axis=0), 0.0)


def test_arrays_types_and_read_only():
    mesh = SurfaceMesh(CUBE_POINTS.tolist(), CUBE_TRIANGLES.astype(np.int32))
    assert mesh.points.dtype == np.float64 and mesh.triangles.dtype == np.int64
    assert mesh.points.flags.c_contiguous and mesh.triangles.flags.c_contiguous
    with pytest.raises(ValueError):
        mesh.points[0, 0] = 5.0
    with pytest.raises(ValueError):
        mesh.triangles[0, 0] = 1


def test_to_pyvista():
    mesh = sphere_mesh(2, 1.5)
    poly = mesh.to_pyvista()
    assert poly.n_points == mesh.n_points and poly.n_cells == mesh.n_triangles
    assert np.array_equal(poly.regular_faces, mesh.triangles)
    assert poly.area == pytest.approx(mesh.area, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# validation and orientation
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# file I/O
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", ["stl", "obj", "ply", "vtk", "vtp", "vtu", "off"])
@pytest.mark.parametrize("mesh", [sphere_mesh(2, 1.5, (0.1, 0.2, 0.3)), torus_mesh(8, "perturbed-flipped")],
                         ids=["sphere", "torus"])
def test_round_trip(tmp_path, ext, mesh):
    path = tmp_path / f"surface.{ext}"
    write_surface(mesh, path)
    back = read_surface(path)
    assert back.n_points == mesh.n_points  # STL's per-facet vertices merged again
    assert back.n_triangles == mesh.n_triangles
    assert back.euler_characteristic == mesh.euler_characteristic
    assert back.area == pytest.approx(mesh.area, rel=1e-12)
    assert back.enclosed_volume == pytest.approx(mesh.enclosed_volume, rel=1e-12)


def test_binary_stl_round_trip(tmp_path):
    mesh = sphere_mesh(3)
    path = tmp_path / "s.stl"
    write_surface(mesh, path, binary=True)
    back = read_surface(path)
    assert back.n_points == mesh.n_points and back.euler_characteristic == 2
    assert back.area == pytest.approx(mesh.area, rel=1e-6)  # float32 coordinates


def test_read_merges_near_duplicates_and_drops_unused(tmp_path):
    import meshio

    # a facet soup of the cube: every triangle has its own three points, jittered by 1e-14
    soup = (2 * CUBE_POINTS)[CUBE_TRIANGLES].reshape(-1, 3)
    soup = soup + 1e-14 * np.random.default_rng(0).uniform(-1, 1, soup.shape)
    soup = np.concatenate([soup, [[50.0, 50, 50]]])  # an unused point
    path = tmp_path / "soup.vtu"
    meshio.write(path, meshio.Mesh(soup, [("triangle", np.arange(36).reshape(12, 3))]))
    mesh = read_surface(path)
    assert mesh.n_points == 8 and mesh.euler_characteristic == 2
    assert mesh.area == pytest.approx(24.0, rel=1e-12)


@pytest.mark.parametrize("name,binary,rel", [("s.vtk", True, 1e-12), ("s_ascii.vtk", False, 1e-8), ("s.vtp", True, 1e-12)])
def test_read_vtk_polydata_as_pyvista_writes_it(tmp_path, name, binary, rel):
    # pyvista and ParaView write surfaces as polygonal data (legacy DATASET POLYDATA or .vtp),
    # which meshio does not read
    pyvista = pytest.importorskip("pyvista")
    mesh = sphere_mesh(2, 1.5, (0.1, 0.2, 0.3))
    path = tmp_path / name
    pyvista.PolyData.from_regular_faces(mesh.points, mesh.triangles).save(path, binary=binary)
    if path.suffix == ".vtk":
        assert b"DATASET POLYDATA" in path.read_bytes()[:300]
    back = read_surface(path)
    assert back.n_points == mesh.n_points and back.n_triangles == mesh.n_triangles
    assert back.euler_characteristic == 2
    assert back.area == pytest.approx(mesh.area, rel=rel)  # VTK's ASCII writer rounds the coordinates
    assert back.enclosed_volume == pytest.approx(mesh.enclosed_volume, rel=rel)


@pytest.mark.parametrize("name", ["cube.vtp", "cube.vtk"])
def test_read_polydata_quads_and_strips_rejected(tmp_path, name):
    pyvista = pytest.importorskip("pyvista")
    path = tmp_path / name
    pyvista.Cube().save(path)  # six quads
    with pytest.raises(ValueError, match=rf"{name}.*non-triangle.*quad.*triangulate"):
        read_surface(path)
    strips = tmp_path / f"strips{path.suffix}"
    pyvista.Sphere().strip().save(strips)
    with pytest.raises(ValueError, match=r"non-triangle.*triangle_strip.*triangulate"):
        read_surface(strips)


def test_read_missing_file(tmp_path):
    path = tmp_path / "nowhere.stl"
    with pytest.raises(FileNotFoundError, match="nowhere.stl"):
        read_surface(path)


@pytest.mark.parametrize("ext", ["stl", "ply", "vtu", "vtp"])
def test_read_unreadable_file(tmp_path, ext):
    path = tmp_path / f"garbage.{ext}"
    path.write_text("this is not\na mesh at all\n")
    with pytest.raises(ValueError, match=rf"garbage\.{ext}.*\.obj"):
        read_surface(path)


def test_read_unknown_extension(tmp_path):
    path = tmp_path / "surface.xyz123"
    path.write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"surface\.xyz123.*\.stl, \.obj, \.ply"):
        read_surface(path)


def test_read_without_triangles(tmp_path):
    import meshio

    path = tmp_path / "lines.vtu"
    meshio.write(path, meshio.Mesh(UNIT_TET, [("line", np.array([[0, 1], [1, 2]]))]))
    with pytest.raises(ValueError, match=r"lines\.vtu.*no triangle cells.*line"):
        read_surface(path)


def test_read_quads_rejected(tmp_path):
    import meshio

    path = tmp_path / "cube.vtu"
    meshio.write(path, meshio.Mesh(CUBE_POINTS, [("quad", CUBE_QUADS)]))
    with pytest.raises(ValueError, match=r"non-triangle.*triangulate"):
        read_surface(path)


def test_read_open_surface_names_file(tmp_path):
    path = tmp_path / "open.obj"
    write_surface(SurfaceMesh(SPHERE.points, SPHERE.triangles[1:], check=False), path)
    with pytest.raises(ValueError, match=r"open\.obj.*the surface is open"):
        read_surface(path)


def test_write_errors(tmp_path):
    with pytest.raises(ValueError, match=r"\.xyz123"):
        write_surface(SPHERE, tmp_path / "s.xyz123")
    with pytest.raises(FileNotFoundError, match="missing_dir"):
        write_surface(SPHERE, tmp_path / "missing_dir" / "s.stl")


def test_read_merges_near_duplicates_on_either_side_of_a_rounding_step(tmp_path):
    import meshio

    # a facet soup of a sphere whose copies of a vertex differ by up to 1e-11 (3% of the merge
    # distance 1e-10 * diagonal = 3.5e-10): copies of one vertex are one node, whatever grid the
    # coordinates would round to
    mesh = sphere_mesh(2)
    soup = np.asarray(mesh.points)[np.asarray(mesh.triangles)].reshape(-1, 3)
    soup = soup + 1e-11 * np.random.default_rng(1).uniform(-1, 1, soup.shape)
    path = tmp_path / "soup.vtu"
    meshio.write(path, meshio.Mesh(soup, [("triangle", np.arange(len(soup)).reshape(-1, 3))]))
    back = read_surface(path)
    assert back.n_points == mesh.n_points == 162 and back.euler_characteristic == 2
    assert back.area == pytest.approx(mesh.area, rel=1e-10)


def test_read_keeps_points_farther_apart_than_the_merge_distance(tmp_path):
    import meshio

    # two tetrahedra 1e-9 * diagonal apart (3x the merge distance) stay two components
    second = UNIT_TET + [1 + 1e-9 * np.sqrt(3.0) * 2, 0, 0]
    points = np.concatenate([UNIT_TET, second])
    path = tmp_path / "two.vtu"
    meshio.write(path, meshio.Mesh(points, [("triangle", np.concatenate([tet_surface(range(4)), tet_surface(range(4, 8))]))]))
    back = read_surface(path)
    assert back.n_points == 8 and back.euler_characteristic == 4


def test_read_ignores_non_finite_points_no_triangle_uses(tmp_path):
    import meshio

    points = np.concatenate([UNIT_TET, [[np.nan, 0.0, 0.0]]])
    path = tmp_path / "tet.vtu"
    meshio.write(path, meshio.Mesh(points, [("triangle", tet_surface(range(4)))]))
    assert read_surface(path).area == pytest.approx(1.5 + np.sqrt(3) / 2, rel=1e-14)
    points[1, 2] = np.inf
    meshio.write(path, meshio.Mesh(points, [("triangle", tet_surface(range(4)))]))
    with pytest.raises(ValueError, match=r"tet\.vtu': 1 point\(s\) used by triangles have non-finite .*rows 1 of the file"):
        read_surface(path)


def test_read_empty_or_misnamed_file_names_the_extension(tmp_path):
    import meshio

    # an STL saved under .obj: meshio's OBJ reader finds no point and no cell in it
    path = tmp_path / "ball.obj"
    meshio.write(path, meshio.Mesh(UNIT_TET, [("triangle", tet_surface(range(4)))]), file_format="stl")
    with pytest.raises(ValueError, match=r"ball\.obj' holds no points and no cells as read by the \.obj reader: the file "
                                         r"is empty or its content is not in the format its extension says"):
        read_surface(path)
    empty = tmp_path / "empty.stl"
    empty.write_text("")
    with pytest.raises(ValueError, match=r"empty\.stl' holds no points and no cells as read by the \.stl reader"):
        read_surface(empty)
