"""Tests for cutfem.geometry.box: the structured box of Kuhn tets, its arithmetic numbering and sizes.

Expected ids, coordinates and counts come from the lattice formulas (node (i, j, k) at
lower + (i, j, k) * spacing, six Kuhn tets per cube); none is produced by the code under test.
"""

import numpy as np
import pytest

from cutfem.geometry.box import structured_box
from cutfem.geometry.mesh import TetMesh


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
    from cutfem.geometry.numbering import CUBE_CORNERS

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


@pytest.mark.parametrize("cells", [(1, 1, 1), (3, 2, 4), (5, 1, 2)])
def test_kuhn_face_keys_number_the_faces_in_sorted_triple_order(cells):
    """The lattice face keys of a structured box name the same faces as the sorted node triples
    (equal keys exactly for equal triples) and, with the box's own node ids, in the same order; with
    the nodes renumbered at random they still group the faces exactly."""
    from cutfem.geometry.box import kuhn_face_keys
    from cutfem.geometry.keys import tet_face_keys

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
    from cutfem.geometry.box import KUHN_EDGE_CODES, KUHN_TETS

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
