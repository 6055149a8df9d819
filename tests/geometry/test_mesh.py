"""Tests for cutfem.geometry.mesh: the topology of background meshes (a structured box and pytetwild's), I/O, bad input.

Expected counts come from closed formulas for the Kuhn split of an nx x ny x nz grid of cuboids
(6 tets per cuboid, one diagonal per cuboid face, one main diagonal per cuboid), expected volumes
and areas from the box dimensions; none is produced by the code under test.
"""

import numpy as np
import pytest

from cutfem.geometry.box import structured_box
from cutfem.geometry.mesh import TetMesh, read_mesh, unstructured_box, write_mesh


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
# the topology of a structured box, against closed-form counts
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


# ----------------------------------------------------------------------------------------------
# topology with large node ids
# ----------------------------------------------------------------------------------------------


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
