"""Tests of cutfem.geometry.band_search: the band search finds the same cut as evaluating every node
(of the structured box, of the same tets as a plain TetMesh, of an array of nodal values), whatever
the chunks of its compiled passes, and its mixed Kuhn tets are a numpy reference's."""

import numpy as np
import pytest

from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.mesh import TetMesh
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry import cut_kernels

# background boxes with binary-exact nodes (spacing 0.25) and the paper's torus box (spacing 0.1)
SPHERE_BOX = structured_box([-2.0] * 3, [2.0] * 3, spacing=0.25)
TORUS_BOX = structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1)


class PlainFunction:
    """A level set given only by values, no Lipschitz bound (the cut then evaluates every node)."""

    def __init__(self, f):
        self.f = f

    def value(self, x):
        return self.f(np.asarray(x, float))


@pytest.mark.parametrize(
    "box, levelset",
    [
        (SPHERE_BOX, Sphere(1.1, center=(0.07, -0.03, 0.11))),
        (SPHERE_BOX, Sphere(1.25)),  # exact zero nodal values
        (TORUS_BOX, Torus(1.0, 0.5)),  # exact and rounding-size zero values
    ],
    ids=["sphere", "sphere-zeros", "torus-zeros"],
)
def test_band_search_and_plain_mesh_agree(box, levelset):
    band = cut_mesh(box, levelset)
    plain = cut_mesh(TetMesh(box.points, box.tets), levelset)
    everything = cut_mesh(box, PlainFunction(levelset.value))  # structured, no Lipschitz bound
    nodal = cut_mesh(box, levelset.value(box.points))  # an array of nodal values
    for other in (plain, everything, nodal):
        assert np.array_equal(np.sort(band.tet_ids), np.sort(other.tet_ids))
        assert other.n_triangles == band.n_triangles
        assert other.area == pytest.approx(band.area, rel=1e-13)
        assert other.enclosed_volume == pytest.approx(band.enclosed_volume, rel=1e-13)
        ob, oo = np.argsort(band.tet_ids), np.argsort(other.tet_ids)
        np.testing.assert_allclose(band.piece_areas[ob], other.piece_areas[oo], rtol=1e-12, atol=1e-15)
        # the structured box takes the basis gradients from the Kuhn table, the plain mesh from the
        # vertex coordinates: equal up to rounding
        np.testing.assert_allclose(band.normals[ob], other.normals[oo], rtol=0, atol=1e-14)


def test_band_search_and_cut_in_small_chunks_are_the_same(monkeypatch):
    """The count-then-fill kernels (the band search's refinement, the mixed tets) give the same cut
    with chunks of 7 rows as with one chunk: the same arrays, in the same order."""

    box = structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1)
    one = cut_mesh(box, Torus(1.0, 0.5))
    monkeypatch.setattr(cut_kernels, "COUNT_FILL_CHUNK", 7)
    small = cut_mesh(box, Torus(1.0, 0.5))
    for name in ("tet_ids", "tets", "node_ids", "values", "vertices", "triangles", "triangle_tets", "normals"):
        np.testing.assert_array_equal(getattr(small, name), getattr(one, name))


@pytest.mark.parametrize("cells_per_chunk", [7, 1 << 14])
def test_mixed_kuhn_tets_in_chunks_against_numpy(monkeypatch, cells_per_chunk):
    """The mixed Kuhn tets of cells, counted and filled chunk by chunk on all cores: exactly the
    tets of a cell-order pass (a numpy reference: the corner values gathered and snapped, the
    table's mask of each cell, cell by cell, then Kuhn type), the corners that break a bound
    against their cell's centre counted with the largest ratio, also with no cell at all."""
    from cutfem.geometry.box import KUHN_TETS

    monkeypatch.setattr(cut_kernels, "COUNT_FILL_CHUNK", cells_per_chunk)
    rng = np.random.default_rng(5)
    k, p = 1000, 3000
    values = rng.standard_normal(p)
    values[rng.random(p) < 0.3] = 1.0  # some cells without a sign change
    values[:40] = rng.uniform(-1e-3, 1e-3, 40)  # snapped to zero below
    corner = rng.integers(0, p, size=(k, 8)).astype(np.int32)
    corner[:5] = np.arange(40).reshape(5, 8)
    cell_ids = np.sort(rng.choice(10**7, size=k, replace=False))
    table = rng.random((256, 6)) < 0.5
    table[0] = table[255] = False
    centre = rng.standard_normal(k)
    tol, bound, dist = 2e-3, 2.5, 0.7
    tet_ids, nodes, vals, broken, ratio = cut_kernels.mixed_kuhn_tets(values, corner, cell_ids, table, KUHN_TETS, tol=tol,
                                                                  centre=centre, bound=bound, dist=dist)
    cv = values[corner]
    dphi = np.abs(cv - centre[:, None])
    assert broken == np.count_nonzero(dphi > bound) > 0 and ratio == np.max(dphi) / dist
    cv[np.abs(cv) <= tol] = 0.0
    assert np.count_nonzero(cv[:5] == 0.0) == 40
    signs = ((cv < 0) * (1 << np.arange(8))).sum(axis=1)
    mask = table[signs]
    kt = np.asarray(KUHN_TETS)
    np.testing.assert_array_equal(tet_ids, (6 * cell_ids[:, None] + np.arange(6))[mask])
    np.testing.assert_array_equal(nodes, corner[:, kt][mask])
    np.testing.assert_array_equal(vals, cv[:, kt][mask])
    assert nodes.dtype == corner.dtype
    plain = cut_kernels.mixed_kuhn_tets(values, corner, cell_ids, table, KUHN_TETS, tol=tol)  # no centre: no check
    assert plain[3:] == (0, 0.0)
    for a, b in zip(plain[:3], (tet_ids, nodes, vals)):
        np.testing.assert_array_equal(a, b)
    none = cut_kernels.mixed_kuhn_tets(values, corner[:0], cell_ids[:0], table, KUHN_TETS, centre=centre[:0])
    assert [len(a) for a in none[:3]] == [0, 0, 0] and none[3:] == (0, 0.0)
