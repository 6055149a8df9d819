"""Background meshes at the edges of the API (issue 45, items 2b, 2c, 2g and part 4): meshes that
are tangled or overlap, boxes whose spacing contradicts their corners or whose sizes pass int64,
spacings so small that counts overflow, empty meshes and unmerged STL soups."""

import re

import meshio
import numpy as np
import pytest

from cutfem.runs.cli import main
from cutfem.memory import InsufficientMemoryError
from cutfem.geometry.box import StructuredBox, structured_box
from cutfem.geometry.mesh import TetMesh, read_mesh

# -- 2c: a spacing that contradicts the corners and the cells -------------------------------------


def test_structured_box_refuses_a_spacing_that_does_not_match_its_corners():
    # 10 cells of 0.2 reach 2.0, not the upper corner 1.0: the box used to report bounds [0, 1]^3
    # while its nodes reached 2.0
    with pytest.raises(ValueError, match=r"spacing=\[0\.2, 0\.2, 0\.2\] does not match the corners and cells.*"
                                         r"lower \+ cells \* spacing = \[2\.0, 2\.0, 2\.0\].*"
                                         r"consistent spacing is \(upper - lower\) / cells = \[0\.1, 0\.1, 0\.1\]"):
        StructuredBox([0] * 3, [1] * 3, [10] * 3, spacing=0.2)


def test_structured_box_accepts_a_spacing_that_matches_to_round_off():
    box = StructuredBox([0] * 3, [1] * 3, [10] * 3, spacing=0.1)
    assert box.points.max() == pytest.approx(1.0, abs=1e-15)
    # a box far from the origin: (upper - lower) / cells carries the corners' round-off
    far = structured_box([1e8] * 3, [1e8 + 1] * 3, spacing=0.001)
    assert far.spacing.tolist() == [0.001] * 3 and far.cells.tolist() == [1000] * 3
    StructuredBox([0] * 3, [1] * 3, [10] * 3, spacing=0.1 * (1 + 1e-12))


# -- 2g and part 4: sizes past int64, spacings that overflow the cell counts -----------------------


def test_cells_past_int64_are_refused_with_the_real_counts():
    # (3e6 + 1)**3 nodes used to wrap in int64 and be reported as 8.55e18
    with pytest.raises(InsufficientMemoryError, match=r"3,000,000 x 3,000,000 x 3,000,000 cells has 2\.70e\+19 nodes "
                                                      r"and 1\.62e\+20 tets: their ids do not fit in 64-bit integers.*"
                                                      r"6\.75e\+18 bytes.*give fewer cells"):
        structured_box([0] * 3, [1] * 3, cells=3_000_000)
    with pytest.raises(InsufficientMemoryError, match=r"1\.00e\+19 x .* cells has 1\.00e\+57 nodes"):
        structured_box([0] * 3, [1] * 3, cells=1e19)


def test_sizes_below_int64_are_exact_python_integers():
    box = structured_box([0] * 3, [1] * 3, cells=1_000_000)  # 6e18 tets: the ids still fit
    assert box.n_points == 1_000_001**3 and box.n_tets == 6 * 10**18
    assert isinstance(box.n_points, int) and isinstance(box.n_cells, int)


@pytest.mark.parametrize("spacing, nodes", [(1e-300, r"9\.99e\+899"), (1e-320, r"1\.00e\+960")])
def test_tiny_spacings_state_the_real_counts(spacing, nodes):
    # the cell counts overflowed to -9223372036854775808 ("need at least one cell per axis")
    with pytest.raises(InsufficientMemoryError) as err:
        structured_box([0] * 3, [1] * 3, spacing=spacing)
    text = str(err.value)
    assert re.search(rf"at spacing=1e-3[02]0 has {nodes} nodes", text), text
    assert "use a coarser spacing: at least 8.66e-07 for the ids to fit" in text
    assert "-9223372036854775808" not in text


def test_a_spacing_whose_box_passes_int64_is_told_to_coarsen():
    # 1e7 cells a side fit in int64, their product does not: the fix is about the spacing given
    with pytest.raises(InsufficientMemoryError, match=r"at spacing=1e-07 has 1\.00e\+21 nodes.*use a coarser spacing: "
                                                      r"at least 8\.66e-07"):
        structured_box([0] * 3, [1] * 3, spacing=1e-7)


def test_coordinates_near_1e30_state_the_real_counts():
    with pytest.raises(InsufficientMemoryError, match=r"at spacing=0\.1 has 7\.99e\+93 nodes.*at least 1\.73e\+24"):
        structured_box([-1e30] * 3, [1e30] * 3, spacing=0.1)


@pytest.mark.parametrize("argv", [["run", "poisson-cut", "--levels", "1e-320"],
                                  ["run", "mean-curvature-cut", "--spacing", "1e-320"]])
def test_cli_tiny_spacing_is_one_clear_line_and_exit_2(argv, capsys):
    assert main(argv + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "-9223372036854775808" not in err and "upper > lower" not in err
    assert re.search(r"spacing=1e-320 has 1\.\d\de\+961 nodes.*use a coarser spacing", err), err


# -- 2b: tangled and overlapping background meshes ------------------------------------------------


def _shuffled_box(cells=6, seed=0, jitter=0.2):
    """A valid mesh of [-1, 1]^3 as a mesh file may hold it: interior nodes jittered, nodes and tets
    renumbered at random, half the tets with two vertices swapped (negative volume)."""
    box = structured_box([-1] * 3, [1] * 3, cells=cells)
    rng = np.random.default_rng(seed)
    interior = ~np.isin(np.arange(box.n_points), box.boundary_nodes)
    points = box.points + interior[:, None] * rng.uniform(-jitter, jitter, box.points.shape) * (2 / cells)
    perm = rng.permutation(box.n_points)
    new = np.empty_like(perm)
    new[perm] = np.arange(box.n_points)
    tets = new[box.tets][rng.permutation(box.n_tets)]
    swap = rng.random(len(tets)) < 0.5
    tets[swap, 2], tets[swap, 3] = tets[swap, 3], tets[swap, 2].copy()
    return points[perm], tets


def test_valid_meshes_in_any_vertex_order_are_accepted():
    points, tets = _shuffled_box()
    mesh = TetMesh(points, tets, orient=True)
    assert mesh.volumes.sum() == pytest.approx(8.0, rel=1e-12)
    # every tet inverted (the other orientation convention): reordering makes the mesh consistent
    box = structured_box([-1] * 3, [1] * 3, cells=3)
    flipped = box.tets[:, [1, 0, 2, 3]]
    assert TetMesh(box.points, flipped, orient=True).volumes.sum() == pytest.approx(8.0, rel=1e-12)


def test_a_mesh_with_a_cavity_is_not_an_overlap():
    box = structured_box([-1] * 3, [1] * 3, cells=4)
    centre = box.points[box.tets].mean(axis=1)
    keep = np.max(np.abs(centre), axis=1) > 0.5  # the 2 x 2 x 2 central cells removed: an inner boundary
    mesh = TetMesh(box.points, box.tets[keep])
    assert mesh.volumes.sum() == pytest.approx(8.0 - 1.0, rel=1e-12)


def test_a_node_pushed_through_a_face_is_refused_as_tangled(tmp_path):
    # the node at (-0.5, -0.5, -0.5) of a 4 x 4 x 4 box moved across the face x = -1: read_mesh used to
    # flip its inverted tets, and the box of volume 8 then had tets of volume 8.1
    box = structured_box([-1] * 3, [1] * 3, cells=4)
    points = box.points.copy()
    node = int(np.flatnonzero(np.all(points == -0.5, axis=1))[0])
    points[node] = [-1.2, -0.5, -0.5]
    path = tmp_path / "tangled.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", box.tets)]))
    with pytest.raises(ValueError, match=r"the mesh is tangled: \d+ interior faces have their two tets on the same side "
                                         r"\(first tet pairs: \(\d+, \d+\).*; \d+ of them are inverted .* first tets \[\d+"
                                         r".*untangle the mesh"):
        read_mesh(path)


def test_a_slightly_folded_node_is_refused():
    # a smaller push: the node crosses the face of its star only just (the 8.0062 of the issue)
    box = structured_box([-1] * 3, [1] * 3, cells=4)
    points = box.points.copy()
    node = int(np.flatnonzero(np.all(points == -0.5, axis=1))[0])
    points[node] = [-1.05, -0.5, -0.5]
    with pytest.raises(ValueError, match="the mesh is tangled"):
        TetMesh(points, box.tets, orient=True)
    # without orient the inverted tets are not the news: reordering them would not help
    with pytest.raises(ValueError, match=r"the mesh is tangled.*cannot make the mesh consistent") as err:
        TetMesh(points, box.tets)
    assert "pass orient=True" not in str(err.value)


def test_two_overlapping_meshes_are_refused(tmp_path):
    # two box meshes with their own nodes, one shifted into the other: |NEG| of a ball of 0.905 was 1.63
    a = structured_box([-1] * 3, [1] * 3, cells=8)
    b = structured_box([-0.93] * 3, [1.07] * 3, cells=7)
    points = np.vstack([a.points, b.points])
    tets = np.vstack([a.tets, b.tets + a.n_points])
    with pytest.raises(ValueError, match=r"the mesh overlaps itself: \d+ \(point of its boundary, tet\) pairs.*"
                                         r"inside tet \d+.*covered twice.*Give one conforming mesh"):
        TetMesh(points, tets)
    path = tmp_path / "two.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", tets)]))
    with pytest.raises(ValueError, match="the mesh overlaps itself"):
        read_mesh(path)


def test_a_mesh_nested_inside_another_is_refused():
    outer = structured_box([-1] * 3, [1] * 3, cells=5)
    inner = structured_box([-0.31, -0.27, -0.23], [0.29, 0.33, 0.26], cells=2)  # wholly inside, no node shared
    points = np.vstack([outer.points, inner.points])
    tets = np.vstack([outer.tets, inner.tets + outer.n_points])
    with pytest.raises(ValueError, match=r"the mesh overlaps itself: \d+ \(point of its boundary, tet\) pairs"):
        TetMesh(points, tets)


def test_a_star_wound_twice_around_a_node_is_refused():
    # 14 tets around the origin: a 7-gon on the equator whose corners step by 4 pi / 7 (it goes round
    # twice), coned to the two poles.  Every interior face has its tets on opposite sides and no
    # boundary point is inside a tet, yet every direction around the origin is covered twice
    n = 7
    angle = 4 * np.pi * np.arange(n) / n
    points = np.vstack([[0, 0, 0], [0, 0, 1], [0, 0, -1], np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)])
    tets = [[0, 1, 3 + i, 3 + (i + 1) % n] for i in range(n)] + [[0, 2, 3 + (i + 1) % n, 3 + i] for i in range(n)]
    with pytest.raises(ValueError, match=r"the mesh winds around 1 interior nodes more than once \(first: node 0 at "
                                         r"\[0\.0, 0\.0, 0\.0\], whose 14 tets .* cover the directions around it 2 times: "
                                         r"solid angles summing to 25\.13 instead of 4 pi\).*re-mesh"):
        TetMesh(points, np.array(tets), orient=True)
    # the same star wound once (step 2 pi / 7) is a valid mesh of a bipyramid
    angle = 2 * np.pi * np.arange(n) / n
    points[3:] = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)
    assert TetMesh(points, np.array(tets), orient=True).volumes.sum() == pytest.approx(2 / 3 * 7 / 2 * np.sin(2 * np.pi / 7))


def test_a_ring_wound_twice_around_a_boundary_edge_is_refused():
    # 7 tets around the edge between the poles, the ring stepping by about 4 pi / 7: both ends of
    # the edge are on the boundary, and the boundary of one turn runs through the tets of the other
    n = 7
    angle = 4 * np.pi * np.arange(n) / n + 0.05 * np.random.default_rng(1).uniform(-1, 1, n)
    points = np.vstack([[0, 0, -1], [0, 0, 1], np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)])
    tets = np.array([[0, 1, 2 + i, 2 + (i + 1) % n] for i in range(n)])
    with pytest.raises(ValueError, match=r"the mesh overlaps itself"):
        TetMesh(points, tets, orient=True)


def test_a_tet_given_twice_is_refused_at_construction():
    box = structured_box([0] * 3, [1] * 3, cells=2)
    tets = np.vstack([box.tets, box.tets[5:6]])
    with pytest.raises(ValueError, match=r"3 faces are shared by more than two tets \(first: face \[.*\] of tets "
                                         r"\[\d+, \d+, \d+\]\).*a tet given twice"):
        TetMesh(box.points, tets)


# -- part 4: a mesh with no tets ----------------------------------------------------------------


def test_a_mesh_without_tets_is_refused():
    with pytest.raises(ValueError, match=r"a TetMesh needs at least one tet; got 0 tets \(on 4 points\)"):
        TetMesh(np.eye(4, 3), np.zeros((0, 4), dtype=int))


# -- part 4: STL soups whose copies of a vertex are 1e-7 apart -----------------------------------


def _soup(path, gap=1e-7, drop_first=False):
    """An icosphere (level 2) written as a facet soup: every triangle with its own three vertices,
    each moved by up to ``gap`` per coordinate."""
    from cutfem.geometry.surface_meshes import sphere_mesh

    sphere = sphere_mesh(2)
    rng = np.random.default_rng(0)
    tri = sphere.triangles[1:] if drop_first else sphere.triangles
    points = sphere.points[tri].reshape(-1, 3) + rng.uniform(-gap, gap, (3 * len(tri), 3))
    meshio.write(path, meshio.Mesh(points, [("triangle", np.arange(len(points)).reshape(-1, 3))]), binary=False)
    return sphere


def test_an_unmerged_stl_soup_is_named_with_the_tolerance_that_merges_it(tmp_path):
    from cutfem.geometry.surface import read_surface

    path = tmp_path / "soup.stl"
    sphere = _soup(path)
    # it was "the surface is open: 960 boundary edge(s) ... close the holes"
    with pytest.raises(ValueError, match=r"the surface is an unmerged triangle soup: 960 of its 960 boundary edges have "
                                         r"both ends within 2\.\de-07 of another vertex.*closer than 1e-10 times the "
                                         r"bounding-box diagonal.*read_surface\(path, merge_tolerance=\de-0[67]\)") as err:
        read_surface(path)
    assert "close the holes" not in str(err.value)
    tolerance = float(re.search(r"merge_tolerance=([0-9.e-]+)\)", str(err.value)).group(1))
    merged = read_surface(path, merge_tolerance=tolerance)
    assert merged.n_points == sphere.n_points and merged.n_triangles == sphere.n_triangles


def test_a_soup_with_a_real_hole_names_both(tmp_path):
    from cutfem.geometry.surface import read_surface

    path = tmp_path / "holed.stl"
    _soup(path, drop_first=True)
    with pytest.raises(ValueError, match=r"unmerged triangle soup: 954 of its 957 boundary edges.*the other 3 boundary "
                                         r"edges are holes"):
        read_surface(path)


def test_a_real_hole_is_still_a_hole(tmp_path):
    from cutfem.geometry.surface import read_surface
    from cutfem.geometry.surface_meshes import sphere_mesh

    sphere = sphere_mesh(2)
    path = tmp_path / "open.stl"
    meshio.write(path, meshio.Mesh(sphere.points, [("triangle", sphere.triangles[1:])]), binary=False)
    with pytest.raises(ValueError, match=r"the surface is open: 3 boundary edge\(s\).*close the holes"):
        read_surface(path)
    with pytest.raises(ValueError, match=r"merge_tolerance must be a number in \[0, 0\.01\)"):
        read_surface(path, merge_tolerance=0.5)
