"""Tests for cutfem.geometry.surface: the topology, geometry and files of closed triangle surface
meshes (docs/math.md §2).

Expected numbers come from closed-form geometry (the cube), never from the code under test.
"""

import numpy as np
import pytest

from cutfem.geometry.surface import SurfaceMesh, read_surface, write_surface
from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh

# ----------------------------------------------------------------------------------------------
# small hand-made meshes
# ----------------------------------------------------------------------------------------------


# unit cube, vertex index x + 2y + 4z; each face quad listed counter-clockwise seen from outside
CUBE_POINTS = np.array([[(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], dtype=float)
CUBE_QUADS = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
CUBE_TRIANGLES = np.concatenate([CUBE_QUADS[:, [0, 1, 2]], CUBE_QUADS[:, [0, 2, 3]]])


def tet_surface(ids):
    """Outward faces of a positively oriented tetrahedron (a, b, c, d)."""
    a, b, c, d = ids
    return np.array([[b, c, d], [a, d, c], [a, b, d], [a, c, b]])


UNIT_TET = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
SPHERE = sphere_mesh(1)


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
