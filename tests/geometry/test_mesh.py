"""Tests for cutfem.geometry.mesh: structured and unstructured background meshes, topology, I/O, bad input.

Expected counts come from closed formulas for the Kuhn split of an nx x ny x nz grid of cuboids
(6 tets per cuboid, one diagonal per cuboid face, one main diagonal per cuboid), expected volumes
and areas from the box dimensions; none is produced by the code under test.
"""

import numpy as np
import pytest

from cutfem.geometry.mesh import TetMesh, read_mesh, structured_box, unstructured_box, write_mesh


def kuhn_counts(nx, ny, nz):
    """(V, E, F, T, boundary faces) of the Kuhn triangulation of an nx x ny x nz grid.

    Edges: the grid lines, one diagonal in every cuboid face (of the whole grid), one main
    diagonal per cuboid.  Faces: 4T = 2 F_interior + F_boundary with two triangles on each of the
    2 (nx ny + ny nz + nx nz) boundary squares.
    """
    V = (nx + 1) * (ny + 1) * (nz + 1)
    lines = nx * (ny + 1) * (nz + 1) + ny * (nx + 1) * (nz + 1) + nz * (nx + 1) * (ny + 1)
    face_diagonals = nx * ny * (nz + 1) + ny * nz * (nx + 1) + nx * nz * (ny + 1)
    T = 6 * nx * ny * nz
    E = lines + face_diagonals + nx * ny * nz
    Fb = 2 * (2 * nx * ny + 2 * ny * nz + 2 * nx * nz)
    F = (4 * T + Fb) // 2
    return V, E, F, T, Fb


def face_areas(points, faces):
    p = points[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def check_box_topology(mesh, lower, upper, envelope=0.0):
    """Checks shared by structured and unstructured meshes of the box [lower, upper].

    ``envelope``: how far (absolute length) the mesh boundary may lie from the box planes; zero
    for a structured box (then everything is checked to rounding), tetwild's envelope for an
    unstructured mesh.  Volume and area may then differ by at most area * envelope and a relative
    1e-3.
    """
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    extent = upper - lower
    box_volume = np.prod(extent)
    box_area = 2 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[0] * extent[2])
    tol = envelope + 1e-12 * np.max(np.abs(extent))
    # positive volumes that fill the box
    assert np.all(mesh.volumes > 0)
    assert np.all(mesh.points >= lower - tol) and np.all(mesh.points <= upper + tol)
    assert abs(mesh.volumes.sum() - box_volume) <= box_area * envelope + 1e-12 * box_volume
    # Euler characteristic of a ball
    assert mesh.n_points - len(mesh.edges) + len(mesh.faces) - mesh.n_tets == 1
    assert mesh.euler_characteristic == 1
    # interior faces: two distinct tets, both holding the face's three nodes
    fi = mesh.interior_faces
    ft = mesh.face_tets[fi]
    assert np.all(ft[:, 0] != ft[:, 1]) and np.all(ft >= 0)
    faces = mesh.faces[fi]
    for side in range(2):
        tets = mesh.tets[ft[:, side]]
        assert np.all((faces[:, :, None] == tets[:, None, :]).any(axis=2))
    # boundary faces: one tet each, lying in one of the six box planes, covering the box surface
    fb = mesh.boundary_faces
    assert np.all(mesh.face_tets[fb, 1] == -1)
    assert len(fi) + len(fb) == len(mesh.faces)
    assert 4 * mesh.n_tets == 2 * len(fi) + len(fb)
    pb = mesh.points[mesh.faces[fb]]  # (Fb, 3, 3)
    on_plane = np.zeros(len(fb), bool)
    for axis in range(3):
        for value in (lower[axis], upper[axis]):
            on_plane |= np.all(np.abs(pb[:, :, axis] - value) <= tol, axis=1)
    assert np.all(on_plane)
    rel = 1e-3 if envelope > 0 else 1e-12
    assert face_areas(mesh.points, mesh.faces[fb]).sum() == pytest.approx(box_area, rel=rel)
    # faces are sorted triples and tet_faces points back to the right face
    assert np.all(np.diff(mesh.faces, axis=1) > 0)
    local = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    rebuilt = np.sort(mesh.tets[:, local], axis=2)  # (M, 4, 3)
    assert np.array_equal(mesh.faces[mesh.tet_faces], rebuilt)


# ----------------------------------------------------------------------------------------------
# structured boxes
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "lower, upper, kwargs, cells",
    [
        ([0.0, 0.0, 0.0], [1.0, 2.0, 3.0], {"spacing": 0.5}, (2, 4, 6)),
        ([-1.0, 0.0, 2.0], [1.0, 1.0, 3.5], {"cells": (3, 2, 4)}, (3, 2, 4)),
        ([-2.0, -2.0, -2.0], [2.0, 2.0, 2.0], {"spacing": (1.0, 0.5, 2.0)}, (4, 8, 2)),
        ([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], {"spacing": 0.4}, (8, 8, 3)),
    ],
)
def test_structured_box_counts_and_topology(lower, upper, kwargs, cells):
    box = structured_box(lower, upper, **kwargs)
    nx, ny, nz = cells
    V, E, F, T, Fb = kuhn_counts(nx, ny, nz)
    assert tuple(box.cells) == cells
    assert box.n_points == V and box.points.shape == (V, 3)
    assert box.n_tets == T and box.tets.shape == (T, 4)
    assert box.n_cells == nx * ny * nz
    assert len(box.edges) == E
    assert len(box.faces) == F
    assert len(box.boundary_faces) == Fb == 2 * (2 * nx * ny + 2 * ny * nz + 2 * nx * nz)
    assert len(box.interior_faces) == F - Fb
    assert box.h == pytest.approx(V ** (-1.0 / 3.0), rel=1e-14)
    np.testing.assert_allclose(box.spacing, (np.array(upper) - np.array(lower)) / np.array(cells), rtol=1e-14)
    # every tet has the volume of a cuboid / 6
    np.testing.assert_allclose(box.volumes, np.prod(box.spacing) / 6, rtol=1e-12)
    check_box_topology(box, lower, upper)


def test_structured_box_grid_boundary_nodes_match_topology():
    box = structured_box([0, 0, 0], [3, 2, 4], cells=(3, 2, 4))
    nx1, ny1, nz1 = 4, 3, 5
    assert len(box.boundary_nodes) == nx1 * ny1 * nz1 - 2 * 1 * 3
    plain = TetMesh(box.points, box.tets)
    assert np.array_equal(box.boundary_nodes, plain.boundary_nodes)
    x = box.points[box.boundary_nodes]
    on = np.any((x == 0) | (x == [3, 2, 4]), axis=1)
    assert np.all(on)


def test_structured_box_subsets_agree_with_full_arrays():
    box = structured_box([-1.0, 0.5, 0.0], [2.0, 2.5, 1.0], cells=(6, 4, 3))
    rng = np.random.default_rng(3)
    cells = rng.choice(box.n_cells, size=20, replace=False)
    expected = box.tets[(6 * cells[:, None] + np.arange(6)).reshape(-1)]
    assert np.array_equal(box.cell_tets(cells), expected)
    nodes = rng.choice(box.n_points, size=30, replace=False)
    np.testing.assert_array_equal(box.node_coordinates(nodes), box.points[nodes])  # compiled against numpy's ids
    np.testing.assert_array_equal(box.node_coordinates(nodes.reshape(5, 6)), box.points[nodes].reshape(5, 6, 3))
    # node (i, j, k) sits at lower + (i, j, k) * spacing, with id i + (nx+1) (j + (ny+1) k)
    ijk = np.array([[0, 0, 0], [6, 4, 3], [2, 1, 3], [5, 0, 1]])
    ids = ijk[:, 0] + 7 * (ijk[:, 1] + 5 * ijk[:, 2])
    np.testing.assert_array_equal(box.node_id(ijk), ids)
    np.testing.assert_array_equal(box.node_index(ids), ijk)
    spacing = np.array([3 / 6, 2 / 4, 1 / 3])
    np.testing.assert_allclose(box.node_coordinates(ids), np.array([-1.0, 0.5, 0.0]) + ijk * spacing, rtol=0, atol=1e-15)
    # the 8 corners of a cell are the 8 nodes of its 6 tets
    corners = box.cell_corner_ids(cells)
    from cutfem.geometry.mesh import CUBE_CORNERS

    cell_ijk = np.stack([cells % 6, (cells // 6) % 4, cells // 24], axis=-1)  # cells (6, 4, 3)
    np.testing.assert_array_equal(corners, box.node_id(cell_ijk)[:, None] + box.node_id(CUBE_CORNERS)[None, :])
    tets6 = box.cell_tets(cells).reshape(-1, 24)
    assert np.all((tets6[:, :, None] == corners[:, None, :]).any(axis=2))
    assert np.all((corners[:, :, None] == tets6[:, None, :]).any(axis=2))
    # the six tets of one cube share its main diagonal
    t6 = box.cell_tets(cells[:1])
    diag = [corners[0, 0], corners[0, 7]]
    assert all(set(diag) <= set(t.tolist()) for t in t6)
    tets = rng.choice(box.n_tets, size=40, replace=False)
    np.testing.assert_array_equal(box.kuhn_tet_nodes(tets), box.tets[tets])


def test_structured_box_node_counts_per_tet_match_the_node_gather():
    """The corner-byte route of StructuredBox.tet_node_counts against the gather of the generic mesh."""
    box = structured_box([0.0, -1.0, 0.0], [1.0, 2.0, 1.5], cells=(3, 5, 4))
    plain = TetMesh(box.points, box.tets)
    rng = np.random.default_rng(5)
    for p in (0.0, 0.3, 0.7, 1.0):
        mask = rng.random(box.n_points) < p
        counts = box.tet_node_counts(mask)
        np.testing.assert_array_equal(counts, mask[box.tets].sum(axis=1))
        np.testing.assert_array_equal(counts, plain.tet_node_counts(mask))


def test_structured_box_plain_tetmesh_has_same_topology():
    box = structured_box([0, 0, 0], [1, 1, 1], cells=3)
    plain = TetMesh(box.points, box.tets)
    assert np.array_equal(plain.faces, box.faces)
    assert np.array_equal(plain.edges, box.edges)
    assert np.array_equal(plain.face_tets, box.face_tets)


# ----------------------------------------------------------------------------------------------
# unstructured (pytetwild)
# ----------------------------------------------------------------------------------------------

LOWER, UPPER = np.array([0.0, 0.0, 0.0]), np.array([1.0, 2.0, 1.5])
# pytetwild keeps the boundary within an envelope of 1e-3 times the bounding-box diagonal (its
# default epsilon); its multi-threaded output varies from run to run, so the box checks allow that.
ENVELOPE = 1e-3 * np.linalg.norm(UPPER - LOWER)


@pytest.fixture(scope="module")
def tetwild_mesh():
    return unstructured_box(LOWER, UPPER, edge_length=0.4, optimize=False)  # no optimization: fast


def test_unstructured_box_fills_the_box(tetwild_mesh):
    m = tetwild_mesh
    assert m.n_tets > 100
    check_box_topology(m, LOWER, UPPER, envelope=ENVELOPE)
    # the mesh is genuinely unstructured: tet volumes vary
    assert m.volumes.max() > 2 * m.volumes.min()
    # a plain copy gives the same topology
    copy = TetMesh(m.points.copy(), m.tets.copy())
    assert len(copy.faces) == len(m.faces) and copy.euler_characteristic == 1


def test_unstructured_box_rejects_bad_edge_length():
    with pytest.raises(ValueError, match="edge_length"):
        unstructured_box(LOWER, UPPER, edge_length=-1.0)


# ----------------------------------------------------------------------------------------------
# I/O
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_read_write_round_trip(tmp_path, suffix):
    box = structured_box([-1, -1, 0], [1, 1, 0.5], cells=(4, 4, 1))
    mesh = TetMesh(box.points, box.tets)
    path = tmp_path / f"box{suffix}"
    write_mesh(mesh, path)
    back = read_mesh(path)
    assert back.points.shape == mesh.points.shape
    np.testing.assert_allclose(back.points, mesh.points, rtol=0, atol=1e-14)
    assert np.array_equal(back.tets, mesh.tets)
    assert back.volumes.sum() == pytest.approx(2 * 2 * 0.5, rel=1e-12)


def test_write_with_data_round_trip(tmp_path):
    import meshio

    box = structured_box([0, 0, 0], [1, 1, 1], cells=2)
    path = tmp_path / "data.vtu"
    write_mesh(box, path, point_data={"x": box.points[:, 0]}, cell_data={"id": np.arange(box.n_tets)})
    m = meshio.read(path)
    np.testing.assert_array_equal(m.point_data["x"], box.points[:, 0])
    np.testing.assert_array_equal(m.cell_data["id"][0], np.arange(48))


def test_read_mesh_reorients_inverted_tets(tmp_path):
    import meshio

    box = structured_box([0, 0, 0], [1, 1, 1], cells=1)
    tets = box.tets.copy()
    tets[:, [2, 3]] = tets[:, [3, 2]]  # all inverted
    path = tmp_path / "inverted.vtu"
    meshio.write(path, meshio.Mesh(box.points, [("tetra", tets)]))
    back = read_mesh(path)
    np.testing.assert_allclose(back.volumes, 1 / 6, rtol=1e-12)


def test_read_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        read_mesh(tmp_path / "nothing.vtu")


def test_read_unreadable_file(tmp_path):
    path = tmp_path / "junk.vtu"
    path.write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="cannot read"):
        read_mesh(path)


def test_read_file_without_tets(tmp_path):
    import meshio

    path = tmp_path / "tri.vtu"
    meshio.write(path, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(ValueError, match="no tetrahedra"):
        read_mesh(path)


def _write_gmsh41(path, points, tets, triangles):
    """A gmsh 4.1 ASCII file as gmsh writes one: a volume (physical group 2 "domain") of tets and its
    boundary surface (physical group 1 "wall") of triangles, node tags from 1."""
    n, lo, hi = len(points), points.min(axis=0), points.max(axis=0)
    box = " ".join(f"{v:.17g}" for v in (*lo, *hi))
    lines = ["$MeshFormat", "4.1 0 8", "$EndMeshFormat", "$PhysicalNames", "2", '2 1 "wall"', '3 2 "domain"',
             "$EndPhysicalNames", "$Entities", "0 0 1 1", f"1 {box} 1 1 0", f"1 {box} 1 2 1 1", "$EndEntities",
             "$Nodes", f"1 {n} 1 {n}", f"3 1 0 {n}", *map(str, range(1, n + 1)),
             *(" ".join(f"{v:.17g}" for v in p) for p in points), "$EndNodes"]
    m, f = len(tets), len(triangles)
    lines += ["$Elements", f"2 {m + f} 1 {m + f}", f"2 1 2 {f}",
              *(" ".join(map(str, (k + 1, *(t + 1)))) for k, t in enumerate(triangles)), f"3 1 4 {m}",
              *(" ".join(map(str, (f + k + 1, *(t + 1)))) for k, t in enumerate(tets)), "$EndElements"]
    path.write_text("\n".join(lines) + "\n")


def test_read_gmsh_file_with_boundary_triangles_and_physical_groups(tmp_path):
    """A gmsh 4.1 file of the 2 x 2 x 2 Kuhn box [0, 1]^3 with its 48 boundary triangles in a
    physical group: the 48 tets and 27 nodes are read, the triangles are left out."""
    box = structured_box([0, 0, 0], [1, 1, 1], cells=2)
    mesh = TetMesh(box.points, box.tets)
    path = tmp_path / "box.msh"
    _write_gmsh41(path, mesh.points, mesh.tets, mesh.faces[mesh.boundary_faces])
    back = read_mesh(path)
    assert (back.n_points, back.n_tets, len(back.boundary_faces)) == (27, 48, 48)
    assert np.array_equal(back.tets, mesh.tets)
    assert back.volumes.sum() == pytest.approx(1.0, rel=1e-14)


def _tetra10(points, tets):
    """(points, (m, 10) quadratic tets): the corners, then the midpoints of the edges 01 12 02 03 13 23
    (the vtk/gmsh order), one midpoint node per edge."""
    pairs = np.sort(tets[:, [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]]], axis=2).reshape(-1, 2)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    mids = 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])
    return np.vstack([points, mids]), np.hstack([tets, len(points) + inverse.reshape(-1, 6)])


def test_read_quadratic_tets_uses_their_corners(tmp_path):
    """A mesh of tetra10 cells only was refused as holding 'no tetrahedra'.  Its corners make the
    straight-sided tets: the 48 tets of the 2 x 2 x 2 box of volume 1, h = 27**(-1/3) (the 98
    mid-edge nodes are used by no tet and do not count)."""
    import meshio

    box = structured_box([0, 0, 0], [1, 1, 1], cells=2)
    points, t10 = _tetra10(box.points, box.tets)
    path = tmp_path / "quadratic.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra10", t10)]))
    back = read_mesh(path)
    assert (back.n_points, back.n_tets, back.n_used_points) == (27 + 98, 48, 27)
    assert np.array_equal(back.tets, box.tets)
    assert back.volumes.sum() == pytest.approx(1.0, rel=1e-14)
    assert back.h == pytest.approx(1 / 3, rel=1e-14)


def test_read_mesh_with_other_volume_cells_is_refused(tmp_path):
    """Tets and a hexahedron: reading the tets alone gave a mesh with a hole where the hexahedron
    was (volume 1 of 2).  Refused, naming the cells and the fix."""
    import meshio

    box = structured_box([0, 0, 0], [1, 1, 1], cells=2)
    cube = np.array([[1, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 0, 1], [2, 0, 1], [2, 1, 1], [1, 1, 1]], float)
    path = tmp_path / "mixed.vtu"
    meshio.write(path, meshio.Mesh(np.vstack([box.points, cube]), [("tetra", box.tets), ("hexahedron", 27 + np.arange(8)[None])]))
    with pytest.raises(ValueError, match=r"1 hexahedron.*tetrahedra only"):
        read_mesh(path)


def test_read_two_dimensional_mesh_is_refused(tmp_path):
    """A 2-D triangle mesh (points with two coordinates) names the tetrahedral mesh needed."""
    import meshio

    path = tmp_path / "plane.msh"
    meshio.write(path, meshio.Mesh(np.array([[0.0, 0], [1, 0], [0, 1]]), [("triangle", np.array([[0, 1, 2]]))]), file_format="gmsh22")
    with pytest.raises(ValueError, match=r"no tetrahedra.*triangle.*3-D mesh of tetrahedra"):
        read_mesh(path)


def test_read_integer_points(tmp_path):
    """Integer coordinates are read as floats: the 2 x 2 x 2 box scaled to [0, 2]^3 has volume 8."""
    import meshio

    box = structured_box([0, 0, 0], [1, 1, 1], cells=2)
    path = tmp_path / "integer.vtu"
    meshio.write(path, meshio.Mesh(np.rint(2 * box.points).astype(np.int32), [("tetra", box.tets)]))
    back = read_mesh(path)
    assert back.points.dtype == np.float64 and back.volumes.sum() == pytest.approx(8.0, rel=1e-14)


# ----------------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------------

UNIT_TET_POINTS = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def test_single_tet_volume_and_counts():
    m = TetMesh(UNIT_TET_POINTS, [[0, 1, 2, 3]])
    assert m.volumes[0] == pytest.approx(1 / 6, rel=1e-15)
    assert (len(m.edges), len(m.faces), len(m.boundary_faces)) == (6, 4, 4)
    assert m.euler_characteristic == 1


def test_nan_point():
    pts = UNIT_TET_POINTS.copy()
    pts[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        TetMesh(pts, [[0, 1, 2, 3]])


def test_index_out_of_range():
    with pytest.raises(ValueError, match=r"indices must lie in \[0, 4\)"):
        TetMesh(UNIT_TET_POINTS, [[0, 1, 2, 4]])
    with pytest.raises(ValueError, match="indices"):
        TetMesh(UNIT_TET_POINTS, [[0, 1, 2, -1]])


def test_degenerate_tet():
    pts = np.vstack([UNIT_TET_POINTS, [[1.0, 1.0, 0.0]]])  # point 4 in the plane z = 0
    with pytest.raises(ValueError, match="degenerate"):
        TetMesh(pts, [[0, 1, 2, 3], [0, 1, 2, 4]])
    with pytest.raises(ValueError, match="degenerate"):
        TetMesh(UNIT_TET_POINTS, [[0, 1, 2, 2]])


def test_inverted_tet_error_and_orient():
    with pytest.raises(ValueError, match="inverted.*orient=True"):
        TetMesh(UNIT_TET_POINTS, [[0, 2, 1, 3]])
    m = TetMesh(UNIT_TET_POINTS, [[0, 2, 1, 3]], orient=True)
    assert m.volumes[0] == pytest.approx(1 / 6, rel=1e-15)
    assert sorted(m.tets[0].tolist()) == [0, 1, 2, 3]


def _jittered_box(cells=4, seed=0):
    """(points, tets) of the Kuhn mesh of [-1, 1]^3 with its interior nodes moved at random by up
    to 0.1 of the spacing: an unstructured mesh (tets of different shapes) with positive volumes."""
    box = structured_box([-1.0] * 3, [1.0] * 3, cells=cells)
    pts = box.points.copy()
    inner = np.all(np.abs(pts) < 1 - 1e-9, axis=1)
    pts[inner] += np.random.default_rng(seed).uniform(-0.1, 0.1, (inner.sum(), 3)) * (2.0 / cells)
    return pts, box.tets.copy()


def test_unused_nodes_do_not_change_h():
    """h = N**(-1/3) counts the nodes of the tets: nodes that no tet uses (a mesh file's stray
    points) are not nodes of the mesh.  125 nodes for 4 cells a side: h = 125**(-1/3) = 0.2 with or
    without 1000 unused ones (these made h = 1125**(-1/3) = 0.096)."""
    pts, tets = _jittered_box()
    stray = np.random.default_rng(1).uniform(-1, 1, (1000, 3))
    plain, padded = TetMesh(pts, tets), TetMesh(np.vstack([stray, pts]), tets + len(stray))
    assert plain.h == pytest.approx(0.2, rel=1e-14)
    assert padded.h == pytest.approx(0.2, rel=1e-14)
    far = TetMesh(np.vstack([pts, [[50.0, -7.0, 3.0]]]), tets)  # one stray point far off the box
    assert [b.tolist() for b in far.bounds] == [[-1.0] * 3, [1.0] * 3]
    # a stray point with NaN coordinates is no node either; a NaN node of a tet is refused
    nan = TetMesh(np.vstack([pts, [[np.nan, 0.0, np.inf]]]), tets)
    assert nan.h == pytest.approx(0.2, rel=1e-14) and nan.volumes.sum() == pytest.approx(8.0, rel=1e-13)
    bad = pts.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"^1 nodes of the tets are NaN or infinite \(first: point 7\)"):
        TetMesh(bad, tets)


def test_coincident_nodes_used_by_tets_are_refused():
    """Two used nodes at one point split the mesh there (a crack: their faces are not shared), so a
    P1 field is discontinuous across it and the faces drop out of the face penalties.  Refused,
    naming both nodes; an unused copy is harmless and accepted."""
    pts, tets = _jittered_box()
    node = 62  # the centre (2, 2, 2) of the 5 x 5 x 5 nodes
    users = np.flatnonzero((tets == node).any(axis=1))
    cracked = tets.copy()
    cracked[users[::2]] = np.where(cracked[users[::2]] == node, len(pts), cracked[users[::2]])
    with pytest.raises(ValueError, match=r"2 nodes coincide.*nodes 62 and 125.*merge"):
        TetMesh(np.vstack([pts, pts[node]]), cracked)
    m = TetMesh(np.vstack([pts, pts[node]]), tets)  # the copy is not used
    assert len(m.interior_faces) == TetMesh(pts, tets).interior_faces.size


def test_nearly_coincident_nodes_used_by_tets_are_refused():
    """A copy of a node 1e-14 away (a mesher's rounding) splits the mesh as an exact copy does: 650
    interior faces instead of 672 were accepted.  Refused when the nodes of the tets are closer than
    1e-10 times the diagonal of their box (here 2 sqrt(3) 1e-10 = 3.5e-10), naming both nodes; a
    copy 4e-10 away (above the tolerance) is a node of its own."""
    pts, tets = _jittered_box()
    node = 62
    users = np.flatnonzero((tets == node).any(axis=1))
    cracked = tets.copy()
    cracked[users[::2]] = np.where(cracked[users[::2]] == node, len(pts), cracked[users[::2]])
    for shift in ([1e-14, 0, 0], [-2e-10, 1e-10, 2e-10]):  # 3.0e-10 < 3.46e-10
        with pytest.raises(ValueError, match=r"2 nodes.*nodes 62 and 125.*closer than 3\.46e-10.*merge"):
            TetMesh(np.vstack([pts, pts[node] + shift]), cracked)
    far = TetMesh(np.vstack([pts, pts[node] + [0, 0, 4e-10]]), cracked)  # 4e-10 > 3.46e-10: two nodes
    assert (len(far.interior_faces), len(TetMesh(pts, tets).interior_faces)) == (650, 672)


def test_close_pairs_are_the_pairs_within_the_distance():
    """close_pairs gives exactly the pairs of points at distance <= r, as the O(n^2) distance
    table does: on a lattice (many equal coordinates along every axis) with copies moved by
    0.5 r, 0.99 r and 1.5 r, and on random points."""
    from cutfem.geometry.mesh import close_pairs

    rng = np.random.default_rng(3)
    lattice = np.stack(np.meshgrid(*(np.arange(6.0),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    r = 1e-6
    copies = lattice[[7, 100, 150, 200]] + np.array([[0.5, 0, 0], [0, 0.99, 0], [0.6, 0.6, 0.6], [1.5, 0, 0]]) * r
    for pts in (np.vstack([lattice, copies]), rng.uniform(0, 1, (400, 3)), np.vstack([lattice, lattice[:3]])):
        radius = r if len(pts) != 400 else 0.03
        d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
        i, j = np.nonzero(np.triu(d <= radius, k=1))
        expected = sorted(zip(i.tolist(), j.tolist()))
        assert sorted(map(tuple, close_pairs(pts, radius).tolist())) == expected
    assert len(expected) == 3  # the exact copies


def test_bad_shapes():
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        TetMesh(np.zeros((4, 2)), [[0, 1, 2, 3]])
    with pytest.raises(ValueError, match=r"tets must have shape \(M, 4\)"):
        TetMesh(UNIT_TET_POINTS, [[0, 1, 2]])


def test_spacing_not_dividing_the_box_grows_the_box_at_exactly_that_spacing():
    """A box that is not a whole number of cells is grown symmetrically to the next whole number;
    the spacing used is the one asked for, bit for bit, and the grown box contains the given one."""
    box = structured_box([0, -1, 2], [1, 1, 2.5], spacing=0.3)
    assert np.all(box.spacing == 0.3)
    np.testing.assert_array_equal(box.cells, [4, 7, 2])  # ceil(1/0.3), ceil(2/0.3), ceil(0.5/0.3)
    np.testing.assert_allclose(box.lower, [0.5 - 0.6, -1.05, 2.25 - 0.3], rtol=0, atol=1e-15)
    np.testing.assert_allclose(box.upper - box.lower, box.cells * 0.3, rtol=1e-15)
    np.testing.assert_allclose(0.5 * (box.lower + box.upper), [0.5, 0.0, 2.25], atol=1e-15)
    # the node coordinates step by exactly the spacing
    x = box.node_coordinates(np.arange(box.node_shape[0]))[:, 0]
    np.testing.assert_array_equal(x, box.lower[0] + np.arange(5) * 0.3)
    # per-axis spacings, and a box that fits in one axis only keeps that axis as given
    box = structured_box([0, 0, 0], [1, 1, 1], spacing=(0.25, 0.3, 0.5))
    np.testing.assert_array_equal(box.spacing, [0.25, 0.3, 0.5])
    np.testing.assert_array_equal(box.cells, [4, 4, 2])
    assert box.lower[0] == 0 and box.upper[0] == 1 and box.lower[2] == 0 and box.upper[2] == 1
    assert box.lower[1] == pytest.approx(-0.1) and box.upper[1] == pytest.approx(1.1)


def test_spacing_that_fits_keeps_the_box():
    box = structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1)
    np.testing.assert_array_equal(box.cells, [32, 32, 12])
    np.testing.assert_array_equal(box.lower, [-1.6, -1.6, -0.6])
    np.testing.assert_array_equal(box.upper, [1.6, 1.6, 0.6])
    assert np.all(box.spacing == 0.1)


def test_structured_box_bad_arguments():
    with pytest.raises(ValueError, match="exactly one of spacing= or cells="):
        structured_box([0, 0, 0], [1, 1, 1])
    with pytest.raises(ValueError, match="exactly one of spacing= or cells="):
        structured_box([0, 0, 0], [1, 1, 1], spacing=0.5, cells=2)
    for bad in (-0.5, 0.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="spacing must be a positive finite number"):
            structured_box([0, 0, 0], [1, 1, 1], spacing=bad)
    with pytest.raises(ValueError, match="upper > lower"):
        structured_box([0, 0, 0], [1, 0, 1], cells=2)
    with pytest.raises(ValueError, match="at least one cell"):
        structured_box([0, 0, 0], [1, 1, 1], cells=(2, 0, 2))


# ----------------------------------------------------------------------------------------------
# sorting helpers and the Kuhn gradient table
# ----------------------------------------------------------------------------------------------


def test_stable_argsort_is_the_stable_argsort():
    """The radix argsort equals np.argsort(kind="stable") for narrow and wide keys (one and
    several radix passes), negative keys, many ties, and other integer dtypes."""
    from cutfem.geometry.mesh import stable_argsort

    rng = np.random.default_rng(7)
    for trial in range(120):
        n = int(rng.integers(0, 5000))
        bits = int(rng.integers(1, 63))
        keys = rng.integers(0, 2**bits, n, dtype=np.int64)
        if trial % 3 == 0:
            keys %= max(1, n // 4)  # ties
        if trial % 5 == 0:
            keys -= 2 ** (bits - 1)  # negative keys
        for dtype in (np.int64, np.int32, np.uint16):
            k = keys.astype(dtype) if dtype is np.int64 or bits < 15 else keys
            np.testing.assert_array_equal(stable_argsort(k), np.argsort(k, kind="stable"))


def test_dense_unique_is_unique():
    from cutfem.geometry.mesh import dense_unique

    rng = np.random.default_rng(3)
    ids = rng.integers(0, 1000, (300, 4))
    u, inv = dense_unique(ids, 1000)
    eu, einv = np.unique(ids, return_inverse=True)
    np.testing.assert_array_equal(u, eu)
    np.testing.assert_array_equal(inv, einv.reshape(ids.shape))
    assert inv.dtype == np.int32
    u64, inv64 = dense_unique(ids, 1000, np.int64)
    assert inv64.dtype == np.int64
    np.testing.assert_array_equal(u64, u)
    np.testing.assert_array_equal(inv64, inv)
    with pytest.raises(ValueError, match="cannot hold"):
        dense_unique(ids, 1000, np.int8)


@pytest.mark.parametrize("lower, upper, cells", [([0, 0, 0], [1, 1, 1], 3), ([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], (16, 16, 6)), ([0.3, -2, 5], [0.9, 1, 5.5], (5, 7, 4))])
def test_kuhn_gradient_table_equals_the_barycentric_gradients(lower, upper, cells):
    """On a structured box the gradients from the reference table divided by the spacing, and the
    constant volume, are the barycentric gradients and volumes computed from the coordinates."""
    from cutfem.geometry.mesh import barycentric_gradients

    box = structured_box(lower, upper, cells=cells)
    ids = np.arange(box.n_tets)
    grads, vol = barycentric_gradients(box.points[box.tets])
    table = box.gradient_table[ids % 6]
    scale = 1.0 / box.spacing.min()
    np.testing.assert_allclose(table, grads, rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(vol, box.tet_volume, rtol=1e-12)
    # and every gradient of the table is (-1, 0, 1) / spacing, componentwise
    ref = np.rint(table * box.spacing)
    assert set(np.unique(ref)) <= {-1.0, 0.0, 1.0}
    np.testing.assert_array_equal(table, ref / box.spacing)


@pytest.mark.parametrize("base", [2**21 - 3, 2**22 + 5, 20_000_000, 2**31 + 7])
def test_face_keys_group_faces_with_large_node_ids(base):
    """Faces of tets whose node ids lie above 2**21 and 2**22 (a single int64 of three ids would
    overflow there) and at 20 million are grouped exactly: the two tets sharing a face pair up, the
    others stay alone, and the sorted columns are the face's node ids."""
    from cutfem.geometry.mesh import pair_up, tet_face_keys

    n = base + 10
    # two tets sharing the face {base, base+1, base+2}, listed in different orders, and one apart
    tets = np.array([[base, base + 1, base + 2, base + 3], [base + 4, base + 2, base, base + 1], [base + 5, base + 6, base + 7, base + 9]])
    keys = tet_face_keys(tets, n)
    assert len(keys) == 3 and all(col.shape == (12,) for col in keys)
    rows = np.stack(keys, axis=1)
    np.testing.assert_array_equal(rows, np.sort(tets[:, None, :].repeat(4, 1)[:, np.arange(4)[:, None], [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1))
    order, starts, counts = pair_up(keys)
    assert counts.sum() == 12 and len(counts) == 11  # 12 face rows, one face shared
    shared = np.flatnonzero(counts == 2)
    assert shared.size == 1
    pair = np.sort(order[starts[shared[0]] : starts[shared[0]] + 2])
    np.testing.assert_array_equal(pair, [3, 4])  # face opposite local vertex 3 of tet 0 and vertex 0 of tet 1
    np.testing.assert_array_equal(rows[pair[0]], [base, base + 1, base + 2])
    # the groups come in lexicographic order of the rows
    firsts = rows[order[starts]]
    assert np.all(np.diff(firsts[:, 0]) >= 0)
    np.testing.assert_array_equal(np.lexsort(firsts.T[::-1]), np.arange(len(firsts)))


@pytest.mark.parametrize("base", [2**21 + 1, 2**22 + 3])
def test_tetmesh_topology_with_large_node_ids(base):
    """The face and edge topology of a mesh whose tets use node ids above 2**21 and 2**22 (the old
    single-integer face key stopped at 2**21): two tets sharing one face."""
    points = np.zeros((base + 5, 3))  # untouched zeros: no memory is paid for them
    points[base : base + 5] = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]]
    tets = np.array([[0, 1, 2, 3], [0, 2, 1, 4]]) + base
    mesh = TetMesh(points, tets, check=False)
    assert len(mesh.faces) == 7 and len(mesh.interior_faces) == 1
    np.testing.assert_array_equal(mesh.faces[mesh.interior_faces[0]], [base, base + 1, base + 2])
    np.testing.assert_array_equal(mesh.face_tets[mesh.interior_faces[0]], [0, 1])
    assert len(mesh.edges) == 9 and mesh.edges.max() == base + 4 and mesh.edges.min() == base


def test_sorted_row_keys_pairs_with_large_ids():
    from cutfem.geometry.mesh import sorted_row_keys

    n = 20_000_001
    rows = np.array([[n - 1, 2**22 + 1], [2**22 + 1, n - 1], [3, 2**21 + 9]])
    k = sorted_row_keys(rows, n)
    assert k[0] == k[1] == (2**22 + 1) * n + n - 1 and k[2] == 3 * n + 2**21 + 9
    with pytest.raises(ValueError, match="tet_face_keys"):
        sorted_row_keys(np.zeros((2, 3), int), 10)


def test_stable_argsort_of_columns_is_the_lexsort():
    """Column tuples (mixed dtypes, negative values, widths summing past 63 bits) sort as np.lexsort."""
    from cutfem.geometry.mesh import stable_argsort

    rng = np.random.default_rng(11)
    for trial in range(40):
        n = int(rng.integers(0, 3000))
        cols = []
        for j in range(int(rng.integers(1, 4))):
            bits = int(rng.integers(1, 40))
            c = rng.integers(0, 2**bits, n, dtype=np.int64)
            if trial % 3 == 0:
                c %= 3  # ties
            if trial % 4 == j:
                c -= 2 ** (bits - 1)
            cols.append(c.astype(np.int32) if bits < 31 and trial % 2 else c)
        np.testing.assert_array_equal(stable_argsort(tuple(cols)), np.lexsort(cols[::-1]))


@pytest.mark.parametrize("cells", [(1, 1, 1), (3, 2, 4), (5, 1, 2)])
def test_kuhn_face_keys_number_the_faces_in_sorted_triple_order(cells):
    """The lattice face keys of a structured box name the same faces as the sorted node triples
    (equal keys exactly for equal triples) and, with the box's own node ids, in the same order; with
    the nodes renumbered at random they still group the faces exactly."""
    from cutfem.geometry.mesh import kuhn_face_keys, tet_face_keys

    box = structured_box([0, 0, 0], [1, 1, 1], cells=cells)
    kuhn = np.arange(box.n_tets) % 6
    triples = np.stack(tet_face_keys(box.tets, box.n_points), axis=1).astype(np.int64)  # (4M, 3)
    triple_key = (triples[:, 0] * box.n_points + triples[:, 1]) * box.n_points + triples[:, 2]
    keys = kuhn_face_keys(box.tets, kuhn)
    assert keys.shape == (4 * box.n_tets,) and keys.min() >= 0 and keys.max() < 12 * box.n_points
    # same partition of the face rows, and the same order of the groups
    _, first_k, inv_k = np.unique(keys, return_index=True, return_inverse=True)
    _, first_t, inv_t = np.unique(triple_key, return_index=True, return_inverse=True)
    assert len(first_k) == len(box.faces)
    np.testing.assert_array_equal(first_k, first_t)
    np.testing.assert_array_equal(inv_k, inv_t)
    # any numbering of the nodes: the same partition (orders may differ)
    perm = np.random.default_rng(5).permutation(box.n_points)
    renamed = kuhn_face_keys(perm[box.tets], kuhn)
    _, inv_r = np.unique(renamed, return_inverse=True)
    _, pair = np.unique(inv_r * len(first_k) + inv_k, return_inverse=True)
    assert len(np.unique(inv_r)) == len(first_k) and pair.max() + 1 == len(first_k)


def test_kuhn_edge_codes_are_the_lattice_steps():
    """KUHN_EDGE_CODES[l, i, j] is the set of axes along which nodes i and j of Kuhn tet l differ,
    and the lower of the two nodes is the one with the smaller id in every cell."""
    from cutfem.geometry.mesh import KUHN_EDGE_CODES, KUHN_TETS

    box = structured_box([0, 0, 0], [1, 1, 1], cells=(3, 2, 2))
    ijk = box.node_index(box.tets)  # (M, 4, 3)
    step = np.abs(ijk[:, :, None, :] - ijk[:, None, :, :])  # (M, 4, 4, 3) in {0, 1}
    assert step.max() == 1
    codes = step[..., 0] + 2 * step[..., 1] + 4 * step[..., 2]
    np.testing.assert_array_equal(codes, KUHN_EDGE_CODES[np.arange(box.n_tets) % 6])
    # node above the lower one along the code c has the id + o(c), increasing in c
    nx1, ny1 = box.node_shape[0], box.node_shape[1]
    offset = lambda c: (c & 1) + nx1 * ((c >> 1) & 1) + nx1 * ny1 * (c >> 2)
    lo, hi = np.minimum(box.tets[:, :, None], box.tets[:, None, :]), np.maximum(box.tets[:, :, None], box.tets[:, None, :])
    np.testing.assert_array_equal(hi - lo, offset(codes))
    assert np.all(np.diff([offset(c) for c in range(8)]) > 0)
    assert KUHN_TETS.shape == (6, 4)


def test_side_subtetrahedra_partition_each_tet():
    """The NEG and POS parts of each tet (whole tets and sub-tets of the cut ones, from the compiled
    pass) fill it: their volumes add up to the tet's, every sub-tet lies in its parent and on its
    side (the linear phi_h at its vertices), and the sub-tets of a count come grouped, 1 then 3
    per tet, each tet's pieces in the order of the prism."""
    from cutfem.geometry.markers import NEG, POS, side_subtetrahedra
    from cutfem.geometry.quadrature import signed_volumes

    rng = np.random.default_rng(9)
    points = rng.random((60, 3))
    tets = np.array([rng.choice(60, 4, replace=False) for _ in range(300)])
    values = rng.normal(size=60)
    values[:5] = 0.0  # nodes on the zero level (the zero rule's snap)
    volume = np.abs(signed_volumes(points[tets]))
    total = np.zeros(len(tets))
    for side, sign in ((NEG, -1.0), (POS, 1.0)):
        whole, sub, parent = side_subtetrahedra(points, tets, values, side)
        total += np.bincount(whole, weights=volume[whole], minlength=len(tets))
        total += np.bincount(parent, weights=np.abs(signed_volumes(sub)), minlength=len(tets))
        # phi_h at the sub-tets' vertices: barycentric coordinates in the parent tet
        x = points[tets[parent]]
        T = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=-1)
        lam = np.linalg.solve(T[:, None], (sub - x[:, None, 0])[..., None])[..., 0]
        bary = np.concatenate([1 - lam.sum(-1, keepdims=True), lam], axis=-1)
        assert bary.min() > -1e-9
        phi = np.einsum("mvk,mk->mv", bary, values[tets[parent]])
        assert (sign * phi).min() > -1e-9
        assert np.count_nonzero(np.diff(parent) <= 0) <= 6  # at most 7 increasing runs: 1 + 3 + 3 sub-tets
    np.testing.assert_allclose(total, volume, rtol=1e-10, atol=1e-15)


def test_longest_edges_of_tets_and_triangles():
    """The compiled longest edge equals the largest of numpy's edge norms, bit for bit, for tets
    and triangles given by node numbers; other shapes are an error."""
    from cutfem.geometry.markers import longest_edges

    rng = np.random.default_rng(1)
    P = rng.random((100, 3))
    for k in (3, 4):
        S = rng.integers(0, 100, (200, k))
        ref = np.max([np.linalg.norm(P[S[:, b]] - P[S[:, a]], axis=1) for a in range(k) for b in range(a + 1, k)], axis=0)
        np.testing.assert_array_equal(longest_edges(P, S), ref)
    with pytest.raises(ValueError, match=r"\(m, 3\) or \(m, 4\)"):
        longest_edges(P, np.zeros((5, 2), dtype=np.int64))


def test_read_mesh_names_a_missing_reader_package(tmp_path, monkeypatch):
    """A format whose meshio reader needs another package (.xdmf with HDF5 data: h5py) says which
    package to install, instead of passing on the import error as a broken file."""
    import meshio

    from cutfem.geometry.mesh import read_mesh

    path = tmp_path / "m.xdmf"
    path.write_text("<Xdmf/>")

    def read(_):
        raise ModuleNotFoundError("No module named 'h5py'", name="h5py")

    monkeypatch.setattr(meshio, "read", read)
    with pytest.raises(ValueError, match=r"needs the package 'h5py' for this format; install it \(pip install h5py\)"):
        read_mesh(path)
